"""The README's service installation, run as written into a temporary root, then the installed unit
checked by systemd-analyze and its ExecStart run as systemd would (notify socket, watchdog), on the
bundled recorded flight. Slow (a fresh virtual environment and `pip install .`): CI runs it with the
other slow tests (.ci/run, step 2)."""
from __future__ import annotations

import configparser
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MARKER = "<!-- service install:"
# Lines that need a real system (a user, systemd itself, its journal): not run in the temporary root.
SYSTEM_ONLY = ("useradd", "systemctl", "journalctl")


def readme_service_commands() -> list[str]:
    """The shell lines of the README's service-install block, exactly as written there."""
    text = (REPO / "README.md").read_text()
    assert MARKER in text, "the README's service block lost its marker"
    block = text.split(MARKER, 1)[1].split("```sh\n", 1)[1].split("```", 1)[0]
    return [line for line in block.splitlines() if line.strip()]


def in_root(text: str, root: Path) -> str:
    """A command or unit line with the system's /opt and /etc moved under ``root``, run without sudo."""
    text = re.sub(r"(^|&& )sudo ", r"\1", text)
    return re.sub(r"(?<![\w.])/(opt|etc)/", lambda m: f"{root}/{m.group(1)}/", text)


class NotifySocket:
    """systemd's end of the notify protocol: every datagram the service sends."""

    def __init__(self, path: Path):
        self.path = str(path)
        self.messages: list[str] = []
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._socket.bind(self.path)
        self._socket.settimeout(0.1)
        self._running = True
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        while self._running:
            try:
                self.messages.append(self._socket.recv(4096).decode())
            except socket.timeout:
                pass

    def close(self):
        self._running = False
        self._thread.join()
        self._socket.close()


@pytest.mark.slow
def test_the_readme_service_installation_works_as_written(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    ran = []
    for line in readme_service_commands():
        if line.split()[1 if line.startswith("sudo ") else 0] in SYSTEM_ONLY:
            continue
        command = in_root(line, root)
        result = subprocess.run(command, shell=True, cwd=REPO, capture_output=True, text=True, timeout=600,
                                env={**os.environ, "PYTHONPATH": ""})
        assert result.returncode == 0, f"{line}\n{result.stdout[-2000:]}\n{result.stderr[-3000:]}"
        assert "Traceback" not in result.stderr, result.stderr
        ran.append((line, result))
    assert [line for line, _ in ran if "pip install" in line], "the block installs nothing"
    # The installed config on the bundled flight: it found its calibration and map beside it and tracked.
    trial = next(result for line, result in ran if " run --config " in line)
    assert f"map {root}/etc/companion/warehouse.yaml" in trial.stderr
    assert re.search(r"\| tracking \|", trial.stdout), trial.stdout[-2000:]

    # The unit as installed: systemd-analyze verify (ExecStart's program in the root, as it will be in /opt).
    unit = root / "etc" / "systemd" / "system" / "companion.service"
    assert unit.is_file()
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is needed for this test (apt-get install systemd)"
    checked = tmp_path / "companion.service"
    checked.write_text(in_root(unit.read_text(), root))
    verify = subprocess.run([analyze, "verify", str(checked)], capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0 and not verify.stderr.strip(), verify.stderr

    # Its ExecStart as systemd runs it (notify socket, watchdog, journald's stream), on the recorded flight.
    service = configparser.ConfigParser(strict=False, interpolation=None)
    service.optionxform = str
    service.read_string(checked.read_text())
    exec_start = shlex.split(service["Service"]["ExecStart"])
    assert Path(exec_start[0]).is_file() and str(root) in exec_start[0]
    notify = NotifySocket(tmp_path / "notify.sock")
    environment = dict(pair.split("=", 1) for pair in shlex.split(service["Service"].get("Environment", "")))
    process = subprocess.Popen(
        [*exec_start, "--replay", str(REPO / "companion" / "data" / "sequences" / "warehouse_aisle")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd="/",
        env={"PATH": os.environ["PATH"], **environment, "NOTIFY_SOCKET": notify.path,
             "WATCHDOG_USEC": "2000000", "JOURNAL_STREAM": "8:1234"})
    try:
        deadline = time.monotonic() + 60
        while not any("| tracking |" in m for m in notify.messages) and time.monotonic() < deadline:
            time.sleep(0.1)
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
        notify.close()
    assert process.returncode == 0, stderr
    assert notify.messages[0].startswith("READY=1")
    assert "WATCHDOG=1" in notify.messages and notify.messages[-1] == "STOPPING=1"
    assert any(m.startswith("STATUS=") and "| tracking |" in m for m in notify.messages)
    # journald priorities on every line, and the reason the link cannot open (no UART in CI) said once
    assert all(re.match(r"<\d>", line) for line in stderr.splitlines()), stderr[-2000:]
    assert stderr.count("link /dev/ttyAMA0,921600: cannot open") == 1, stderr
    assert "SIGTERM: stopping" in stderr and "Traceback" not in stderr
