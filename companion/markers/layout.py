"""The RS marker: cell layout and Reed-Solomon encoding (decoding: ``companion.markers.codec``).

Layout (docs/marker-spec.md has the figure). For an n x n data grid (n = 6 by
default), p parity symbols per code and a one-cell white gap:

* the *inner marker* is an ordinary ArUco marker: n x n data cells inside a
  one-cell black border, (n + 2) cells square, starting at cell o = p + 1;
* every data row is one n-bit symbol (leftmost cell = most significant bit),
  every data column too (top cell = most significant bit);
* the row code RS(n + p, n) over GF(2^n) protects the n row symbols; its p
  parity symbols are laid out as p *rows* of n cells above the inner marker
  and again below it (each bit under the data column of the same index);
* the column code protects the n column symbols; its p parity symbols are
  p *columns* of n cells left of the inner marker and again right of it;
* parity symbol k sits k cells away from the gap (k = 0 nearest the marker);
* a white gap of one cell separates the parity bands from the black border;
* the four void corners carry one large and two small black circles each.

Where each of these lies is written once, here: ``inner_origin`` (the inner
marker's first cell), ``data_origin`` (the first data cell),
``parity_band`` (the row, or column, of each parity copy).

Grid coordinates (u, v) are in cells from the grid's outer top-left corner,
u right and v down; cell (row r, column c) spans u in [c, c + 1], v in [r, r + 1].
The grid is N = n + 2 + 2 (p + 1) cells square: 14 for n = 6, p = 2.
"""
from __future__ import annotations

from functools import cached_property

import cv2
import numpy as np
import reedsolo

from companion.markers.dictionary import MarkerDictionary, load_dictionary

UNKNOWN = -1  # a sampled cell that could not be read (black 1, white 0)
GAP_CELLS = 1
PRIMITIVE_POLYNOMIALS = {5: 0x25, 6: 0x43, 8: 0x11D}  # x^5+x^2+1, x^6+x+1, x^8+x^4+x^3+x^2+1

# Corner circles of the top-left corner as (u, v, radius) in cells, per parity;
# the other corners are these rotated about the grid centre.
TOP_LEFT_CIRCLES = {
    2: ((1.0, 1.0, 0.8), (3.0, 1.0, 0.4), (1.0, 3.0, 0.4)),
    4: ((2.0, 2.0, 1.2), (4.5, 2.0, 0.6), (2.0, 4.5, 0.6)),
}


class MarkerLayoutError(ValueError):
    """A layout was asked for with parameters we do not support."""


