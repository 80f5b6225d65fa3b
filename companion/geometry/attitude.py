"""The flight controller's recent attitude, looked up at a frame's capture time.

``AttitudeHistory`` is the one home of "roll and pitch at time t": the MAVLink
link thread (``companion.mavlink.attitude``), a replayed ``attitude.csv``
(``companion.capture.attitude_csv``) or ``companion localize`` add
``AttitudeSample`` values in time order; the pipeline asks ``at(t_ns)`` for
the attitude at a frame's capture time.

* Between two samples at most ``max_age_s`` apart, roll and pitch are
  interpolated linearly.
* After the newest sample (the sample after the frame has not arrived yet),
  the newest is held if it is at most ``max_age_s`` older than the frame.
* Otherwise the attitude is stale or missing: ``at`` returns None and the
  pose stage works without it.

Angles are body FRD relative to the local level frame, Z-Y-X Euler
(``companion.geometry.frames``). Thread-safe: one lock around a short deque.
"""
from __future__ import annotations

import collections
import math
import threading
from typing import Callable

from companion.types import AttitudeSample, Frame

DEFAULT_MAX_AGE_S = 0.1
NS_PER_S = 1_000_000_000

# What the pipeline calls for a frame's attitude: a history looked up at the
# frame's time (live), or a recording's attitude at the frame's recorded time (replay).
AttitudeLookup = Callable[[Frame], "AttitudeSample | None"]


class AttitudeHistory:
    """The last ``capacity`` attitude samples; ``at(t_ns)`` interpolates (see the module docstring)."""

    def __init__(self, max_age_s: float = DEFAULT_MAX_AGE_S, capacity: int = 256):
        if not (isinstance(max_age_s, (int, float)) and math.isfinite(max_age_s) and max_age_s > 0):
            raise ValueError(f"attitude max_age_s must be a positive number, got {max_age_s!r}")
        self.max_age_ns = int(max_age_s * NS_PER_S)
        self._samples: collections.deque[AttitudeSample] = collections.deque(maxlen=capacity)
        self._lock = threading.Lock()
        self.out_of_order = 0

    def add(self, sample: AttitudeSample) -> bool:
        """Append a sample; one not newer than the newest is dropped (False)."""
        with self._lock:
            if self._samples and sample.t_ns <= self._samples[-1].t_ns:
                self.out_of_order += 1
                return False
            self._samples.append(sample)
            return True

    def clear(self) -> None:
        """Forget every sample (the autopilot rebooted: its clock started again)."""
        with self._lock:
            self._samples.clear()

    def newest(self) -> AttitudeSample | None:
        with self._lock:
            return self._samples[-1] if self._samples else None

    def samples(self) -> list[AttitudeSample]:
        """A copy of the samples held, oldest first."""
        with self._lock:
            return list(self._samples)

    def at(self, t_ns: int) -> AttitudeSample | None:
        """Roll and pitch at ``t_ns``, or None when the attitude is stale or missing there."""
        with self._lock:
            before, after = _around(self._samples, t_ns)
        if before is None:
            # before the first sample: only a sample just after the frame will do
            if after is not None and after.t_ns - t_ns <= self.max_age_ns:
                return AttitudeSample(t_ns, after.roll_rad, after.pitch_rad)
            return None
        if after is not None and after.t_ns - before.t_ns <= self.max_age_ns:
            return _interpolated(before, after, t_ns)
        return AttitudeSample(t_ns, before.roll_rad, before.pitch_rad) if t_ns - before.t_ns <= self.max_age_ns else None

    def lookup(self, frame: Frame) -> AttitudeSample | None:
        """The attitude at the frame's capture time (an ``AttitudeLookup`` for live frames)."""
        return self.at(frame.t_ns)


def history_of(samples, max_age_s: float = DEFAULT_MAX_AGE_S) -> AttitudeHistory:
    """A history holding all these samples (time order), for a recording's attitude."""
    samples = list(samples)
    history = AttitudeHistory(max_age_s, capacity=max(len(samples), 1))
    for sample in samples:
        history.add(sample)
    return history


def _around(samples, t_ns: int) -> tuple[AttitudeSample | None, AttitudeSample | None]:
    """(newest sample at or before t_ns, oldest sample after it); either may be None.

    Frames are looked up near the newest samples, so a live history is
    searched from its end; a recording's is bisected.
    """
    n = len(samples)
    if n == 0:
        return None, None
    if samples[-1].t_ns <= t_ns:
        return samples[-1], None
    lo, hi = 0, n - 1  # invariant: samples[hi].t_ns > t_ns
    if n > 16:
        while lo < hi:
            mid = (lo + hi) // 2
            if samples[mid].t_ns > t_ns:
                hi = mid
            else:
                lo = mid + 1
    else:
        while hi > 0 and samples[hi - 1].t_ns > t_ns:
            hi -= 1
    return (samples[hi - 1] if hi > 0 else None), samples[hi]


def _interpolated(a: AttitudeSample, b: AttitudeSample, t_ns: int) -> AttitudeSample:
    # x(t) = x_a + (x_b - x_a) (t - t_a) / (t_b - t_a), angle differences wrapped to [-pi, pi]
    f = (t_ns - a.t_ns) / (b.t_ns - a.t_ns) if b.t_ns > a.t_ns else 0.0
    roll = a.roll_rad + math.remainder(b.roll_rad - a.roll_rad, 2 * math.pi) * f
    pitch = a.pitch_rad + (b.pitch_rad - a.pitch_rad) * f
    return AttitudeSample(t_ns, roll, pitch)
