"""Detector stage: sub-pixel geometry from the inner square's four outer edges.

The inner black square's outer edges are straight black-to-white steps
whatever the marker's code. Profiles across them (one ``cv2.remap`` for all
markers) give the sub-pixel mid-level crossing at every half cell along
every edge; a profile that is not one clean dark-to-bright step (occluded,
out of the image, too little contrast) is dropped.

* Square path: a total-least-squares line per edge, the corners where
  adjacent lines meet (``refine_square_corners``), batched over markers.
* Circles path: the circle-only homography extrapolates poorly (two corners
  on one side of a half-hidden marker); the edge points pin it
  (``refine_homographies``). A point p on the grid line v = c gives one
  equation linear in the image -> grid homography G:  g2 . p - c g3 . p = 0
  (u = c: g1 . p - c g3 . p = 0); a circle centre gives two. G is the null
  vector of the stacked, normalised system; points far from the first fit
  are dropped before the second.
"""
from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np

from companion.detect import homography, sampling
from companion.markers.layout import MarkerLayout
from companion.params import require

EDGES = 4
SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class EdgeParams:
    """Edge profiles and the fits on them.

    profile_step_cells: profiles every this many cells along each edge.
    square_half_width_cells, square_samples, square_stride: square path,
        how far across each edge a profile looks (ArUco's corners are within
        a few tenths of a cell), its samples, every stride-th profile used.
    rough_half_width_cells, rough_samples: the wider first pass for quads
        ArUco rejected (their corners are whole pixels, a few off on small markers).
    min_points_per_edge: a square-path corner moves only if both of its edges
        have this many good points.
    max_corner_move_half_widths, min_corner_move_limit_px: a corner that moves
        further than this many profile half widths (and at least the limit in
        pixels) is a bad fit and keeps its input value.
    circles_half_width_cells, circles_samples, circles_stride: the same for
        the circles path's homography refinement (one profile per cell).
    outlier_cells: circles path: edge points further than this from their
        grid line after the first fit are dropped before the second.
    circles_iterations: profile-and-refit rounds of the circles path.
    """

    profile_step_cells: float = 0.5
    square_half_width_cells: float = 0.35
    square_samples: int = 11
    square_stride: int = 1
    rough_half_width_cells: float = 0.7
    rough_samples: int = 21
    min_points_per_edge: int = 5
    max_corner_move_half_widths: float = 1.5
    min_corner_move_limit_px: float = 1.0
    circles_half_width_cells: float = 0.6
    circles_samples: int = 15
    circles_stride: int = 2
    outlier_cells: float = 0.12
    circles_iterations: int = 1

    def __post_init__(self):
        require(0.0 < self.profile_step_cells <= 1.0, "profile_step_cells", "in (0, 1]", self.profile_step_cells)
        for key in ("square_half_width_cells", "rough_half_width_cells", "circles_half_width_cells",
                    "max_corner_move_half_widths", "min_corner_move_limit_px", "outlier_cells"):
            require(getattr(self, key) > 0, key, "> 0", getattr(self, key))
        for key in ("square_samples", "rough_samples", "circles_samples"):
            require(getattr(self, key) >= 6, key, ">= 6", getattr(self, key))
        for key in ("square_stride", "circles_stride", "min_points_per_edge", "circles_iterations"):
            require(getattr(self, key) >= 1, key, ">= 1", getattr(self, key))
        require(self.min_points_per_edge >= 2, "min_points_per_edge", ">= 2", self.min_points_per_edge)


@dataclass(frozen=True)
class EdgePoints:
    """Points found on the inner square's edges of M candidates.

    px: (M, E, 2) image points on the edges, NaN where the profile was rejected.
    edge: (E,) which edge each sample belongs to (0 top, 1 right, 2 bottom, 3 left).
    profile: (E,) index of each sample in the refiner's full profile list.
    """

    px: np.ndarray
    edge: np.ndarray
    profile: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.px[..., 0])


@dataclass(frozen=True)
class EdgeFit:
    """A refined homography: H (3, 3) grid -> image; edge_points used; rms_cells of the fit."""

    H: np.ndarray
    edge_points: int
    rms_cells: float


