"""Frame sources, the common part: the one-frame mailbox, the counters and the source thread.

The sources themselves: a live camera (``companion.capture.v4l2``) or a
replay of recorded frames (``companion.capture.replay``).

Every source runs its own thread and hands frames to the pipeline through a
one-frame mailbox (:class:`LatestFrame`): the pipeline always gets the newest
frame, never a growing queue. ``Frame.t_ns`` is the capture time on the
monotonic clock:

* camera: when the driver delivered the frame (``grab()`` returned);
* real-time replay: the frame's recorded time shifted onto the monotonic
  clock (``t_ns = start_ns + t_recorded``); the frame is handed over at that
  moment, exactly as a camera would;
* as-fast-as-possible replay: its recorded time shifted the same way, so the
  filter sees the flight's own motion (the replay waits for the pipeline
  instead of dropping frames, and runs ahead of the clock). The messages go
  out faster than the flight, so this mode is for throughput, not for a
  flight controller.

Unreadable frames are skipped and counted; a camera that vanishes or stalls
is released and reopened with exponential backoff (:class:`Backoff`) while
the daemon runs on.
A source that cannot deliver says why in ``lost_reason`` (None while it
delivers), which the daemon's health report shows; its log messages are
throttled (``companion.log_throttle.LogThrottle``) so that a fault that repeats every frame
never floods the log.
"""
from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from companion.types import Frame

log = logging.getLogger(__name__)


class SourceError(ValueError):
    """A source that cannot be opened or read as a whole (names the path)."""


@dataclass
class SourceCounters:
    captured: int = 0      # frames produced by the capture thread
    dropped: int = 0       # frames overwritten before the pipeline took them
    corrupt: int = 0       # frames that could not be read or decoded, skipped
    reopens: int = 0       # camera (re)open attempts after the first
    repeated: int = 0      # camera frames identical to the one before (no new view), skipped


class FrameSource(Protocol):
    counters: SourceCounters
    error: Exception | None
    lost_reason: str | None

    def start(self) -> None: ...

    def get(self, timeout_s: float) -> Frame | None: ...

    @property
    def finished(self) -> bool: ...

    def close(self) -> None: ...


class LatestFrame:
    """A one-frame mailbox between a producer thread and the pipeline.

    ``put`` replaces an unread frame (newest wins, the old one is dropped)
    unless ``wait_for_taker`` is set, when it blocks until the frame was taken.
    """

    def __init__(self):
        self._frame: Frame | None = None
        self._closed = False
        self._changed = threading.Condition()

    def put(self, frame: Frame, wait_for_taker: bool = False) -> bool:
        """Store ``frame``; True if an unread frame was overwritten."""
        with self._changed:
            if wait_for_taker:
                self._changed.wait_for(lambda: self._frame is None or self._closed)
            overwritten = self._frame is not None
            self._frame = frame
            self._changed.notify_all()
            return overwritten

    def take(self, timeout_s: float) -> Frame | None:
        """The newest unread frame, waiting up to ``timeout_s``; None if none came."""
        with self._changed:
            self._changed.wait_for(lambda: self._frame is not None or self._closed, timeout=timeout_s)
            frame, self._frame = self._frame, None
            self._changed.notify_all()
            return frame

    def close(self) -> None:
        with self._changed:
            self._closed = True
            self._changed.notify_all()


def to_gray(image: np.ndarray) -> np.ndarray | None:
    """(H, W) uint8 from a gray or BGR image; None if it is not an image."""
    if image is None or image.size == 0 or image.dtype != np.uint8:
        return None
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    return None


class Backoff:
    """The waits between attempts at what keeps failing (opening a camera, reading a replay): ``initial_s``,
    doubling up to ``max_s`` (a camera plugged back after a long outage is retried within ``max_s``);
    ``reset`` once it worked."""

    def __init__(self, initial_s: float, max_s: float):
        self.initial_s, self.max_s = initial_s, max_s
        self.wait_s = initial_s

    def next_s(self) -> float:
        """The wait before the next attempt (the one after it is twice as long, up to ``max_s``)."""
        wait_s, self.wait_s = self.wait_s, min(2 * self.wait_s, self.max_s)
        return wait_s

    def reset(self) -> None:
        self.wait_s = self.initial_s


class ThreadedSource:
    """Thread, mailbox and counters shared by the camera and the replay."""

    thread_name = "source"

    def __init__(self):
        self.counters = SourceCounters()
        self.error: Exception | None = None  # what ended the thread, if it failed
        # Why the source delivers nothing right now (device gone, files unreadable), None while it delivers.
        self.lost_reason: str | None = None
        self._mailbox = LatestFrame()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run_guarded, name=self.thread_name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def get(self, timeout_s: float) -> Frame | None:
        return self._mailbox.take(timeout_s)

    @property
    def finished(self) -> bool:
        """True once the source has nothing more to give (end of a replay)."""
        return self._done.is_set()

    def close(self) -> None:
        self._stop.set()
        self._mailbox.close()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def _publish(self, frame: Frame, wait_for_taker: bool = False) -> None:
        self.counters.captured += 1
        if self._mailbox.put(frame, wait_for_taker):
            self.counters.dropped += 1

    def _run_guarded(self) -> None:
        try:
            self._run()
        except Exception as error:
            log.exception("%s thread failed", self.thread_name)
            self.error = error
        finally:
            self._done.set()
            self._mailbox.close()

    def _run(self) -> None:
        raise NotImplementedError
