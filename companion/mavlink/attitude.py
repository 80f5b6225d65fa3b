"""The flight controller's attitude over MAVLink: requested, put on our clock, kept in an ``AttitudeHistory``.

``AttitudeStream`` is the link's attitude part (``companion.mavlink.link``
calls it from its thread):

* **Request.** ``MAV_CMD_SET_MESSAGE_INTERVAL`` asks the autopilot for
  ATTITUDE (30) at ``rate_hz`` (50 by default) as soon as it is seen, and again
  every ``request_retry_s`` while ATTITUDE arrives at less than half that
  rate (a reboot, a lost command). ATTITUDE_QUATERNION (31) is used too if
  the autopilot streams it.
* **Time alignment: a filtered receive-time offset.** A sample carries the
  autopilot's ``time_boot_ms``; its time on our monotonic clock is
  ``time_boot_ms + offset``, with ``offset`` the smallest ``receive time -
  time_boot_ms`` of the last ``window_s`` (10 s): transport and scheduling
  only ever delay a message, so the smallest difference belongs to the
  promptest one, and a sliding window follows the two clocks' drift (tens of
  ppm: under a millisecond per window). ``time_boot_ms`` truncates the
  autopilot's clock to whole milliseconds, so half a millisecond is added.
  Error: the promptest message's delay plus up to +-0.5 ms (measured in
  ``tests/test_attitude_link.py`` against a peer with jitter: within 2 ms).
  No TIMESYNC is needed from the autopilot. A ``time_boot_ms`` that goes
  back by more than a second (a reboot) restarts the filter and the history.
"""
from __future__ import annotations

import collections
import logging
import math
from typing import Callable

from companion.geometry import frames
from companion.geometry.attitude import AttitudeHistory
from companion.mavlink import messages as mm
from companion.mavlink.interval import StreamRequest
from companion.types import AttitudeSample

log = logging.getLogger(__name__)

ATTITUDE_MESSAGES = ("ATTITUDE", "ATTITUDE_QUATERNION")
NS_PER_MS = 1_000_000
REBOOT_STEP_MS = 1000  # time_boot_ms going back further than this: the autopilot restarted


def restarted(previous_boot_ms: int | None, boot_ms: int) -> bool:
    """Whether an autopilot whose ``time_boot_ms`` was ``previous_boot_ms`` (None: not yet seen) and is now
    ``boot_ms`` restarted in between: its clock went back by more than ``REBOOT_STEP_MS``."""
    return previous_boot_ms is not None and boot_ms < previous_boot_ms - REBOOT_STEP_MS


class BootClock:
    """Maps the autopilot's ``time_boot_ms`` onto our monotonic clock (see the module docstring)."""

    def __init__(self, window_s: float = 10.0):
        self.window_ns = int(window_s * 1e9)
        # (receive_ns, offset_ns) with rising offsets: the front is the window's minimum
        self._candidates: collections.deque[tuple[int, int]] = collections.deque()
        self._last_boot_ms: int | None = None

    def to_monotonic_ns(self, boot_ms: int, receive_ns: int) -> int:
        """Our time of a sample stamped ``boot_ms`` and received at ``receive_ns``."""
        offset_ns = receive_ns - boot_ms * NS_PER_MS
        # sliding-window minimum: drop later candidates that are no smaller, then the expired ones
        while self._candidates and self._candidates[-1][1] >= offset_ns:
            self._candidates.pop()
        self._candidates.append((receive_ns, offset_ns))
        while self._candidates[0][0] < receive_ns - self.window_ns:
            self._candidates.popleft()
        self._last_boot_ms = boot_ms
        # t = (time_boot_ms + 0.5 ms) + min(receive - time_boot_ms)
        return boot_ms * NS_PER_MS + NS_PER_MS // 2 + self._candidates[0][1]

    def went_back(self, boot_ms: int) -> bool:
        """Whether ``boot_ms`` is far before the last one (the autopilot restarted)."""
        return restarted(self._last_boot_ms, boot_ms)

    def reset(self) -> None:
        self._candidates.clear()
        self._last_boot_ms = None


class AttitudeStream:
    """Asks the autopilot for its attitude and files each sample, on our clock, in ``history``.

    Called from the link's thread only (``on_message``, ``requests_due``);
    ``history`` is what the pipeline thread reads.
    """

    def __init__(self, history: AttitudeHistory, rate_hz: float = 50.0, window_s: float = 10.0,
                 request_retry_s: float = 2.0):
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 500.0):
            raise ValueError(f"attitude rate_hz must be in [1, 500], got {rate_hz!r}")
        self.history = history
        self.rate_hz = rate_hz
        self.request_retry_s = request_retry_s
        self.clock = BootClock(window_s)
        self.on_sample: Callable[[AttitudeSample], None] | None = None   # each sample filed (the recording)
        self.received = 0
        self.request = StreamRequest(mm.mavlink2.MAVLINK_MSG_ID_ATTITUDE, rate_hz, request_retry_s)

    def on_message(self, message, receive_ns: int) -> AttitudeSample | None:
        """File an ATTITUDE or ATTITUDE_QUATERNION received at ``receive_ns``; returns the sample filed."""
        boot_ms = int(message.time_boot_ms)
        if self.clock.went_back(boot_ms):
            log.warning("link: the flight controller's clock went back (reboot?): attitude history restarted")
            self.clock.reset()
            self.history.clear()
        roll_rad, pitch_rad = _roll_pitch(message)
        if not (math.isfinite(roll_rad) and math.isfinite(pitch_rad)):
            return None
        sample = AttitudeSample(self.clock.to_monotonic_ns(boot_ms, receive_ns), roll_rad, pitch_rad)
        if self.history.add(sample):
            self.received += 1
            self.request.arrived(receive_ns)
            if self.on_sample is not None:
                self.on_sample(sample)
        return sample

    @property
    def requests(self) -> int:
        return self.request.requests

    def requests_due(self, now_s: float, target_system: int, target_component: int) -> list:
        """The SET_MESSAGE_INTERVAL command to send now, if ATTITUDE is missing or slow (else [])."""
        return self.request.due(now_s, target_system, target_component)

    def autopilot_appeared(self) -> None:
        """A flight controller was seen (again): ask at once."""
        self.request.ask_at_once()


def _roll_pitch(message) -> tuple[float, float]:
    """(roll_rad, pitch_rad) of an ATTITUDE (Euler 3-2-1) or ATTITUDE_QUATERNION (w, x, y, z)."""
    if message.get_type() == "ATTITUDE":
        return float(message.roll), float(message.pitch)
    q = [message.q1, message.q2, message.q3, message.q4]
    try:
        return frames.roll_pitch_321(frames.rotation_from_quaternion(q))
    except ValueError:
        return math.nan, math.nan
