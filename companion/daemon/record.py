"""Flight recording: what the daemon saw and did, as a sequence folder that replay reads back.

``companion run --record DIR`` (or the config's ``record`` section) adds a
:class:`Recorder` to the pipeline's observers. The folder it writes::

    DIR/video.avi        the frames the pipeline processed (FFV1 lossless, or MJPEG)
    DIR/timestamps.csv   frame,t_ns,file   one row per recorded frame (t_ns: capture time, 0 = first frame)
    DIR/estimates.csv    one row per pipeline frame: the verdict, the raw pose, what was sent, covariance
    DIR/detections.csv   one row per decoded marker: symbol, path, corrections, corners
    DIR/attitude.csv     t_ns,roll_deg,pitch_deg  the flight controller's attitude (when there is one:
                         each sample from the link; a replay's at each frame), same time base
    DIR/events.csv       frame,t_ns,level,text  the daemon's log while recording (INFO and above: every
                         STATUSTEXT is among it, in its longer form): the newest pipeline frame when
                         it was logged, and its time plus the time since that frame (blank: before
                         the first frame)
    DIR/groundtruth.csv  copied from a replayed sequence that has one (same frame numbers)
    DIR/map.yaml         a copy of the facility map
    DIR/sequence.yaml    camera, map (map.yaml), rate, counts, why the recording stopped

so that ``source: {kind: replay, path: DIR}`` replays it with no other file,
wherever the folder is copied.

The observer runs on the pipeline thread and only queues: images go through
a bounded budget (``queue_frames``); when the writer thread falls behind (a
slow disk) the image is dropped and counted, its estimate row is still
written, and the pipeline never waits. The recording stops by itself at
``max_duration_s`` or ``max_size_mb``, when the disk is nearly full (logged
once, with the reason), on a write error, before a file would pass the
process's file size limit (RLIMIT_FSIZE), or when the daemon stops; it is not
started on a disk with less than ``min_free_mb`` free. OpenCV's video writer
does not report a refused write: at the stop the video is read back for the
frames it holds whole (``avi_frames``) and timestamps.csv lists only those. A
recording that stops, whatever the reason, leaves whole rows only (a row the
disk took part of is cut off); one that holds no frame is removed. A recording
failure never stops the daemon.
"""
from __future__ import annotations

import csv
import datetime
import io
import logging
import math
import os
import queue
import resource
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from companion.capture.attitude_csv import ATTITUDE_FILE, COLUMNS as ATTITUDE_COLUMNS, attitude_row
from companion.capture.replay import SEQUENCE_FILE, TIMESTAMPS_FILE
from companion.daemon.pipeline import FrameRecord
from companion.files import write_whole
from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.types import AttitudeSample, Frame

LOGGER = "companion"   # the daemon's logger (every module's is it or a child of it)
log = logging.getLogger(LOGGER)

VIDEO_FILE = "video.avi"
ESTIMATES_FILE = "estimates.csv"
DETECTIONS_FILE = "detections.csv"
EVENTS_FILE = "events.csv"
GROUNDTRUTH_FILE = "groundtruth.csv"
MAP_FILE = "map.yaml"
# room taken at the start and given back at the stop, for the last rows and the final sequence.yaml when the
# disk filled up under the recording (another program, or faster than the checks)
RESERVE_FILE = ".reserve"
RESERVE_BYTES = 64 << 10

# codec -> what it is; both are AVI files any OpenCV/ffmpeg reads
CODECS = {"ffv1": "FFV1, lossless",
          "mjpg": "motion JPEG at record.jpeg_quality: smaller (1.4x on the bundled noisy flight), "
                  "a few grey levels off"}

# Why a frame gave no fresh vision fix, first cause first ("ok": a fix went out).
VERDICTS = ("ok", "no marker", "pose withheld", "filter gating", "link")

AXES = ("north", "east", "down", "roll", "pitch", "yaw")
AXIS_UNITS = ("m", "m", "m", "rad", "rad", "rad")
COVARIANCE_COLUMNS = tuple(f"cov_{AXES[i]}_{AXES[j]}" for i in range(6) for j in range(i, 6))
ESTIMATE_COLUMNS = (
    "frame", "t_ns", "verdict", "pose_status", "markers", "sent", "latency_ns",
    "detect_ns", "pose_ns", "fuse_ns", "send_ns",
    *(f"meas_{a}_{u}" for a, u in zip(AXES, AXIS_UNITS)),
    *(f"{a}_{u}" for a, u in zip(AXES, AXIS_UNITS)),
    "v_north_m_s", "v_east_m_s", "v_down_m_s", "tracking", "reset_counter",
    *COVARIANCE_COLUMNS,
)
EVENT_COLUMNS = ("frame", "t_ns", "level", "text")
DETECTION_COLUMNS = ("frame", "t_ns", "symbol", "id", "path", "corrected", "quality",
                     "tl_x", "tl_y", "tr_x", "tr_y", "br_x", "br_y", "bl_x", "bl_y")

