"""Replay of recorded frames: a sequence folder, a video file or a folder of images.

A sequence folder may also hold the flight controller's attitude
(``attitude.csv``, ``companion.capture.attitude_csv``): ``ReplaySource.attitude_lookup``
gives the pipeline each frame's roll and pitch at its recorded capture time,
as the live link gives them at the camera's.
"""
from __future__ import annotations

import csv
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.capture.attitude_csv import AttitudeFileError, sequence_attitude
from companion.capture.source import Backoff, SourceError, ThreadedSource, to_gray
from companion.log_throttle import LogThrottle
from companion.geometry.attitude import DEFAULT_MAX_AGE_S, AttitudeLookup, history_of
from companion.geometry.camera import CameraModel
from companion.types import AttitudeSample, Frame
from companion.yaml_input import read_yaml

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm", ".webp"}


VIDEO_SUFFIXES = {".avi", ".mp4", ".mkv", ".mov", ".webm"}


SEQUENCE_FILE = "sequence.yaml"


TIMESTAMPS_FILE = "timestamps.csv"


# Unreadable frames spanning this much recorded time make the replay "lost" until one reads again.
LOST_AFTER_S = 1.0


@dataclass(frozen=True)
class Recording:
    """What a replay plays: frame numbers, recorded times and where the pixels are.

    frames: (N,) frame numbers; t_ns: (N,) recorded capture times (ns, rising);
    files: N image paths, or None when ``video`` holds the frames in order;
    attitude: the flight controller's roll and pitch (``attitude.csv``, on the
    time base of ``t_ns``), or None.
    """

    path: Path
    frames: np.ndarray
    t_ns: np.ndarray
    files: list[Path] | None
    video: Path | None
    attitude: tuple[AttitudeSample, ...] | None = None

    @property
    def period_ns(self) -> int:
        """Median spacing of the frames (the gap inserted when looping)."""
        return int(np.median(np.diff(self.t_ns))) if len(self.t_ns) > 1 else 33_333_333


