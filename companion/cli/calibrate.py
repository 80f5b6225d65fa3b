"""``companion calibrate IMAGES... --board 9x6 --square-mm 25 --out camera.yaml``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from companion.capture.replay import image_files
from companion.geometry.calibration import (Board, CalibrationError, calibrate,
                                            write_calibration)


def image_paths(inputs: list[str]) -> list[Path]:
    paths = []
    for item in map(Path, inputs):
        if item.is_dir():
            paths += image_files(item)
        elif item.is_file():
            paths.append(item)
        else:
            raise CalibrationError(f"{item}: no such file or directory")
    return paths


def parse_board(text: str) -> tuple[int, int]:
    try:
        columns, rows = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"board must be COLUMNSxROWS of inner corners, e.g. 9x6, not {text!r}") from None
    if columns < 2 or rows < 2:
        raise argparse.ArgumentTypeError("a board needs at least 2x2 inner corners")
    return columns, rows


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", help="chessboard images, or folders of them")
    parser.add_argument("--board", type=parse_board, default=(9, 6), help="inner corners COLUMNSxROWS (default 9x6)")
    parser.add_argument("--square-mm", type=float, default=25.0, help="printed square side in mm (default 25)")
    parser.add_argument("--out", type=Path, default=Path("camera.yaml"), help="output calibration YAML (default camera.yaml)")


def main(args: argparse.Namespace) -> int:
    if args.square_mm <= 0:
        print(f"companion calibrate: --square-mm must be positive, not {args.square_mm}", file=sys.stderr)
        return 2
    try:
        paths = image_paths(args.images)
        images = {str(p): cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths}
        unreadable = [name for name, image in images.items() if image is None]
        if unreadable:
            raise CalibrationError(f"cannot read image(s): {', '.join(unreadable)}")
        calibration = calibrate(images, Board(*args.board, args.square_mm / 1000.0))
    except CalibrationError as error:
        print(f"companion calibrate: {error}", file=sys.stderr)
        return 2
    write_calibration(args.out, calibration)
    fx, fy, cx, cy = calibration.K[0, 0], calibration.K[1, 1], calibration.K[0, 2], calibration.K[1, 2]
    print(f"{len(calibration.views)} of {len(paths)} views, RMS {calibration.rms_px:.3f} px, "
          f"fx {fx:.1f} fy {fy:.1f} cx {cx:.1f} cy {cy:.1f} -> {args.out}")
    return 0
