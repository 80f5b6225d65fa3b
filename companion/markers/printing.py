"""`companion markers`: printable RS markers as PNG (with JSON sidecars), SVG, or PDF sheets.

Sizes: ``--size-mm`` is the printed side of the inner black square (the
``size_m`` of maps and configs); the whole grid with its quiet zone is
``(N + 2 q) / (n + 2)`` times that.

* PNG: one image per marker at exactly ``--dpi`` (its pHYs chunk, in whole
  pixels per metre: 300 dpi is stored as 11811 px/m, 299.9994 dpi). The
  inner square is the whole number of pixels nearest to ``--size-mm`` at that
  resolution, so a print at ``--dpi`` is within half a pixel of the size;
  cells are as many pixels wide as that takes (a 35 mm square at 300 dpi is
  413 px: cells of 51 and 52 px, ``companion.markers.layout.marker_image``).
  Next to it a JSON sidecar with the geometry in the PNG's pixel coordinates
  (pixel centres at integers, so the black square's outer edge is at half
  pixels). A PNG side beyond ``MAX_PNG_SIDE_PX`` is refused (use SVG or PDF), and
  so is one with fewer than ``MIN_PX_PER_CELL`` pixels per cell, or a ``--dpi``
  outside ``MIN_DPI``..``MAX_DPI`` (what printers print at).
* SVG: vector, width and height in mm, cells as rectangles (horizontal runs
  merged), circles as circles; at most ``MAX_SVG_SIDE_MM`` across.
* PDF: sheets of markers at exact scale on A4, Letter or A3 with crop marks,
  the symbol, id, parity and inner-square size below each, and a 50 mm scale
  bar; drawn with reportlab as vector shapes, labels sized by Helvetica's
  metrics. A marker larger than a page is tiled over several pages
  (``tile_geometry``): each page holds whole cells of it, with crop marks at
  the tile's corners and alignment ticks at every cell boundary along its
  edges; cut along the marks and butt the tiles edge to edge.

In every format a cell is at least ``MIN_CELL_MM`` (``check_printable``): a
printer cannot print a smaller one, nor the corner circles inside it.
"""
from __future__ import annotations

import io
import math
import struct
import zlib
from dataclasses import dataclass

import cv2
import numpy as np
from reportlab.lib.units import mm as PT_PER_MM  # 72 / 25.4 points per millimetre
from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.pdfgen.canvas import FILL_NON_ZERO, Canvas

from companion.markers.dictionary import DictionaryError
from companion.markers.layout import MarkerLayout, cell_edges_px, cell_point_to_px, marker_image

MM_PER_INCH = 25.4
PAGES_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4), "a3": (297.0, 420.0)}


def page_name(page: str) -> str:
    """A page size as people write it: "A4", "A3", "letter"."""
    return page.upper() if page.startswith("a") else page

# A PNG side beyond this (144 MB of pixels) is refused: large markers are for SVG or PDF.
MAX_PNG_SIDE_PX = 12_000
# A PNG cell of fewer pixels cannot draw the corner circles (0.8 cell across) round.
MIN_PX_PER_CELL = 5
# What printers print at: 72 dpi (screen) up to 4800 dpi (photo printers).
MIN_DPI, MAX_DPI = 72.0, 4800.0
# The smallest printed cell in any format: 6 dots of a 600 dpi laser printer.
MIN_CELL_MM = 0.25
# An SVG wider than this (10 m) is no print: a larger marker is a sign shop's job, from a smaller SVG scaled up.
MAX_SVG_SIDE_MM = 10_000.0
MAX_TILED_PAGES = 500
DEFAULT_DICTIONARY = "6x6"

# PDF sheet geometry (mm)
PAGE_MARGIN_MM = 8.0  # most printers cannot print the outer 4-6 mm
CROP_MARK_GAP_MM = 1.0  # crop marks start this far outside the cut square's corner
CROP_MARK_LENGTH_MM = 3.0
CROP_MARK_WIDTH_MM = 0.1
SLOT_SPACING_MM = 1.0
LABEL_SIZES_PT = (9.0, 6.5)  # symbol line, details line
LABEL_LINE_MM = 4.0
SCALE_BAR_MM = 50.0
FOOTER_MM = 8.0  # space kept at the page bottom for the footer and scale bar