def image_files(folder: Path) -> list[Path]:
    """The image files directly inside ``folder`` (by suffix, the ones OpenCV reads), sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def open_recording(path, fps: float | None = None, fps_option: str = "source.fps") -> Recording:
    """A sequence folder (timestamps.csv), a video file, or a folder of images.

    fps: frame rate for a video or image folder without timestamps (a video's
    own rate is used when not given); fps_option: how the caller's user gives
    it (the config key, or a command's flag), named in the errors.
    """
    path = Path(path)
    check_recording_path(path)
    if path.is_dir() and (path / TIMESTAMPS_FILE).exists():
        return _read_sequence_folder(path)
    if path.is_dir():
        files = image_files(path)
        if not files:
            raise SourceError(f"{path}: no {TIMESTAMPS_FILE} and no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        if not fps:
            raise SourceError(f"{path}: an image folder without {TIMESTAMPS_FILE} needs {fps_option}")
        return _evenly_spaced(path, len(files), fps, files=files, video=None)
    capture = cv2.VideoCapture(str(path))
    count, video_fps = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), capture.get(cv2.CAP_PROP_FPS)
    capture.release()
    if count <= 0:
        raise SourceError(f"{path}: not a readable video")
    rate = fps or video_fps
    if not rate or rate <= 0:
        raise SourceError(f"{path}: the video states no frame rate; set {fps_option}")
    return _evenly_spaced(path, count, rate, files=None, video=path)


def check_recording_path(path) -> None:
    """SourceError when ``path`` cannot be a recording: missing, or a file that is no video (a map given
    for a sequence); a folder or a video file passes (``open_recording`` reads it)."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    if not path.is_dir() and path.suffix.lower() not in VIDEO_SUFFIXES:
        raise SourceError(f"{path}: not a sequence folder, image folder or video "
                          f"({', '.join(sorted(VIDEO_SUFFIXES))})")


def _evenly_spaced(path: Path, count: int, fps: float, files, video) -> Recording:
    t_ns = (np.arange(count) * (1e9 / fps)).astype(np.int64)
    return Recording(path=path, frames=np.arange(count), t_ns=t_ns, files=files, video=video)


def _read_sequence_folder(folder: Path) -> Recording:
    csv_path = folder / TIMESTAMPS_FILE
    try:
        with open(csv_path, newline="") as handle:
            reader = csv.DictReader(handle)
            missing = {"frame", "t_ns", "file"} - set(reader.fieldnames or ())
            if missing:
                raise SourceError(f"{csv_path}: header lacks {', '.join(sorted(missing))} (want frame,t_ns,file)")
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise SourceError(f"{csv_path}: cannot read ({getattr(error, 'strerror', None) or error}): not a "
                          "timestamps table (frame,t_ns,file)") from None
    if not rows:
        raise SourceError(f"{csv_path}: no frames")
    try:
        frames = np.array([int(r["frame"]) for r in rows])
        t_ns = np.array([int(r["t_ns"]) for r in rows], dtype=np.int64)
    except (TypeError, ValueError) as error:
        raise SourceError(f"{csv_path}: frame and t_ns must be integers ({error})") from None
    if np.any(np.diff(t_ns) <= 0):
        raise SourceError(f"{csv_path}: t_ns must rise from row to row")
    names = [r["file"] for r in rows]
    try:
        attitude = sequence_attitude(folder)
    except AttitudeFileError as error:
        raise SourceError(str(error)) from None
    attitude = tuple(attitude) if attitude is not None else None
    if all(names):
        return Recording(folder, frames, t_ns, [folder / n for n in names], video=None, attitude=attitude)
    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if any(names) or not videos:
        raise SourceError(f"{csv_path}: column 'file' must name every frame, or be empty with one video in {folder}")
    return Recording(folder, frames, t_ns, None, video=videos[0], attitude=attitude)


def read_sequence_info(folder) -> dict:
    """The parsed ``sequence.yaml`` of a sequence folder ({} if there is none)."""
    path = Path(folder) / SEQUENCE_FILE
    if not path.is_file():
        return {}
    return read_yaml(path, SourceError, "sequence info")


def sequence_camera(folder, info: dict | None = None) -> CameraModel | None:
    """The camera a sequence folder's ``sequence.yaml`` describes (its ``camera`` section: what
    ``companion run --record`` and ``companion simulate`` write), or None when it has none; CameraError
    names sequence.yaml and the key when the section is malformed."""
    info = read_sequence_info(folder) if info is None else info
    if "camera" not in info:
        return None
    return CameraModel.from_config(info["camera"], str(Path(folder) / SEQUENCE_FILE))


def sequence_map_path(folder, info: dict | None = None, way_out: str = "--map, or map: in a config") -> Path | None:
    """The facility map a sequence folder's ``sequence.yaml`` names, or None when it names none.

    The map is relative to the folder: ``companion simulate`` puts a copy in it
    (``map.yaml``), so a copied folder keeps its map. Older sequences named it
    relative to the repository they were made in (``../../maps/x.yaml``): it is
    looked for there too, and in the folders above. SourceError when named but
    found nowhere, naming sequence.yaml and the way out (``way_out``: how the command is given a map).
    """
    folder = Path(folder)
    info = read_sequence_info(folder) if info is None else info
    name = info.get("map")
    if name is None:
        return None
    if not isinstance(name, str) or not name:
        raise SourceError(f"{folder / SEQUENCE_FILE}: map: must be a path, got {name!r}")
    candidate = Path(name)
    if candidate.is_absolute():
        if candidate.is_file():
            return candidate
    else:
        for base in [folder, *folder.resolve().parents]:
            if (base / candidate).is_file():
                return base / candidate
        # an old sequence's "../../maps/x.yaml" copied elsewhere: the same path below a folder above
        tail = Path(*[part for part in candidate.parts if part != ".."])
        for base in folder.resolve().parents:
            if (base / tail).is_file():
                return base / tail
    raise SourceError(f"{folder / SEQUENCE_FILE}: map: {name} is found neither beside the sequence nor in a folder "
                      f"above it; give the map ({way_out})")


class ReplaySource(ThreadedSource):
    """Plays a Recording, paced in real time or as fast as the pipeline takes frames.

    ``Frame.index`` is the recording's frame number (plus the frame count of
    the recording for each completed loop), so skipped frames leave gaps.
    ``clock_offset_ns``: ``Frame.t_ns = t_recorded + clock_offset_ns`` at either pace
    (set when the replay starts; the next loop adds the recording's length); as
    fast as possible the frames are handed over ahead of their times.

    Unreadable frames are skipped and counted, and keep their place in time
    (a real-time replay whose files vanished waits for each frame's time as
    if it played it); the log names the first of a run and then at most one
    a few seconds. After ``LOST_AFTER_S`` of recorded time without a readable
    frame the replay is lost (``lost_reason``, logged once); a loop in which
    nothing could be read is retried after a backoff (``backoff_initial_s``
    doubling to ``backoff_max_s``), and the first readable frame ends it.
    """

    thread_name = "replay"

    def __init__(self, recording: Recording, realtime: bool = True, loop: bool = False,
                 backoff_initial_s: float = 0.5, backoff_max_s: float = 2.0):
        super().__init__()
        self.recording = recording
        self.realtime = realtime
        self.loop = loop
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.clock_offset_ns: int | None = None
        self._started = threading.Event()
        self._unreadable_log = LogThrottle(log)
        self._unreadable_run = 0  # unreadable frames in a row

    def start(self) -> None:
        super().start()
        self._started.wait(timeout=5.0)

    def frames(self, poll_s: float = 1.0):
        """Every frame of a started replay, in order, until it has finished (for offline tools)."""
        while True:
            frame = self.get(poll_s)
            if frame is not None:
                yield frame
            elif self.finished:
                return

    def recorded_t_ns(self, frame: Frame) -> int:
        """The frame's time in the recording (``t_ns`` less ``clock_offset_ns``; a loop's frames run on after
        the recording's end)."""
        return frame.t_ns - self.clock_offset_ns

    def attitude_lookup(self, max_age_s: float = DEFAULT_MAX_AGE_S) -> AttitudeLookup | None:
        """The recording's attitude at each replayed frame's recorded capture time; None without attitude.csv.

        A frame's ``index`` (loops included) names its recorded time, so the
        lookup is exact whatever the pace (real time, or as fast as possible) and
        however the loops shifted the frames' times.
        """
        rec = self.recording
        if rec.attitude is None:
            return None
        history = history_of(rec.attitude, max_age_s)
        recorded_t_ns = dict(zip(rec.frames.tolist(), rec.t_ns.tolist()))
        frames_per_loop = int(rec.frames[-1]) + 1

        def lookup(frame: Frame) -> AttitudeSample | None:
            t_ns = recorded_t_ns.get(frame.index % frames_per_loop)
            return None if t_ns is None else history.at(t_ns)

        return lookup

    def _run(self) -> None:
        rec = self.recording
        loop_length_ns = int(rec.t_ns[-1] - rec.t_ns[0]) + rec.period_ns
        # Start one period ahead so the first frame is decoded before it is due.
        self.clock_offset_ns = time.monotonic_ns() + rec.period_ns - int(rec.t_ns[0])
        self._started.set()
        offset_ns = self.clock_offset_ns
        frames_per_loop = int(rec.frames[-1]) + 1
        loop_count = 0
        backoff = Backoff(self.backoff_initial_s, self.backoff_max_s)
        while not self._stop.is_set():
            readable = 0
            for image, number, recorded_t_ns, where in self._images():
                t_ns = int(recorded_t_ns) + offset_ns
                # Sleep until the frame's capture time, interruptibly.
                if self.realtime and self._stop.wait(max(0.0, (t_ns - time.monotonic_ns()) * 1e-9)):
                    return
                if self._stop.is_set():
                    return
                if image is None:
                    self._skip_unreadable(where, rec.video if rec.files is None else Path(where))
                    continue
                self._readable_again()
                readable += 1
                index = int(number) + loop_count * frames_per_loop
                # as fast as possible, too, a frame keeps its recorded time (then ahead of the clock): the
                # filter sees the flight's own motion, a --record of it the flight's own time line
                self._publish(Frame(image=image, t_ns=t_ns, index=index), wait_for_taker=not self.realtime)
            if not self.loop:
                return
            offset_ns += loop_length_ns
            loop_count += 1
            if readable:
                backoff.reset()
                continue
            # Nothing readable in a whole loop: wait before the next try, keeping time rising.
            waited_ns = time.monotonic_ns()
            if self._stop.wait(backoff.next_s()):
                return
            offset_ns += time.monotonic_ns() - waited_ns

    def _skip_unreadable(self, where, path: Path) -> None:
        """One frame skipped (``where``: the frame; ``path``: its file, the video or the image); after
        ``LOST_AFTER_S`` of them in a row the replay is lost: its files gone (a disk removed or unmounted),
        or unreadable (the reason short enough to be read in a STATUSTEXT's 50 characters)."""
        self.counters.corrupt += 1
        self._unreadable_run += 1
        if self.lost_reason is not None:
            log.debug("replay: %s is unreadable; skipped", where)
            return
        self._unreadable_log.log(logging.WARNING, "replay: %s is unreadable; skipped (%d so far)",
                                 where, self.counters.corrupt)
        if self._unreadable_run * self.recording.period_ns >= LOST_AFTER_S * 1e9:
            self.lost_reason = (f"{path.name} missing ({path.parent})" if not path.exists() else
                                f"{self._unreadable_run} unreadable frames (the last: {where})")
            log.warning("replay: nothing readable for %.1f s of recording (%s); %s", LOST_AFTER_S, self.lost_reason,
                        "retrying, with a pause after each loop that reads nothing" if self.loop else
                        "reading on to its end")

    def _readable_again(self) -> None:
        if self.lost_reason is not None:
            log.warning("replay: frames readable again after %d unreadable ones", self._unreadable_run)
            self.lost_reason = None
        self._unreadable_run = 0

    def _images(self):
        """Yields (gray image or None if unreadable, frame number, recorded t_ns, what it was)."""
        rec = self.recording
        if rec.files is not None:
            for file, number, t_ns in zip(rec.files, rec.frames, rec.t_ns):
                yield read_gray(file), number, t_ns, file
            return
        capture = cv2.VideoCapture(str(rec.video))
        try:
            for number, t_ns in zip(rec.frames, rec.t_ns):
                ok, image = capture.read()
                yield (to_gray(image) if ok else None), number, t_ns, f"{rec.video} frame {number}"
        finally:
            capture.release()


def read_gray(path: Path) -> np.ndarray | None:
    """An image file as (H, W) uint8 gray, or None if it is missing or not an image.

    Decoded from the bytes (OpenCV's imread prints a warning of its own for every missing file).
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError:
        return None
    return to_gray(cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)) if data.size else None


def replay_source(path, realtime: bool = True, loop: bool = False, fps: float | None = None,
                  fps_option: str = "source.fps") -> ReplaySource:
    """A replay of a sequence folder, video file or image folder (see ``open_recording``)."""
    return ReplaySource(open_recording(path, fps, fps_option), realtime=realtime, loop=loop)
