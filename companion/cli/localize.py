"""``companion localize SEQUENCE``: print the unfiltered pose of every frame (``companion.localize``)."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from companion.capture.source import SourceError
from companion.geometry import frames
from companion.geometry.camera import CameraError
from companion.geometry.facility_map import FacilityMap, MapError
from companion.geometry.pose import PoseSolver
from companion.localize import (FrameResult, LocalizeError, ReplayFailed, groundtruth, localize, resources,
                                sequence_pose_params)


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
    parser.add_argument("--no-attitude", dest="attitude", action="store_false",
                        help="leave out the sequence's attitude.csv (the flight controller's roll and pitch)")


def main(args) -> int:
    """0: every frame localized (or tried); 1: the replay failed or skipped frames (the results so far are
    printed, then the error); 2: the sequence, map or camera cannot be used."""
    results = []
    if args.fps is not None and not args.fps > 0:
        print(f"companion localize: --fps must be positive, not {args.fps}", file=sys.stderr)
        return 2
    if args.max_markers is not None and args.max_markers < 1:
        print(f"companion localize: --max-markers must be 1 or more, not {args.max_markers}", file=sys.stderr)
        return 2
    try:
        facility_map, camera = resources(Path(args.sequence), args.map_path, args.camera_path)
        truth = groundtruth(Path(args.sequence))
        params = sequence_pose_params(Path(args.sequence), args.map_path, max_markers=args.max_markers)
        solver = PoseSolver(facility_map, camera, params)
        for result in localize(Path(args.sequence), solver, truth, fps=args.fps, use_attitude=args.attitude):
            results.append(result)
            print(json.dumps(result_json(result, facility_map)) if args.json else table_row(result, len(results) == 1))
    except ReplayFailed as error:
        print(summary(results), file=sys.stderr if args.json else sys.stdout)
        print(f"companion localize: {error}", file=sys.stderr)
        return 1
    except (LocalizeError, MapError, CameraError, SourceError) as error:
        print(f"companion localize: {error}", file=sys.stderr)
        return 2
    print(summary(results), file=sys.stderr if args.json else sys.stdout)
    return 0


def result_json(result: FrameResult, facility_map: FacilityMap) -> dict:
    """One JSON-ready line: status, markers, pose in map and NED, covariance, errors."""
    s = result.solution
    line = {
        "frame": result.frame, "t_ns": result.t_ns, "status": s.status, "detected_ids": list(result.detected_ids),
        "marker_ids": list(s.marker_ids), "rejected_ids": list(s.rejected_ids), "ambiguous": s.ambiguous,
        "attitude_used": s.used_attitude,
    }
    if result.attitude is not None:
        line["attitude_roll_pitch_deg"] = _round(np.degrees([result.attitude.roll_rad, result.attitude.pitch_rad]), 4)
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
    """The pose in the map frame: x, y, z and the heading (the body's forward axis, counter-clockwise from the
    map's +x seen from above, as the map file states marker headings); --json adds the NED pose sent."""
    head = f"{'frame':>6} {'t_ms':>9} {'seen':>4} {'used':>4} {'status':<20} {'x_m':>7} {'y_m':>7} {'z_m':>6} " \
           f"{'hdg_deg':>8} {'rms_px':>6} {'sd_m':>6} {'err_m':>6} {'yaw_err':>7}"
    s, m = result.solution, result.solution.measurement
    notes = (" (amb.)" if s.ambiguous and m is not None else "") + (" +att" if s.used_attitude else "")
    row = f"{result.frame:>6} {result.t_ns / 1e6:>9.1f} {len(result.detected_ids):>4} {len(s.marker_ids):>4} " \
          f"{s.status + notes:<20}"
    if m is not None:
        heading = frames.map_heading_deg(m.T_map_body[:3, 0])   # the body's forward axis
        sd_m = math.sqrt(float(np.trace(m.covariance_ned[:3, :3])))
        x, y, z = m.T_map_body[:3, 3]
        row += f" {x:>7.3f} {y:>7.3f} {z:>6.3f} {heading:>8.2f} {m.reprojection_rms_px:>6.2f} {sd_m:>6.3f}"
        if result.error_m is not None:
            row += f" {result.error_m:>6.3f} {result.yaw_error_deg:>7.2f}"
    return f"{head}\n{row}" if header else row


def summary(results: list[FrameResult]) -> str:
    """Frames with a pose, and median / max errors when ground truth was known."""
    posed = [r for r in results if r.solution.measurement is not None]
    text = f"{len(posed)}/{len(results)} frames with a pose"
    with_attitude = sum(r.solution.used_attitude for r in posed)
    if any(r.attitude is not None for r in results):
        text += f" ({with_attitude} with the flight controller's attitude)"
    errors = [r.error_m for r in posed if r.error_m is not None]
    if errors:
        yaw_errors = [r.yaw_error_deg for r in posed if r.yaw_error_deg is not None]
        text += (f"; position error median {np.median(errors):.4f} m, max {np.max(errors):.4f} m; "
                 f"yaw error median {np.median(yaw_errors):.3f} deg, max {np.max(yaw_errors):.3f} deg")
    return text
