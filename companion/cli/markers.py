"""``companion markers``: write printable RS markers (``companion.markers.printing``)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from companion.cli.output import output_dir, removed_if_left_empty
from companion.files import write_whole
from companion.markers.charuco import DEFAULT_DICTIONARY as CHARUCO_DICTIONARY
from companion.markers.charuco import CharucoError, CharucoSpec, charuco_pdf
from companion.markers.dictionary import DictionaryError
from companion.markers.layout import MarkerLayout
from companion.markers.printing import (DEFAULT_DICTIONARY, PAGES_MM, MarkerPrint, PrintingError, check_dpi,
                                        check_pdf, check_png_size, check_printable, check_size_mm, check_svg_size,
                                        fits_one_page, largest_on_one_page_mm, marker_png, marker_svg, markers_pdf,
                                        num, page_name, resolve_marker_ids, sheet_geometry, tile_geometry)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--symbols", help="comma-separated symbols, e.g. A,B,7,HOME")
    which.add_argument("--all", action="store_true", help="all 50 symbols of the dictionary")
    which.add_argument("--charuco", nargs="?", const="8x11", metavar="COLSxROWS", type=parse_squares,
                       help="a ChArUco calibration board as a PDF instead (default 8x11 squares; see "
                            "--square-mm, --marker-mm, --aruco-dictionary, --page)")
    parser.add_argument("--parity", type=int, choices=(2, 4), default=2,
                        help="Reed-Solomon parity symbols per code (default 2; 4 is the robust variant)")
    parser.add_argument("--dictionary", choices=("5x5", "6x6", "8x8"), default=DEFAULT_DICTIONARY,
                        help="data grid size (default 6x6)")
    parser.add_argument("--size-mm", type=float, default=35.0,
                        help="printed side of the inner black square in mm, cells of at least 0.25 mm (default 35)")
    parser.add_argument("--format", choices=("png", "svg", "pdf"), default=None,
                        help="png (one file per marker + JSON sidecar), svg, or pdf sheets (default png; a "
                             "--charuco board is a PDF only)")
    parser.add_argument("--out", type=Path, default=Path("markers"), help="output folder (default ./markers)")
    parser.add_argument("--dpi", type=float, default=300.0,
                        help="PNG print resolution, 72 to 4800, stored in the file; the inner square is the nearest "
                             "whole number of pixels to --size-mm at it, at least 5 px per cell (default 300)")
    parser.add_argument("--quiet-zone-cells", type=int, default=1,
                        help="white margin around the grid in cells (default 1, as wide as the black border)")
    parser.add_argument("--page", choices=tuple(PAGES_MM), default="a4",
                        help="PDF page size (default a4); a marker larger than the page is tiled over several")
    board = parser.add_argument_group("ChArUco board (--charuco)")
    board.add_argument("--square-mm", type=float, default=CharucoSpec.square_mm,
                       help=f"chessboard square side (default {CharucoSpec.square_mm:g})")
    board.add_argument("--marker-mm", type=float, default=CharucoSpec.marker_mm,
                       help=f"ArUco marker side inside the white squares (default {CharucoSpec.marker_mm:g})")
    board.add_argument("--aruco-dictionary", default=CHARUCO_DICTIONARY,
                       help=f"OpenCV's dictionary of the board's markers (default {CHARUCO_DICTIONARY})")


def main(args: argparse.Namespace) -> int:
    try:
        with removed_if_left_empty(args.out):
            return write_charuco(args) if args.charuco else generate(args)
    except (PrintingError, DictionaryError, CharucoError) as error:
        print(f"companion markers: error: {error}", file=sys.stderr)
        return 2


def parse_squares(text: str) -> tuple[int, int]:
    """``COLSxROWS`` squares of a ChArUco board."""
    try:
        columns, rows = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be COLUMNSxROWS of squares, e.g. 8x11, not {text!r}") from None
    return columns, rows


def write_charuco(args: argparse.Namespace) -> int:
    """The ChArUco board PDF: ``charuco-8x11-22mm-16mm-a4.pdf`` in --out."""
    if args.format not in (None, "pdf"):
        raise PrintingError(f"--format {args.format}: a --charuco board is written as a PDF only (leave out --format)")
    spec = CharucoSpec(*args.charuco, args.square_mm, args.marker_mm, args.aruco_dictionary)
    document = charuco_pdf(spec, args.page)
    path = output_dir(args.out, "--out") / f"{spec.file_stem()}-{args.page}.pdf"
    write_whole(path, document)
    print(f"{path}: {spec.describe()}, {spec.corners} corners; calibrate with: "
          f"companion calibrate IMAGES... {spec.calibrate_options()}")
    return 0


def generate(args: argparse.Namespace) -> int:
    args.format = args.format or "png"
    size_mm = check_size_mm(args.size_mm)
    if args.quiet_zone_cells < 1:
        raise PrintingError(f"--quiet-zone-cells must be at least 1 (the quiet zone must be at least as wide "
                            f"as the black border), not {args.quiet_zone_cells}")
    check_dpi(args.dpi)
    layout = MarkerLayout(args.parity, args.dictionary)
    ids = resolve_marker_ids(layout, args.symbols, args.all)
    markers = [MarkerPrint(layout, marker_id, size_mm, args.quiet_zone_cells) for marker_id in ids]
    check_printable(markers[0])
    if args.format == "png":
        check_png_size(markers[0], args.dpi)
    elif args.format == "svg":
        check_svg_size(markers[0])
    else:
        check_pdf(markers, args.page)
    out_dir: Path = output_dir(args.out, "--out")

    if args.format == "pdf":
        path = out_dir / f"markers-p{layout.parity}-{args.dictionary}-{num(size_mm)}mm-{args.page}.pdf"
        write_whole(path, markers_pdf(markers, args.page))
        print(f"{path}: {describe_pdf(markers, args.page)}")
        return 0
    for marker in markers:
        if args.format == "svg":
            path = out_dir / f"{marker.file_stem()}.svg"
            write_whole(path, marker_svg(marker))
            print(f"{path}: {marker.symbol} id {marker.marker_id}, {num(marker.outer_mm)} mm square, "
                  f"inner square {num(size_mm)} mm")
        else:
            png, sidecar = marker_png(marker, args.dpi)
            path = out_dir / f"{marker.file_stem()}.png"
            write_whole(path, png)
            try:
                write_whole(path.with_suffix(".json"), json.dumps(sidecar, indent=2) + "\n")
            except BaseException:
                path.unlink(missing_ok=True)  # a PNG is printed at the size its sidecar states: both or neither
                raise
            width, height = sidecar["image_px"]
            print(f"{path}: {marker.symbol} id {marker.marker_id}, {width}x{height} px, inner square "
                  f"{sidecar['inner_px']} px = {sidecar['size_mm']:.3f} mm at {sidecar['dpi']:.4f} dpi")
    return 0


def describe_pdf(markers: list[MarkerPrint], page: str) -> str:
    """How many markers on how many pages; for tiled markers, the tiles and the largest untiled size."""
    first = markers[0]
    sizes = f"inner square {num(first.size_mm)} mm, cut square {num(first.outer_mm)} mm"
    if fits_one_page(markers, page):
        n_pages = sheet_geometry(markers, page).page_count(len(markers))
        return (f"{len(markers)} marker{'s' * (len(markers) > 1)} on {n_pages} {page_name(page)} "
                f"page{'s' * (n_pages > 1)}, {sizes}")
    tiles = tile_geometry(first, page)
    return (f"{len(markers)} markers, each tiled on {tiles.rows} x {tiles.columns} {page_name(page)} pages "
            f"({tiles.per_marker * len(markers)} pages), {sizes}; the largest that fits one {page_name(page)} page is "
            f"{largest_on_one_page_mm(first, page):.1f} mm: cut the tiles at their crop marks and butt them, "
            "cell edges aligned by the ticks")