class MarkerLayout:
    """Cell layout and encoder of RS markers of one parity and dictionary."""

    def __init__(self, parity: int = 2, dictionary: str | int = "6x6", gap_cells: int = GAP_CELLS):
        if parity not in TOP_LEFT_CIRCLES:
            raise MarkerLayoutError(f"parity must be one of {sorted(TOP_LEFT_CIRCLES)}, not {parity}")
        self.dictionary: MarkerDictionary = load_dictionary(dictionary)
        self.parity = parity
        self.gap_cells = gap_cells
        self.data_size = n = self.dictionary.size
        self.inner_origin = parity + gap_cells
        self.inner_cells = n + 2
        self.data_origin = self.inner_origin + 1  # inside the inner marker's one-cell border
        self.n_cells = n + 2 + 2 * self.inner_origin
        # RS(n + p, n) over GF(2^n), shared by the row and the column code (and by the decoder)
        self.rs_codec = reedsolo.RSCodec(nsym=parity, nsize=2**n - 1, c_exp=n, prim=PRIMITIVE_POLYNOMIALS[n])
        self._masks = self._codeword_masks()

    # ----- geometry -------------------------------------------------------------------------

    @cached_property
    def circles(self) -> np.ndarray:
        """(12, 3) float: (u, v, radius) in cells; TL corner (large, top, left), then TR, BR, BL.

        Empty (0, 3) for the gap-less study layout, whose corners have no room.
        """
        if self.gap_cells != GAP_CELLS:
            return np.zeros((0, 3))
        top_left = np.array(TOP_LEFT_CIRCLES[self.parity])
        corners = [top_left]
        for _ in range(3):
            u, v, r = corners[-1].T
            corners.append(np.stack([self.n_cells - v, u, r], axis=1))  # 90 deg clockwise about the centre
        return np.concatenate(corners)

    @cached_property
    def inner_corners_cells(self) -> np.ndarray:
        """(4, 2) grid (u, v) of the inner black square's corners TL, TR, BR, BL."""
        lo, hi = self.inner_origin, self.inner_origin + self.inner_cells
        return np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], dtype=float)

    @property
    def data_span(self) -> slice:
        """The grid rows (and columns) of the data cells."""
        return slice(self.data_origin, self.data_origin + self.data_size)

    def data_cell(self, row: int, column: int) -> tuple[int, int]:
        """Grid (row, column) of data bit (row, column)."""
        return self.data_origin + row, self.data_origin + column

    def parity_band(self, k: int, near_side: bool) -> int:
        """Grid row (or column) of parity symbol k in the band before (True) or after the marker.

        Symbol k sits k cells away from the gap: row p - 1 - k before, N - p + k after.
        """
        if near_side:
            return self.parity - 1 - k
        return self.n_cells - self.parity + k

    def _codeword_masks(self) -> dict[str, np.ndarray]:
        """Boolean (N, N) masks of the data, each parity band, and the fixed cells."""
        shape = (self.n_cells, self.n_cells)
        span = self.data_span
        data = np.zeros(shape, bool)
        data[span, span] = True
        bands = np.zeros(shape, bool)
        for k in range(self.parity):
            for near in (True, False):
                i = self.parity_band(k, near)
                bands[i, span] = True
                bands[span, i] = True
        border = np.zeros(shape, bool)
        lo, hi = self.inner_origin, self.inner_origin + self.inner_cells
        border[lo:hi, lo:hi] = True
        border[lo + 1:hi - 1, lo + 1:hi - 1] = False
        return {"data": data, "parity": bands, "codeword": data | bands, "border": border}

    @property
    def codeword_mask(self) -> np.ndarray:
        """(N, N) bool: the cells that carry data or parity bits."""
        return self._masks["codeword"]

    @property
    def border_mask(self) -> np.ndarray:
        """(N, N) bool: the inner marker's black border (always black)."""
        return self._masks["border"]

    @property
    def white_mask(self) -> np.ndarray:
        """(N, N) bool: cells that are always white (gaps and corner areas; circles aside)."""
        return ~(self._masks["codeword"] | self._masks["border"])

    # ----- encoding -------------------------------------------------------------------------

    def parity_symbols(self, data_bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, n) data bits -> (row-code parity, column-code parity), each (p,) symbols."""
        rows = bits_to_symbols(data_bits)
        columns = bits_to_symbols(data_bits.T)
        return self.parity_of(rows), self.parity_of(columns)

    def parity_of(self, message: np.ndarray) -> np.ndarray:
        """(p,) int parity symbols of a message of (n,) symbols."""
        return np.array(self.rs_codec.encode(bytearray(message.tolist()))[-self.parity:], dtype=np.int64)

    def cells(self, marker_id: int) -> np.ndarray:
        """(N, N) uint8 cells of marker ``marker_id``: 1 = black. Circles are not cells."""
        data_bits = self.dictionary.bits[marker_id]
        n, span = self.data_size, self.data_span
        grid = self.border_mask.astype(np.uint8)
        grid[span, span] = data_bits
        row_parity, column_parity = self.parity_symbols(data_bits)
        for k in range(self.parity):
            row_bits = symbols_to_bits(row_parity[k:k + 1], n)[0]
            column_bits = symbols_to_bits(column_parity[k:k + 1], n)[0]
            for near in (True, False):
                i = self.parity_band(k, near)
                grid[i, span] = row_bits
                grid[span, i] = column_bits
        return grid

    @cached_property
    def all_cells(self) -> np.ndarray:
        """(50, N, N) uint8 cells of every marker of the dictionary."""
        return np.stack([self.cells(i) for i in range(len(self.dictionary.bits))])


def bits_to_symbols(bits: np.ndarray) -> np.ndarray:
    """(m, n) bits -> (m,) int symbols, first column the most significant bit."""
    n = bits.shape[-1]
    return (bits.astype(np.int64) << np.arange(n - 1, -1, -1)).sum(axis=-1)


def symbols_to_bits(symbols: np.ndarray, n: int) -> np.ndarray:
    """(m,) int symbols -> (m, n) uint8 bits, most significant bit first."""
    return ((np.asarray(symbols)[:, None] >> np.arange(n - 1, -1, -1)) & 1).astype(np.uint8)


def marker_image(layout: MarkerLayout, marker_id: int, px_per_cell: float, quiet_zone_cells: int = 1) -> np.ndarray:
    """Render a marker: (H, W) uint8, black 0 on white 255, H = W = ``cell_edges_px(N + 2 q, ppc)[-1]``.

    ``px_per_cell`` may be fractional (a PNG at an exact print resolution):
    pixel j shows the cell under its centre, ``floor((j + 0.5) / ppc)``, so
    cell edges fall on whole pixels and n cells are n ppc pixels wide, rounded
    (exactly, when n ppc is whole). For a whole ppc, cell (r, c) covers pixels
    [(q + c) ppc, (q + c + 1) ppc). Circles are anti-aliased at their exact
    (u, v) centres.
    """
    cells = np.pad(layout.cells(marker_id), quiet_zone_cells).astype(np.uint8)
    side = int(cell_edges_px(cells.shape[0], px_per_cell)[-1])
    index = np.floor((np.arange(side) + 0.5) / px_per_cell).astype(int)
    image = np.where(cells[np.ix_(index, index)] > 0, 0, 255).astype(np.uint8)
    shift = 4
    for u, v, radius in layout.circles:
        centre = cell_point_to_px(np.array([u, v]), px_per_cell, quiet_zone_cells)
        cv2.circle(image, tuple(int(round(c * (1 << shift))) for c in centre), int(round(radius * px_per_cell * (1 << shift))),
                   0, thickness=-1, lineType=cv2.LINE_AA, shift=shift)
    return image


def cell_edges_px(n_cells: int, px_per_cell: float) -> np.ndarray:
    """(n_cells + 1,) int: the first pixel of each cell boundary 0..n_cells in an image drawn by ``marker_image``."""
    # the first pixel j with (j + 0.5) / ppc >= k
    return np.ceil(np.arange(n_cells + 1) * px_per_cell - 0.5).astype(int)


def cell_point_to_px(uv: np.ndarray, px_per_cell: float, quiet_zone_cells: float = 0) -> np.ndarray:
    """Grid (u, v) in cells -> pixel (x, y) in an image rendered by ``marker_image`` (pixel centres at integers)."""
    return (np.asarray(uv, dtype=float) + quiet_zone_cells) * px_per_cell - 0.5
