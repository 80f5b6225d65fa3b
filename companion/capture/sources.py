"""Frame sources: a live V4L2 camera, or a replay of recorded frames.

Every source runs its own thread and hands frames to the pipeline through a
one-frame mailbox (:class:`LatestFrame`): the pipeline always gets the newest
frame, never a growing queue. ``Frame.t_ns`` is the capture time on the
monotonic clock:

* camera: when the driver delivered the frame (``grab()`` returned);
* real-time replay: the frame's recorded time shifted onto the monotonic
  clock (``t_ns = start_ns + t_recorded``); the frame is handed over at that
  moment, exactly as a camera would;
* as-fast-as-possible replay: the moment the frame was read and decoded (the
  replay waits for the pipeline instead of dropping frames). Time is
  compressed, so this mode is for throughput, not for a flight controller.

Unreadable frames are skipped and counted; a camera that vanishes or stalls
is released and reopened with exponential backoff while the daemon runs on.
"""
from __future__ import annotations

import csv
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol

import cv2
import numpy as np

from companion.types import Frame
from companion.yaml_input import read_yaml

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".tif", ".tiff"}
VIDEO_SUFFIXES = {".avi", ".mp4", ".mkv", ".mov", ".webm"}
SEQUENCE_FILE = "sequence.yaml"
TIMESTAMPS_FILE = "timestamps.csv"


class SourceError(ValueError):
    """A source that cannot be opened or read as a whole (names the path)."""


@dataclass
class SourceCounters:
    captured: int = 0      # frames produced by the capture thread
    dropped: int = 0       # frames overwritten before the pipeline took them
    corrupt: int = 0       # frames that could not be read or decoded, skipped
    reopens: int = 0       # camera (re)open attempts after the first


class FrameSource(Protocol):
    counters: SourceCounters
    error: Exception | None

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


class _ThreadedSource:
    """Thread, mailbox and counters shared by the camera and the replay."""

    thread_name = "source"

    def __init__(self):
        self.counters = SourceCounters()
        self.error: Exception | None = None  # what ended the thread, if it failed
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


# ------------------------------------------------------------------ camera

class CaptureSource(_ThreadedSource):
    """A capture device read by its own thread, reopened with backoff when lost.

    open_capture: returns an opened (or failed) cv2.VideoCapture; called
        again after every loss. A device that fails to open, fails to read,
        or delivers nothing for ``stall_timeout_s`` counts as lost.
    """

    thread_name = "capture"

    def __init__(self, open_capture: Callable[[], cv2.VideoCapture], name: str,
                 stall_timeout_s: float = 2.0, backoff_initial_s: float = 0.5,
                 backoff_max_s: float = 8.0):
        super().__init__()
        self.name = name
        self._open_capture = open_capture
        self.stall_timeout_s = stall_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.connected = threading.Event()

    def _run(self) -> None:
        backoff_s = self.backoff_initial_s
        index = 0
        first_attempt = True
        while not self._stop.is_set():
            if not first_attempt:
                self.counters.reopens += 1
            first_attempt = False
            capture = self._open_capture()
            if not capture.isOpened():
                capture.release()
                log.warning("camera %s: cannot open; retrying in %.1f s", self.name, backoff_s)
                self._stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, self.backoff_max_s)
                continue
            log.info("camera %s: opened", self.name)
            self.connected.set()
            try:
                index, delivered = self._read_until_lost(capture, index)
            finally:
                capture.release()
                self.connected.clear()
            if delivered:
                backoff_s = self.backoff_initial_s
            if not self._stop.is_set():
                log.warning("camera %s: lost (no frame for %.1f s); reopening in %.1f s",
                            self.name, self.stall_timeout_s, backoff_s)
                self._stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, self.backoff_max_s)

    def _read_until_lost(self, capture: cv2.VideoCapture, index: int) -> tuple[int, bool]:
        """Read frames until stopped or lost; returns (next index, any frame delivered)."""
        delivered = False
        last_frame_ns = time.monotonic_ns()
        while not self._stop.is_set():
            grabbed = capture.grab()
            t_ns = time.monotonic_ns()
            image = capture.retrieve()[1] if grabbed else None
            gray = to_gray(image) if grabbed else None
            if gray is None:
                if grabbed:
                    self.counters.corrupt += 1
                if (time.monotonic_ns() - last_frame_ns) * 1e-9 > self.stall_timeout_s:
                    return index, delivered
                self._stop.wait(0.005)
                continue
            last_frame_ns = t_ns
            self._publish(Frame(image=gray, t_ns=t_ns, index=index))
            index += 1
            delivered = True
        return index, delivered


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

    return CaptureSource(open_capture, name=str(device), stall_timeout_s=stall_timeout_s)


# ------------------------------------------------------------------ replay

@dataclass(frozen=True)
class Recording:
    """What a replay plays: frame numbers, recorded times and where the pixels are.

    frames: (N,) frame numbers; t_ns: (N,) recorded capture times (ns, rising);
    files: N image paths, or None when ``video`` holds the frames in order.
    """

    path: Path
    frames: np.ndarray
    t_ns: np.ndarray
    files: list[Path] | None
    video: Path | None

    @property
    def period_ns(self) -> int:
        """Median spacing of the frames (the gap inserted when looping)."""
        return int(np.median(np.diff(self.t_ns))) if len(self.t_ns) > 1 else 33_333_333


