"""``companion localize SEQUENCE``: the per-frame pose of a recorded sequence, unfiltered.

Runs the detector and the pose solver on every frame of a sequence folder
(or a video / image folder with ``--fps``) and prints one line per frame: a
table, or JSON lines with ``--json``. The map and camera default to the ones
named in the sequence's ``sequence.yaml``. When the folder has a
``groundtruth.csv`` the error against it is printed too, so the pose stage
can be checked on its own.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion import frames
from companion.camera import CameraError, CameraModel, load_camera
from companion.facility_map import FacilityMap, MapError, load_map
from companion.pose import PoseParams, PoseSolution, PoseSolver
from companion.source import ReplaySource, SourceError, open_recording, read_sequence_info

GET_TIMEOUT_S = 1.0


class LocalizeError(ValueError):
    """The sequence, map or camera cannot be used; the message says which."""


@dataclass(frozen=True)
class FrameResult:
    """One frame's outcome: recorded time, detections seen, the solver's decision,
    and the error against ground truth when known (position m, yaw deg)."""

    frame: int
    t_ns: int
    detected_ids: tuple[int, ...]
    solution: PoseSolution
    error_m: float | None = None
    yaw_error_deg: float | None = None


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sequence", help="sequence folder (sequence.yaml, frames, timestamps.csv), video or image folder")
    parser.add_argument("--map", dest="map_path", help="facility map YAML (default: the sequence's map)")
    parser.add_argument("--camera", dest="camera_path",
                        help="camera file: OpenCV calibration YAML or a config with a camera section "
                             "(default: the sequence's camera)")
    parser.add_argument("--json", action="store_true", help="print JSON lines instead of a table")
    parser.add_argument("--fps", type=float, help="frame rate of a video or image folder without timestamps")
    parser.add_argument("--max-markers", type=int, default=None,
                        help="use at most this many markers per frame (1: single-marker PnP)")


def main(args) -> int:
    try:
        facility_map, camera = resources(Path(args.sequence), args.map_path, args.camera_path)
        truth = groundtruth(Path(args.sequence))
        solver = PoseSolver(facility_map, camera, PoseParams(max_markers=args.max_markers))
        results = []
        for result in localize(Path(args.sequence), solver, truth, fps=args.fps):
            results.append(result)
            print(json.dumps(result_json(result, facility_map)) if args.json else table_row(result, len(results) == 1))
    except (LocalizeError, MapError, CameraError, SourceError) as error:
        print(f"companion localize: {error}", file=sys.stderr)
        return 2
    print(summary(results), file=sys.stderr if args.json else sys.stdout)
    return 0


# ------------------------------------------------------------------ inputs

def resources(sequence: Path, map_path: str | None, camera_path: str | None) -> tuple[FacilityMap, CameraModel]:
    """The facility map and camera: given on the command line, or from sequence.yaml."""
    info = read_sequence_info(sequence) if sequence.is_dir() else {}
    info_file = str(sequence / "sequence.yaml")
    if map_path is None:
        if "map" not in info:
            raise LocalizeError(f"{sequence}: no --map given and no 'map' in sequence.yaml")
        candidate = sequence / str(info["map"])
        map_path = str(candidate if candidate.exists() else Path(str(info["map"])))
    if camera_path is not None:
        camera = load_camera(camera_path)
    elif "camera" in info:
        camera = CameraModel.from_config(info["camera"], info_file)
    else:
        raise LocalizeError(f"{sequence}: no --camera given and no 'camera' section in sequence.yaml")
    return load_map(map_path), camera


def groundtruth(sequence: Path) -> dict[int, np.ndarray] | None:
    """T_map_body (4, 4) by frame number from groundtruth.csv, or None without one."""
    if not (sequence / "groundtruth.csv").is_file():
        return None
    truth = {}
    with open(sequence / "groundtruth.csv", newline="") as handle:
        for row in csv.DictReader(handle):
            try:
                q = [float(row[k]) for k in ("qw", "qx", "qy", "qz")]
                p = [float(row[k]) for k in ("x_m", "y_m", "z_m")]
                truth[int(row["frame"])] = frames.make_transform(frames.rotation_from_quaternion(q), p)
            except (KeyError, ValueError) as error:
                raise LocalizeError(f"{sequence / 'groundtruth.csv'}: bad row {row}: {error}") from None
    return truth


# ---------------------------------------------------------------- the loop

def localize(sequence: Path, solver: PoseSolver, truth: dict[int, np.ndarray] | None = None,
             fps: float | None = None, detector=None):
    """Yield a FrameResult per frame of the recording, in order.

    Frames come from ``companion.source`` (as fast as they are consumed);
    the recorded capture time, not the replay time, stamps each result.
    """
    if detector is None:
        from companion.detector import Detector

        detector = Detector()
    recording = open_recording(sequence, fps)
    recorded_t_ns = dict(zip(recording.frames.tolist(), recording.t_ns.tolist()))
    source = ReplaySource(recording, realtime=False)
    source.start()
    try:
        while True:
            frame = source.get(GET_TIMEOUT_S)
            if frame is None:
                if source.finished:
                    return
                continue
            t_ns = int(recorded_t_ns[frame.index])
            detections = detector.detect(frame.image)
            solution = solver.solve_detailed(detections, t_ns)
            yield frame_result(frame.index, t_ns, detections, solution, solver.facility_map, truth)
    finally:
        source.close()


def frame_result(index: int, t_ns: int, detections, solution: PoseSolution, facility_map: FacilityMap,
                 truth: dict[int, np.ndarray] | None) -> FrameResult:
    error_m = yaw_error_deg = None
    m = solution.measurement
    if m is not None and truth is not None and index in truth:
        error_m, yaw_error_deg = pose_errors(m.T_map_body, truth[index], facility_map.T_ned_map)
    return FrameResult(index, t_ns, tuple(d.id for d in detections), solution, error_m, yaw_error_deg)


def pose_errors(T_map_body: np.ndarray, T_map_body_true: np.ndarray, T_ned_map: np.ndarray) -> tuple[float, float]:
    """(position error m, absolute NED yaw error deg) of a body pose against the truth."""
    error_m = float(np.linalg.norm(T_map_body[:3, 3] - T_map_body_true[:3, 3]))
    yaw = frames.euler_321_from_rotation(T_ned_map[:3, :3] @ T_map_body[:3, :3])[2]
    yaw_true = frames.euler_321_from_rotation(T_ned_map[:3, :3] @ T_map_body_true[:3, :3])[2]
    return error_m, abs(math.degrees(math.remainder(yaw - yaw_true, 2.0 * math.pi)))


# ------------------------------------------------------------------ output

def result_json(result: FrameResult, facility_map: FacilityMap) -> dict:
    """One JSON-ready line: status, markers, pose in map and NED, covariance, errors."""
    s = result.solution
    line = {
        "frame": result.frame, "t_ns": result.t_ns, "status": s.status, "detected_ids": list(result.detected_ids),
        "marker_ids": list(s.marker_ids), "rejected_ids": list(s.rejected_ids), "ambiguous": s.ambiguous,
    }
    m = s.measurement
    if m is not None:
        roll, pitch, yaw = frames.euler_321_from_rotation(m.T_ned_body[:3, :3])
        line.update({
            "position_map_m": _round(m.T_map_body[:3, 3], 5),
            "quaternion_map_wxyz": _round(frames.quaternion_from_rotation(m.T_map_body[:3, :3]), 6),
            "position_ned_m": _round(m.T_ned_body[:3, 3], 5),
            "roll_pitch_yaw_ned_deg": _round(np.degrees([roll, pitch, yaw]), 4),
            "covariance_ned": [_round(row, 9) for row in m.covariance_ned],
            "reprojection_rms_px": round(m.reprojection_rms_px, 4),
        })
    if result.error_m is not None:
        line.update({"error_m": round(result.error_m, 5), "yaw_error_deg": round(result.yaw_error_deg, 4)})
    return line


def _round(values, digits: int) -> list[float]:
    return [round(float(v), digits) for v in np.asarray(values).reshape(-1)]


def table_row(result: FrameResult, header: bool) -> str:
    head = f"{'frame':>6} {'t_ms':>9} {'seen':>4} {'used':>4} {'status':<20} {'x_m':>7} {'y_m':>7} {'z_m':>6} " \
           f"{'yaw_deg':>8} {'rms_px':>6} {'sd_m':>6} {'err_m':>6} {'yaw_err':>7}"
    s, m = result.solution, result.solution.measurement
    row = f"{result.frame:>6} {result.t_ns / 1e6:>9.1f} {len(result.detected_ids):>4} {len(s.marker_ids):>4} " \
          f"{s.status + (' (amb.)' if s.ambiguous and m is not None else ''):<20}"
    if m is not None:
        yaw = math.degrees(frames.euler_321_from_rotation(m.T_ned_body[:3, :3])[2])
        sd_m = math.sqrt(float(np.trace(m.covariance_ned[:3, :3])))
        x, y, z = m.T_map_body[:3, 3]
        row += f" {x:>7.3f} {y:>7.3f} {z:>6.3f} {yaw:>8.2f} {m.reprojection_rms_px:>6.2f} {sd_m:>6.3f}"
        if result.error_m is not None:
            row += f" {result.error_m:>6.3f} {result.yaw_error_deg:>7.2f}"
    return f"{head}\n{row}" if header else row


def summary(results: list[FrameResult]) -> str:
    """Frames with a pose, and median / max errors when ground truth was known."""
    posed = [r for r in results if r.solution.measurement is not None]
    text = f"{len(posed)}/{len(results)} frames with a pose"
    errors = [r.error_m for r in posed if r.error_m is not None]
    if errors:
        yaw_errors = [r.yaw_error_deg for r in posed if r.yaw_error_deg is not None]
        text += (f"; position error median {np.median(errors):.4f} m, max {np.max(errors):.4f} m; "
                 f"yaw error median {np.median(yaw_errors):.3f} deg, max {np.max(yaw_errors):.3f} deg")
    return text