class PrintingError(ValueError):
    """Bad options for `companion markers` (unknown symbol, non-positive size, no room on the page)."""


@dataclass(frozen=True)
class MarkerPrint:
    """One marker to print and its physical scale.

    cell_mm: printed side of one grid cell; the inner square is
    ``layout.inner_cells`` cells.
    """

    layout: MarkerLayout
    marker_id: int
    size_mm: float
    quiet_zone_cells: int

    @property
    def symbol(self) -> str:
        return self.layout.dictionary.symbol_of(self.marker_id)

    @property
    def cell_mm(self) -> float:
        return self.size_mm / self.layout.inner_cells

    @property
    def outer_cells(self) -> int:
        """Cells across the printed square, quiet zone included."""
        return self.layout.n_cells + 2 * self.quiet_zone_cells

    @property
    def outer_mm(self) -> float:
        return self.outer_cells * self.cell_mm

    def file_stem(self) -> str:
        dictionary = f"{self.layout.data_size}x{self.layout.data_size}"
        suffix = "" if dictionary == DEFAULT_DICTIONARY else f"-{dictionary}"
        return f"marker-{self.symbol}-p{self.layout.parity}{suffix}"


# ------------------------------------------------------------------ options

def resolve_marker_ids(layout: MarkerLayout, symbols: str | None, all_symbols: bool) -> list[int]:
    """Marker ids for ``--symbols A,B,7`` (in the given order, duplicates dropped) or ``--all``."""
    dictionary = layout.dictionary
    if all_symbols:
        return list(range(len(dictionary.symbols)))
    names = [s.strip() for s in (symbols or "").split(",") if s.strip()]
    if not names:
        raise PrintingError(f"--symbols is empty; known symbols: {', '.join(dictionary.symbols)}")
    try:
        ids = [dictionary.id_of(name) for name in names]
    except DictionaryError as error:
        raise PrintingError(str(error)) from None
    return list(dict.fromkeys(ids))


def check_size_mm(size_mm: float) -> float:
    if not size_mm > 0 or not np.isfinite(size_mm):
        raise PrintingError(f"--size-mm must be a positive number of millimetres (the inner black "
                            f"square's side), not {size_mm}")
    return size_mm


def check_dpi(dpi: float) -> float:
    if not MIN_DPI <= dpi <= MAX_DPI:
        raise PrintingError(f"--dpi must be {MIN_DPI:g} to {MAX_DPI:g} (what printers print at), not {dpi:g}")
    return dpi


def check_printable(marker: MarkerPrint) -> None:
    """A PrintingError, with the smallest --size-mm that prints, for cells below MIN_CELL_MM."""
    if marker.cell_mm < MIN_CELL_MM:
        smallest = MIN_CELL_MM * marker.layout.inner_cells
        raise PrintingError(f"--size-mm {num(marker.size_mm)} is too small to print: its cells would be "
                            f"{marker.cell_mm:.3g} mm, at least {MIN_CELL_MM:g} mm (--size-mm {num(smallest)} or more "
                            f"for {marker.layout.inner_cells} cells across the inner square)")


# --------------------------------------------------------------------- PNG

def png_px_per_m(dpi: float) -> int:
    """pHYs resolution of ``dpi``: whole pixels per metre (the PNG format's unit)."""
    # px/m = dpi / 0.0254 m per inch
    return max(1, round(dpi * 1000.0 / MM_PER_INCH))


def png_px_per_cell(marker: MarkerPrint, px_per_m: int) -> float:
    """Pixels per cell so that the inner square is the whole number of pixels nearest to its size."""
    # inner px = size m * px/m, rounded; a cell is 1 / inner_cells of it
    inner_px = max(marker.layout.inner_cells, round(marker.size_mm / 1000.0 * px_per_m))
    return inner_px / marker.layout.inner_cells


def png_side_px(marker: MarkerPrint, dpi: float) -> int:
    """Width and height of the marker's PNG at ``dpi``."""
    return int(cell_edges_px(marker.outer_cells, png_px_per_cell(marker, png_px_per_m(dpi)))[-1])


