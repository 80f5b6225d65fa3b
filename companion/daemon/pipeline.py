"""The pipeline of the daemon: per frame, detect -> solve -> fuse -> publish, timing each stage.

The pose stage gets the flight controller's roll and pitch at the frame's
capture time (an ``AttitudeLookup``: the link's history, or a replay's
attitude.csv). When it is stale or missing the pose is solved without it
(``FrameRecord.attitude`` is None); the health judge says so once
(``companion.daemon.health``), and again when it comes back.

Each frame gives one ``FrameRecord``. Observers (``Pipeline.observers``) get
every frame with its record right after it was sent; they run on the pipeline
thread, so an observer only takes what it needs and hands slow work (encoding,
disk, network) to a thread of its own.
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from companion.fusion import PoseFilter, TrackLoss
from companion.geometry import frames
from companion.geometry.attitude import AttitudeLookup
from companion.geometry.pose import PoseSolution
from companion.mavlink.link import MavlinkLink
from companion.types import AttitudeSample, Detection, Estimate, Frame, PoseMeasurement

STAGES = ("detect", "pose", "fuse", "send")


@dataclass(frozen=True)
class FrameRecord:
    """What the pipeline did with one frame (times in nanoseconds).

    detections: the markers decoded in the frame.
    solution: the pose stage's decision (its ``status`` says why there is no
        pose); None when no marker was seen.
    estimate: what the filter gave to send (None while acquiring).
    t_ns: the frame's capture time; done_ns: when the pipeline finished it (both monotonic; a replay
        faster than real time stamps its frames with their recorded times, ahead of the clock).
    sent: the estimate went to the link.
    latency_ns: capture -> sent; None if nothing was sent, or the capture time is not in the past
        (a replay faster than real time).
    attitude: the flight controller's roll and pitch at the capture time
        (None: no attitude source, or it was stale or missing).
    track_loss: why the filter gave up its track at this frame (None: it did not).
    """

    index: int
    t_ns: int
    done_ns: int
    stage_ns: tuple[int, int, int, int]   # detect, pose, fuse, send
    sent: bool
    latency_ns: int | None
    detections: tuple[Detection, ...]
    solution: PoseSolution | None
    estimate: Estimate | None
    attitude: AttitudeSample | None = None
    track_loss: TrackLoss | None = None

    @property
    def markers(self) -> int:
        return len(self.detections)

    @property
    def measurement(self) -> PoseMeasurement | None:
        return None if self.solution is None else self.solution.measurement


FrameObserver = Callable[[Frame, FrameRecord], None]


@dataclass
class PipelineStats:
    """Rolling per-frame records plus totals; read by the status line and benchmarks."""

    records: collections.deque = field(default_factory=lambda: collections.deque(maxlen=2000))
    frames: int = 0
    sent: int = 0

    def add(self, record: FrameRecord) -> None:
        self.records.append(record)
        self.frames += 1
        self.sent += record.sent

    def recent(self, window_s: float, now_ns: int | None = None) -> list[FrameRecord]:
        """The records done in the ``window_s`` before ``now_ns`` (monotonic; default: when the newest was done)."""
        records = list(self.records)
        if not records:
            return []
        newest = records[-1].done_ns if now_ns is None else now_ns
        return [r for r in records if 0 <= newest - r.done_ns <= window_s * 1e9]

    def stage_table(self) -> list[tuple[str, float, float]]:
        """(stage, median ms, p99 ms) for each stage, the total and the capture->send latency."""
        records = list(self.records)
        if not records:
            return []
        per_stage = np.array([r.stage_ns for r in records], dtype=float) / 1e6
        rows = [(name, *_median_p99(per_stage[:, i])) for i, name in enumerate(STAGES)]
        rows.append(("total", *_median_p99(per_stage.sum(axis=1))))
        latencies = [r.latency_ns / 1e6 for r in records if r.latency_ns is not None]
        if latencies:
            rows.append(("capture->send", *_median_p99(np.array(latencies))))
        return rows


def _median_p99(values: np.ndarray) -> tuple[float, float]:
    return float(np.median(values)), float(np.percentile(values, 99))


class Pipeline:
    """Per frame: detect -> solve -> fuse -> publish, timing each stage."""

    def __init__(self, detector, solver, pose_filter: PoseFilter, link: MavlinkLink | None, T_map_ned: np.ndarray,
                 attitude: AttitudeLookup | None = None):
        self.detector = detector
        self.solver = solver
        self.pose_filter = pose_filter
        self.link = link
        self.T_map_ned = T_map_ned
        self.attitude = attitude
        self.stats = PipelineStats()
        self.observers: list[FrameObserver] = []
        self._corners_map: np.ndarray | None = None  # (M, 4, 3) the mapped markers' inner corners, once

    def process(self, frame: Frame) -> FrameRecord:
        t0 = time.perf_counter_ns()
        prior = self._prior()
        detections = self.detector.detect(frame.image, expected_px=self._expected_markers_px(prior, frame.image.shape))
        t1 = time.perf_counter_ns()
        attitude = self._attitude_at(frame)
        solution = self.solver.solve_detailed(detections, frame.t_ns, prior, attitude) if detections else None
        measurement = None if solution is None else solution.measurement
        t2 = time.perf_counter_ns()
        estimate = self.pose_filter.step(frame.t_ns, measurement)
        t3 = time.perf_counter_ns()
        sent = False
        if estimate is not None and self.link is not None:
            sent = self.link.publish(estimate)
        t4 = time.perf_counter_ns()
        done_ns = time.monotonic_ns()
        latency_ns = done_ns - frame.t_ns if sent and done_ns >= frame.t_ns else None
        record = FrameRecord(frame.index, frame.t_ns, done_ns, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), sent, latency_ns,
                             tuple(detections), solution, estimate, attitude, self.pose_filter.loss)
        self.stats.add(record)
        for observer in self.observers:
            observer(frame, record)
        return record

    def _prior(self) -> np.ndarray | None:
        """The fused pose as T_map_body, to help the solver pick between ambiguous fits."""
        estimate = self.stats.records[-1].estimate if self.stats.records else None
        if estimate is None:
            return None
        R = frames.rotation_from_euler_321(estimate.roll_rad, estimate.pitch_rad, estimate.yaw_rad)
        return self.T_map_ned @ frames.make_transform(R, estimate.position_ned_m)

    def _expected_markers_px(self, prior_T_map_body: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
        """(K, 4, 2) inner-square corners (TL, TR, BR, BL) of the mapped markers in view, seen from the prior
        pose (None without one, or when the frame is not the camera model's size): the detector's circles
        path then looks for occluded markers only there, once its square path found a marker."""
        camera = self.solver.camera
        if prior_T_map_body is None or tuple(shape[:2]) != (camera.height, camera.width):
            return None
        if self._corners_map is None:
            markers = list(self.solver.facility_map.markers.values())
            self._corners_map = np.stack([m.corners_map() for m in markers]) if markers else np.zeros((0, 4, 3))
        T_camera_map = camera.T_camera_body @ frames.invert_transform(prior_T_map_body)
        corners_camera = frames.transform_points(T_camera_map, self._corners_map.reshape(-1, 3)).reshape(-1, 4, 3)
        # in view: in front of the camera, and the pinhole image of every corner within the frame grown by a
        # quarter of its size on each side (further out the lens model's polynomial is no prediction)
        with np.errstate(divide="ignore", invalid="ignore"):
            pinhole_px = corners_camera[..., :2] / corners_camera[..., 2:] * camera.K[[0, 1], [0, 1]] + camera.K[:2, 2]
        size_px = np.array([camera.width, camera.height])
        in_view = ((corners_camera[..., 2] > 0) & (pinhole_px >= -0.25 * size_px).all(axis=-1)
                   & (pinhole_px <= 1.25 * size_px).all(axis=-1)).all(axis=1)
        if not in_view.any():
            return np.zeros((0, 4, 2))
        return camera.project(corners_camera[in_view].reshape(-1, 3)).reshape(-1, 4, 2)

    def _attitude_at(self, frame: Frame) -> AttitudeSample | None:
        """The attitude at the frame's capture time; None without a source or when it is stale or missing."""
        return None if self.attitude is None else self.attitude(frame)
