"""Keeping a message stream at its rate: MAV_CMD_SET_MESSAGE_INTERVAL again while it is missing or slow."""
from __future__ import annotations

import collections
import math

from companion.mavlink import messages as mm


class StreamRequest:
    """Asks for ``message_id`` at ``rate_hz`` every ``retry_s`` while fewer than half the expected messages
    arrived over the last ``retry_s`` (arrival times on the monotonic clock, seconds)."""

    def __init__(self, message_id: int, rate_hz: float, retry_s: float):
        self.message_id = message_id
        self.rate_hz = rate_hz
        self.retry_s = retry_s
        self.requests = 0
        self._arrivals_s: collections.deque[float] = collections.deque()
        self._last_request_s = -math.inf

    def arrived(self, receive_ns: int) -> None:
        self._arrivals_s.append(receive_ns * 1e-9)

    def due(self, now_s: float, target_system: int, target_component: int) -> list:
        """The SET_MESSAGE_INTERVAL command to send now, if the stream is missing or slow (else [])."""
        while self._arrivals_s and self._arrivals_s[0] < now_s - self.retry_s:
            self._arrivals_s.popleft()
        slow = len(self._arrivals_s) < 0.5 * self.rate_hz * self.retry_s
        if not slow or now_s - self._last_request_s < self.retry_s:
            return []
        self._last_request_s = now_s
        self.requests += 1
        return [mm.set_message_interval(target_system, target_component, self.message_id, self.rate_hz)]

    def ask_after(self, now_s: float) -> None:
        """The next ``due`` asks no sooner than ``retry_s`` from now (time for a stream to come on its own)."""
        self._last_request_s = now_s

    def ask_at_once(self) -> None:
        """The next ``due`` asks whatever the last request's time (an autopilot appeared)."""
        self._last_request_s = -math.inf