def check_png_size(marker: MarkerPrint, dpi: float) -> None:
    """A PrintingError, suggesting SVG/PDF or the highest DPI that fits, for a PNG beyond MAX_PNG_SIDE_PX; with
    the smallest --size-mm or the lowest --dpi that draws it, for one of fewer than MIN_PX_PER_CELL px per cell."""
    side_px = png_side_px(marker, dpi)
    if side_px > MAX_PNG_SIDE_PX:
        max_dpi = int(dpi * MAX_PNG_SIDE_PX / side_px)
        lower = f", or --dpi {max_dpi} or less" if max_dpi >= MIN_DPI else ""
        raise PrintingError(f"a {num(marker.size_mm)} mm marker at {num(dpi)} dpi is a {side_px} px square PNG "
                            f"(at most {MAX_PNG_SIDE_PX}): use --format svg or --format pdf (vector, any size){lower}")
    px_per_cell = png_px_per_cell(marker, png_px_per_m(dpi))
    if px_per_cell < MIN_PX_PER_CELL:
        inner_px = MIN_PX_PER_CELL * marker.layout.inner_cells
        smallest_mm = math.ceil(10 * inner_px * MM_PER_INCH / dpi) / 10
        higher = f", or --dpi {math.ceil(inner_px * MM_PER_INCH / marker.size_mm)}"
        higher = higher if inner_px * MM_PER_INCH / marker.size_mm <= MAX_DPI else ""
        raise PrintingError(f"a {num(marker.size_mm)} mm marker at {num(dpi)} dpi has {px_per_cell:.3g} px per cell "
                            f"(at least {MIN_PX_PER_CELL}): use --size-mm {num(smallest_mm)} or more{higher}")


def check_svg_size(marker: MarkerPrint) -> None:
    if marker.outer_mm > MAX_SVG_SIDE_MM:
        raise PrintingError(f"a {num(marker.size_mm)} mm marker with {marker.quiet_zone_cells} quiet-zone cell(s) is a "
                            f"{num(marker.outer_mm)} mm square SVG (at most {num(MAX_SVG_SIDE_MM)} mm): use a smaller "
                            "--size-mm or --quiet-zone-cells")


def png_with_phys(png: bytes, px_per_m: int) -> bytes:
    """The PNG file ``png`` with its pHYs chunk (resolution in pixels per metre) set to ``px_per_m``.

    An existing pHYs chunk is replaced; the new one goes right after IHDR.
    """
    signature = b"\x89PNG\r\n\x1a\n"
    if not png.startswith(signature):
        raise PrintingError("not a PNG stream")
    chunks, pos = [], len(signature)
    while pos < len(png):
        (length,) = struct.unpack(">I", png[pos:pos + 4])
        end = pos + 12 + length
        if png[pos + 4:pos + 8] != b"pHYs":
            chunks.append(png[pos:end])
        pos = end
    body = struct.pack(">IIB", px_per_m, px_per_m, 1)  # unit 1: metre
    phys = struct.pack(">I", len(body)) + b"pHYs" + body + struct.pack(">I", zlib.crc32(b"pHYs" + body))
    return signature + chunks[0] + phys + b"".join(chunks[1:])


def png_sidecar(marker: MarkerPrint, px_per_cell: float, px_per_m: int, image_shape: tuple[int, ...]) -> dict:
    """The JSON sidecar of a marker PNG: identity, scale and geometry in PNG pixels."""
    layout, q = marker.layout, marker.quiet_zone_cells
    edges = cell_edges_px(marker.outer_cells, px_per_cell)
    # the inner corners lie on cell boundaries: their drawn pixel edges (centres at integers: edge - 0.5)
    corner_cells = np.round(layout.inner_corners_cells).astype(int) + q
    corners = edges[corner_cells] - 0.5
    circles = np.asarray(layout.circles, dtype=float).reshape(-1, 3)
    circle_centres = cell_point_to_px(circles[:, :2], px_per_cell, q)
    inner_px = int(edges[q + layout.inner_origin + layout.inner_cells] - edges[q + layout.inner_origin])
    return {
        "symbol": marker.symbol,
        "id": marker.marker_id,
        "parity": layout.parity,
        "dictionary": f"{layout.data_size}x{layout.data_size}",
        "cells": layout.n_cells,
        "inner_cells": layout.inner_cells,
        "inner_origin_cells": layout.inner_origin,
        "px_per_cell": px_per_cell,
        "quiet_zone_cells": q,
        "inner_px": inner_px,
        # printed size at the pHYs resolution: exact for what the file says
        "size_mm": inner_px / px_per_m * 1000.0,
        "dpi": px_per_m * MM_PER_INCH / 1000.0,
        "image_px": [int(image_shape[1]), int(image_shape[0])],
        "inner_corners_px": corners.astype(float).tolist(),
        "circles_px": [[float(x), float(y), float(r * px_per_cell)]
                       for (x, y), r in zip(circle_centres, circles[:, 2])],
    }