# rows (estimates, detections) waiting for the writer beyond which even rows are dropped
MAX_QUEUED_ROWS = 2000
FLUSH_INTERVAL_S = 1.0
FOLDER_GONE = "the folder was removed"
DAEMON_STOPPED = "the daemon stopped"
# Kept below a file size limit (RLIMIT_FSIZE): the frame about to be written and what the video writer
# still holds (its buffer: 256 KiB for OpenCV's FFmpeg, 32 KiB for its MJPEG writer) are at most two of the
# largest steps the video's size was seen to take, at least this; and the index written on closing.
FILE_LIMIT_MIN_STEPS_BYTES = 1 << 20
FILE_LIMIT_SLACK_BYTES = 64 << 10
INDEX_BYTES_PER_FRAME = 32


class RecordError(ValueError):
    """A recording that cannot start (the folder is not empty, or cannot be written): ``problem`` names the
    folder; the message puts the key that gives it first (``record.path: ...``; ``companion run`` names the
    config file with it, or ``--record``)."""

    def __init__(self, problem: str):
        super().__init__(f"record.path: {problem}")
        self.problem = problem


@dataclass(frozen=True)
class RecordParams:
    """The ``record`` section (and ``--record DIR``).

    path: the sequence folder to write; ``{time}`` in it becomes the local
        start time (``2026-12-01T12-33-52``), so a service writes a new folder
        per run. It must not exist or be empty.
    codec: a key of ``CODECS``; jpeg_quality: 1-100, for mjpg.
    max_duration_s, max_size_mb: the recording stops (the daemon goes on) at
        whichever comes first; and when the disk has less than ``min_free_mb``
        (or two seconds of recording) left: with less at the start, it does not start.
    queue_frames: images waiting for the disk before new ones are dropped.
    """

    path: Path
    codec: str = "ffv1"
    jpeg_quality: int = 95
    max_duration_s: float = 3600.0
    max_size_mb: float = 4000.0
    min_free_mb: float = 50.0
    queue_frames: int = 30

    def __post_init__(self):
        if self.codec not in CODECS:
            raise ValueError(f"codec must be one of {', '.join(CODECS)}, got {self.codec!r}")
        if not (isinstance(self.jpeg_quality, int) and 1 <= self.jpeg_quality <= 100):
            raise ValueError(f"jpeg_quality must be an integer in 1..100, got {self.jpeg_quality!r}")
        for name in ("max_duration_s", "max_size_mb", "min_free_mb"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if not (isinstance(self.queue_frames, int) and self.queue_frames >= 1):
            raise ValueError(f"queue_frames must be an integer >= 1, got {self.queue_frames!r}")


@dataclass
class RecordCounters:
    frames: int = 0          # images written
    rows: int = 0            # estimate rows written (one per pipeline frame while recording)
    dropped_frames: int = 0  # images the writer could not keep up with (their rows are kept)
    dropped_rows: int = 0    # rows (and events) dropped because even the row queue was full
    bytes: int = 0           # size of the folder's files at the last check


def verdict(record: FrameRecord) -> str:
    """Why this frame gave no fresh vision fix, or "ok" (one of ``VERDICTS``).

    "filter gating": the pose was measured but the filter did not take it
    (it failed the gate, or the filter is still confirming a new fix).
    "link": a fresh estimate was made but not sent (no handshake yet, rate limit, send failed).
    """
    if not record.detections:
        return "no marker"
    if record.measurement is None:
        return "pose withheld"
    if record.estimate is None or not record.estimate.tracking:
        return "filter gating"
    return "ok" if record.sent else "link"


def expand_folder(path: Path, now: datetime.datetime | None = None) -> Path:
    """``path`` with ``{time}`` replaced by the local time (``%Y-%m-%dT%H-%M-%S``)."""
    stamp = (now or datetime.datetime.now()).strftime("%Y-%m-%dT%H-%M-%S")
    return Path(str(path).replace("{time}", stamp))


def estimate_row(record: FrameRecord, t0_ns: int) -> list:
    """The estimates.csv row of one pipeline frame (empty cells where there is no value)."""
    measurement, estimate = record.measurement, record.estimate
    row = [record.index, record.t_ns - t0_ns, verdict(record),
           record.solution.status if record.solution is not None else "no marker",
           record.markers, int(record.sent), "" if record.latency_ns is None else record.latency_ns,
           *record.stage_ns]
    if measurement is not None:
        roll, pitch, yaw = frames.euler_321_from_rotation(measurement.T_ned_body[:3, :3])
        row += [f"{v:.6f}" for v in measurement.T_ned_body[:3, 3]] + [f"{v:.6f}" for v in (roll, pitch, yaw)]
    else:
        row += [""] * 6
    if estimate is not None:
        row += [f"{v:.6f}" for v in estimate.position_ned_m]
        row += [f"{v:.6f}" for v in (estimate.roll_rad, estimate.pitch_rad, estimate.yaw_rad)]
        row += [f"{v:.6f}" for v in estimate.velocity_ned_m_s]
        row += [int(estimate.tracking), estimate.reset_counter]
        covariance = np.asarray(estimate.covariance_ned)
        row += [f"{covariance[i, j]:.6g}" for i in range(6) for j in range(i, 6)]
    else:
        row += [""] * (6 + 3 + 2 + len(COVARIANCE_COLUMNS))
    return row


def detection_rows(record: FrameRecord, t0_ns: int) -> list[list]:
    return [[record.index, record.t_ns - t0_ns, d.symbol, d.id, d.path, d.corrected, f"{d.quality:.3f}",
             *(f"{v:.3f}" for v in np.asarray(d.corners_px).ravel())] for d in record.detections]


class Recorder:
    """A pipeline observer that records into a sequence folder from its own writer thread.

    camera, map_path: written into sequence.yaml (the map copied beside it);
    groundtruth: a groundtruth.csv to copy (a replayed sequence's), or None;
    source: a description of the source for sequence.yaml;
    attitude_of_frames: record each frame's attitude (``FrameRecord.attitude``:
        a replay's, which has no stream of its own); otherwise the samples
        come through ``attitude`` (the link's, as they arrive).
    The daemon's log lines (the ``companion`` logger, INFO and above) come through ``event`` while it
    records (``LogToEvents``, attached from ``start`` to ``close``).
    """

    def __init__(self, params: RecordParams, camera: CameraModel, map_path: Path,
                 groundtruth: Path | None = None, source: str = "", attitude_of_frames: bool = False):
        self.params = params
        self.folder = expand_folder(params.path)
        self.camera = camera
        self.source = source
        self.attitude_of_frames = attitude_of_frames
        self.counters = RecordCounters()
        self.stop_reason: str | None = None
        self._started_utc = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        self._t0_ns: int | None = None
        self._last_t_ns: int | None = None
        self._last_attitude_t_ns: int | None = None
        # (index, t_ns, monotonic ns when it came) of the newest pipeline frame queued
        self._newest: tuple[int, int, int] | None = None
        self._log_handler = LogToEvents(self)
        self._rows: queue.Queue = queue.Queue(maxsize=MAX_QUEUED_ROWS)
        self._image_budget = threading.Semaphore(params.queue_frames)
        self._stopped = threading.Event()   # no more rows taken (limit reached, error, close)
        self._refused = False               # not started for want of room: nothing written, nothing to close
        self._finished = False
        self._said_folder_gone = False
        self._made_folder = False
        self._folder_id: tuple[int, int] | None = None
        self._file_limit = file_size_limit()
        self._video_bytes = 0   # the video's size on disk at the last check
        self._video_step = 0    # the largest growth of the video's size between two checks
        self._writer: cv2.VideoWriter | None = None
        self._files = {}
        self._csv = {}
        self._thread = threading.Thread(target=self._run, name="record", daemon=True)
        try:   # an unreadable parent makes even exists() fail (PermissionError): the same one line
            if self.folder.exists() and (not self.folder.is_dir() or any(self.folder.iterdir())):
                raise RecordError(f"{self.folder} already exists and is not an empty folder; "
                                  "choose a new one (a {time} in the path makes one per run)")
            no_room = self._room_problem()
            if no_room is not None:   # said at start(); no folder is made
                self._refused = True
                self._stop(no_room)
                return
            self._made_folder = not self.folder.exists()
            self.folder.mkdir(parents=True, exist_ok=True)
            folder = os.stat(self.folder)
            self._folder_id = (folder.st_dev, folder.st_ino)
            shutil.copyfile(map_path, self.folder / MAP_FILE)
            if groundtruth is not None and groundtruth.is_file():
                shutil.copyfile(groundtruth, self.folder / GROUNDTRUTH_FILE)
            self._open_tables()
            self._write_info()
            (self.folder / RESERVE_FILE).write_bytes(os.urandom(RESERVE_BYTES))   # random: not compressed away
        except OSError as error:
            for handle in self._files.values():
                try:
                    handle.close()
                except OSError:
                    pass
            if self._folder_id is not None:   # the folder was new or empty: what is in it is ours
                self._remove_files()
            raise RecordError(f"cannot write {self.folder}: {error.strerror or error}") from None

    def _room_problem(self) -> str | None:
        """Why the disk has no room for a recording (checked before anything is written), or None."""
        existing = self.folder
        while not existing.exists():
            existing = existing.parent
        free_mb = shutil.disk_usage(existing).free / 1e6
        if free_mb < self.params.min_free_mb:
            return (f"{free_mb:.1f} MB free on the disk of {self.folder}, less than record.min_free_mb "
                    f"({self.params.min_free_mb:g} MB)")
        if self._file_limit is not None and self._file_limit < self._file_reserve():
            return (f"a file may have at most {self._file_limit / 1e6:.2f} MB here (RLIMIT_FSIZE, ulimit -f), "
                    "too little for a video")
        return None

    def _file_reserve(self) -> int:
        """Bytes a file keeps below the file size limit (see FILE_LIMIT_MIN_STEPS_BYTES)."""
        return (max(2 * self._video_step, FILE_LIMIT_MIN_STEPS_BYTES) + FILE_LIMIT_SLACK_BYTES
                + INDEX_BYTES_PER_FRAME * (self.counters.frames + 1))

    # ------------------------------------------------------ pipeline thread

    def __call__(self, frame: Frame, record: FrameRecord) -> None:
        """Queue the frame and its record; never blocks (see the module docstring)."""
        if self._stopped.is_set():
            return
        image = frame.image if self._image_budget.acquire(blocking=False) else None
        if image is None:
            self.counters.dropped_frames += 1
        try:
            self._rows.put_nowait(("frame", image, record))
        except queue.Full:
            self.counters.dropped_rows += 1
            if image is not None:
                self._image_budget.release()
        # after its row: an event that names it is queued after it
        self._newest = (record.index, record.t_ns, time.monotonic_ns())
        if self.attitude_of_frames and record.attitude is not None:
            self.attitude(AttitudeSample(record.t_ns, record.attitude.roll_rad, record.attitude.pitch_rad))

    def attitude(self, sample: AttitudeSample) -> None:
        """Record one attitude sample of the flight controller, ``t_ns`` on the frames' (monotonic) clock;
        never blocks (the link's thread calls it for each ATTITUDE)."""
        if self._stopped.is_set():
            return
        try:
            self._rows.put_nowait(("attitude", None, sample))
        except queue.Full:
            pass

    def event(self, level: str, text: str) -> None:
        """Record one log line at the newest pipeline frame; never blocks (whichever thread logged it calls this)."""
        if self._stopped.is_set():
            return
        try:
            self._rows.put_nowait(("event", None, (self._newest, time.monotonic_ns(), level, text)))
        except queue.Full:
            self.counters.dropped_rows += 1

    # -------------------------------------------------------------- control

    def start(self) -> None:
        if self._refused:
            log.warning("recording not started: %s; the daemon goes on without it", self.stop_reason)
            return
        self._thread.start()
        logging.getLogger(LOGGER).addHandler(self._log_handler)
        log.info("recording to %s (%s, at most %.0f s or %.0f MB)", self.folder, self.params.codec,
                 self.params.max_duration_s, self.params.max_size_mb)

    def close(self) -> None:
        """Stop taking frames, write what is queued, close the files; idempotent."""
        logging.getLogger(LOGGER).removeHandler(self._log_handler)
        self._stop(DAEMON_STOPPED)
        if self._refused:
            return
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)
        elif not self._thread.ident:
            self._finish()   # never started: still leave a consistent folder

    # ---------------------------------------------------------------- writer

    def _stop(self, reason: str) -> None:
        if not self._stopped.is_set():
            self.stop_reason = reason
            self._stopped.set()

    def _run(self) -> None:
        next_flush_s = time.monotonic() + FLUSH_INTERVAL_S
        try:
            while True:
                try:
                    item = self._rows.get(timeout=0.1)
                except queue.Empty:
                    if self._stopped.is_set():
                        break
                    continue
                self._write(*item)
                if self._limit_reached():
                    break
                if time.monotonic() >= next_flush_s:
                    for handle in self._files.values():
                        handle.flush()
                    next_flush_s = time.monotonic() + FLUSH_INTERVAL_S
        except OSError as error:
            if self._folder_gone():
                self._stop(FOLDER_GONE)
                self._say_folder_gone()
            else:
                self._stop(f"write failed: {error.strerror or error}")
                log.error("recording stopped: %s (%s)", self.stop_reason, self.folder)
        finally:
            self._drain()
            self._finish()

    def _folder_gone(self) -> bool:
        """Whether the recording's folder is no longer there (removed, or replaced by another)."""
        try:
            folder = os.stat(self.folder)
        except OSError:
            return True
        return (folder.st_dev, folder.st_ino) != self._folder_id

    def _say_folder_gone(self) -> None:
        """Said once: what was recorded went with the folder; nothing more is written."""
        if not self._said_folder_gone:
            self._said_folder_gone = True
            log.error("recording stopped: %s was removed while recording; %d frames were lost with it "
                      "(the daemon goes on)", self.folder, self.counters.frames)

    def _limit_reached(self) -> bool:
        return self._stopped.is_set() and self.stop_reason != DAEMON_STOPPED

    def _write(self, kind: str, image: np.ndarray | None, payload) -> None:
        if kind == "attitude":
            self._write_attitude(payload)
            return
        if kind == "event":
            self._write_event(*payload)
            return
        record: FrameRecord = payload
        if self._t0_ns is None:
            self._t0_ns = record.t_ns
        self._csv[ESTIMATES_FILE].writerow(estimate_row(record, self._t0_ns))
        self._csv[DETECTIONS_FILE].writerows(detection_rows(record, self._t0_ns))
        self.counters.rows += 1
        if image is not None:
            try:
                self._write_image(image, record)
            finally:
                self._image_budget.release()
        self._check_limits(record.t_ns)

    def _write_attitude(self, sample: AttitudeSample) -> None:
        """One attitude.csv row; samples before the first frame have no place on its time base, and one
        not after the last written (the link's clock filter can step back) would stop replay reading it."""
        if self._t0_ns is None or (self._last_attitude_t_ns is not None and sample.t_ns <= self._last_attitude_t_ns):
            return
        self._last_attitude_t_ns = sample.t_ns
        self._csv[ATTITUDE_FILE].writerow(attitude_row(sample, self._t0_ns))

    def _write_event(self, newest: tuple[int, int, int] | None, logged_ns: int, level: str, text: str) -> None:
        self._csv[EVENTS_FILE].writerow(self._event_row(newest, logged_ns, level, text))

    def _event_row(self, newest: tuple[int, int, int] | None, logged_ns: int, level: str, text: str) -> tuple:
        """One events.csv row: the newest frame when it was logged, and on the frames' time base that frame's
        capture time plus the time since the frame came (a line logged while no frame comes, a stalled
        camera, is at its own time, not at the last frame's); blank before the first frame. One line, as every
        table's row is (a cut at the last whole line keeps whole rows)."""
        if newest is None or self._t0_ns is None:
            frame, t_ns = "", ""
        else:
            index, capture_ns, came_ns = newest
            frame, t_ns = index, capture_ns - self._t0_ns + max(logged_ns - came_ns, 0)
        return frame, t_ns, level, " ".join(text.splitlines())

    def _append_stop_event(self) -> None:
        """events.csv's last line, once the tables are whole: why the recording stopped (the log's own line
        about it comes after it stopped taking lines); left out, whole, when the disk refuses it."""
        path = self.folder / EVENTS_FILE
        line = io.StringIO()
        csv.writer(line).writerow(self._event_row(self._newest, time.monotonic_ns(),
                                                  "INFO" if self.stop_reason == DAEMON_STOPPED else "WARNING",
                                                  f"recording stopped: {self.stop_reason}"))
        try:
            size = path.stat().st_size
        except OSError:
            return
        try:
            with open(path, "ab") as handle:
                handle.write(line.getvalue().encode())
        except OSError:
            try:
                os.truncate(path, size)   # no part of a line left behind
            except OSError:
                pass

    def _write_image(self, image: np.ndarray, record: FrameRecord) -> None:
        if self._last_t_ns is not None and record.t_ns <= self._last_t_ns:
            return  # replay must see rising times; the row above still says what happened
        if self._writer is None:
            self._writer = self._open_video(image.shape[1], image.shape[0])
        if (image.shape[1], image.shape[0]) != self._video_size:
            self.counters.dropped_frames += 1
            return
        # OpenCV's MJPEG writer takes 3-channel frames (its gray mode writes garbage)
        self._writer.write(image if self.params.codec == "ffv1" else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        self._csv[TIMESTAMPS_FILE].writerow((record.index, record.t_ns - self._t0_ns, ""))
        self._last_t_ns = record.t_ns
        self.counters.frames += 1

    def _open_video(self, width: int, height: int) -> cv2.VideoWriter:
        path = str(self.folder / VIDEO_FILE)
        fps = 30.0  # nominal: timestamps.csv holds the real times
        if self.params.codec == "ffv1":
            writer = cv2.VideoWriter(path, cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), fps, (width, height),
                                     [cv2.VIDEOWRITER_PROP_IS_COLOR, 0])
        else:
            writer = cv2.VideoWriter(path, cv2.CAP_OPENCV_MJPEG, cv2.VideoWriter_fourcc(*"MJPG"), fps,
                                     (width, height))
            writer.set(cv2.VIDEOWRITER_PROP_QUALITY, self.params.jpeg_quality)
        if not writer.isOpened():
            raise OSError(f"OpenCV cannot write a {self.params.codec} video to {path}")
        self._video_size = (width, height)
        return writer

    def _check_limits(self, t_ns: int) -> None:
        """After every frame (a stat of the folder and its files, and of the disk: cheap beside the frame)."""
        duration_s = (t_ns - self._t0_ns) * 1e-9
        if self._folder_gone():
            self._stop(FOLDER_GONE)
            self._say_folder_gone()
            return
        if duration_s >= self.params.max_duration_s:
            self._stop(f"duration limit reached ({self.params.max_duration_s:g} s)")
        else:
            sizes = file_sizes(self.folder)
            self.counters.bytes = sum(sizes.values())
            video_bytes = sizes.get(VIDEO_FILE, 0)
            self._video_step = max(self._video_step, video_bytes - self._video_bytes)
            self._video_bytes = video_bytes
            largest = max(sizes, key=sizes.get)
            free_mb = shutil.disk_usage(self.folder).free / 1e6
            # keep room for the last rows, the index ffmpeg writes on closing and for the rest of the system
            reserve_mb = max(self.params.min_free_mb, 2.0 * self.counters.bytes / 1e6 / max(duration_s, 1.0))
            if self.counters.bytes >= self.params.max_size_mb * 1e6:
                self._stop(f"size limit reached ({self.params.max_size_mb:g} MB)")
            elif free_mb < reserve_mb:
                self._stop(f"disk nearly full ({free_mb:.1f} MB free, {reserve_mb:.1f} MB kept free)")
            elif self._file_limit is not None and sizes[largest] + self._file_reserve() > self._file_limit:
                # OpenCV's video writer says nothing of a write the kernel refuses: stopped before
                self._stop(f"file size limit reached ({largest} at {sizes[largest] / 1e6:.2f} MB of the "
                           f"{self._file_limit / 1e6:.2f} MB a file may have here: RLIMIT_FSIZE, ulimit -f)")
        if self._limit_reached():
            log.warning("recording stopped: %s; %d frames in %s (the daemon goes on)",
                        self.stop_reason, self.counters.frames, self.folder)

    def _drain(self) -> None:
        """Forget what is still queued after a limit or an error (it would pass the limit)."""
        while True:
            try:
                _, image, _ = self._rows.get_nowait()
            except queue.Empty:
                return
            if image is not None:
                self._image_budget.release()

    def _open_tables(self) -> None:
        headers = {TIMESTAMPS_FILE: ("frame", "t_ns", "file"), ESTIMATES_FILE: ESTIMATE_COLUMNS,
                   DETECTIONS_FILE: DETECTION_COLUMNS, ATTITUDE_FILE: ATTITUDE_COLUMNS, EVENTS_FILE: EVENT_COLUMNS}
        for name, header in headers.items():
            handle = open(self.folder / name, "w", newline="")
            self._files[name] = handle
            self._csv[name] = csv.writer(handle)
            self._csv[name].writerow(header)

    def _finish(self) -> None:
        """Close the video and the tables and leave a folder that holds only whole things (see
        ``_make_whole``); a recording that holds no frame is removed, there is nothing to replay."""
        if self._finished:
            return
        self._finished = True
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        gone = self._folder_gone()
        try:   # the room kept for what follows
            (self.folder / RESERVE_FILE).unlink(missing_ok=True)
        except OSError:
            pass
        unwritten, why = [], ""
        for name, handle in self._files.items():
            try:
                handle.close()
            except OSError as error:   # the last rows could not be flushed (disk full)
                unwritten.append(name)
                why = error.strerror or str(error)
        if gone:   # nothing to finish: what was written went with the folder
            self._stop(FOLDER_GONE)
            self._say_folder_gone()
            return
        if unwritten:
            log.error("recording: the last rows of %s could not be written (%s)", ", ".join(unwritten), why)
        try:
            self._make_whole()
            self._append_stop_event()
            if self.counters.frames == 0:
                self._remove_files()
                log.warning("recording: no frame recorded (%s); %s %s", self.stop_reason or "recording",
                            self.folder, "removed" if not self.folder.exists() else "left empty")
                return
            attitude = self.folder / ATTITUDE_FILE
            if attitude.is_file() and attitude.stat().st_size <= len(",".join(ATTITUDE_COLUMNS)) + 2:
                attitude.unlink()   # no attitude from the link: no file
            self.counters.bytes = folder_bytes(self.folder)
        except OSError as error:
            if self._folder_gone():   # removed as the recording stopped
                self._say_folder_gone()
                return
            log.error("recording: cannot read back %s: %s", self.folder, error.strerror or error)
        try:
            self._write_info()
        except OSError as error:   # the one written at the start stays: camera and map, what replay needs
            if self._folder_gone():
                self._say_folder_gone()
                return
            log.error("recording: cannot write %s: %s", self.folder / SEQUENCE_FILE, error.strerror or error)
        log.info("recorded %d frames (%d dropped) to %s: %s", self.counters.frames, self.counters.dropped_frames,
                 self.folder, self.stop_reason or "recording")

    def _make_whole(self) -> None:
        """Cut each table after its last whole line (a full disk stops a flush anywhere in a row), and
        timestamps.csv after the last frame the video holds whole: OpenCV's writer says nothing of a write
        the disk refused (full, a file size limit the checks did not foresee), the video file tells. A video
        that lost frames is the reason the recording stopped (unless a write error came first)."""
        for name in self._files:
            cut_after_last_line(self.folder / name)
        timestamps, video = self.folder / TIMESTAMPS_FILE, self.folder / VIDEO_FILE
        listed = count_rows(timestamps)
        held = avi_frames(video) if video.is_file() else 0
        if held < listed:
            keep_rows(timestamps, held)
            if not (self.stop_reason or "").startswith("write failed"):
                self.stop_reason = (f"video write failed: {VIDEO_FILE} holds {held} of the {listed} frames "
                                    "written (the disk refused the rest)")
            log.error("recording: %s holds %d of the %d frames written: the disk refused the rest (full, or a "
                      "file size limit); %s lists those %d", video, held, listed, TIMESTAMPS_FILE, held)
        self.counters.frames = min(listed, held)

    def _remove_files(self) -> None:
        """Remove what the recording wrote, and the folder if it made it (it was new or empty)."""
        for name in (VIDEO_FILE, *self._files, GROUNDTRUTH_FILE, MAP_FILE, SEQUENCE_FILE, RESERVE_FILE):
            try:
                (self.folder / name).unlink(missing_ok=True)
            except OSError:
                pass
        if self._made_folder:
            try:
                self.folder.rmdir()
            except OSError:
                pass

    def _write_info(self) -> None:
        """sequence.yaml: written at start (a crash still leaves a readable folder) and at the end."""
        t_ns = recorded_times(self.folder / TIMESTAMPS_FILE) if self.counters.frames else np.zeros(0, np.int64)
        info = {
            "generator": "companion run --record",
            "started_utc": self._started_utc,
            "source": self.source,
            "map": MAP_FILE,
            "camera": self.camera.to_config(),
            "video": VIDEO_FILE if self.counters.frames else None,
            "video_codec": self.params.codec,
            "frames": self.counters.frames,
            "fps": recorded_fps(t_ns),
            "duration_s": float(t_ns[-1] - t_ns[0]) * 1e-9 if len(t_ns) else 0.0,
            "pipeline_frames": self.counters.rows,
            "dropped_frames": self.counters.dropped_frames,
            "dropped_rows": self.counters.dropped_rows,
            "size_mb": round(self.counters.bytes / 1e6, 3),
            "stopped": self.stop_reason or "recording",
        }
        write_whole(self.folder / SEQUENCE_FILE, yaml.safe_dump(info, sort_keys=False))


