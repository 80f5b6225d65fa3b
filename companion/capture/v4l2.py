"""A live V4L2 camera read by its own thread, reopened with backoff when it vanishes or stalls."""
from __future__ import annotations

import grp
import logging
import os
import pwd
import threading
import time
from typing import Callable

import cv2
import numpy as np

from companion.capture.source import Backoff, ThreadedSource, to_gray
from companion.types import Frame

log = logging.getLogger(__name__)


class CaptureSource(ThreadedSource):
    """A capture device read by its own thread, reopened with backoff when lost.

    open_capture: returns an opened (or failed) cv2.VideoCapture; called
        again after every loss. A device that fails to open, fails to read,
        or delivers nothing for ``stall_timeout_s`` counts as lost.
    """

    thread_name = "capture"

    def __init__(self, open_capture: Callable[[], cv2.VideoCapture], name: str,
                 stall_timeout_s: float = 2.0, backoff_initial_s: float = 0.5,
                 backoff_max_s: float = 2.0, diagnose: Callable[[], str] | None = None):
        super().__init__()
        self.name = name
        self._open_capture = open_capture
        # Why the device cannot be opened (missing, permissions), asked after a failed open.
        self._diagnose = diagnose or (lambda: "the driver refused it")
        self.stall_timeout_s = stall_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.connected = threading.Event()
        # the last image delivered, kept across reopens: a covered lens reads the same after one
        self._last_image = None
        self._said: str | None = None  # the loss last logged, until a frame comes

    def _run(self) -> None:
        backoff = Backoff(self.backoff_initial_s, self.backoff_max_s)
        index = 0
        first_attempt = True
        while not self._stop.is_set():
            if not first_attempt:
                self.counters.reopens += 1
            first_attempt = False
            capture = self._open_capture()
            if not capture.isOpened():
                capture.release()
                wait_s = backoff.next_s()
                self._cannot_open(wait_s)
                self._stop.wait(wait_s)
                continue
            log.log(logging.INFO if self.lost_reason is None else logging.DEBUG, "camera %s: opened", self.name)
            if self.lost_reason is not None:  # still lost until a frame comes (the health says no more)
                self.lost_reason = f"camera {self.name}: opened, no frame yet"
            self.connected.set()
            try:
                index, delivered, why = self._read_until_lost(capture, index)
            finally:
                capture.release()
                self.connected.clear()
            if delivered:
                backoff.reset()
            if not self._stop.is_set():
                wait_s = backoff.next_s()
                self._lost(f"camera {self.name}: {why}", "reopening", wait_s)
                self._stop.wait(wait_s)

    def _cannot_open(self, backoff_s: float) -> None:
        self._lost(f"camera {self.name}: cannot open: {self._diagnose()}", "retrying", backoff_s)

    def _lost(self, reason: str, then: str, backoff_s: float) -> None:
        """Why the camera delivers nothing, for the health (``lost_reason``) and the log: once per distinct
        reason until a frame comes, its repeats at DEBUG."""
        log.log(logging.WARNING if reason != self._said else logging.DEBUG, "%s; %s with backoff (%.1f s, up to "
                "%.0f s)", reason, then, backoff_s, self.backoff_max_s)
        self.lost_reason = self._said = reason

    def _read_until_lost(self, capture: cv2.VideoCapture, index: int) -> tuple[int, bool, str]:
        """Read frames until stopped or lost; returns (next index, any frame delivered, why it was lost).

        A frame identical to the one before is no new view (a driver handing over the same buffer again,
        or a covered lens reading one flat level; a live sensor's noise makes two captures differ): it is
        counted, not delivered, so that no pose goes out stamped now from an old image, and a camera that
        repeats itself stalls like one that delivers nothing.
        """
        delivered = False
        last_frame_ns = time.monotonic_ns()
        while not self._stop.is_set():
            grabbed = capture.grab()
            t_ns = time.monotonic_ns()
            image = capture.retrieve()[1] if grabbed else None
            gray = to_gray(image) if grabbed else None
            repeated = gray is not None and self._last_image is not None and same_image(gray, self._last_image)
            if gray is None or repeated:
                if repeated:
                    self.counters.repeated += 1
                elif grabbed:
                    self.counters.corrupt += 1
                if (time.monotonic_ns() - last_frame_ns) * 1e-9 > self.stall_timeout_s:
                    return index, delivered, (
                        f"the same image over and over for {self.stall_timeout_s:.1f} s (a frozen driver, "
                        f"or a covered lens)" if repeated else f"no frame for {self.stall_timeout_s:.1f} s")
                if not repeated:
                    self._stop.wait(0.005)
                continue
            last_frame_ns, self._last_image, self.lost_reason, self._said = t_ns, gray, None, None
            self._publish(Frame(image=gray, t_ns=t_ns, index=index))
            index += 1
            delivered = True
        return index, delivered, "stopped"


