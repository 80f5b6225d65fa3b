"""``companion detect IMAGE... [--json] [--draw DIR]``: find RS markers in image files.

One line per image. With ``--json`` each line is a JSON object:

    {"image": "a.png", "detections": [{"symbol": "A", "id": 0,
      "corners": [[x, y], [x, y], [x, y], [x, y]], "path": "square", "corrected": 0}], "ms": 3.1}

corners: the inner black square's corners TL, TR, BR, BL in the marker's
upright orientation, pixels (centre of the top-left pixel at 0, 0); path:
"square" or "circles" (found by its corner circles); corrected: RS symbols
corrected or recovered from erasures; ms: detection time.

Directories expand to the images directly inside them (sorted). An image
that cannot be read is reported on stderr, skipped and counted; the exit
status is then 1.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from companion.cli.output import output_dir, removed_if_left_empty
from companion.detect.circles import CIRCLES_RUN_MODES, CircleParams
from companion.capture.replay import image_files
from companion.detect.detector import DICTIONARIES, Detector, DetectorParams
from companion.files import write_whole
from companion.params import ParamsError
from companion.types import Detection

PATH_COLOURS = {"square": (40, 200, 40), "circles": (0, 140, 255)}  # BGR


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE",
                        help="image files, or directories of them")
    parser.add_argument("--json", action="store_true", help="one JSON object per image and line")
    parser.add_argument("--draw", type=Path, metavar="DIR",
                        help="write annotated copies of the images here, as PNG (not over the images read)")
    parser.add_argument("--parity", type=int, choices=(2, 4), default=DetectorParams.parity,
                        help="RS parity symbols of the markers")
    parser.add_argument("--dictionary", default=DetectorParams.dictionary,
                        help=f"marker dictionary: {', '.join(DICTIONARIES)} (default %(default)s)")
    parser.add_argument("--circles", choices=CIRCLES_RUN_MODES, default=CircleParams.run,
                        help="when the occluded (corner circles) path runs")


def main(args: argparse.Namespace) -> int:
    paths, missing = expand_images(args.images)
    for path in missing:
        print(f"companion detect: {path}: no such file or directory", file=sys.stderr)
    if not paths and not missing:
        print("companion detect: no images found in " + ", ".join(map(str, args.images)), file=sys.stderr)
        return 2
    try:
        params = DetectorParams(parity=args.parity, dictionary=args.dictionary, circles=CircleParams(run=args.circles))
    except ParamsError as error:
        print(f"companion detect: {error}", file=sys.stderr)
        return 2
    detector = Detector(params)
    drawn = drawn_paths(paths, args.draw) if args.draw else {}
    inputs = {path.resolve() for path in paths}
    overwritten = [copy for copy in drawn.values() if copy.resolve() in inputs]
    if overwritten:
        print(f"companion detect: --draw {args.draw}: an annotated copy would replace an image it reads "
              f"({overwritten[0]}): give another folder", file=sys.stderr)
        return 2
    with removed_if_left_empty(args.draw):
        if args.draw:
            output_dir(args.draw, "--draw")
        unread, unwritten = detect_each(detector, paths, drawn, args.json)
    unread += len(missing)
    images = len(paths) + len(missing)
    if unread:
        print(f"companion detect: {unread} of {images} images could not be read", file=sys.stderr)
    if unwritten:
        print(f"companion detect: {unwritten} of {images} annotated copies could not be written", file=sys.stderr)
    return 1 if unread or unwritten else 0


def detect_each(detector: Detector, paths: list[Path], drawn: dict[Path, Path], as_json: bool) -> tuple[int, int]:
    """Detect in each image, print its line, write its annotated copy where ``drawn`` names one; (images that
    could not be read, copies that could not be written), each said as it happens."""
    unread = unwritten = 0
    for path in paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            print(f"companion detect: {path}: not a readable image, skipped", file=sys.stderr)
            unread += 1
            continue
        start = time.perf_counter_ns()
        detections = detector.detect(gray)
        ms = (time.perf_counter_ns() - start) / 1e6
        print(json_line(path, detections, ms) if as_json else text_line(path, detections, ms), flush=True)
        if path in drawn:
            try:
                write_whole(drawn[path], cv2.imencode(".png", draw(gray, detections))[1].tobytes())
            except OSError as error:
                print(f"companion detect: --draw {drawn[path]}: cannot write: {error.strerror or error}",
                      file=sys.stderr)
                unwritten += 1
    return unread, unwritten


def expand_images(inputs: list[Path]) -> tuple[list[Path], list[Path]]:
    """(image files, inputs that do not exist); directories give their images, sorted."""
    images, missing = [], []
    for path in inputs:
        if path.is_dir():
            images.extend(image_files(path))
        elif path.exists():
            images.append(path)
        else:
            missing.append(path)
    return images, missing


def detection_record(d: Detection) -> dict:
    return {"symbol": d.symbol, "id": int(d.id), "corners": [[round(float(x), 3), round(float(y), 3)]
                                                              for x, y in d.corners_px],
            "path": d.path, "corrected": int(d.corrected)}


def json_line(path: Path, detections: list[Detection], ms: float) -> str:
    return json.dumps({"image": str(path), "detections": [detection_record(d) for d in detections],
                       "ms": round(ms, 3)})


def text_line(path: Path, detections: list[Detection], ms: float) -> str:
    found = "; ".join(f"{d.symbol} (id {d.id}, {d.path}, corrected {d.corrected}) at "
                      f"({d.corners_px[:, 0].mean():.1f}, {d.corners_px[:, 1].mean():.1f})" for d in detections)
    return f"{path}: {found or 'no markers'} [{ms:.1f} ms]"


def draw(gray: np.ndarray, detections: list[Detection]) -> np.ndarray:
    """BGR copy of the image with each marker's outline (TL corner marked), symbol and circles."""
    image = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    shift = 4
    for d in detections:
        colour = PATH_COLOURS.get(d.path, (255, 0, 255))
        corners = np.round(d.corners_px * (1 << shift)).astype(np.int32)
        cv2.polylines(image, [corners], True, colour, 2, cv2.LINE_AA, shift)
        cv2.circle(image, tuple(corners[0]), 5 << shift, (0, 0, 255), 2, cv2.LINE_AA, shift)
        for centre in np.round(d.circles_px * (1 << shift)).astype(np.int32):
            cv2.circle(image, tuple(centre), 3 << shift, (255, 80, 0), 1, cv2.LINE_AA, shift)
        label = f"{d.symbol} {d.path} c{d.corrected}"
        origin = tuple(int(v) for v in d.corners_px.min(axis=0) - [0, 6])
        cv2.putText(image, label, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(image, label, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    return image


def drawn_paths(paths: list[Path], folder: Path) -> dict[Path, Path]:
    """Where each image's annotated copy goes: its name as a PNG in ``folder``, numbered when an earlier
    image has the same name."""
    drawn, used = {}, set()
    for path in paths:
        name, n = f"{path.stem}.png", 1
        while name in used:
            n += 1
            name = f"{path.stem}_{n}.png"
        used.add(name)
        drawn[path] = folder / name
    return drawn