class LogToEvents(logging.Handler):
    """The daemon's log lines, INFO and above, into a recording's events.csv (``Recorder.event``)."""

    def __init__(self, recorder: Recorder):
        super().__init__(logging.INFO)
        self.recorder = recorder

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.recorder.event(record.levelname, record.getMessage())
        except Exception:   # logging's own rule: a handler never raises into the code that logs
            self.handleError(record)


def recorded_times(timestamps: Path) -> np.ndarray:
    """The t_ns column of timestamps.csv."""
    with open(timestamps, newline="") as handle:
        return np.array([int(r["t_ns"]) for r in csv.DictReader(handle)], dtype=np.int64)


def recorded_fps(t_ns: np.ndarray) -> float | None:
    """Frames per second from the median spacing of the frames' times."""
    if len(t_ns) < 2:
        return None
    spacing_ns = float(np.median(np.diff(t_ns)))
    return round(1e9 / spacing_ns, 3) if spacing_ns > 0 and math.isfinite(spacing_ns) else None


def cut_after_last_line(path: Path) -> None:
    """Truncate ``path`` after its last newline: a row the disk took only part of is not left half there.
    Only the end is read; truncating takes no room on a full disk."""
    with open(path, "rb") as handle:
        size = handle.seek(0, os.SEEK_END)
        end = size
        while end > 0:
            start = max(0, end - 65536)
            handle.seek(start)
            newline = handle.read(end - start).rfind(b"\n")
            if newline >= 0:
                end = start + newline + 1
                break
            end = start
    if end < size:
        os.truncate(path, end)