def marker_png(marker: MarkerPrint, dpi: float) -> tuple[bytes, dict]:
    """The PNG file of one marker at ``dpi`` (its resolution in the file's pHYs chunk), and its sidecar
    (``png_sidecar``, written beside it as ``<stem>.json``)."""
    check_png_size(marker, dpi)
    px_per_m = png_px_per_m(dpi)
    px_per_cell = png_px_per_cell(marker, px_per_m)
    image = marker_image(marker.layout, marker.marker_id, px_per_cell, marker.quiet_zone_cells)
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise PrintingError(f"OpenCV could not encode the PNG of {marker.symbol}")
    return png_with_phys(encoded.tobytes(), px_per_m), png_sidecar(marker, px_per_cell, px_per_m, image.shape)


# --------------------------------------------------------------------- SVG

def cell_runs(cells: np.ndarray) -> list[tuple[int, int, int]]:
    """Horizontal runs of black cells in an (N, N) 0/1 grid: (row, first column, length)."""
    runs = []
    for row, line in enumerate(np.asarray(cells)):
        padded = np.r_[0, (line > 0).astype(np.int8), 0]
        edges = np.flatnonzero(np.diff(padded))
        runs.extend((row, int(start), int(stop - start)) for start, stop in zip(edges[::2], edges[1::2]))
    return runs


def num(value: float) -> str:
    """A compact decimal for SVG attributes (up to 6 decimals)."""
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def marker_svg(marker: MarkerPrint) -> str:
    """The marker (with its quiet zone) as an SVG document: user units are cells, size in mm."""
    q, side = marker.quiet_zone_cells, marker.outer_cells
    layout = marker.layout
    side_mm = num(marker.outer_mm)
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{side_mm}mm" height="{side_mm}mm" '
        f'viewBox="0 0 {side} {side}">',
        f"<title>RS marker {marker.symbol} (id {marker.marker_id}), parity {layout.parity}, "
        f"{layout.data_size}x{layout.data_size}, inner square {num(marker.size_mm)} mm</title>",
        f'<rect x="0" y="0" width="{side}" height="{side}" fill="#ffffff"/>',
        '<g fill="#000000">',
    ]
    for row, column, length in cell_runs(layout.cells(marker.marker_id)):
        lines.append(f'<rect x="{column + q}" y="{row + q}" width="{length}" height="1"/>')
    for u, v, radius in np.asarray(layout.circles, dtype=float).reshape(-1, 3):
        lines.append(f'<circle cx="{num(u + q)}" cy="{num(v + q)}" r="{num(radius)}"/>')
    lines += ["</g>", "</svg>"]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------- PDF

# One of the 14 standard PDF fonts: every reader has it, nothing is embedded, and
# reportlab carries its Adobe metrics, so label widths are measured, not guessed.
LABEL_FONT = "Helvetica"
FOOTER_TEXT_PT = 6.5


def text_width_mm(text: str, size_pt: float) -> float:
    """Printed width of ``text`` in the label font at ``size_pt``, from the font's glyph widths."""
    return stringWidth(text, LABEL_FONT, size_pt) / PT_PER_MM