class EdgeRefiner:
    """Edge profiles of one layout's inner square, and the fits built on them."""

    def __init__(self, layout: MarkerLayout, params: EdgeParams, min_contrast_gray: float):
        """min_contrast_gray: white - black gray levels of a good profile."""
        self.params = params
        self.min_contrast_gray = min_contrast_gray
        lo, hi = layout.inner_origin, layout.inner_origin + layout.inner_cells
        self.inner_cells = layout.inner_cells
        along = np.arange(lo + params.profile_step_cells, hi, params.profile_step_cells)
        k = len(along)
        top = np.column_stack([along, np.full(k, lo)])
        right = np.column_stack([np.full(k, hi), along])
        bottom = np.column_stack([along[::-1], np.full(k, hi)])
        left = np.column_stack([np.full(k, lo), along[::-1]])
        self._points = np.concatenate([top, right, bottom, left])  # clockwise, in corner order
        self._normals = np.repeat(np.array([[0, -1], [1, 0], [0, 1], [-1, 0]], float), k, axis=0)  # outward
        self._edge = np.repeat(np.arange(EDGES), k)
        self._axis = np.repeat([1, 0, 1, 0], k)  # the coordinate that is constant on the edge: 1 = v, 0 = u
        self._value = np.repeat([lo, hi, hi, lo], k).astype(float)
        self._width_profiles = (np.arange(len(self._points)).reshape(EDGES, -1)[:, 1::2]).ravel()  # one per cell
        self._profile_cache: dict[tuple, tuple] = {}

    # ------------------------------------------------------------ edge points

    def edge_points(self, gray: np.ndarray, H: np.ndarray, half_width_cells: float, samples: int,
                    stride: int) -> EdgePoints:
        """Mid-level crossings across the four edges of M grids (H: (M, 3, 3) grid -> image).

        half_width_cells: how far across each edge to look (both ways);
        samples: per profile; stride: use every stride-th profile along each edge.
        """
        keep, points, normals, edge, offsets, grid = self._profiles(half_width_cells, samples, stride)
        m, e = len(H), len(points)
        values, inside = sampling.sample_image(gray, homography.project(H, grid))
        values = values.reshape(m * e, samples)
        inside = inside.reshape(m * e, samples).all(axis=1)
        end = max(samples // 6, 1)
        black = values[:, :end].sum(axis=1) / end
        white = values[:, -end:].sum(axis=1) / end
        mid = (black + white) / 2
        with np.errstate(invalid="ignore", divide="ignore"):
            above = values >= mid[:, None]
            crossings = np.count_nonzero(above[:, 1:] != above[:, :-1], axis=1)
            good = (inside & (white - black >= self.min_contrast_gray) & (crossings == 1)
                    & above[:, -1] & ~above[:, 0])
            k = np.maximum(np.argmax(above, axis=1), 1)  # first sample at or above the mid level (from the 2nd)
            rows = np.arange(m * e)
            before, after = values[rows, k - 1], values[rows, k]
            # linear interpolation of the crossing between samples k - 1 and k
            frac = np.minimum(np.maximum((mid - before) / (after - before), 0.0), 1.0)
        offset = offsets[k - 1] + frac * (offsets[1] - offsets[0])
        on_edge = points[None] + (offset.reshape(m, e)[..., None] * normals[None])  # (M, E, 2) grid
        px = homography.project(H, on_edge)
        px[~good.reshape(m, e)] = np.nan
        return EdgePoints(px, edge, keep)

    def _profiles(self, half_width_cells: float, samples: int, stride: int) -> tuple:
        """The profiles' layout (fixed per refiner and arguments, cached): kept profile indices (E,), their
        grid points and outward normals (E, 2), edges (E,), offsets across (S,) and sample points (E * S, 2)."""
        key = (half_width_cells, samples, stride)
        if key not in self._profile_cache:
            keep = (np.arange(len(self._points)).reshape(EDGES, -1)[:, ::stride]).ravel()
            points, normals = self._points[keep], self._normals[keep]
            offsets = np.linspace(-half_width_cells, half_width_cells, samples)  # inside (black) -> outside (white)
            grid = (points[:, None, :] + offsets[None, :, None] * normals[:, None, :]).reshape(-1, 2)
            self._profile_cache[key] = (keep, points, normals, self._edge[keep], offsets, grid)
        return self._profile_cache[key]

    def step_widths_px(self, gray: np.ndarray, H: np.ndarray, cell_px: float, max_half_width_px: float = 8.0,
                       samples: int = 17) -> np.ndarray:
        """(4,) how wide each of one marker's four inner-square edges is, pixels (median over its profiles).

        H: (3, 3) grid -> image; cell_px: its cell size in pixels. Width = the
        profile's rise over its steepest slope: ~1.7 px for a sharp edge
        through a lens blur of 0.7 px, the smear's length across the edge for
        a smeared one (a ramp that outgrows the profile reads as about the
        profile's length). Profiles reach 0.8 cells or ``max_half_width_px``
        each way, one per cell; NaN for an edge without a rising profile.
        """
        half_width_cells = min(0.8, max_half_width_px / max(cell_px, 1e-9))
        offsets = np.linspace(-half_width_cells, half_width_cells, samples)
        grid = (self._points[self._width_profiles, None, :]
                + offsets[None, :, None] * self._normals[self._width_profiles, None, :]).reshape(-1, 2)
        values, _ = sampling.sample_image(gray, homography.project(H, grid))
        values = values.reshape(len(self._width_profiles), samples)
        step_px = (offsets[1] - offsets[0]) * cell_px
        with np.errstate(invalid="ignore", divide="ignore"):
            # width = (white - black) / steepest slope
            widths = (values[:, -1] - values[:, 0]) / (np.diff(values, axis=1).max(axis=1) / step_px)
        widths[~(widths > 0)] = np.nan
        return sampling.nan_median_rows(widths.reshape(EDGES, -1))

    # ---------------------------------------------------------- square path

    def refine_square_corners(self, gray: np.ndarray, H: np.ndarray, corners_px: np.ndarray,
                              rough: bool = False) -> np.ndarray:
        """(M, 4, 2) inner corners from line fits to the edges; a corner keeps its input value
        unless both of its edges have ``min_points_per_edge`` good points.

        rough: the wider first pass (corners off by up to ``rough_half_width_cells``).
        """
        p = self.params
        half_width_cells = p.rough_half_width_cells if rough else p.square_half_width_cells
        samples = p.rough_samples if rough else p.square_samples
        points = self.edge_points(gray, H, half_width_cells, samples, p.square_stride)
        lines, enough = _fit_lines(points, p.min_points_per_edge)  # (M, 4, 3), (M, 4)
        # corner i is where edge i - 1 (the one ending there) meets edge i (the one starting there)
        previous = lines[:, homography.PREVIOUS_CORNER]
        meet = np.cross(previous, lines)
        ok = enough & enough[:, homography.PREVIOUS_CORNER] & (np.abs(meet[..., 2]) > 1e-9)
        with np.errstate(divide="ignore", invalid="ignore"):
            refined = meet[..., :2] / meet[..., 2:3]
        moved = np.linalg.norm(refined - corners_px, axis=2)
        cell_px = homography.mean_side_px(corners_px) / self.inner_cells
        # a corner moved further than the profiles reach is a bad fit, not a better corner
        limit_px = np.maximum(p.max_corner_move_half_widths * half_width_cells * cell_px, p.min_corner_move_limit_px)
        ok &= np.isfinite(moved) & (moved < limit_px[:, None])
        return np.where(ok[..., None], refined, corners_px)

    # --------------------------------------------------------- circles path

    def refine_homographies(self, gray: np.ndarray, H: np.ndarray,
                            anchors: list[tuple[np.ndarray, np.ndarray]]) -> list[EdgeFit]:
        """Refine M homographies H (M, 3, 3) (grid -> image) on their edges, batched.

        anchors: per candidate, (grid (K, 2), image (K, 2)) correspondences
        (circle centres) kept in the fit.
        """
        p = self.params
        fits = [EdgeFit(h, 0, np.nan) for h in H]
        for _ in range(p.circles_iterations):
            points = self.edge_points(gray, H, p.circles_half_width_cells, p.circles_samples, p.circles_stride)
            axis, value, valid = self._axis[points.profile], self._value[points.profile], points.valid
            fits = [self._refit(fit, points.px[i], axis[valid[i]], value[valid[i]], valid[i], *anchors[i])
                    for i, fit in enumerate(fits)]
            H = np.stack([fit.H for fit in fits])
        return fits

    def _refit(self, fit: EdgeFit, px: np.ndarray, axis: np.ndarray, value: np.ndarray, valid: np.ndarray,
               anchors_grid: np.ndarray, anchors_px: np.ndarray) -> EdgeFit:
        """One candidate's homography from its anchors and its good edge points (px[valid] on lines axis = value)."""
        on_edge_px = px[valid]
        if len(on_edge_px) < 4:
            return fit
        G = _solve(anchors_grid, anchors_px, on_edge_px, axis, value)
        if G is None:
            return fit
        residuals = _line_residuals(G, on_edge_px, axis, value)
        keep = residuals < self.params.outlier_cells
        kept = int(np.count_nonzero(keep))
        if 4 <= kept < len(keep):
            refit = _solve(anchors_grid, anchors_px, on_edge_px[keep], axis[keep], value[keep])
            if refit is not None:
                G, residuals = refit, _line_residuals(refit, on_edge_px, axis, value)
        used = keep if kept >= 4 else np.ones(len(keep), bool)
        errors = np.concatenate([residuals[used], _grid_distances(G, anchors_px, anchors_grid)])
        return EdgeFit(homography.inv3(G), int(np.count_nonzero(used)), math.sqrt(float(np.mean(errors * errors))))


def _fit_lines(points: EdgePoints, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line (a, b, c), a x + b y + c = 0, per candidate and edge.

    Returns lines (M, 4, 3) and enough (M, 4) bool (at least ``min_points`` points).
    """
    m = len(points.px)
    px = points.px.reshape(m, EDGES, -1, 2)
    valid = np.isfinite(px[..., 0])
    count = valid.sum(axis=2)
    xy = np.where(valid[..., None], px, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = xy.sum(axis=2) / count[..., None]
        d = np.where(valid[..., None], px - centre[:, :, None, :], 0.0)
        cov = np.einsum("meki,mekj->meij", d, d)
    cov = np.nan_to_num(cov) + np.eye(2) * 1e-12
    _, vectors = np.linalg.eigh(cov)
    normal = vectors[..., :, 0]  # smallest eigenvalue: the line's normal
    c = -(normal * np.nan_to_num(centre)).sum(axis=2)
    return np.concatenate([normal, c[..., None]], axis=2), count >= min_points


def _solve(anchors_grid, anchors_px, on_edge_px, axis, value) -> np.ndarray | None:
    """G (3, 3) image -> grid from anchor correspondences and points on grid lines u = c or v = c."""
    k, e = len(anchors_px), len(on_edge_px)
    if 2 * k + e < 8:
        return None
    # normalised image points (homogeneous): centred, mean distance sqrt(2); grid: centred, max |coordinate| 1
    all_px = np.concatenate([anchors_px, on_edge_px])
    centre = all_px.sum(axis=0) / len(all_px)
    offsets = all_px - centre
    scale = SQRT2 / max(float(np.sqrt((offsets * offsets).sum(axis=1)).sum()) / len(all_px), 1e-9)
    points = np.ones((k + e, 3))
    points[:, :2] = offsets * scale
    grid_all = np.concatenate([anchors_grid, np.column_stack([value, value])])
    g_centre = grid_all.sum(axis=0) / len(grid_all)
    g_scale = 1.0 / max(float(np.abs(grid_all - g_centre).max()), 1e-9)
    ag = (anchors_grid - g_centre) * g_scale
    line = (value - g_centre[axis]) * g_scale
    a, p = points[:k], points[k:]
    A = np.zeros((2 * k + e, 9))
    # anchor (x, y) <-> (u, v):  g1 . p - u g3 . p = 0  and  g2 . p - v g3 . p = 0
    A[:k, 0:3] = a
    A[:k, 6:9] = -ag[:, :1] * a
    A[k:2 * k, 3:6] = a
    A[k:2 * k, 6:9] = -ag[:, 1:2] * a
    # edge point on u = c:  g1 . p - c g3 . p = 0;  on v = c:  g2 . p - c g3 . p = 0
    on_u = axis == 0
    A[2 * k + np.flatnonzero(on_u), 0:3] = p[on_u]
    A[2 * k + np.flatnonzero(~on_u), 3:6] = p[~on_u]
    A[2 * k:, 6:9] = -line[:, None] * p
    # the unit g minimising |A g|: the eigenvector of A^T A (9 x 9) with the smallest eigenvalue
    _, vectors = np.linalg.eigh(A.T @ A)
    # G = S^-1 G_normalised T, S and T the grid's and the image's normalisations
    S_inv = np.array([[1.0 / g_scale, 0.0, g_centre[0]], [0.0, 1.0 / g_scale, g_centre[1]], [0.0, 0.0, 1.0]])
    T = np.array([[scale, 0.0, -scale * centre[0]], [0.0, scale, -scale * centre[1]], [0.0, 0.0, 1.0]])
    G = S_inv @ vectors[:, 0].reshape(3, 3) @ T
    if not np.isfinite(G).all() or abs(G[2, 2]) < 1e-12:
        return None
    G = G / G[2, 2]
    return G if abs(homography.det3(G)) > 1e-15 else None


def _line_residuals(G, on_edge_px, axis, value) -> np.ndarray:
    """(E,) distance in cells of each edge point, mapped by G, from its grid line."""
    grid = homography.project(G, on_edge_px)
    return np.abs(grid[np.arange(len(grid)), axis] - value)


def _grid_distances(G: np.ndarray, points_px: np.ndarray, points_grid: np.ndarray) -> np.ndarray:
    """(K,) distances in cells between image points mapped by G and their grid positions."""
    if len(points_px) == 0:
        return np.zeros(0)
    return np.linalg.norm(homography.project(G, points_px) - points_grid, axis=1)
