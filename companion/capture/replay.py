"""Replay of recorded frames: a sequence folder, a video file or a folder of images."""
from __future__ import annotations

import csv
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.capture.source import SourceError, ThreadedSource, to_gray
from companion.types import Frame
from companion.yaml_input import read_yaml

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm", ".webp"}


VIDEO_SUFFIXES = {".avi", ".mp4", ".mkv", ".mov", ".webm"}


SEQUENCE_FILE = "sequence.yaml"


TIMESTAMPS_FILE = "timestamps.csv"


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


def image_files(folder: Path) -> list[Path]:
    """The image files directly inside ``folder`` (by suffix, the ones OpenCV reads), sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def open_recording(path, fps: float | None = None) -> Recording:
    """A sequence folder (timestamps.csv), a video file, or a folder of images.

    fps: frame rate for a video or image folder without timestamps (a video's
    own rate is used when not given).
    """
    path = Path(path)
    if path.is_dir() and (path / TIMESTAMPS_FILE).exists():
        return _read_sequence_folder(path)
    if path.is_dir():
        files = image_files(path)
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


class ReplaySource(ThreadedSource):
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
