"""A recorded flight read back for the report: per-frame arrays, gaps in vision, per-marker counts.

Reads the files ``companion.daemon.record`` writes (``estimates.csv``,
``detections.csv``, ``events.csv``, ``sequence.yaml``) and, when present, the
``groundtruth.csv`` of a simulated or replayed sequence (matched by frame
number). Every error names the file, and the row and column when it is one
value.
"""
from __future__ import annotations

import collections
import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.capture.replay import SEQUENCE_FILE, read_sequence_info
from companion.capture.source import SourceError
from companion.daemon.record import (AXES, AXIS_UNITS, DETECTIONS_FILE, ESTIMATES_FILE, EVENTS_FILE,
                                     GROUNDTRUTH_FILE, VERDICTS)

# a stretch without a fresh fix is a gap when it lasts longer than this, or 3 frame periods if longer
GAP_MIN_S = 0.2
GROUNDTRUTH_NED = ("north_m", "east_m", "down_m")


class ReportError(ValueError):
    """A folder or file the report cannot use; the message names it."""


@dataclass(frozen=True)
class Gap:
    """A stretch without a fresh vision fix: from the last fix before it to the first fix after it."""

    start_s: float
    end_s: float
    frames: int
    reason: str                    # the most frequent verdict of its frames, or the frames' own absence
    reasons: dict[str, int]        # every verdict (and pose status) in it, with its frame count

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


@dataclass(frozen=True)
class MarkerCounts:
    symbol: str
    id: int
    frames: int                    # frames it was decoded in
    square: int                    # ... by its black square
    circles: int                   # ... by its corner circles
    corrected_frames: int          # frames whose read needed Reed-Solomon corrections
    corrections: int               # corrected symbols, summed


@dataclass(frozen=True)
class Event:
    """A line of the daemon's log while it recorded (events.csv): at the newest frame when it was logged, t_s
    from the first frame (frame and t_s None: before the first frame); level a logging level's name."""

    frame: int | None
    t_s: float | None
    level: str
    text: str

    @property
    def is_warning(self) -> bool:
        """WARNING or worse."""
        return self.level in ("WARNING", "ERROR", "CRITICAL")


@dataclass
class FlightLog:
    """One flight, frame by frame (N pipeline frames, times in seconds from the first frame).

    measured, estimated: (N, 6) north, east, down (m), roll, pitch, yaw (rad), NaN where there is none;
    position_sd_m: (N, 3) from the estimate's covariance diagonal; stage_ms: (N, 4) detect, pose, fuse, send.
    truth_ned_m, truth_yaw_rad: (N, 3), (N,) from groundtruth.csv by frame number, NaN where unknown.
    """

    folder: Path
    info: dict
    frame: np.ndarray
    t_s: np.ndarray
    verdict: np.ndarray
    pose_status: np.ndarray
    sent: np.ndarray
    tracking: np.ndarray
    latency_ms: np.ndarray
    stage_ms: np.ndarray
    measured: np.ndarray
    estimated: np.ndarray
    position_sd_m: np.ndarray
    markers: list[MarkerCounts] = field(default_factory=list)
    events: list[Event] | None = None   # None: the recording has no events.csv (made before it had one)
    truth_ned_m: np.ndarray | None = None
    truth_yaw_rad: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if len(self.t_s) else 0.0

    @property
    def frame_period_s(self) -> float:
        return float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else 0.0

    @property
    def fix(self) -> np.ndarray:
        """(N,) bool: a fresh vision fix went out in this frame."""
        return self.verdict == "ok"

    def gaps(self) -> list[Gap]:
        """The stretches without a fresh fix longer than ``GAP_MIN_S`` (or 3 frame periods), in time order."""
        minimum_s = max(GAP_MIN_S, 3 * self.frame_period_s)
        gaps, start = [], None
        for i, ok in enumerate(list(self.fix) + [True]):
            if not ok and start is None:
                start = i
            elif ok and start is not None:
                begin_s = self.t_s[start - 1] if start > 0 else self.t_s[0]
                end_s = self.t_s[i] if i < len(self.t_s) else self.t_s[-1]
                if end_s - begin_s > minimum_s:
                    gaps.append(self._gap(start, i, float(begin_s), float(end_s)))
                start = None
        return gaps

    def _gap(self, first: int, stop: int, start_s: float, end_s: float) -> Gap:
        reasons = collections.Counter(self.verdict[first:stop])
        reason = reasons.most_common(1)[0][0]
        detail = dict(reasons.most_common())
        withheld = collections.Counter(s for v, s in zip(self.verdict[first:stop], self.pose_status[first:stop])
                                       if v == "pose withheld")
        for status, count in withheld.most_common():
            detail[f"pose withheld: {status}"] = count
        if reason == "pose withheld" and withheld:
            reason = f"pose withheld ({withheld.most_common(1)[0][0]})"
        # a camera that delivered nothing for most of the gap is why, not the verdict of its few frames
        longest_s = float(np.diff(self.t_s[max(first - 1, 0):stop + 1]).max(initial=0.0))
        if longest_s > (end_s - start_s) / 2:
            reason = f"no frames for {longest_s:.1f} s"
        return Gap(start_s, end_s, stop - first, reason, detail)

    def errors_m(self, which: str = "estimated") -> np.ndarray:
        """(N,) position error against the ground truth (NaN where either is missing)."""
        if self.truth_ned_m is None:
            return np.full(len(self.t_s), np.nan)
        values = self.estimated if which == "estimated" else self.measured
        return np.linalg.norm(values[:, :3] - self.truth_ned_m, axis=1)

    def yaw_errors_deg(self, which: str = "estimated") -> np.ndarray:
        if self.truth_yaw_rad is None:
            return np.full(len(self.t_s), np.nan)
        values = self.estimated if which == "estimated" else self.measured
        # wrapped to [-180, 180)
        return np.degrees((values[:, 5] - self.truth_yaw_rad + math.pi) % (2 * math.pi) - math.pi)


