"""The live view's page in a real headless browser: Debian's Chromium driven by Selenium through
/usr/bin/chromedriver (`.ci/run` installs both; selenium comes with the test extras).

The daemon runs as a user starts it (`companion run --http`), replaying the hover flight in a loop.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from mavlink_peer import free_port

REPO = Path(__file__).resolve().parent.parent
HOVER = REPO / "tests" / "data" / "sequences" / "warehouse_hover"
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1400,1000")
WAIT_S = 20.0


def require_browser():
    """The browser test is part of the suite: a machine without it fails, naming what to install."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    try:
        import selenium  # noqa: F401
    except ImportError:
        missing.append("the selenium package")
    if missing:
        pytest.fail(f"the browser test needs {', '.join(missing)}: apt-get install chromium chromium-driver; "
                    "pip install -e '.[test]' (bash .ci/run does both)")


@pytest.fixture
def daemon(tmp_path):
    """(live view URL, the daemon's process)."""
    port = free_port("tcp")
    config = tmp_path / "daemon.yaml"
    config.write_text(yaml.safe_dump({
        "source": {"kind": "replay", "path": str(HOVER), "realtime": True, "loop": True},
        "map": str(REPO / "maps" / "warehouse.yaml"),
        "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}", "origin_wait_s": 0.0, "duplicate_listen_s": 0.0,
                    "statustext_interval_s": 0.2},
    }))
    process = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config),
                                "--http", f"127.0.0.1:{port}"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            if process.poll() is not None or time.monotonic() > deadline:
                process.kill()
                pytest.fail(f"the daemon did not serve the live view: {process.communicate()[1]}")
            time.sleep(0.1)
    yield f"http://127.0.0.1:{port}/", process
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=20)
    assert process.returncode == 0, stderr


@pytest.fixture
def browser():
    require_browser()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    profile = tempfile.mkdtemp(prefix="companion-chromium-")
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    driver.set_page_load_timeout(WAIT_S)
    yield driver
    driver.quit()
    shutil.rmtree(profile, ignore_errors=True)


def wait_until(driver, script: str, what: str):
    """Poll a JavaScript expression until it is truthy; its value."""
    from selenium.webdriver.support.ui import WebDriverWait
    return WebDriverWait(driver, WAIT_S, poll_frequency=0.1).until(
        lambda d: d.execute_script(f"return {script}"), message=f"the page never showed {what}")


def test_the_page_loads_updates_its_image_and_shows_the_state(browser, daemon):
    browser.get(daemon[0])
    assert browser.title == "companion live view"
    # the image: a decoded 640x480 frame, then newer ones without a reload
    first = int(wait_until(browser, "document.getElementById('frame').naturalWidth === 640 && "
                                    "+document.getElementById('frame').dataset.index > 0 && "
                                    "document.getElementById('frame').dataset.index", "a camera frame"))
    later = int(wait_until(browser, f"+document.getElementById('frame').dataset.index > {first} + 5 && "
                                    "document.getElementById('frame').dataset.index", "the image updating"))
    assert later > first + 5
    # the status: the filter's state (the hover flight is tracked), the link's, the status line
    wait_until(browser, "document.getElementById('status-state').textContent === 'tracking'", "the tracking state")
    # read in one script: the page rebuilds the status panel on every poll, so a found element goes stale
    state_class, link, line = browser.execute_script(
        "const element = id => document.getElementById(id);"
        "return [element('status-state').className, element('status-link').textContent,"
        "        element('status-line').textContent];")
    assert state_class == "tracking"
    # one row a name: the health's state and the filter's ("state" was the filter's, then the health's again)
    names = browser.execute_script(
        "return [...document.querySelectorAll('#status td:first-child')].map(td => td.textContent);")
    assert len(names) == len(set(names)) and {"state", "filter", "link"} <= set(names)
    assert browser.execute_script("return document.getElementById('status-filter').textContent") == "tracking"
    assert link in ("streaming", "handshake", "connecting")
    assert "fps" in line
    wait_until(browser, "document.getElementById('statustexts').textContent.includes('companion: tracking markers')",
               "the STATUSTEXT list")
    wait_until(browser, "document.getElementById('estimate-tracking') && "
                        "document.getElementById('estimate-tracking').textContent === 'yes'", "the estimate")
    # the map panel: the markers and the estimate's dot (the tracking colour #6fdc6f) are drawn
    wait_until(browser, """(() => {
        const c = document.getElementById('map'), d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let dot = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] === 0x6f && d[i + 1] === 0xdc && d[i + 2] === 0x6f) dot++;
        return dot > 20;
    })()""", "the estimate on the map")
    if os.environ.get("COMPANION_SCREENSHOT"):
        browser.save_screenshot(os.environ["COMPANION_SCREENSHOT"])


def test_the_page_says_when_the_daemon_is_gone(browser, daemon):
    url, process = daemon
    browser.get(url)
    wait_until(browser, "document.getElementById('connection').textContent === 'live'", "the live state")
    process.send_signal(signal.SIGINT)
    process.wait(timeout=20)
    wait_until(browser, "document.getElementById('connection').textContent === 'daemon not answering'",
               "the lost daemon")
