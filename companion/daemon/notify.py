"""systemd's notify protocol: READY, WATCHDOG, STATUS, STOPPING on $NOTIFY_SOCKET.

The protocol is one datagram of ``KEY=VALUE`` lines sent to the unix socket
named in ``$NOTIFY_SOCKET`` (a leading ``@`` means the abstract namespace).
Without that variable (not started by systemd) every call does nothing.
"""
from __future__ import annotations

import logging
import os
import socket

from companion.log_throttle import LogThrottle

log = logging.getLogger(__name__)


class Notifier:
    """Sends sd_notify messages; a no-op outside systemd."""

    def __init__(self, environ: dict[str, str] | None = None):
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        if address.startswith("@"):
            address = "\0" + address[1:]
        self._address = address or None
        self._socket: socket.socket | None = None
        if self._address:
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._socket.setblocking(False)
        self.watchdog_interval_s = watchdog_interval_s(env)
        self._failed_log = LogThrottle(log, interval_s=60.0)   # sent several times a second: a failure repeats

    @property
    def enabled(self) -> bool:
        return self._socket is not None

    def send(self, *lines: str) -> bool:
        """Send one datagram; True if it went out."""
        if self._socket is None:
            return False
        try:
            self._socket.sendto("\n".join(lines).encode(), self._address)
            return True
        except OSError as error:
            self._failed_log.log(logging.WARNING, "sd_notify to %r failed: %s", self._address, error)
            return False

    def ready(self, status: str = "") -> bool:
        return self.send("READY=1", *([f"STATUS={status}"] if status else []))

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None


def watchdog_interval_s(environ: dict[str, str]) -> float | None:
    """How often to send WATCHDOG=1 (half of $WATCHDOG_USEC), or None if not asked.

    systemd sets WATCHDOG_PID to the process it watches; another pid (a
    child that inherited the environment) must not answer for it.
    """
    usec = environ.get("WATCHDOG_USEC")
    pid = environ.get("WATCHDOG_PID")
    if not usec or (pid and pid.strip() != str(os.getpid())):
        return None
    try:
        return int(usec) / 2e6
    except ValueError:
        return None
