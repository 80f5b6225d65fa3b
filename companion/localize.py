"""``companion localize SEQUENCE``: the per-frame pose of a recorded sequence, unfiltered.

Runs the detector and the pose solver on every frame of a sequence folder
(or a video / image folder with ``--fps``) and prints one line per frame: a
table, or JSON lines with ``--json``. The map and camera default to the ones
named in the sequence's ``sequence.yaml``; the detector reads the map's
markers (its parity and dictionary) and aligns corners through the camera's
lens. When the folder has a ``groundtruth.csv`` the error against it is
printed too, so the pose stage can be checked on its own. When it has an
``attitude.csv`` (the flight controller's roll and pitch), each frame's pose
uses the attitude at its capture time, as the daemon does (``--no-attitude``
leaves it out). The map's own error is each marker's ``sd`` where the map
states one (a surveyed map does), else (``PoseParams.map_sd_m``, ``map_sd_deg``)
what the sequence says of its map (``companion simulate`` writes 0 for
the copy it rendered from: exact), else the default of a surveyed site;
with ``--map`` the sequence's word is not about that map. Exit status: 0, or
1 when the replay failed or skipped unreadable frames (the frames read are
still printed, then a one-line error), 2 when the sequence, map or camera
cannot be used.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.geometry import frames
from companion.geometry.camera import CameraModel, load_camera
from companion.geometry.facility_map import FacilityMap, load_map
from companion.geometry.attitude import DEFAULT_MAX_AGE_S, history_of
from companion.geometry.pose import PoseParams, PoseSolution, PoseSolver
from companion.capture.replay import (ReplaySource, check_recording_path, open_recording, read_sequence_info,
                                      sequence_camera, sequence_map_path)
from companion.capture.source import SourceError
from companion.sim.simulate import POSE_COLUMNS
from companion.types import AttitudeSample


class LocalizeError(ValueError):
    """The sequence, map or camera cannot be used; the message says which."""


class ReplayFailed(LocalizeError):
    """The replay ended with an error or skipped unreadable frames: the results are incomplete."""


@dataclass(frozen=True)
class FrameResult:
    """One frame's outcome: recorded time, detections seen, the solver's decision,
    the error against ground truth when known (position m, yaw deg), and the
    flight controller's attitude at the frame (None: none recorded, or stale)."""

    frame: int
    t_ns: int
    detected_ids: tuple[int, ...]
    solution: PoseSolution
    error_m: float | None = None
    yaw_error_deg: float | None = None
    attitude: AttitudeSample | None = None


# ------------------------------------------------------------------ inputs

def resources(sequence: Path, map_path: str | None, camera_path: str | None) -> tuple[FacilityMap, CameraModel]:
    """The facility map and camera: given on the command line, or from sequence.yaml."""
    try:
        check_recording_path(sequence)
    except SourceError as error:
        raise LocalizeError(str(error)) from None
    info = read_sequence_info(sequence) if sequence.is_dir() else {}
    info_file = str(sequence / "sequence.yaml")
    if map_path is None:
        named = sequence_map_path(sequence, info) if sequence.is_dir() else None
        if named is None:
            raise LocalizeError(f"{sequence}: no --map given and no 'map' in {info_file if info else 'a sequence.yaml'}")
        map_path = str(named)
    camera = load_camera(camera_path) if camera_path is not None else sequence_camera(sequence, info)
    if camera is None:
        raise LocalizeError(f"{sequence}: no --camera given and no 'camera' section in sequence.yaml")
    return load_map(map_path), camera


MAP_ERROR_KEYS = ("map_sd_m", "map_sd_deg")


