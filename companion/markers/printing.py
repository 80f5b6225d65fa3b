"""`companion markers`: printable RS markers as PNG (with JSON sidecars), SVG, or PDF sheets.

Sizes: ``--size-mm`` is the printed side of the inner black square (the
``size_m`` of maps and configs); the whole grid with its quiet zone is
``(N + 2 q) / (n + 2)`` times that.

* PNG: one image per marker with an integer number of pixels per cell
  (``--dpi`` picks it: the nearest integer to the cell's size at that DPI),
  and a pHYs chunk whose resolution makes the inner square print at
  ``--size-mm`` (so the stored DPI is near, not exactly, ``--dpi``). Next to
  it a JSON sidecar with the geometry in the PNG's pixel coordinates
  (pixel centres at integers, so the black square's outer edge is at half
  pixels).
* SVG: vector, width and height in mm, cells as rectangles (horizontal runs
  merged), circles as circles.
* PDF: sheets of markers at exact scale on A4 or Letter with crop marks, the
  symbol, id, parity and inner-square size beside each, and a 50 mm scale bar.
"""
from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.markers.dictionary import DictionaryError
from companion.markers.layout import MarkerLayout, cell_point_to_px, marker_image
from companion.markers.pdf import PdfPage, text_width_mm, write_pdf

MM_PER_INCH = 25.4
PAGES_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}
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


# --------------------------------------------------------------------- PNG

def png_px_per_cell(cell_mm: float, dpi: float) -> int:
    """Integer pixels per cell nearest to the cell's size at ``dpi`` (at least 1)."""
    # px = mm / 25.4 * dpi
    return max(1, round(cell_mm / MM_PER_INCH * dpi))


def png_px_per_m(marker: MarkerPrint, px_per_cell: int) -> int:
    """pHYs resolution (integer pixels per metre) that prints the inner square at ``size_mm``."""
    # px/m = inner square px / inner square m
    return max(1, round(marker.layout.inner_cells * px_per_cell / (marker.size_mm / 1000.0)))


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


def png_sidecar(marker: MarkerPrint, px_per_cell: int, px_per_m: int, image_shape: tuple[int, ...]) -> dict:
    """The JSON sidecar of a marker PNG: identity, scale and geometry in PNG pixels."""
    layout, q = marker.layout, marker.quiet_zone_cells
    corners = cell_point_to_px(layout.inner_corners_cells, px_per_cell, q)
    circles = np.asarray(layout.circles, dtype=float).reshape(-1, 3)
    circle_centres = cell_point_to_px(circles[:, :2], px_per_cell, q)
    inner_px = layout.inner_cells * px_per_cell
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
        # printed size from the pHYs resolution: exact for what the file says
        "size_mm": inner_px / px_per_m * 1000.0,
        "dpi": px_per_m * MM_PER_INCH / 1000.0,
        "image_px": [int(image_shape[1]), int(image_shape[0])],
        "inner_corners_px": corners.tolist(),
        "circles_px": [[float(x), float(y), float(r * px_per_cell)]
                       for (x, y), r in zip(circle_centres, circles[:, 2])],
    }


def write_marker_png(marker: MarkerPrint, dpi: float, out_dir: Path) -> tuple[Path, dict]:
    """Write ``<stem>.png`` and ``<stem>.json`` into ``out_dir``; return the PNG path and sidecar."""
    px_per_cell = png_px_per_cell(marker.cell_mm, dpi)
    px_per_m = png_px_per_m(marker, px_per_cell)
    image = marker_image(marker.layout, marker.marker_id, px_per_cell, marker.quiet_zone_cells)
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise PrintingError(f"OpenCV could not encode the PNG of {marker.symbol}")
    path = out_dir / f"{marker.file_stem()}.png"
    path.write_bytes(png_with_phys(encoded.tobytes(), px_per_m))
    sidecar = png_sidecar(marker, px_per_cell, px_per_m, image.shape)
    path.with_suffix(".json").write_text(json.dumps(sidecar, indent=2) + "\n")
    return path, sidecar


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


def marker_labels(marker: MarkerPrint) -> tuple[str, str]:
    layout = marker.layout
    return (f"{marker.symbol}   id {marker.marker_id}",
            f"parity {layout.parity}, {layout.data_size}x{layout.data_size}, inner square {num(marker.size_mm)} mm")