def same_image(image: np.ndarray, other: np.ndarray) -> bool:
    """Whether two frames are equal pixel for pixel (a sparse look first: two captures of a live sensor
    differ almost everywhere, so the whole frames are compared only for a repeat)."""
    return (image.shape == other.shape and np.array_equal(image[::16, ::16], other[::16, ::16])
            and np.array_equal(image, other))


def v4l2_source(device: str | int, width: int | None = None, height: int | None = None,
                fps: float | None = None, pixel_format: str | None = None,
                stall_timeout_s: float = 2.0) -> CaptureSource:
    """A V4L2 camera (``/dev/videoN`` or an index) with the requested mode.

    pixel_format: a FOURCC such as "MJPG" or "YUYV"; the driver may pick the
    closest mode it has: the opened mode is logged.
    """

    def open_capture() -> cv2.VideoCapture:
        capture = cv2.VideoCapture(device, cv2.CAP_V4L2, [
            cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(stall_timeout_s * 1000),
            cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(stall_timeout_s * 1000),
        ])
        if not capture.isOpened():
            return capture
        if pixel_format:
            capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*pixel_format))
        if width:
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps:
            capture.set(cv2.CAP_PROP_FPS, fps)
        # One driver buffer: a frame waiting in a queue is a frame of latency.
        capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        log.info("camera %s: %dx%d at %.1f fps", device, capture.get(cv2.CAP_PROP_FRAME_WIDTH),
                 capture.get(cv2.CAP_PROP_FRAME_HEIGHT), capture.get(cv2.CAP_PROP_FPS))
        return capture

    return CaptureSource(open_capture, name=str(device), stall_timeout_s=stall_timeout_s,
                         diagnose=lambda: device_problem(device))


def device_path(device: str | int) -> str:
    """The device node of a V4L2 device given as a path or an index."""
    return f"/dev/video{device}" if isinstance(device, int) or str(device).isdigit() else str(device)


def opencv_warnings(shown: bool) -> None:
    """Show OpenCV's own warnings or only its errors. Left out below debug: at every reopen of a missing
    camera OpenCV warns "can't be used to capture by name", without the cause ``device_problem`` gives."""
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_WARNING if shown else cv2.utils.logging.LOG_LEVEL_ERROR)


def device_problem(device: str | int) -> str:
    """Why a V4L2 device does not open: missing, not readable by this user (naming the
    device's group), or present and readable but refused by the driver (busy, no capture)."""
    path = device_path(device)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        return f"{path} does not exist (camera unplugged or another number? `v4l2-ctl --list-devices`)"
    except PermissionError:
        return f"permission denied on a folder of {path}"
    if not os.access(path, os.R_OK | os.W_OK):
        group = _name(grp.getgrgid, info.st_gid)
        user = _name(pwd.getpwuid, os.geteuid())
        return (f"permission denied: user {user} may not read and write {path} (group {group}, mode "
                f"{info.st_mode & 0o777:o}); add the user to group {group} (sudo usermod -aG {group} {user}; "
                f"the systemd unit: SupplementaryGroups={group})")
    return f"{path} exists and is readable, but the driver did not open it (in use by another program, or no capture device)"


def _name(lookup, number: int) -> str:
    try:
        return lookup(number)[0]
    except KeyError:
        return str(number)
