"""Pose accuracy on rendered sequences: joint PnP against single-marker PnP.

Renders (in memory, with ``companion.sim.simulate``) flights through
``maps/warehouse.yaml`` chosen to see markers at 1-6 m with the default
camera (640x480, 70 degree field of view, forward, tilted 20 degrees down),
or reads recorded sequence folders (``--sequence``). Every frame goes through
the detector once; the same detections then feed

* joint PnP: ``PoseSolver`` (all mapped markers, gates, ambiguity handling);
* single-marker PnP: ``PoseSolver`` with ``max_markers=1`` (the largest marker);
* naive IPPE: ``SOLVEPNP_IPPE_SQUARE`` on the largest marker, its best
  solution taken as is (no gates, no ambiguity handling): the baseline.

Prints per-frame position and yaw error against ground truth by number of
mapped markers seen and by range (median camera-marker distance), the
fraction of frames with a pose, the worst errors, the solve times (medians,
ratio to the naive baseline), and the issue's targets.

    PYTHONPATH=. python benchmarks/bench_pose.py [--detector rs|aruco] [--sequence DIR ...] [--fps 10]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from common import REPO, aruco_detector, aruco_found
from companion.geometry import frames
from companion.sim import simulate
from companion.sim import trajectory
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, load_map
from companion.localize import pose_errors
from companion.geometry.pose import PoseParams, PoseSolver
from companion.types import Detection

MAP_PATH = REPO / "maps" / "warehouse.yaml"
METHODS = ("joint", "single", "naive")
RANGE_BINS_M = ((1.0, 3.0), (3.0, 6.0), (6.0, math.inf))
TARGETS = "median position error <= 0.02 m at 1-3 m, <= 0.05 m at 3-6 m; median yaw error <= 0.5 deg; no pose > 0.5 m off"


# --------------------------------------------------------------- scenarios

def scenarios() -> dict[str, trajectory.Trajectory]:
    """Flights through the example warehouse covering 1-6 m (x, y, z, heading deg ccw from map +x)."""
    return {
        "approach office wall": trajectory.smooth_path([(12.0, 5.0, 1.4, 0.0), (16.6, 5.0, 1.4, 0.0)], speed_m_s=0.5),
        "approach dock wall": trajectory.smooth_path([(6.5, 9.0, 1.5, 180.0), (1.8, 9.0, 1.5, 180.0)], speed_m_s=0.5),
        "aisle 1, rack R2 side": trajectory.smooth_path([(4.0, 4.3, 1.4, 90.0), (15.0, 4.3, 1.4, 90.0)], speed_m_s=0.8),
        "aisle 2, north wall": trajectory.smooth_path([(4.0, 8.0, 1.5, 90.0), (14.5, 8.0, 1.5, 90.0)], speed_m_s=0.8),
        "aisle 0, rack R1 side": trajectory.smooth_path([(4.0, 0.9, 1.3, 90.0), (14.0, 0.9, 1.3, 90.0)], speed_m_s=0.8),
        "hover far, office wall": trajectory.hover((12.5, 1.25, 1.5), 0.0, duration_s=4.0),
        "hover near, rack R2": trajectory.hover((8.5, 5.0, 1.4), 90.0, duration_s=3.0),
    }


@dataclass
class SequenceFrames:
    """Frames with ground truth: (H, W) uint8 images, recorded t_ns, T_map_body (4, 4)."""

    name: str
    camera: CameraModel
    images: list = field(default_factory=list)
    t_ns: list = field(default_factory=list)
    T_map_body: list = field(default_factory=list)


def rendered(facility_map: FacilityMap, camera: CameraModel, fps: float) -> list[SequenceFrames]:
    world = simulate.build_world(facility_map)
    out = []
    for seed, (name, flight) in enumerate(scenarios().items()):
        simulator = simulate.Simulator(world, camera, flight, seed=seed)
        sequence = SequenceFrames(name, camera)
        for index, t_ns in enumerate(simulate.frame_times_ns(flight.duration_s, fps)):
            frame = simulator.render_frame(index, t_ns)
            sequence.images.append(frame.image)
            sequence.t_ns.append(t_ns)
            sequence.T_map_body.append(frame.T_map_body)
        out.append(sequence)
    return out


def recorded(path: Path) -> SequenceFrames:
    seq = simulate.read_sequence(path)
    sequence = SequenceFrames(path.name, CameraModel.from_config(seq.info["camera"], str(path / "sequence.yaml")))
    for (index, image), t_ns, T in zip(seq.images(), seq.t_ns, seq.T_map_body):
        sequence.images.append(image)
        sequence.t_ns.append(int(t_ns))
        sequence.T_map_body.append(T)
    return sequence


# --------------------------------------------------------------- detectors

def make_detector(name: str, camera: CameraModel):
    """The RS detector (``companion.detect.detector``, aligning corners through the camera's lens)
    or OpenCV ArUco on the same inner squares."""
    if name == "rs":
        from companion.detect.detector import Detector

        return Detector(camera=camera)
    return ArucoDetector()


class ArucoDetector:
    """OpenCV ArUco on the dictionary's ArUco view (the RS marker's inner square), sub-pixel corners."""

    def __init__(self):
        from companion.markers.dictionary import load_dictionary

        self.dictionary = load_dictionary("6x6")
        self.detector = aruco_detector(self.dictionary.aruco())

    def detect(self, gray: np.ndarray) -> list[Detection]:
        return [Detection(self.dictionary.symbols[i], i, corners, "square", 0, 1.0)
                for i, corners in aruco_found(self.detector, gray)]


# ----------------------------------------------------------------- methods

def naive_ippe(facility_map: FacilityMap, camera: CameraModel, detections: list[Detection]) -> np.ndarray | None:
    """T_map_body from the largest mapped marker's best IPPE solution, no checks."""
    mapped = [d for d in detections if d.id in facility_map.markers]
    if not mapped:
        return None
    detection = max(mapped, key=lambda d: cv2.contourArea(d.corners_px.astype(np.float32)))
    marker = facility_map.markers[detection.id]
    ok, rvec, tvec = cv2.solvePnP(marker.corners_marker(), detection.corners_px, camera.K, camera.dist,
                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok:
        return None
    T_camera_map = frames.transform_from_rotvec(rvec, tvec) @ frames.invert_transform(marker.T_map_marker)
    # T_map_body = T_map_camera T_camera_body
    return frames.invert_transform(T_camera_map) @ camera.T_camera_body


@dataclass
class FrameRecord:
    """One frame: mapped markers seen, their median range from the true camera, and per method
    (position error m, yaw error deg) or None, and solve time s."""

    seen: int
    range_m: float
    errors: dict
    seconds: dict


def evaluate(sequence: SequenceFrames, facility_map: FacilityMap, detector_name: str,
             params: PoseParams) -> list[FrameRecord]:
    camera = sequence.camera
    detector = make_detector(detector_name, camera)
    joint = PoseSolver(facility_map, camera, params)
    single = PoseSolver(facility_map, camera, replace(params, max_markers=1))
    records = []
    for image, t_ns, T_true in zip(sequence.images, sequence.t_ns, sequence.T_map_body):
        detections = detector.detect(image)
        mapped = [d for d in detections if d.id in facility_map.markers]
        camera_m = (T_true @ camera.T_body_camera)[:3, 3]
        ranges = [np.linalg.norm(facility_map.markers[d.id].T_map_marker[:3, 3] - camera_m) for d in mapped]
        errors, seconds = {}, {}
        for name, solve in (
            ("joint", lambda: _body(joint.solve(detections, t_ns))),
            ("single", lambda: _body(single.solve(detections, t_ns))),
            ("naive", lambda: naive_ippe(facility_map, camera, detections)),
        ):
            start = time.perf_counter()
            T = solve()
            seconds[name] = time.perf_counter() - start
            errors[name] = None if T is None else pose_errors(T, T_true, facility_map.T_ned_map)
        records.append(FrameRecord(len(mapped), float(np.median(ranges)) if ranges else math.nan, errors, seconds))
    return records


def _body(measurement):
    return None if measurement is None else measurement.T_map_body


# ------------------------------------------------------------------ report

def group_rows(records: list[FrameRecord]) -> list[tuple[str, list[FrameRecord]]]:
    seen = [r for r in records if r.seen > 0]
    rows = [(f"markers {k}", [r for r in seen if r.seen == k]) for k in (1, 2)]
    rows.append(("markers 3+", [r for r in seen if r.seen >= 3]))
    for lo, hi in RANGE_BINS_M:
        label = f"range {lo:g}-{hi:g} m" if math.isfinite(hi) else f"range > {lo:g} m"
        rows.append((label, [r for r in seen if lo <= r.range_m < hi]))
    rows.append(("all with markers", seen))
    return rows


def stats(records: list[FrameRecord], method: str) -> str:
    errors = [r.errors[method] for r in records if r.errors[method] is not None]
    posed = f"{len(errors) / len(records):5.0%}" if records else "    -"
    if not errors:
        return f"{posed} {'-':>7} {'-':>7} {'-':>7} {'-':>7}"
    position = np.array([e[0] for e in errors])
    yaw = np.array([e[1] for e in errors])
    return f"{posed} {np.median(position):7.3f} {np.percentile(position, 95):7.3f} {position.max():7.3f} {np.median(yaw):7.2f}"


def report(records: list[FrameRecord], sources: str, detector_name: str, params: PoseParams) -> str:
    lines = [f"bench_pose: {len(records)} frames ({sources}), detector {detector_name}",
             f"corner_sigma_px {params.corner_sigma_px}, max_position_sd_m {params.max_position_sd_m}, "
             f"max_tilt_deg {params.max_tilt_deg}", ""]
    head = "posed  med_m   p95_m   max_m  yaw_deg"
    lines.append(f"{'':<18} {'frames':>6} | {'joint PnP':<37} | {'single-marker PnP':<37} | {'naive IPPE (no gates)':<37}")
    lines.append(f"{'':<18} {'':>6} | {head:<37} | {head:<37} | {head:<37}")
    for label, rows in group_rows(records):
        cells = " | ".join(f"{stats(rows, m):<37}" for m in METHODS)
        lines.append(f"{label:<18} {len(rows):>6} | {cells}")
    lines.append("")
    for method in METHODS:
        errors = [r.errors[method][0] for r in records if r.errors[method] is not None]
        over = sum(e > 0.5 for e in errors)
        lines.append(f"{method:<7} poses > 0.5 m off: {over} of {len(errors)}; worst {max(errors, default=math.nan):.3f} m")
    lines.append("")
    naive_s = np.median([r.seconds["naive"] for r in records if r.seen > 0])
    for method in METHODS:
        t = np.median([r.seconds[method] for r in records if r.seen > 0])
        lines.append(f"solve time {method:<7} median {t * 1e3:7.3f} ms  ({t / naive_s:5.1f} x naive)")
    lines.append("")
    lines += target_lines(records)
    return "\n".join(lines)


def target_lines(records: list[FrameRecord]) -> list[str]:
    def joint_errors(lo, hi):
        return [r.errors["joint"] for r in records if r.errors["joint"] is not None and lo <= r.range_m < hi]

    near, mid, every = joint_errors(1.0, 3.0), joint_errors(3.0, 6.0), joint_errors(0.0, math.inf)
    checks = [
        ("median position error 1-3 m <= 0.02 m", near and np.median([e[0] for e in near]) <= 0.02),
        ("median position error 3-6 m <= 0.05 m", mid and np.median([e[0] for e in mid]) <= 0.05),
        ("median yaw error <= 0.5 deg", every and np.median([e[1] for e in every]) <= 0.5),
        ("no pose > 0.5 m from the truth", all(e[0] <= 0.5 for e in every)),
    ]
    return [f"target (joint): {name}: {'met' if ok else 'NOT met'}" for name, ok in checks]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detector", choices=("rs", "aruco"), default="rs")
    parser.add_argument("--sequence", action="append", type=Path, help="recorded sequence folder (repeatable)")
    parser.add_argument("--fps", type=float, default=10.0, help="frame rate of the rendered flights")
    parser.add_argument("--corner-sigma", type=float, default=PoseParams.corner_sigma_px,
                        help="PoseParams.corner_sigma_px: the detector's corner noise, px")
    parser.add_argument("--max-position-sd", type=float, default=PoseParams.max_position_sd_m,
                        help="PoseParams.max_position_sd_m, m")
    parser.add_argument("--max-tilt", type=float, default=PoseParams.max_tilt_deg,
                        help="PoseParams.max_tilt_deg: largest plausible body roll/pitch, deg")
    args = parser.parse_args(argv)
    params = PoseParams(corner_sigma_px=args.corner_sigma, max_position_sd_m=args.max_position_sd,
                        max_tilt_deg=args.max_tilt)
    facility_map = load_map(MAP_PATH)
    if args.sequence:
        sequences = [recorded(p) for p in args.sequence]
    else:
        sequences = rendered(facility_map, CameraModel.from_config(simulate.DEFAULT_CAMERA, "simulate.DEFAULT_CAMERA"), args.fps)
    records = []
    for sequence in sequences:
        records += evaluate(sequence, facility_map, args.detector, params)
    sources = ", ".join(f"{s.name}: {len(s.images)}" for s in sequences)
    print(report(records, sources, args.detector, params))
    return 0


if __name__ == "__main__":
    sys.exit(main())