def sheet_geometry(marker: MarkerPrint, page: str) -> SheetGeometry:
    """Grid of equal slots that fits the page inside its margins and footer."""
    page_w, page_h = PAGES_MM[page]
    mark_reach = CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    labels = marker_labels(marker)
    label_w = max(text_width_mm(text, size) for text, size in zip(labels, LABEL_SIZES_PT))
    slot_w = max(marker.outer_mm + 2 * mark_reach, label_w)
    slot_h = marker.outer_mm + 2 * mark_reach + len(labels) * LABEL_LINE_MM
    usable_w = page_w - 2 * PAGE_MARGIN_MM
    usable_h = page_h - 2 * PAGE_MARGIN_MM - FOOTER_MM
    # n slots need n w + (n - 1) spacing <= usable
    columns = int((usable_w + SLOT_SPACING_MM) // (slot_w + SLOT_SPACING_MM))
    rows = int((usable_h + SLOT_SPACING_MM) // (slot_h + SLOT_SPACING_MM))
    if columns < 1 or rows < 1:
        raise PrintingError(f"a marker with a {num(marker.size_mm)} mm inner square needs a "
                            f"{num(slot_w)} x {num(slot_h)} mm slot, more than a {page} page offers "
                            f"({num(usable_w)} x {num(usable_h)} mm inside the margins); use a smaller --size-mm")
    return SheetGeometry((page_w, page_h), (slot_w, slot_h), columns, rows)


def draw_marker(pdf: PdfPage, marker: MarkerPrint, x_mm: float, y_mm: float) -> None:
    """Draw the marker's cells and circles with the cut square's top-left at (x, y) mm."""
    cell, q = marker.cell_mm, marker.quiet_zone_cells
    layout = marker.layout
    pdf.begin_group()
    for row, column, length in cell_runs(layout.cells(marker.marker_id)):
        pdf.rect(x_mm + (column + q) * cell, y_mm + (row + q) * cell, length * cell, cell)
    pdf.fill()
    circles = np.asarray(layout.circles, dtype=float).reshape(-1, 3)
    for u, v, radius in circles:
        pdf.circle(x_mm + (u + q) * cell, y_mm + (v + q) * cell, radius * cell)
    if len(circles):
        pdf.fill()
    pdf.end_group()


def draw_crop_marks(pdf: PdfPage, x_mm: float, y_mm: float, side_mm: float) -> None:
    """Two short lines outside each corner of the square, along its edges' extensions."""
    near, far = CROP_MARK_GAP_MM, CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    for cx, sx in ((x_mm, -1), (x_mm + side_mm, 1)):
        for cy, sy in ((y_mm, -1), (y_mm + side_mm, 1)):
            pdf.line(cx + sx * near, cy, cx + sx * far, cy, CROP_MARK_WIDTH_MM)
            pdf.line(cx, cy + sy * near, cx, cy + sy * far, CROP_MARK_WIDTH_MM)


def draw_footer(pdf: PdfPage, page_index: int, n_pages: int) -> None:
    width, height = pdf.width_mm, pdf.height_mm
    bar_y = height - PAGE_MARGIN_MM - 1.5
    pdf.rect(PAGE_MARGIN_MM, bar_y, SCALE_BAR_MM, 1.0)
    pdf.fill()
    pdf.text(PAGE_MARGIN_MM + SCALE_BAR_MM + 3.0, bar_y + 1.0,
             f"this bar is {num(SCALE_BAR_MM)} mm: print at 100 % (no fit to page)", 6.5)
    page_text = f"companion RS markers, page {page_index + 1}/{n_pages}"
    pdf.text(width - PAGE_MARGIN_MM - text_width_mm(page_text, 6.5), bar_y + 1.0, page_text, 6.5)


def markers_pdf(markers: list[MarkerPrint], page: str = "a4") -> bytes:
    """A PDF of marker sheets (all ``markers`` share layout, size and quiet zone)."""
    geometry = sheet_geometry(markers[0], page)
    mark_reach = CROP_MARK_GAP_MM + CROP_MARK_LENGTH_MM
    slot_w, slot_h = geometry.slot_mm
    # centre the columns on the page
    left_mm = (geometry.page_mm[0] - geometry.columns * (slot_w + SLOT_SPACING_MM) + SLOT_SPACING_MM) / 2
    pages = []
    for start in range(0, len(markers), geometry.per_page):
        pdf = PdfPage(*geometry.page_mm)
        for k, marker in enumerate(markers[start:start + geometry.per_page]):
            row, column = divmod(k, geometry.columns)
            slot_x = left_mm + column * (slot_w + SLOT_SPACING_MM)
            slot_y = PAGE_MARGIN_MM + row * (slot_h + SLOT_SPACING_MM)
            x = slot_x + (slot_w - marker.outer_mm) / 2
            y = slot_y + mark_reach
            draw_marker(pdf, marker, x, y)
            draw_crop_marks(pdf, x, y, marker.outer_mm)
            labels = marker_labels(marker)
            label_w = max(text_width_mm(text, size_pt) for text, size_pt in zip(labels, LABEL_SIZES_PT))
            label_x = min(x, slot_x + (slot_w - label_w) / 2)  # under the marker, inside the slot
            baseline = y + marker.outer_mm + mark_reach + LABEL_LINE_MM - 0.5
            for line, (text, size_pt) in enumerate(zip(labels, LABEL_SIZES_PT)):
                pdf.text(label_x, baseline + line * LABEL_LINE_MM, text, size_pt)
        pages.append(pdf)
    for index, pdf in enumerate(pages):
        draw_footer(pdf, index, len(pages))
    first = markers[0]
    title = (f"RS markers, parity {first.layout.parity}, {first.layout.data_size}x{first.layout.data_size}, "
             f"inner square {num(first.size_mm)} mm")
    return write_pdf(pages, title)


# --------------------------------------------------------------------- CLI
