"""ChArUco calibration boards: the board's definition, and its PDF at exact scale.

A ChArUco board is a chessboard whose white squares hold ArUco markers: the
markers name the chessboard corners around them, so a view that shows only
part of the board still gives corners that are known by number, unlike a
plain chessboard that must be seen whole. The corners are the calibration
points (chessboard corners are found to a fraction of a pixel); the markers
only identify them.

The markers come from **OpenCV's** predefined dictionaries (``DICT_5X5_100``
by default), not from the RS markers' dictionary: OpenCV's ``CharucoDetector``
then does the detection, and the board is the one any OpenCV tool knows by
its four numbers (squares across and down, square and marker side). OpenCV's
current layout is used: the top-left square is black and the markers sit in
the white squares, numbered from 0 along the rows.

``companion markers --charuco`` writes the PDF; ``companion calibrate
--charuco`` reads views of it (``companion.geometry.calibration``).
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import cv2
import numpy as np
from reportlab.lib.units import mm as PT_PER_MM  # 72 / 25.4 points per millimetre
from reportlab.pdfgen.canvas import Canvas

from companion.markers.printing import MIN_CELL_MM, PAGE_MARGIN_MM, PAGES_MM, SCALE_BAR_MM, SheetPage, cell_runs, num, page_name

DEFAULT_DICTIONARY = "DICT_5X5_100"
LABEL_PT = 8.0
FOOTER_PT = 6.5
FOOTER_MM = 14.0   # kept at the page bottom for the label, the scale bar and its note


class CharucoError(ValueError):
    """A board that cannot be made (sizes, dictionary) or printed (too big for the page)."""


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board: ``columns`` x ``rows`` squares of ``square_mm``, markers of ``marker_mm`` side."""

    columns: int = 8
    rows: int = 11
    square_mm: float = 22.0
    marker_mm: float = 16.0
    dictionary: str = DEFAULT_DICTIONARY

    def __post_init__(self):
        if not (isinstance(self.columns, int) and isinstance(self.rows, int) and self.columns >= 3
                and self.rows >= 3):
            raise CharucoError(f"a ChArUco board needs at least 3x3 squares, not {self.columns}x{self.rows}")
        if not (self.square_mm > 0 and 0 < self.marker_mm < self.square_mm):
            raise CharucoError(f"the marker side ({num(self.marker_mm)} mm) must be positive and smaller than "
                               f"the square ({num(self.square_mm)} mm)")
        if not (self.dictionary.startswith("DICT_") and hasattr(cv2.aruco, self.dictionary)):
            raise CharucoError(f"unknown OpenCV dictionary {self.dictionary!r} (e.g. DICT_5X5_100, DICT_4X4_250)")
        markers = self.columns * self.rows // 2
        available = self.aruco_dictionary().bytesList.shape[0]
        if markers > available:
            raise CharucoError(f"{self.columns}x{self.rows} squares hold {markers} markers, more than the "
                               f"{available} of {self.dictionary}")

    def aruco_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board, lengths in metres (its chessboard corners are the calibration points)."""
        return cv2.aruco.CharucoBoard((self.columns, self.rows), self.square_mm / 1000.0,
                                      self.marker_mm / 1000.0, self.aruco_dictionary())

    @property
    def corners(self) -> int:
        """Inner chessboard corners: the calibration points of a whole view."""
        return (self.columns - 1) * (self.rows - 1)

    def describe(self) -> str:
        return (f"ChArUco {self.columns}x{self.rows} squares of {num(self.square_mm)} mm, markers "
                f"{num(self.marker_mm)} mm, OpenCV {self.dictionary}")

    def calibrate_options(self) -> str:
        """The ``companion calibrate`` options that name this board."""
        options = f"--charuco {self.columns}x{self.rows} --square-mm {num(self.square_mm)} --marker-mm {num(self.marker_mm)}"
        return options if self.dictionary == DEFAULT_DICTIONARY else options + f" --aruco-dictionary {self.dictionary}"

    def file_stem(self) -> str:
        return f"charuco-{self.columns}x{self.rows}-{num(self.square_mm)}mm-{num(self.marker_mm)}mm"


def board_cells(spec: CharucoSpec) -> tuple[list[tuple[int, int]], list[tuple[int, float, float]]]:
    """The black squares as (row, column), and each marker as (id, left mm, top mm) on the board.

    Read from OpenCV's board itself (its marker corners, top-left first, in
    metres from the board's top-left corner, y down): the squares without a
    marker are the black ones.
    """
    board = spec.board()
    markers, white = [], set()
    for marker_id, corners in zip(board.getIds().ravel(), board.getObjPoints()):
        left_m, top_m = np.asarray(corners, dtype=float).reshape(-1, 3)[0, :2]
        markers.append((int(marker_id), left_m * 1000.0, top_m * 1000.0))
        white.add((int(top_m * 1000.0 // spec.square_mm), int(left_m * 1000.0 // spec.square_mm)))
    black = [(r, c) for r in range(spec.rows) for c in range(spec.columns) if (r, c) not in white]
    return black, markers


def marker_cells(spec: CharucoSpec, marker_id: int) -> np.ndarray:
    """(n + 2, n + 2) 0/1 grid of one marker with its one-cell black border (1: black)."""
    side = spec.aruco_dictionary().markerSize + 2
    image = cv2.aruco.generateImageMarker(spec.aruco_dictionary(), marker_id, side, borderBits=1)
    return (image < 128).astype(np.uint8)


def check_printable(spec: CharucoSpec) -> None:
    """A CharucoError, with the smallest --marker-mm that prints, for marker cells below MIN_CELL_MM."""
    cells = spec.aruco_dictionary().markerSize + 2
    if spec.marker_mm / cells < MIN_CELL_MM:
        raise CharucoError(f"--marker-mm {num(spec.marker_mm)} is too small to print: its cells would be "
                           f"{spec.marker_mm / cells:.3g} mm, at least {MIN_CELL_MM:g} mm (--marker-mm "
                           f"{num(MIN_CELL_MM * cells)} or more for the {cells} cells of a {spec.dictionary} marker)")


def charuco_pdf(spec: CharucoSpec, page: str = "a4") -> bytes:
    """One page: the board at exact scale, centred, with its description, the calibrate options and a
    50 mm scale bar below it. Vector shapes, drawn as the RS marker sheets are (``SheetPage``)."""
    check_printable(spec)
    page_w, page_h = PAGES_MM[page]
    board_w, board_h = spec.columns * spec.square_mm, spec.rows * spec.square_mm
    usable_w, usable_h = page_w - 2 * PAGE_MARGIN_MM, page_h - 2 * PAGE_MARGIN_MM - FOOTER_MM
    if board_w > usable_w or board_h > usable_h:
        raise CharucoError(f"the board is {num(board_w)} x {num(board_h)} mm, more than one {page_name(page)} page offers "
                           f"({num(usable_w)} x {num(usable_h)} mm inside the margins); use a smaller --square-mm "
                           "or fewer squares")
    left, top = (page_w - board_w) / 2, PAGE_MARGIN_MM + (usable_h - board_h) / 2
    out = io.BytesIO()
    canvas = Canvas(out, pagesize=(page_w * PT_PER_MM, page_h * PT_PER_MM), pageCompression=0, invariant=1)
    canvas.setTitle(spec.describe())
    canvas.setCreator("companion markers --charuco")
    sheet = SheetPage(canvas, page_w, page_h)
    black, markers = board_cells(spec)
    sheet.fill_rects([(left + c * spec.square_mm, top + r * spec.square_mm, spec.square_mm, spec.square_mm)
                      for r, c in black])
    for marker_id, marker_left, marker_top in markers:
        cells = marker_cells(spec, marker_id)
        cell_mm = spec.marker_mm / cells.shape[0]
        x0, y0 = left + marker_left, top + marker_top
        sheet.fill_rects([(x0 + column * cell_mm, y0 + row * cell_mm, length * cell_mm, cell_mm)
                          for row, column, length in cell_runs(cells)])
    baseline = top + board_h + 6.0
    sheet.text(left, baseline, spec.describe(), LABEL_PT)
    sheet.text(left, baseline + 4.0, f"companion calibrate {spec.calibrate_options()}", FOOTER_PT)
    bar_y = page_h - PAGE_MARGIN_MM - 1.5
    sheet.fill_rects([(PAGE_MARGIN_MM, bar_y, SCALE_BAR_MM, 1.0)])
    note = f"this bar is {num(SCALE_BAR_MM)} mm: print at 100 % (no fit to page), glue the sheet flat on a rigid board"
    sheet.text(PAGE_MARGIN_MM + SCALE_BAR_MM + 3.0, bar_y + 1.0, note, FOOTER_PT)
    canvas.showPage()
    canvas.save()
    return out.getvalue()
