"""The systemd unit (checked by systemd-analyze) and the notify protocol on a real socket."""
from __future__ import annotations

import configparser
import logging
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from companion.daemon.notify import Notifier, watchdog_interval_s

REPO = Path(__file__).resolve().parent.parent
UNIT = REPO / "systemd" / "companion.service"


def unit_sections() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # keys are case-sensitive in systemd
    parser.read(UNIT)
    return parser


def test_unit_is_a_watched_notify_service_of_an_unprivileged_user():
    service = unit_sections()["Service"]
    assert service["Type"] == "notify"
    assert service["WatchdogSec"].rstrip("s").isdigit() and int(service["WatchdogSec"].rstrip("s")) > 0
    assert service["Restart"] == "on-failure"
    assert service["User"] not in ("", "root")
    assert {"video", "dialout"} <= set(service["SupplementaryGroups"].split())
    assert " run --config " in service["ExecStart"]
    assert unit_sections()["Install"]["WantedBy"] == "multi-user.target"


def test_a_config_that_cannot_work_is_not_restarted_over_and_over(tmp_path):
    """A typo in the config exits 2 at once: Restart=on-failure restarted it every 2-3 s forever (never 5
    starts in systemd's 10 s burst limit), repeating the one line that names the key."""
    config = tmp_path / "companion.yaml"
    config.write_text("mavlink: {max_rate_hz: 100}\n")
    run = subprocess.run([sys.executable, "-m", "companion", "run", "--config", str(config)], capture_output=True,
                         text=True, timeout=60)
    assert run.returncode != 0 and "companion.yaml: " in run.stderr, run.stderr
    prevented = unit_sections()["Service"].get("RestartPreventExitStatus", "").split()
    assert str(run.returncode) in prevented, (run.returncode, prevented)


def test_systemd_analyze_verify_reports_nothing(tmp_path):
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is needed for this test (apt-get install systemd)"
    # verify insists that ExecStart's program exists: point it at this Python.
    text = UNIT.read_text().replace("/opt/companion/venv/bin/companion", sys.executable)
    unit = tmp_path / "companion.service"
    unit.write_text(text)
    result = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "" and result.stderr.strip() == "", result.stderr


def receive_all(sock: socket.socket) -> list[str]:
    messages = []
    sock.settimeout(0.5)
    while True:
        try:
            messages.append(sock.recv(4096).decode())
        except socket.timeout:
            return messages


@pytest.mark.parametrize("abstract", [False, True])
def test_notifier_sends_the_protocol_datagrams(tmp_path, abstract):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if abstract:
        name = f"companion-test-{os.getpid()}"
        sock.bind("\0" + name)
        address = "@" + name
    else:
        address = str(tmp_path / "notify.sock")
        sock.bind(address)
    notifier = Notifier({"NOTIFY_SOCKET": address})
    assert notifier.enabled
    assert notifier.ready(status="running")
    assert notifier.watchdog() and notifier.status("30 fps") and notifier.stopping()
    notifier.close()
    assert receive_all(sock) == ["READY=1\nSTATUS=running", "WATCHDOG=1", "STATUS=30 fps", "STOPPING=1"]
    sock.close()


def test_a_notify_socket_that_fails_is_said_once_not_at_every_send(tmp_path, caplog):
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})   # no such socket
    with caplog.at_level(logging.WARNING, logger="companion.daemon.notify"):
        assert not any([notifier.watchdog() for _ in range(50)])
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "sd_notify to " in warnings[0] and "failed" in warnings[0], warnings
    notifier.close()


def test_notifier_outside_systemd_does_nothing():
    notifier = Notifier({})
    assert not notifier.enabled and not notifier.ready() and not notifier.watchdog()
    assert notifier.watchdog_interval_s is None


def test_watchdog_interval_is_half_the_timeout_and_only_for_our_pid():
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 5.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": str(os.getpid())}) == 5.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "soon"}) is None