def open_recording(path, fps: float | None = None) -> Recording:
    """A sequence folder (timestamps.csv), a video file, or a folder of images.

    fps: frame rate for a video or image folder without timestamps (a video's
    own rate is used when not given).
    """
    path = Path(path)
    if path.is_dir() and (path / TIMESTAMPS_FILE).exists():
        return _read_sequence_folder(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise SourceError(f"{path}: no {TIMESTAMPS_FILE} and no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        if not fps:
            raise SourceError(f"{path}: an image folder without {TIMESTAMPS_FILE} needs source.fps")
        return _evenly_spaced(path, len(files), fps, files=files, video=None)
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        capture = cv2.VideoCapture(str(path))
        count, video_fps = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), capture.get(cv2.CAP_PROP_FPS)
        capture.release()
        if count <= 0:
            raise SourceError(f"{path}: not a readable video")
        rate = fps or video_fps
        if not rate or rate <= 0:
            raise SourceError(f"{path}: the video states no frame rate; set source.fps")
        return _evenly_spaced(path, count, rate, files=None, video=path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    raise SourceError(f"{path}: not a sequence folder, image folder or video ({', '.join(sorted(VIDEO_SUFFIXES))})")


def _evenly_spaced(path: Path, count: int, fps: float, files, video) -> Recording:
    t_ns = (np.arange(count) * (1e9 / fps)).astype(np.int64)
    return Recording(path=path, frames=np.arange(count), t_ns=t_ns, files=files, video=video)


def _read_sequence_folder(folder: Path) -> Recording:
    csv_path = folder / TIMESTAMPS_FILE
    with open(csv_path, newline="") as handle:
        reader = csv.DictReader(handle)
        missing = {"frame", "t_ns", "file"} - set(reader.fieldnames or ())
        if missing:
            raise SourceError(f"{csv_path}: header lacks {', '.join(sorted(missing))} (want frame,t_ns,file)")
        rows = list(reader)
    if not rows:
        raise SourceError(f"{csv_path}: no frames")
    try:
        frames = np.array([int(r["frame"]) for r in rows])
        t_ns = np.array([int(r["t_ns"]) for r in rows], dtype=np.int64)
    except ValueError as error:
        raise SourceError(f"{csv_path}: frame and t_ns must be integers ({error})") from None
    if np.any(np.diff(t_ns) <= 0):
        raise SourceError(f"{csv_path}: t_ns must rise from row to row")
    names = [r["file"] for r in rows]
    if all(names):
        return Recording(folder, frames, t_ns, [folder / n for n in names], video=None)
    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if any(names) or not videos:
        raise SourceError(f"{csv_path}: column 'file' must name every frame, or be empty with one video in {folder}")
    return Recording(folder, frames, t_ns, None, video=videos[0])


def read_sequence_info(folder) -> dict:
    """The parsed ``sequence.yaml`` of a sequence folder ({} if there is none)."""
    path = Path(folder) / SEQUENCE_FILE
    if not path.is_file():
        return {}
    return read_yaml(path, SourceError, "sequence info")


class ReplaySource(_ThreadedSource):
    """Plays a Recording, paced in real time or as fast as the pipeline takes frames.

    ``Frame.index`` is the recording's frame number (plus the frame count of
    the recording for each completed loop), so skipped frames leave gaps.
    ``clock_offset_ns``: in real time, ``Frame.t_ns = t_recorded + clock_offset_ns``
    (set when the replay starts; the next loop adds the recording's length).
    """

    thread_name = "replay"

    def __init__(self, recording: Recording, realtime: bool = True, loop: bool = False):
        super().__init__()
        self.recording = recording
        self.realtime = realtime
        self.loop = loop
        self.clock_offset_ns: int | None = None
        self._started = threading.Event()

    def start(self) -> None:
        super().start()
        self._started.wait(timeout=5.0)

    def _run(self) -> None:
        rec = self.recording
        loop_length_ns = int(rec.t_ns[-1] - rec.t_ns[0]) + rec.period_ns
        # Start one period ahead so the first frame is decoded before it is due.
        self.clock_offset_ns = time.monotonic_ns() + rec.period_ns - int(rec.t_ns[0])
        self._started.set()
        offset_ns = self.clock_offset_ns
        frames_per_loop = int(rec.frames[-1]) + 1
        loop_count = 0
        while not self._stop.is_set():
            for image, number, recorded_t_ns, where in self._images():
                if self._stop.is_set():
                    return
                if image is None:
                    self.counters.corrupt += 1
                    log.warning("replay: %s is unreadable; skipped (%d so far)", where, self.counters.corrupt)
                    continue
                index = int(number) + loop_count * frames_per_loop
                if self.realtime:
                    t_ns = int(recorded_t_ns) + offset_ns
                    # Sleep until the frame's capture time, interruptibly.
                    if self._stop.wait(max(0.0, (t_ns - time.monotonic_ns()) * 1e-9)):
                        return
                    self._publish(Frame(image=image, t_ns=t_ns, index=index))
                else:
                    self._publish(Frame(image=image, t_ns=time.monotonic_ns(), index=index),
                                  wait_for_taker=True)
            if not self.loop:
                return
            offset_ns += loop_length_ns
            loop_count += 1

    def _images(self):
        """Yields (gray image or None if unreadable, frame number, recorded t_ns, what it was)."""
        rec = self.recording
        if rec.files is not None:
            for file, number, t_ns in zip(rec.files, rec.frames, rec.t_ns):
                yield to_gray(cv2.imread(str(file), cv2.IMREAD_GRAYSCALE)), number, t_ns, file
            return
        capture = cv2.VideoCapture(str(rec.video))
        try:
            for number, t_ns in zip(rec.frames, rec.t_ns):
                ok, image = capture.read()
                yield (to_gray(image) if ok else None), number, t_ns, f"{rec.video} frame {number}"
        finally:
            capture.release()


def replay_source(path, realtime: bool = True, loop: bool = False, fps: float | None = None) -> ReplaySource:
    """A replay of a sequence folder, video file or image folder (see ``open_recording``)."""
    return ReplaySource(open_recording(path, fps), realtime=realtime, loop=loop)
