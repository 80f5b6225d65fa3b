"""``companion report DIR [--map M]``: DIR/report.html about a recorded flight (``companion.report``)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from companion.capture.replay import sequence_map_path
from companion.capture.source import SourceError
from companion.cli.output import write_failed
from companion.geometry.facility_map import FacilityMap, MapError, load_map
from companion.report.flight_log import FlightLog, ReportError, read_flight


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", type=Path, help="a recording (companion run --record DIR) or any sequence "
                                                  "folder with an estimates.csv")
    parser.add_argument("--map", type=Path, default=None,
                        help="the facility map (default: the one the recording's sequence.yaml names)")
    parser.add_argument("--out", type=Path, default=None, help="the HTML file (default DIR/report.html)")


def main(args: argparse.Namespace) -> int:
    try:
        log = read_flight(args.folder)
        facility_map = report_map(log, args.map)
        from companion.report.html import write_report   # matplotlib: only once the input is good
        out = write_report(log, facility_map, args.out)
    except (ReportError, MapError) as error:
        print(f"companion report: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        return write_failed("report", error, args.out or args.folder)
    gaps = log.gaps()
    print(f"{out}: {len(log.frame)} frames, {log.duration_s:.1f} s, fresh fixes in "
          f"{100 * log.fix.mean():.0f} % of frames, {len(gaps)} gap(s) in vision")
    return 0


def report_map(log: FlightLog, map_path: Path | None) -> FacilityMap | None:
    """--map, else the map sequence.yaml names (beside the recording, or as written); None without one."""
    if map_path is not None:
        return load_map(map_path)
    try:
        named = sequence_map_path(log.folder, log.info)
    except SourceError as error:
        print(f"companion report: {error}: the track is drawn without markers", file=sys.stderr)
        return None
    if named is None:
        print("companion report: no --map and no map in sequence.yaml: the track is drawn without markers",
              file=sys.stderr)
        return None
    return load_map(named)
