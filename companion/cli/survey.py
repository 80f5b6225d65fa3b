"""``companion survey SEQUENCE... --camera C --anchors A --out MAP``: a facility map from walk-throughs
(``companion.survey``)."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from companion.capture.source import SourceError
from companion.cli.output import OutputError, output_dir, output_file, removed_if_left_empty, write_failed
from companion.geometry.camera import CameraError
from companion.geometry.facility_map import MAX_MARKER_SIZE_M, MapError, load_map, write_map
from companion.survey.observations import SurveyError, check_footage, footage_camera
from companion.survey.survey import LOOSE_SD_M, MAX_CORNER_MISFIT, SurveyOptions, SurveyResult, survey


REFILM = "film them again together with mapped markers, from more than one place and closer"


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sequences", nargs="+", metavar="SEQUENCE",
                        help="walk-through: sequence folder, video file or image folder (several: walks of one site)")
    parser.add_argument("--camera",
                        help="camera file: OpenCV calibration YAML or a config with a camera section (default: the "
                             "camera each sequence folder's sequence.yaml names, as companion run --record writes it)")
    frame = parser.add_mutually_exclusive_group(required=True)
    frame.add_argument("--anchors", help="map file with the frame and at least one measured marker (anchors)")
    frame.add_argument("--map", dest="existing", help="existing map to extend: its markers are the anchors")
    parser.add_argument("--out", required=True, help="the map to write (YAML, docs/map-format.md)")
    parser.add_argument("--size-m", type=float, help="inner-square side of the markers to survey (default: the "
                                                     "anchors file's survey.sizes_m, then its default_size_m)")
    parser.add_argument("--report", metavar="DIR", help="write survey.json and survey.png into DIR")
    parser.add_argument("--fps", type=float, help="frame rate of a video or image folder without timestamps")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bars on stderr (default: when stderr is a terminal)")


def main(args) -> int:
    """0: map written; 2: the input cannot make a map (nothing written)."""
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    writing = args.out
    try:
        if args.size_m is not None and not (math.isfinite(args.size_m) and 0 < args.size_m <= MAX_MARKER_SIZE_M):
            raise SurveyError(f"--size-m must be a positive number of metres up to {MAX_MARKER_SIZE_M:g}, got "
                              f"{args.size_m:g}")
        anchors = load_map(args.anchors or args.existing)
        check_footage([Path(s) for s in args.sequences], args.fps)
        camera = footage_camera([Path(s) for s in args.sequences], args.camera)
        # where the results go, before minutes of survey work
        output_file(Path(args.out), "--out")
        with removed_if_left_empty(args.report):
            if args.report:
                output_dir(Path(args.report), "--report")
            options = SurveyOptions(size_m=args.size_m, fps=args.fps, progress=progress)
            result = survey([Path(s) for s in args.sequences], camera, anchors, options,
                            extend=args.existing is not None)
            report = ()
            if args.report:  # first: the map is written last, once everything else worked
                from companion.survey.report import write_report

                writing = args.report
                report = write_report(result, args.report)
                writing = args.out
            try:
                _write_map(result, args)
            except BaseException:
                for path in report:  # no report of a map that was not written
                    path.unlink(missing_ok=True)
                raise
    except (SurveyError, MapError, CameraError, SourceError, OutputError) as error:
        print(f"companion survey: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        return write_failed("survey", error, writing)
    print(summary(result))
    _notes(result)
    return 0


def _write_map(result: SurveyResult, args) -> None:
    header = (f"Surveyed by companion survey from {', '.join(args.sequences)}\n"
              f"with {'the map ' + args.existing if args.existing else 'the anchors ' + args.anchors}: "
              f"{sum(not s.anchor for s in result.markers)} markers surveyed.\n"
              "Each surveyed marker's note: one standard deviation of its position and angle, frames seen in.")
    write_map(result.facility_map, args.out, header)  # whole or not at all


def _length(metres: float) -> str:
    if not math.isfinite(metres):
        return "unbounded"
    return f"{metres:.1f} m" if metres >= 1 else f"{metres * 100:.0f} cm"


def summary(result: SurveyResult) -> str:
    """A table of the markers (anchors first) and one line on the frames."""
    lines = [f"{'marker':<7} {'kind':<9} {'frames':>6} {'sd_mm':>6} {'sd_deg':>6} {'rms_px':>6}"]
    for s in sorted(result.markers, key=lambda s: (not s.anchor, s.marker.id)):
        kind = "anchor" if s.anchor else "weak" if s.weakly_linked else "surveyed"
        sd = "     -      -" if s.anchor else f"{s.sd_position_m * 1000:>6.1f} {s.sd_angle_deg:>6.2f}"
        rms = f"{s.rms_px:>6.2f}" if math.isfinite(s.rms_px) else "     -"
        lines.append(f"{s.marker.symbol:<7} {kind:<9} {s.frames:>6} {sd} {rms}")
    lines.append(f"{result.frames_read} frames read, {result.frames_adjusted} adjusted, "
                 f"point noise {result.sigma_px:.3f} px")
    return "\n".join(lines)


def _notes(result: SurveyResult) -> None:
    """What the operator should know besides the table, on stderr."""
    if result.frames_skipped:
        print(f"companion survey: {result.frames_skipped} unreadable frames were skipped", file=sys.stderr)
    if result.dropped:
        names = ", ".join(f"{symbol} ({frames} frame{'s' if frames > 1 else ''})"
                          for symbol, frames in result.dropped.items())
        print(f"companion survey: not mapped, seen in fewer than 3 frames: {names}", file=sys.stderr)
    for a in result.anchors:
        if a.tied:
            print(f"companion survey: anchor {a.symbol}: the images move it by {a.position_m * 1000:.1f} mm, "
                  f"{a.angle_deg:.2f} deg", file=sys.stderr)
        else:
            print(f"companion survey: anchor {a.symbol}: not checked against the other anchors (no frame links its "
                  f"markers to theirs; film them together to check it)", file=sys.stderr)
    weak = [s.marker.symbol for s in result.markers if s.weakly_linked]
    if weak:
        print(f"companion survey: weakly linked to the anchors, need another look: {', '.join(weak)} (the images "
              f"fit another place for them nearly as well, their sd covers both; {REFILM})", file=sys.stderr)
    loose = result.loose
    if loose:
        names = ", ".join(f"{s.marker.symbol} ({_length(s.sd_position_m)})" for s in loose)
        print(f"companion survey: placed loosely (sd over {LOOSE_SD_M * 100:g} cm), need another look: {names} (the "
              f"images barely tie them to the rest; {REFILM})", file=sys.stderr)
    if result.misfit:
        named = ", ".join(f"{symbol} ({rms:.2f} px{', on a vertical wall' if wall else ''})"
                          for symbol, rms, wall in result.worst_fitting)
        print(f"companion survey: the images do not fit one map: the corners are off by {result.corner_misfit:.1f} "
              f"times the noise the detector states for them (at most {MAX_CORNER_MISFIT:g} when all is as stated); "
              f"the map may be bent by tens of centimetres with every sd still small. Check a marker of another size "
              f"(survey.sizes_m: state every size that differs), a marker taken to hang on a vertical wall that tilts "
              f"(survey.on_vertical_wall), an anchor that moved, and the camera calibration. The markers that fit "
              f"worst (RMS point error): {named}", file=sys.stderr)
    for check in result.moved:
        print(f"companion survey: marker {check.symbol} disagrees with the map by {check.position_error_m * 100:.1f} cm, "
              f"{check.angle_error_deg:.1f} deg: surveyed again", file=sys.stderr)
