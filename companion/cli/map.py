"""``companion map check SEQUENCE --map MAP [--camera C]``: find markers that moved (``companion.survey.check``)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from companion.capture.source import SourceError
from companion.geometry.camera import CameraError
from companion.geometry.facility_map import MapError, load_map
from companion.survey.check import MarkerCheck, check_map
from companion.survey.observations import SurveyError, check_footage, footage_camera


def configure_parser(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    check = sub.add_parser("check", help="replay a walk-through against a map and flag markers that moved",
                           description="Per marker seen: its pose estimated from the others against its map entry. "
                                       "Exit 1 when a marker moved.")
    check.add_argument("sequences", nargs="+", metavar="SEQUENCE",
                       help="walk-through: sequence folder, video file or image folder")
    check.add_argument("--map", dest="map_path", required=True, help="the facility map to check")
    check.add_argument("--camera",
                       help="camera file: OpenCV calibration YAML or a config with a camera section (default: the "
                            "camera a sequence folder's sequence.yaml names, as companion run --record writes it)")
    check.add_argument("--json", action="store_true", help="JSON lines instead of a table")
    check.add_argument("--fps", type=float, help="frame rate of a video or image folder without timestamps")
    check.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                       help="progress bars on stderr (default: when stderr is a terminal)")


def main(args) -> int:
    """0: every marker seen is where the map says; 1: a marker moved; 2: the input cannot be checked."""
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    try:
        facility_map = load_map(args.map_path)
        sequences = [Path(s) for s in args.sequences]
        check_footage(sequences, args.fps)
        camera = footage_camera(sequences, args.camera)
        checks = check_map(sequences, facility_map, camera, fps=args.fps, progress=progress)
    except (SurveyError, MapError, CameraError, SourceError) as error:
        print(f"companion map check: {error}", file=sys.stderr)
        return 2
    for k, check in enumerate(checks):
        print(json.dumps(check.as_json()) if args.json else table_row(check, k == 0))
    moved = [c.symbol for c in checks if c.verdict == "moved"]
    if moved:
        print(f"companion map check: moved: {', '.join(moved)}", file=sys.stderr)
    return 1 if moved else 0


def table_row(check: MarkerCheck, header: bool) -> str:
    head = f"{'marker':<7} {'frames':>6} {'error_cm':>8} {'limit_cm':>8} {'error_deg':>9} {'limit_deg':>9}  verdict"
    if check.position_error_m is None:
        row = f"{check.symbol:<7} {check.frames:>6} {'-':>8} {'-':>8} {'-':>9} {'-':>9}  {check.verdict}"
    else:
        row = (f"{check.symbol:<7} {check.frames:>6} {check.position_error_m * 100:>8.2f} "
               f"{check.position_limit_m * 100:>8.2f} {check.angle_error_deg:>9.2f} {check.angle_limit_deg:>9.2f}  "
               f"{check.verdict}")
    return f"{head}\n{row}" if header else row