@dataclass(frozen=True)
class SheetPage:
    """The current page of a reportlab canvas, addressed in mm from the page's top-left corner, y down
    (like the marker grid); reportlab's user space is in points from the bottom-left corner, y up."""

    canvas: Canvas
    width_mm: float
    height_mm: float

    def point(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        return x_mm * PT_PER_MM, (self.height_mm - y_mm) * PT_PER_MM

    def fill_rects(self, rects_mm: list[tuple[float, float, float, float]]) -> None:
        """Fill rectangles (top-left x, y, width, height in mm) black, as one path."""
        path = self.canvas.beginPath()
        for x, y, width, height in rects_mm:
            # PDF "re" takes the lower-left corner and a positive height upward.
            path.rect(*self.point(x, y + height), width * PT_PER_MM, height * PT_PER_MM)
        self.canvas.drawPath(path, stroke=0, fill=1, fillMode=FILL_NON_ZERO)

    def fill_circles(self, circles_mm: list[tuple[float, float, float]]) -> None:
        """Fill circles (centre x, y, radius in mm) black, as one path of Bezier quarter arcs."""
        path = self.canvas.beginPath()
        for cx, cy, radius in circles_mm:
            path.circle(*self.point(cx, cy), radius * PT_PER_MM)
        self.canvas.drawPath(path, stroke=0, fill=1, fillMode=FILL_NON_ZERO)

    def lines(self, segments_mm: list[tuple[float, float, float, float]], width_mm: float) -> None:
        """Stroke black line segments (x0, y0, x1, y1 in mm)."""
        self.canvas.setLineWidth(width_mm * PT_PER_MM)
        self.canvas.lines([(*self.point(x0, y0), *self.point(x1, y1)) for x0, y0, x1, y1 in segments_mm])

    def text(self, x_mm: float, baseline_mm: float, text: str, size_pt: float) -> None:
        """Black label-font text starting at x with its baseline at ``baseline_mm``."""
        self.canvas.setFont(LABEL_FONT, size_pt)
        self.canvas.drawString(*self.point(x_mm, baseline_mm), text)


@dataclass(frozen=True)
class SheetGeometry:
    """Where marker slots go on a page (mm). A slot holds the cut square, its crop marks and label."""

    page_mm: tuple[float, float]
    slot_mm: tuple[float, float]
    columns: int
    rows: int

    @property
    def per_page(self) -> int:
        return self.columns * self.rows

    def page_count(self, n_markers: int) -> int:
        return -(-n_markers // self.per_page)


def marker_labels(marker: MarkerPrint) -> tuple[str, str]:
    layout = marker.layout
    return (f"{marker.symbol}   id {marker.marker_id}",
            f"parity {layout.parity}, {layout.data_size}x{layout.data_size}, inner square {num(marker.size_mm)} mm")


def label_width_mm(marker: MarkerPrint) -> float:
    """Width of the marker's widest label line."""
    return max(text_width_mm(text, size_pt) for text, size_pt in zip(marker_labels(marker), LABEL_SIZES_PT))


def sheet_geometry(markers: list[MarkerPrint], page: str) -> SheetGeometry:
    """Grid of equal slots, wide enough for the widest label, that fits the page inside its margins and footer.

    All ``markers`` share layout, size and quiet zone.
    """
    geometry = _slot_grid(markers, page)
    if geometry.columns < 1 or geometry.rows < 1:
        marker = markers[0]
        page_w, page_h = PAGES_MM[page]
        usable_w, usable_h = page_w - 2 * PAGE_MARGIN_MM, page_h - 2 * PAGE_MARGIN_MM - FOOTER_MM
        raise PrintingError(f"a marker with a {num(marker.size_mm)} mm inner square needs a "
                            f"{num(geometry.slot_mm[0])} x {num(geometry.slot_mm[1])} mm slot, more than one "
                            f"{page_name(page)} page offers ({num(usable_w)} x {num(usable_h)} mm inside the margins); the largest "
                            f"that fits is {largest_on_one_page_mm(marker, page):.1f} mm")
    return geometry


def _slot_grid(markers: list[MarkerPrint], page: str) -> SheetGeometry:
    """The slots' size and how many fit across and down the page (0 when one does not fit)."""
    marker = markers[0]
    page_w, page_h = PAGES_MM[page]
    mark_reach = CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    slot_w = max(marker.outer_mm + 2 * mark_reach, max(label_width_mm(m) for m in markers))
    slot_h = marker.outer_mm + 2 * mark_reach + len(LABEL_SIZES_PT) * LABEL_LINE_MM
    usable_w = page_w - 2 * PAGE_MARGIN_MM
    usable_h = page_h - 2 * PAGE_MARGIN_MM - FOOTER_MM
    # n slots need n w + (n - 1) spacing <= usable
    columns = int((usable_w + SLOT_SPACING_MM) // (slot_w + SLOT_SPACING_MM))
    rows = int((usable_h + SLOT_SPACING_MM) // (slot_h + SLOT_SPACING_MM))
    return SheetGeometry((page_w, page_h), (slot_w, slot_h), columns, rows)


def fits_one_page(markers: list[MarkerPrint], page: str) -> bool:
    geometry = _slot_grid(markers, page)
    return geometry.columns >= 1 and geometry.rows >= 1


def largest_on_one_page_mm(marker: MarkerPrint, page: str) -> float:
    """The largest inner square, in tenths of a mm, whose marker, crop marks and labels fit one ``page``."""
    def fits(tenths: int) -> bool:
        return fits_one_page([MarkerPrint(marker.layout, marker.marker_id, tenths / 10, marker.quiet_zone_cells)], page)

    low, high = 0, 10_000  # bisection on the slot check itself, labels (with their printed size) and all
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (middle, high) if fits(middle) else (low, middle)
    return low / 10


def draw_marker(sheet: SheetPage, marker: MarkerPrint, x_mm: float, y_mm: float) -> None:
    """Draw the marker's cells and circles with the cut square's top-left at (x, y) mm, as one q/Q group."""
    cell, q = marker.cell_mm, marker.quiet_zone_cells
    layout = marker.layout
    sheet.canvas.saveState()  # PDF q ... Q: one marker, one group
    sheet.fill_rects([(x_mm + (column + q) * cell, y_mm + (row + q) * cell, length * cell, cell)
                      for row, column, length in cell_runs(layout.cells(marker.marker_id))])
    circles = np.asarray(layout.circles, dtype=float).reshape(-1, 3)
    if len(circles):
        sheet.fill_circles([(x_mm + (u + q) * cell, y_mm + (v + q) * cell, radius * cell)
                            for u, v, radius in circles])
    sheet.canvas.restoreState()


def draw_crop_marks(sheet: SheetPage, x_mm: float, y_mm: float, side_mm: float, height_mm: float | None = None) -> None:
    """Two short lines outside each corner of the square (or rectangle), along its edges' extensions."""
    near, far = CROP_MARK_GAP_MM, CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    height_mm = side_mm if height_mm is None else height_mm
    segments = []
    for cx, sx in ((x_mm, -1), (x_mm + side_mm, 1)):
        for cy, sy in ((y_mm, -1), (y_mm + height_mm, 1)):
            segments += [(cx + sx * near, cy, cx + sx * far, cy), (cx, cy + sy * near, cx, cy + sy * far)]
    sheet.lines(segments, CROP_MARK_WIDTH_MM)


def draw_footer(sheet: SheetPage, page_index: int, n_pages: int) -> None:
    bar_y = sheet.height_mm - PAGE_MARGIN_MM - 1.5
    sheet.fill_rects([(PAGE_MARGIN_MM, bar_y, SCALE_BAR_MM, 1.0)])
    sheet.text(PAGE_MARGIN_MM + SCALE_BAR_MM + 3.0, bar_y + 1.0,
               f"this bar is {num(SCALE_BAR_MM)} mm: print at 100 % (no fit to page)", FOOTER_TEXT_PT)
    page_text = f"companion RS markers, page {page_index + 1}/{n_pages}"
    sheet.text(sheet.width_mm - PAGE_MARGIN_MM - text_width_mm(page_text, FOOTER_TEXT_PT), bar_y + 1.0,
               page_text, FOOTER_TEXT_PT)


@dataclass(frozen=True)
class TileGeometry:
    """A marker too large for a page, cut into tiles of whole cells (one per page).

    column_cells, row_cells: the cell boundaries between tiles, from 0 to the
    marker's outer cells (tile (r, c) holds columns column_cells[c] up to
    column_cells[c + 1], and rows likewise).
    """

    page_mm: tuple[float, float]
    column_cells: tuple[int, ...]
    row_cells: tuple[int, ...]

    @property
    def columns(self) -> int:
        return len(self.column_cells) - 1

    @property
    def rows(self) -> int:
        return len(self.row_cells) - 1

    @property
    def per_marker(self) -> int:
        return self.columns * self.rows


def tile_geometry(marker: MarkerPrint, page: str) -> TileGeometry:
    """Tiles of whole cells, as even as can be, each with its marks and label inside the page's margins."""
    page_w, page_h = PAGES_MM[page]
    mark_reach = CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    tile_w = page_w - 2 * PAGE_MARGIN_MM - 2 * mark_reach
    tile_h = page_h - 2 * PAGE_MARGIN_MM - FOOTER_MM - 2 * mark_reach - LABEL_LINE_MM
    cells_w, cells_h = int(tile_w // marker.cell_mm), int(tile_h // marker.cell_mm)
    if cells_w < 1 or cells_h < 1:
        raise PrintingError(f"one {num(marker.cell_mm)} mm cell does not fit one {page_name(page)} page; use a smaller --size-mm")
    n = marker.outer_cells
    columns, rows = -(-n // cells_w), -(-n // cells_h)
    # even cuts: tile k starts at round(k n / count) (no tile is wider than cells_w)
    return TileGeometry((page_w, page_h), tuple(round(k * n / columns) for k in range(columns + 1)),
                        tuple(round(k * n / rows) for k in range(rows + 1)))


def draw_tile(sheet: SheetPage, marker: MarkerPrint, geometry: TileGeometry, row: int, column: int) -> None:
    """Tile (row, column) of the marker at the page's top-left margin: its cells (the marker clipped
    to them), crop marks at its corners, an alignment tick at every cell boundary along its
    edges, and a label saying which tile it is."""
    cell = marker.cell_mm
    c0, c1 = geometry.column_cells[column], geometry.column_cells[column + 1]
    r0, r1 = geometry.row_cells[row], geometry.row_cells[row + 1]
    mark_reach = CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    x, y = PAGE_MARGIN_MM + mark_reach, PAGE_MARGIN_MM + mark_reach
    width, height = (c1 - c0) * cell, (r1 - r0) * cell
    canvas = sheet.canvas
    canvas.saveState()
    clip = canvas.beginPath()
    clip.rect(*sheet.point(x, y + height), width * PT_PER_MM, height * PT_PER_MM)
    canvas.clipPath(clip, stroke=0, fill=0)
    draw_marker(sheet, marker, x - c0 * cell, y - r0 * cell)
    canvas.restoreState()
    draw_crop_marks(sheet, x, y, width, height)
    near, far = CROP_MARK_GAP_MM, CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM * 2 / 3
    ticks = []
    for k in range(1, c1 - c0):  # inner cell boundaries: the corners have crop marks
        tx = x + k * cell
        ticks += [(tx, y - near, tx, y - far), (tx, y + height + near, tx, y + height + far)]
    for k in range(1, r1 - r0):
        ty = y + k * cell
        ticks += [(x - near, ty, x - far, ty), (x + width + near, ty, x + width + far, ty)]
    sheet.lines(ticks, CROP_MARK_WIDTH_MM)
    layout = marker.layout
    sheet.text(x, y + height + mark_reach + LABEL_LINE_MM - 0.5,
               f"{marker.symbol}   id {marker.marker_id}, parity {layout.parity}, {layout.data_size}x{layout.data_size}, "
               f"inner square {num(marker.size_mm)} mm: tile row {row + 1}/{geometry.rows}, column {column + 1}/"
               f"{geometry.columns} (cells {c0}-{c1 - 1} x {r0}-{r1 - 1}); cut at the marks, butt the tiles",
               LABEL_SIZES_PT[1])


def check_pdf(markers: list[MarkerPrint], page: str) -> None:
    """The PrintingError ``markers_pdf`` would raise, found without drawing: a cell larger than the page, or
    more than MAX_TILED_PAGES pages of tiles."""
    if not fits_one_page(markers, page):
        tiled_pages(markers, page)


def tiled_pages(markers: list[MarkerPrint], page: str) -> TileGeometry:
    """``tile_geometry`` of the markers, if they take at most MAX_TILED_PAGES pages."""
    geometry = tile_geometry(markers[0], page)
    n_pages = geometry.per_marker * len(markers)
    if n_pages > MAX_TILED_PAGES:
        raise PrintingError(f"{len(markers)} marker(s) of {num(markers[0].size_mm)} mm would take {n_pages} {page_name(page)} "
                            f"pages (at most {MAX_TILED_PAGES}); use --format svg, or fewer or smaller markers")
    return geometry


def tiled_pdf(markers: list[MarkerPrint], page: str) -> bytes:
    """Each marker on ``tile_geometry`` pages, tile by tile (row by row)."""
    geometry = tiled_pages(markers, page)
    n_pages = geometry.per_marker * len(markers)
    out, canvas = _pdf_canvas(markers, geometry.page_mm)
    sheet = SheetPage(canvas, *geometry.page_mm)
    page_index = 0
    for marker in markers:
        for row in range(geometry.rows):
            for column in range(geometry.columns):
                draw_tile(sheet, marker, geometry, row, column)
                draw_footer(sheet, page_index, n_pages)
                canvas.showPage()
                page_index += 1
    canvas.save()
    return out.getvalue()


def _pdf_canvas(markers: list[MarkerPrint], page_mm: tuple[float, float]) -> tuple[io.BytesIO, Canvas]:
    out = io.BytesIO()
    # Uncompressed content streams stay readable and checkable; invariant: the same
    # markers give the same bytes (fixed dates and document id).
    canvas = Canvas(out, pagesize=(page_mm[0] * PT_PER_MM, page_mm[1] * PT_PER_MM), pageCompression=0, invariant=1)
    first = markers[0]
    canvas.setTitle(f"RS markers, parity {first.layout.parity}, {first.layout.data_size}x{first.layout.data_size}, "
                    f"inner square {num(first.size_mm)} mm")
    canvas.setCreator("companion markers")
    canvas.setProducer("companion markers (reportlab)")
    return out, canvas


def markers_pdf(markers: list[MarkerPrint], page: str = "a4") -> bytes:
    """A PDF of marker sheets (all ``markers`` share layout, size and quiet zone); markers larger
    than a page are tiled (``tiled_pdf``)."""
    if not fits_one_page(markers, page):
        return tiled_pdf(markers, page)
    geometry = sheet_geometry(markers, page)
    n_pages = geometry.page_count(len(markers))
    mark_reach = CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    page_w, page_h = geometry.page_mm
    slot_w, slot_h = geometry.slot_mm
    # centre the columns on the page
    left_mm = (page_w - geometry.columns * (slot_w + SLOT_SPACING_MM) + SLOT_SPACING_MM) / 2
    out, canvas = _pdf_canvas(markers, geometry.page_mm)
    sheet = SheetPage(canvas, page_w, page_h)
    for page_index in range(n_pages):
        start = page_index * geometry.per_page
        for k, marker in enumerate(markers[start:start + geometry.per_page]):
            row, column = divmod(k, geometry.columns)
            slot_x = left_mm + column * (slot_w + SLOT_SPACING_MM)
            slot_y = PAGE_MARGIN_MM + row * (slot_h + SLOT_SPACING_MM)
            x = slot_x + (slot_w - marker.outer_mm) / 2
            y = slot_y + mark_reach
            draw_marker(sheet, marker, x, y)
            draw_crop_marks(sheet, x, y, marker.outer_mm)
            label_x = min(x, slot_x + (slot_w - label_width_mm(marker)) / 2)  # under the marker, inside the slot
            baseline = y + marker.outer_mm + mark_reach + LABEL_LINE_MM - 0.5
            for line, (text, size_pt) in enumerate(zip(marker_labels(marker), LABEL_SIZES_PT)):
                sheet.text(label_x, baseline + line * LABEL_LINE_MM, text, size_pt)
        draw_footer(sheet, page_index, n_pages)
        canvas.showPage()
    canvas.save()
    return out.getvalue()
