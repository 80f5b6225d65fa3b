"""A fault that repeats every frame is logged a few times, not every time (README: "Nothing is silent")."""
from __future__ import annotations

import logging
import time


class LogThrottle:
    """At most one message per ``interval_s`` at its level; the ones in between go to DEBUG.

    The message that passes says how many were held back since the last one.
    """

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0):
        self.logger = logger
        self.interval_s = interval_s
        self._last_s = -float("inf")
        self._held_back = 0

    def log(self, level: int, message: str, *args) -> None:
        now_s = time.monotonic()
        if now_s - self._last_s < self.interval_s:
            self._held_back += 1
            self.logger.debug(message, *args)
            return
        if self._held_back:
            message += f" ({self._held_back} similar message(s) in the last {now_s - self._last_s:.0f} s)"
        self.logger.log(level, message, *args)
        self._last_s, self._held_back = now_s, 0
