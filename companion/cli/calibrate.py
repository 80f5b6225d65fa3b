"""``companion calibrate``: camera intrinsics from views of a ChArUco board (or a chessboard).

    companion calibrate IMAGES... --charuco 8x11 --square-mm 22 --marker-mm 16 --out camera.yaml
    companion calibrate --device /dev/video0 --charuco --save-views views/ --out camera.yaml
    companion calibrate board.mp4 --charuco --out camera.yaml        # the still views of a video, as --device
    companion calibrate IMAGES... --board 9x6 --square-mm 25 --out camera.yaml      # plain chessboard

Every view left out is named with its reason; the result gives the RMS
reprojection error and each coefficient's standard deviation.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import sys
import threading
from pathlib import Path

import cv2
import numpy as np

from companion.capture.replay import (IMAGE_SUFFIXES, TIMESTAMPS_FILE, VIDEO_SUFFIXES, ReplaySource, image_files,
                                      open_recording)
from companion.capture.source import SourceError
from companion.cli.output import output_dir, output_file, removed_if_left_empty, write_failed
from companion.files import write_whole
from companion.geometry.calibration import (MIN_VIEWS, PARAMETERS, Board, Calibration, CalibrationError, CaptureGoal,
                                            CharucoBoard, calibrate, capture_live, recorded_views,
                                            write_calibration)
from companion.markers.charuco import DEFAULT_DICTIONARY, CharucoError, CharucoSpec


def split_inputs(inputs: list[str]) -> tuple[list[Path], list[Path]]:
    """(image files, recordings): the images given and those in the folders given; videos and sequence
    folders (``timestamps.csv``), whose still views are picked as live capture picks them."""
    images, recordings = [], []
    for item in map(Path, inputs):
        is_sequence = item.is_dir() and (item / TIMESTAMPS_FILE).is_file()
        is_video = item.is_file() and item.suffix.lower() in VIDEO_SUFFIXES
        if is_sequence or is_video:
            recordings.append(item)
        elif item.is_dir():
            found = image_files(item)
            if not found:
                raise CalibrationError(f"{item}: no images in the folder ({', '.join(sorted(IMAGE_SUFFIXES))}), and no "
                                       f"{TIMESTAMPS_FILE} of a recording")
            images += found
        elif item.is_file():
            images.append(item)
        else:
            raise CalibrationError(f"{item}: no such file or directory")
    return images, recordings


def parse_grid(text: str) -> tuple[int, int]:
    try:
        columns, rows = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be COLUMNSxROWS, e.g. 9x6, not {text!r}") from None
    if columns < 2 or rows < 2:
        raise argparse.ArgumentTypeError("a board needs at least 2x2")
    return columns, rows


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="*",
                        help="images of the board, folders of them, or videos (and sequence folders) from which a "
                             "view is taken each time the board rests still somewhere new, as with --device")
    parser.add_argument("--device", default=None,
                        help="calibrate live from this V4L2 camera (/dev/video0): a view is taken each time the "
                             "board is held still somewhere new; stops when the goal is met (Ctrl-C: stop now)")
    target = parser.add_mutually_exclusive_group()
    target.add_argument("--charuco", nargs="?", const="8x11", type=parse_grid, metavar="COLSxROWS",
                        help="the board: ChArUco, COLSxROWS squares (the default: 8x11, as `companion markers "
                             "--charuco` prints it); partial views count")
    target.add_argument("--board", type=parse_grid, default=None, metavar="COLSxROWS",
                        help="a plain chessboard of COLSxROWS inner corners instead, seen whole in every view")
    parser.add_argument("--square-mm", type=float, default=None,
                        help="printed square side in mm (default 22 for --charuco, 25 for a chessboard)")
    parser.add_argument("--marker-mm", type=float, default=None,
                        help=f"ChArUco marker side in mm (default {CharucoSpec.marker_mm:g})")
    parser.add_argument("--aruco-dictionary", default=None,
                        help=f"OpenCV dictionary of the ChArUco markers (default {DEFAULT_DICTIONARY})")
    parser.add_argument("--out", type=Path, default=Path("camera.yaml"),
                        help="output calibration YAML (default camera.yaml)")
    live = parser.add_argument_group("live capture (--device only; --save-views also for videos)")
    live.add_argument("--save-views", type=Path, default=None, metavar="DIR",
                      help="save the views taken (live or from videos) as PNGs (to calibrate again from the folder)")
    live.add_argument("--min-views", type=int, default=None,
                      help=f"views before stopping, {MIN_VIEWS} to {CaptureGoal.max_views} "
                           f"(default {CaptureGoal.min_views})")
    live.add_argument("--coverage", type=float, default=None,
                      help=f"share of the image the corners must cover, more than 0 and at most 1 "
                           f"(default {CaptureGoal.coverage:g})")
    live.add_argument("--width", type=int, default=None, help="camera mode width (pixels)")
    live.add_argument("--height", type=int, default=None, help="camera mode height (pixels)")


def main(args: argparse.Namespace) -> int:
    try:
        check_options(args)
        board = make_board(args)
        # where the results go, before the work, not after it
        output_file(args.out, "--out")
        with removed_if_left_empty(args.save_views):
            if args.save_views is not None:
                output_dir(args.save_views, "--save-views")
            if args.device is not None:
                calibration, views = calibrate_device(args, board)
                paths_count = None
            else:
                calibration, views, paths_count = calibrate_files(args, board)
            # the views saved with a calibration only: a refused or interrupted run writes nothing
            save_views(views, args.save_views)
        write_calibration(args.out, calibration)
    except (CalibrationError, CharucoError) as error:
        print(f"companion calibrate: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        return write_failed("calibrate", error, args.out)
    print_result(calibration, paths_count, args.out)
    return 0


def check_options(args: argparse.Namespace) -> None:
    """The input given, the numbers in their ranges, and no option that does not apply to the input (said, not
    ignored): before any work."""
    if args.device is not None and args.images:
        raise CalibrationError("give images or --device, not both")
    if args.device is None and not args.images:
        raise CalibrationError("give images or videos (files or folders), or --device for a live camera")
    if args.min_views is not None and not MIN_VIEWS <= args.min_views <= CaptureGoal.max_views:
        raise CalibrationError(f"--min-views must be {MIN_VIEWS} to {CaptureGoal.max_views} (a calibration needs "
                               f"{MIN_VIEWS} views, capture stops at {CaptureGoal.max_views}), not {args.min_views}")
    if args.coverage is not None and not 0 < args.coverage <= 1:
        raise CalibrationError(f"--coverage must be more than 0 and at most 1 (the share of the image covered: "
                               f"0.7 is 70 %), not {args.coverage:g}")
    for option, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and value < 1:
            raise CalibrationError(f"{option} must be a positive number of pixels, not {value}")
    if args.device is None:
        live = [option for option, value in (("--min-views", args.min_views), ("--coverage", args.coverage),
                                             ("--width", args.width), ("--height", args.height)) if value is not None]
        if live:
            raise CalibrationError(f"{', '.join(live)}: for live capture (--device) only, not images or videos")
    if args.board is not None:
        charuco = [option for option, value in (("--marker-mm", args.marker_mm),
                                                ("--aruco-dictionary", args.aruco_dictionary)) if value is not None]
        if charuco:
            raise CalibrationError(f"{', '.join(charuco)}: for a ChArUco board only, not a chessboard (--board)")


def calibrate_files(args: argparse.Namespace, board) -> tuple[Calibration, dict[str, np.ndarray], int]:
    """The calibration of the images and recordings given, the views taken from the recordings, and how many
    views it was given (the images and those views)."""
    paths, recordings = split_inputs(args.images)
    if args.save_views is not None and not recordings:
        raise CalibrationError("--save-views: for views taken live (--device) or from videos, not images (they are "
                               "the views)")
    images = {str(p): cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths}
    unreadable = [name for name, image in images.items() if image is None]
    if unreadable:
        raise CalibrationError(f"cannot read image(s): {', '.join(unreadable)}")
    views = {}
    for recording in recordings:
        views.update(views_of_recording(recording, board))
    images.update(views)
    if recordings and not images:
        raise CalibrationError(f"{', '.join(map(str, recordings))}: the board never rested in view (a view: "
                               f"its corners still for {CaptureGoal.still_frames} frames, somewhere new)")
    return calibrate(images, board), views, len(images)


def make_board(args: argparse.Namespace):
    """--board: a chessboard; otherwise the ChArUco board (--charuco, default 8x11 as printed by default)."""
    square_mm = args.square_mm
    if square_mm is not None and not 0 < square_mm < math.inf:
        raise CalibrationError(f"--square-mm must be a positive number of millimetres, not {square_mm:g}")
    if args.board is not None:
        return Board(*args.board, (square_mm or 25.0) / 1000.0)
    columns, rows = args.charuco or (8, 11)
    return CharucoBoard(CharucoSpec(columns, rows, square_mm or CharucoSpec.square_mm,
                                    CharucoSpec.marker_mm if args.marker_mm is None else args.marker_mm,
                                    args.aruco_dictionary or DEFAULT_DICTIONARY))


def calibrate_device(args: argparse.Namespace, board) -> tuple[Calibration, dict[str, np.ndarray]]:
    """Live capture from a V4L2 camera, progress on stdout, Ctrl-C to stop with the views so far; the
    calibration and the views taken."""
    if not isinstance(board, CharucoBoard):
        raise CalibrationError("live capture (--device) needs a ChArUco board, not --board")
    from companion.capture.v4l2 import device_path, device_problem, opencv_warnings, v4l2_source
    path = device_path(args.device)
    if not os.access(path, os.R_OK | os.W_OK):  # missing, or not this user's: say so now, not after retries
        raise CalibrationError(device_problem(args.device))
    opencv_warnings(shown=False)
    source = v4l2_source(args.device, args.width, args.height)
    given = {"min_views": args.min_views, "coverage": args.coverage}
    goal = CaptureGoal(**{name: value for name, value in given.items() if value is not None})
    print(f"hold the {board.describe()} still in view; a view is taken each time it rests somewhere new "
          f"(goal: {goal.min_views} views, {100 * goal.coverage:.0f} % of the image covered; Ctrl-C to stop)")
    with ctrl_c_stops() as stop, started(source):
        if not source.connected.wait(timeout=5.0):
            raise CalibrationError(source.lost_reason or f"{path}: cannot open the camera: {device_problem(path)}")
        return capture_live(source, board, goal, stop, on_event=lambda e: print(e.message, flush=True))


def views_of_recording(path: Path, board) -> dict[str, np.ndarray]:
    """The still views of the board in a video or sequence folder, named '<file> view01', ...; progress on
    stdout. Ctrl-C stops the command (KeyboardInterrupt): a recording is not live, nothing is written."""
    if not isinstance(board, CharucoBoard):
        raise CalibrationError(f"{path}: views from a video need a ChArUco board, not --board")
    try:
        # the pace does not matter (every frame is read in turn): a video that states no rate reads at 30 fps
        source = ReplaySource(open_recording(path, fps=None if path.is_dir() else 30.0), realtime=False)
    except SourceError as error:
        raise CalibrationError(str(error)) from None
    with started(source):
        views = recorded_views(source, board,
                               on_event=lambda event: print(f"{path.name}: {event.message}", flush=True))
    skipped = f", {source.counters.corrupt} unreadable skipped" if source.counters.corrupt else ""
    print(f"{path.name}: {len(views)} views in {source.counters.captured} frames{skipped}")
    return {f"{path.name} {name}": image for name, image in views.items()}


@contextlib.contextmanager
def started(source):
    """The source started, and closed at the end."""
    source.start()
    try:
        yield source
    finally:
        source.close()


@contextlib.contextmanager
def ctrl_c_stops():
    """An event Ctrl-C sets (live capture stops with the views so far); the handler put back at the end."""
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def save_views(views: dict[str, np.ndarray], folder: Path | None) -> None:
    if folder is not None:
        for name, image in views.items():  # (a camera frame always encodes)
            write_whole(folder / f"{name.replace(' ', '-')}.png", cv2.imencode(".png", image)[1].tobytes())


def print_result(calibration: Calibration, images: int | None, out: Path) -> None:
    for name, reason in calibration.rejected:
        print(f"left out {name}: {reason}")
    total = f" of {images}" if images is not None else ""
    print(f"{len(calibration.views)}{total} views, {calibration.points} corners, image coverage "
          f"{100 * calibration.coverage:.0f} %, RMS {calibration.rms_px:.3f} px -> {out}")
    values = calibration.parameters()
    for name in PARAMETERS:
        value, std = values[name], calibration.std[name]
        unit = " px" if name in ("fx", "fy", "cx", "cy") else ""
        relative = f" ({100 * std / abs(value):.2f} %)" if name in ("fx", "fy") else ""
        print(f"  {name:2} {value:12.5f}{unit} ± {std:.5f}{unit}{relative}")