def sequence_pose_params(sequence: Path, map_path: str | None, **given) -> PoseParams:
    """Pose parameters for a sequence: ``given`` and the map's error its ``sequence.yaml`` states.

    ``map_sd_m`` and ``map_sd_deg`` in sequence.yaml say how far the markers
    are from where the sequence's own map says (0: rendered from it). With a
    map given on the command line (``map_path``), or without the keys, the
    defaults hold (a surveyed site).
    """
    info = read_sequence_info(sequence) if sequence.is_dir() and map_path is None else {}
    info_file = sequence / "sequence.yaml"
    stated = {}
    for key in MAP_ERROR_KEYS:
        if key in info:
            value = info[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
                raise LocalizeError(f"{info_file}: {key} must be a number >= 0 (the map's error), not {value!r}")
            stated[key] = float(value)
    return PoseParams(**given, **stated)


def groundtruth(sequence: Path) -> dict[int, np.ndarray] | None:
    """T_map_body (4, 4) by frame number from groundtruth.csv, or None without one."""
    path = sequence / "groundtruth.csv"
    if not path.is_file():
        return None
    truth = {}
    with open(path, newline="") as handle:
        rows = csv.DictReader(handle)
        needed = ("frame", *POSE_COLUMNS)
        missing = [column for column in needed if column not in (rows.fieldnames or ())]
        if missing:
            raise LocalizeError(f"{path}: line 1: no column {', '.join(missing)} (a header of "
                                f"{', '.join(needed)} is needed)")
        for row in rows:
            try:
                pose = [float(row[k]) for k in POSE_COLUMNS]
                truth[int(row["frame"])] = frames.make_transform(frames.rotation_from_quaternion(pose[3:]), pose[:3])
            except (TypeError, ValueError) as error:  # TypeError: a short row's missing values are None
                raise LocalizeError(f"{path}: line {rows.line_num}: bad row {row}: {error}") from None
    return truth


# ---------------------------------------------------------------- the loop

def map_detector(facility_map: FacilityMap, camera: CameraModel):
    """The detector for footage of a map's markers (its parity and dictionary, ``DetectorParams.for_footage``),
    aligning corners through the camera's lens: the survey, map check and localize use it."""
    from companion.detect.detector import Detector, DetectorParams

    return Detector(DetectorParams.for_footage(parity=facility_map.parity, dictionary=facility_map.dictionary),
                    camera=camera)


def localize(sequence: Path, solver: PoseSolver, truth: dict[int, np.ndarray] | None = None,
             fps: float | None = None, detector=None, fps_option: str = "--fps", use_attitude: bool = True,
             attitude_max_age_s: float = DEFAULT_MAX_AGE_S):
    """Yield a FrameResult per frame of the recording, in order.

    Frames come from ``companion.capture`` (as fast as they are consumed);
    the recorded capture time, not the replay time, stamps each result. The
    detector defaults to ``map_detector`` of the solver's map and camera.
    The recording's attitude (if any, and ``use_attitude``) is looked up at
    each frame's recorded time, stale beyond ``attitude_max_age_s``.
    Raises ``ReplayFailed`` at the end when the replay failed or skipped
    frames it could not read.
    """
    if detector is None:
        detector = map_detector(solver.facility_map, solver.camera)
    recording = open_recording(sequence, fps, fps_option)
    attitude = history_of(recording.attitude, attitude_max_age_s) if use_attitude and recording.attitude else None
    source = ReplaySource(recording, realtime=False)
    source.start()
    try:
        for frame in source.frames():
            problem = solver.camera.frame_size_problem(frame.image)
            if problem is not None:
                raise LocalizeError(f"{sequence}: {problem}")
            t_ns = source.recorded_t_ns(frame)
            detections = detector.detect(frame.image)
            sample = attitude.at(t_ns) if attitude is not None else None
            solution = solver.solve_detailed(detections, t_ns, attitude=sample)
            yield frame_result(frame.index, t_ns, detections, solution, solver.facility_map, truth, sample)
    finally:
        source.close()
    if source.error is not None:
        raise ReplayFailed(f"{sequence}: the replay failed: {source.error}")
    if source.counters.corrupt:
        raise ReplayFailed(f"{sequence}: {source.counters.corrupt} of {len(recording.frames)} frames could not "
                           "be read (skipped)")


def frame_result(index: int, t_ns: int, detections, solution: PoseSolution, facility_map: FacilityMap,
                 truth: dict[int, np.ndarray] | None, attitude: AttitudeSample | None = None) -> FrameResult:
    error_m = yaw_error_deg = None
    m = solution.measurement
    if m is not None and truth is not None and index in truth:
        error_m, yaw_error_deg = pose_errors(m.T_map_body, truth[index], facility_map.T_ned_map)
    return FrameResult(index, t_ns, tuple(d.id for d in detections), solution, error_m, yaw_error_deg, attitude)


def pose_errors(T_map_body: np.ndarray, T_map_body_true: np.ndarray, T_ned_map: np.ndarray) -> tuple[float, float]:
    """(position error m, absolute NED yaw error deg) of a body pose against the truth."""
    error_m = float(np.linalg.norm(T_map_body[:3, 3] - T_map_body_true[:3, 3]))
    yaw = frames.euler_321_from_rotation(T_ned_map[:3, :3] @ T_map_body[:3, :3])[2]
    yaw_true = frames.euler_321_from_rotation(T_ned_map[:3, :3] @ T_map_body_true[:3, :3])[2]
    return error_m, abs(math.degrees(math.remainder(yaw - yaw_true, 2.0 * math.pi)))


# ------------------------------------------------------------------ output
