"""Detector stage: read a marker's N x N cell grid from the image through its homography.

Everything here is batched over M candidates at once: one ``cv2.remap`` call
samples every point of every candidate, and the cell statistics are numpy
reductions, so the cost grows with the number of pixels read, not with a
Python loop.

Homographies map grid cells to image pixels (``companion.detect.homography``).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from companion.detect import homography
from companion.markers.layout import UNKNOWN, MarkerLayout
from companion.params import require

# Sub-cell sample offsets (fractions of a cell from its centre): a 3 x 3
# pattern inside the middle 60 % of the cell, away from the blurred edges.
SUB_CELL_OFFSETS = np.array([-0.2, 0.0, 0.2])
REMAP_ROW = 16384


@dataclass(frozen=True)
class SamplingParams:
    """How a candidate's grid is read (both paths).

    min_contrast_gray: gray levels between a candidate's black (border) and
        white (gap ring) below which it is dropped; every stage's floor on a
        marker's contrast (quad screen, edge profiles, circle candidates).
    ambiguity_fraction: cells whose mean is within this share of the
        candidate's contrast from its black/white midpoint are unknown (erasures).
    occlusion_reach_cells: circles path: codeword cells this close
        (Chebyshev) to a border cell read white or a gap cell read black are
        erased (something stands in front of the marker there).
    """

    min_contrast_gray: float = 20.0
    ambiguity_fraction: float = 0.15
    occlusion_reach_cells: int = 1

    def __post_init__(self):
        require(self.min_contrast_gray > 0, "min_contrast_gray", "> 0", self.min_contrast_gray)
        require(0.0 <= self.ambiguity_fraction < 0.5, "ambiguity_fraction", "in [0, 0.5)", self.ambiguity_fraction)
        require(self.occlusion_reach_cells >= 0, "occlusion_reach_cells", ">= 0", self.occlusion_reach_cells)


def sample_image(gray: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear intensities at pixel positions.

    xy: (..., 2) float pixel positions. Returns (values (...) float32, inside (...) bool);
    points outside the image (or not finite) read as NaN and inside = False.
    """
    shape = xy.shape[:-1]
    if xy.size == 0:
        return np.zeros(shape, np.float32), np.zeros(shape, bool)
    flat = xy.reshape(-1, 2).astype(np.float32)
    h, w = gray.shape
    # 0 <= x <= w - 1 and 0 <= y <= h - 1 (False for NaN; OpenCV's range test costs half numpy's four)
    inside = cv2.inRange(flat.reshape(-1, 1, 2), (0.0, 0.0), (w - 1.0, h - 1.0)).ravel() > 0
    outside = ~inside
    # points outside (NaN and inf among them) read NaN below: any finite position off the image will do
    np.copyto(flat, -10.0, where=outside[:, None])
    # remap wants maps under 32767 columns: lay the points out in rows of REMAP_ROW
    count = len(flat)
    cols = max(min(count, REMAP_ROW), 1)
    rows = -(-count // cols)
    if rows * cols != count:
        flat = np.concatenate([flat, np.full((rows * cols - count, 2), -10.0, np.float32)])
    values = cv2.remap(gray, flat.reshape(rows, cols, 2), None, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0).reshape(-1)[:count].astype(np.float32)
    values[outside] = np.nan
    return values.reshape(shape), inside.reshape(shape)


@dataclass(frozen=True)
class CellSamples:
    """Intensity statistics of every cell of M sampled grids.

    mean: (M, N, N) float32, mean over the cell's sub-samples (NaN where a
        sub-sample fell outside the image).
    inside: (M, N, N) bool, every sub-sample of the cell is inside the image.
    """

    mean: np.ndarray
    inside: np.ndarray


@lru_cache(maxsize=8)
def _cell_sample_points(n_cells: int, offsets: tuple[float, ...]) -> np.ndarray:
    points = cell_sample_points_uncached(n_cells, np.array(offsets))
    points.flags.writeable = False
    return points


def cell_sample_points(n_cells: int, offsets: np.ndarray = SUB_CELL_OFFSETS) -> np.ndarray:
    """(S * N * N, 2) grid (u, v) of the sub-samples, sample-major (sample, row, column), so that a cell's
    statistics reduce over whole rows of N * N values (reductions over a short last axis cost several
    times more); read-only."""
    return _cell_sample_points(n_cells, tuple(float(o) for o in offsets))


def cell_sample_points_uncached(n_cells: int, offsets: np.ndarray) -> np.ndarray:
    rows, cols = np.mgrid[0:n_cells, 0:n_cells]
    dv, du = np.meshgrid(offsets, offsets, indexing="ij")
    u = cols[None] + 0.5 + du.reshape(-1, 1, 1)
    v = rows[None] + 0.5 + dv.reshape(-1, 1, 1)
    return np.stack([u, v], axis=-1).reshape(-1, 2)


def sample_cells(gray: np.ndarray, H: np.ndarray, n_cells: int,
                 offsets: np.ndarray = SUB_CELL_OFFSETS) -> CellSamples:
    """Sample every cell of M grids: H (M, 3, 3) grid -> image."""
    m = len(H)
    s = len(offsets) ** 2
    values, inside = sample_image(gray, homography.project(H, cell_sample_points(n_cells, offsets)))
    values = values.reshape(m, s, n_cells, n_cells)
    inside_cells = inside.reshape(m, s, n_cells, n_cells).all(axis=1)
    return CellSamples(values.mean(axis=1), inside_cells)


@dataclass(frozen=True)
class GridLevels:
    """Each candidate's own black and white levels: (M,) medians of its border cells and its gap ring."""

    black: np.ndarray
    white: np.ndarray

    @property
    def contrast(self) -> np.ndarray:
        return self.white - self.black


def inside_grids(points_px: np.ndarray, H: np.ndarray, n_cells: int) -> np.ndarray:
    """(K,) bool: image points inside the whole N x N grid outline of any of M grids (H: (M, 3, 3))."""
    if len(points_px) == 0 or len(H) == 0:
        return np.zeros(len(points_px), bool)
    outline = homography.project(H, np.array([[0, 0], [n_cells, 0], [n_cells, n_cells], [0, n_cells]], float))  # (M, 4, 2)
    # inside a convex clockwise polygon: on the right of (or on) every edge
    edge = outline[:, homography.NEXT_CORNER] - outline
    to_point = points_px[:, None, None, :] - outline[None]  # (K, M, 4, 2)
    cross = edge[None, ..., 0] * to_point[..., 1] - edge[None, ..., 1] * to_point[..., 0]
    return (cross >= 0).all(axis=2).any(axis=1)


def gap_ring_mask(layout: MarkerLayout) -> np.ndarray:
    """(N, N) bool: the one-cell white ring just outside the inner black square."""
    n, o = layout.n_cells, layout.inner_origin
    ring = np.zeros((n, n), bool)
    ring[o - 1:o + layout.inner_cells + 1, o - 1:o + layout.inner_cells + 1] = True
    ring[o:o + layout.inner_cells, o:o + layout.inner_cells] = False
    return ring


def grid_levels(cells: CellSamples, border: np.ndarray, gap: np.ndarray) -> GridLevels:
    """Black and white levels of M grids from their border and gap-ring cells ((N, N) bool masks).

    Medians of the readable cells, so a partly hidden border or ring still gives the marker's own levels.
    """
    return GridLevels(nan_median_rows(cells.mean[:, border]), nan_median_rows(cells.mean[:, gap]))


def classify_cells(cells: CellSamples, levels: GridLevels, ambiguity_fraction: float) -> np.ndarray:
    """(M, N, N) int8 grids: 1 black, 0 white, -1 unknown.

    A cell is unknown when it is (partly) outside the image, or its mean lies
    within ``ambiguity_fraction`` x contrast of the midpoint between the
    candidate's black and white levels.
    """
    mid = ((levels.black + levels.white) / 2)[:, None, None]
    margin = (ambiguity_fraction * levels.contrast)[:, None, None]
    with np.errstate(invalid="ignore"):
        grid = (cells.mean < mid).astype(np.int8)
        unsure = ~cells.inside | ~np.isfinite(cells.mean) | (np.abs(cells.mean - mid) < margin)
    grid[unsure] = UNKNOWN
    return grid


def nan_median_rows(values: np.ndarray) -> np.ndarray:
    """(M, K) -> (M,) median of each row's finite values (NaN for an all-NaN row).

    np.nanmedian goes through masked arrays and costs ~0.5 ms a call; sorting
    puts NaN last, so the median is read at the middle of the finite prefix.
    """
    ordered = np.sort(values, axis=1)
    count = np.isfinite(ordered).sum(axis=1)
    lo = np.maximum(count - 1, 0) // 2
    hi = count // 2
    rows = np.arange(len(values))
    median = (ordered[rows, lo] + ordered[rows, hi]) / 2
    median[count == 0] = np.nan
    return median


class CellProbe:
    """One sample at the centre of every border, gap-ring and codeword cell: a cheap first look.

    ``read(gray, H)`` for M homographies gives per candidate the contrast
    (gap-ring median - border median), the fractions of readable border
    cells below and gap-ring cells above the midpoint, and the fraction of
    codeword cells below it; a candidate that is no marker fails here before
    any expensive step. Cells marked ``hidden`` (e.g. where an occluder is
    known to stand) are left out, as if outside the image.
    """

    def __init__(self, layout: MarkerLayout):
        border, gap, codeword = layout.border_mask, gap_ring_mask(layout), layout.codeword_mask
        self._probed = border | gap | codeword
        self._is_border, self._is_gap = border[self._probed], gap[self._probed]
        self._is_codeword = codeword[self._probed]
        self._points = np.argwhere(self._probed)[:, ::-1] + 0.5  # (u, v) cell centres
        # (P, 3): which probed cells are border, gap-ring and codeword cells (class counts as one product)
        self._classes = np.column_stack([self._is_border, self._is_gap, self._is_codeword]).astype(np.float64)

    def read(self, gray: np.ndarray, H: np.ndarray, hidden: np.ndarray | None = None) -> "ProbeReading":
        """M candidates: H (M, 3, 3) grid -> image; hidden: optional (M, N, N) bool cells to leave out."""
        values, _ = sample_image(gray, homography.project(H, self._points))
        if hidden is not None:
            values[hidden[:, self._probed]] = np.nan
        black, white = nan_median_rows(values[:, self._is_border]), nan_median_rows(values[:, self._is_gap])
        mid = (black + white)[:, None] / 2
        readable = np.isfinite(values)
        dark = values < mid  # False where unreadable
        grid = np.full((len(H),) + self._probed.shape, UNKNOWN, np.int8)
        grid[:, self._probed] = np.where(readable, dark, UNKNOWN)
        # per class (border, gap ring, codeword): readable cells and dark ones among them
        readable_counts = readable.astype(np.float64) @ self._classes
        dark_counts = dark.astype(np.float64) @ self._classes
        shares = np.stack([dark_counts[:, 0], readable_counts[:, 1] - dark_counts[:, 1], dark_counts[:, 2]], axis=1)
        shares /= np.maximum(readable_counts, 1)
        return ProbeReading(white - black, shares[:, 0], shares[:, 1], shares[:, 2], grid)


@dataclass(frozen=True)
class ProbeReading:
    """Per candidate (M,): contrast, border_black, gap_white, dark_codeword (see ``CellProbe``);
    grid (M, N, N) int8: the probed cells read at one sample each (others unknown)."""

    contrast: np.ndarray
    border_black: np.ndarray
    gap_white: np.ndarray
    dark_codeword: np.ndarray
    grid: np.ndarray


def erase_near_bad_fixed_cells(grids: np.ndarray, border: np.ndarray, gap: np.ndarray,
                               codeword: np.ndarray, reach_cells: int) -> np.ndarray:
    """Occlusion probes: codeword cells next to a fixed cell that reads wrong become unknown.

    grids: (M, N, N) int8 classified grids. A border cell that reads white or
    a gap-ring cell that reads black shows something in front of the marker
    there; codeword cells within ``reach_cells`` (Chebyshev) of it are more
    likely hidden than read, so they are erased rather than left as errors.
    Returns a new (M, N, N) int8 array.
    """
    bad = (border[None] & (grids == 0)) | (gap[None] & (grids == 1))
    n = grids.shape[-1]
    # dilation by a (2r + 1) square: rows and columns each summed over a band |i - j| <= r
    band = (np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= reach_cells).astype(np.float32)
    near_bad = (band @ bad.astype(np.float32) @ band) > 0
    out = grids.copy()
    out[near_bad & codeword[None]] = UNKNOWN
    return out