def keep_rows(table: Path, rows: int) -> None:
    """Truncate a CSV file after its header line and ``rows`` rows."""
    with open(table, "rb") as handle:
        end = sum(len(line) for _, line in zip(range(rows + 1), handle))
    os.truncate(table, end)


def avi_frames(path: Path) -> int:
    """How many frames an AVI file holds whole: its video chunks (``##dc``, ``##db`` in a ``movi`` list)
    that end inside the file, in order, up to the first that does not (or is empty: a size never set). A
    writer the disk stopped leaves a file that ends inside a chunk, and RIFF and list sizes it never set
    (0, or past the end of the file): those are taken to reach the end of the file. Reads 12 bytes a chunk."""
    size = os.path.getsize(path)
    frames = 0
    with open(path, "rb") as handle:
        def walk(start: int, end: int, in_movi: bool) -> bool:   # False: the file ended inside a frame
            nonlocal frames
            position = start
            while position + 8 <= end:
                handle.seek(position)
                header = handle.read(12)
                tag, length = header[:4], int.from_bytes(header[4:8], "little")
                if tag in (b"RIFF", b"LIST") and len(header) == 12:
                    list_end = position + 8 + length
                    if length < 4 or list_end > end:
                        list_end = end
                    kind = header[8:12]
                    if kind in (b"AVI ", b"AVIX", b"movi", b"rec "):
                        if not walk(position + 12, list_end, in_movi or kind == b"movi"):
                            return False
                    position = list_end + (length & 1 if list_end < end else 0)
                    continue
                if in_movi and tag[2:4] in (b"dc", b"db"):
                    if length == 0 or position + 8 + length > size:   # OpenCV's MJPEG writer sets it last
                        return False
                    frames += 1
                position += 8 + length + (length & 1)
            return True

        walk(0, size, False)
    return frames


def count_rows(table: Path) -> int:
    """The rows of a CSV file under its header line (0 when not even the header is there)."""
    with open(table, "rb") as handle:
        return max(0, sum(1 for _ in handle) - 1)


def file_sizes(folder: Path) -> dict[str, int]:
    """Name -> size of the files in ``folder``."""
    return {p.name: p.stat().st_size for p in folder.iterdir() if p.is_file()}


def folder_bytes(folder: Path) -> int:
    return sum(file_sizes(folder).values())


def file_size_limit() -> int | None:
    """The largest file this process may write (RLIMIT_FSIZE, ``ulimit -f``), None when unlimited."""
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    return None if soft == resource.RLIM_INFINITY else soft