def read_flight(folder) -> FlightLog:
    """Read a recording (or any sequence folder with an estimates.csv)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ReportError(f"{folder}: {'not a folder' if folder.exists() else 'no such folder'} (a flight "
                          "recording is a folder: `companion run --record DIR`)")
    estimates = folder / ESTIMATES_FILE
    if not estimates.is_file():
        raise ReportError(f"{folder}: no {ESTIMATES_FILE} (a flight recorded with `companion run --record "
                          f"{folder}` has one)")
    try:
        info = read_sequence_info(folder) if (folder / SEQUENCE_FILE).is_file() else {}
    except SourceError as error:
        raise ReportError(str(error)) from None
    table = _Table(estimates, ("frame", "t_ns", "verdict"))
    if not table.rows:
        raise ReportError(f"{estimates}: no frames")
    t_ns = table.integers("t_ns")
    verdicts = np.array(table.texts("verdict"))
    unknown = [i for i, v in enumerate(verdicts) if v not in VERDICTS]
    if unknown:
        raise ReportError(f"{estimates}: row {unknown[0] + 2}, column verdict: unknown value "
                          f"{str(verdicts[unknown[0]])!r} (known: {', '.join(VERDICTS)})")
    measured = np.column_stack([table.floats(f"meas_{a}_{u}") for a, u in zip(AXES, AXIS_UNITS)])
    estimated = np.column_stack([table.floats(f"{a}_{u}") for a, u in zip(AXES, AXIS_UNITS)])
    variances = np.column_stack([table.floats(f"cov_{a}_{a}") for a in AXES[:3]])
    log = FlightLog(
        folder=folder, info=info, frame=table.integers("frame"), t_s=(t_ns - t_ns[0]) * 1e-9,
        verdict=verdicts, pose_status=np.array(table.texts("pose_status")),
        sent=table.integers("sent").astype(bool), tracking=np.nan_to_num(table.floats("tracking")).astype(bool),
        latency_ms=table.floats("latency_ns") / 1e6,
        stage_ms=np.column_stack([table.floats(f"{s}_ns") for s in ("detect", "pose", "fuse", "send")]) / 1e6,
        measured=measured, estimated=estimated, position_sd_m=np.sqrt(np.clip(variances, 0, None)),
    )
    if (folder / DETECTIONS_FILE).is_file():
        log.markers = marker_counts(folder / DETECTIONS_FILE)
    if (folder / EVENTS_FILE).is_file():
        log.events = read_events(folder / EVENTS_FILE, int(t_ns[0]))
    if (folder / GROUNDTRUTH_FILE).is_file():
        log.truth_ned_m, log.truth_yaw_rad = _groundtruth(folder / GROUNDTRUTH_FILE, log.frame)
    return log


def marker_counts(path: Path) -> list[MarkerCounts]:
    """Per marker: frames decoded, by which path, with how many corrections (most seen first)."""
    table = _Table(path, ("frame", "symbol", "id", "path", "corrected"))
    ids, corrected = table.integers("id"), table.integers("corrected")
    counts = {}
    for symbol, marker_id, path_name, fixes in zip(table.texts("symbol"), ids, table.texts("path"), corrected):
        entry = counts.setdefault(int(marker_id), [symbol, 0, 0, 0, 0, 0])
        entry[1] += 1
        entry[2] += path_name == "square"
        entry[3] += path_name == "circles"
        entry[4] += fixes > 0
        entry[5] += int(fixes)
    markers = [MarkerCounts(v[0], k, *v[1:]) for k, v in counts.items()]
    return sorted(markers, key=lambda m: (-m.frames, m.id))


def read_events(path: Path, t0_ns: int) -> list[Event]:
    """events.csv; its times on estimates.csv's base (``t0_ns``: that file's first time)."""
    table = _Table(path, ("frame", "t_ns", "level", "text"))
    frames, t_ns = table.integers("frame", empty_ok=True), table.integers("t_ns", empty_ok=True)
    return [Event(int(f) if np.isfinite(f) else None, (t - t0_ns) * 1e-9 if np.isfinite(t) else None,
                  level, text)
            for f, t, level, text in zip(frames, t_ns, table.texts("level"), table.texts("text"))]


def _groundtruth(path: Path, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    table = _Table(path, ("frame", *GROUNDTRUTH_NED, "yaw_rad"))
    by_frame = {int(f): i for i, f in enumerate(table.integers("frame"))}
    ned = np.column_stack([table.floats(c) for c in GROUNDTRUTH_NED])
    yaw = table.floats("yaw_rad")
    rows = [by_frame.get(int(f), -1) for f in frames]
    truth_ned = np.array([ned[r] if r >= 0 else [np.nan] * 3 for r in rows]).reshape(-1, 3)
    truth_yaw = np.array([yaw[r] if r >= 0 else np.nan for r in rows])
    return truth_ned, truth_yaw


class _Table:
    """A CSV file's columns, with errors naming the file, row and column."""

    def __init__(self, path: Path, required: tuple[str, ...]):
        self.path = path
        try:
            with open(path, newline="") as handle:
                reader = csv.DictReader(handle)
                self.columns = set(reader.fieldnames or ())
                self.rows = list(reader)
        except (OSError, UnicodeDecodeError, csv.Error) as error:
            raise ReportError(f"{path}: cannot read: {error}") from None
        missing = [c for c in required if c not in self.columns]
        if missing:
            raise ReportError(f"{path}: missing column(s) {', '.join(missing)}")

    def texts(self, column: str) -> list[str]:
        return [row.get(column) or "" for row in self.rows]

    def floats(self, column: str) -> np.ndarray:
        """Empty cells (and an absent optional column) are NaN."""
        if column not in self.columns:
            return np.full(len(self.rows), np.nan)
        values = np.empty(len(self.rows))
        for i, row in enumerate(self.rows):
            text = row.get(column) or ""
            try:
                values[i] = float(text) if text else np.nan
            except ValueError:
                raise ReportError(f"{self.path}: row {i + 2}, column {column}: not a number: {text!r}") from None
        return values

    def integers(self, column: str, empty_ok: bool = False) -> np.ndarray:
        """int64; with ``empty_ok`` empty cells are allowed and the array is float, NaN there."""
        values = self.floats(column)
        empty = np.isnan(values) & empty_ok
        bad = np.flatnonzero(~empty & (~np.isfinite(values) | (values != np.round(values))))
        if len(bad):
            raise ReportError(f"{self.path}: row {bad[0] + 2}, column {column}: must be an integer"
                              f"{' or empty' if empty_ok else ''}, got {self.rows[bad[0]].get(column)!r}")
        return values if empty_ok else values.astype(np.int64)
