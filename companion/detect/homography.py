"""Homographies between a marker's grid and the image: the one helper every detector stage uses.

A homography H (3, 3) maps grid coordinates (u, v) in cells
(``companion.markers.layout``: origin at the grid's outer top-left corner,
u right, v down) to image pixels (x right, y down, pixel centres at
integers):  (x, y) = (H (u, v, 1)^T)[:2] / (H (u, v, 1)^T)[2].  Stages hold
them batched, (M, 3, 3) for M candidates; a homography that could not be
built is all NaN and projects to NaN.

Written for speed (they run on every candidate of every frame, mostly on
arrays of a few dozen values, where numpy's cost per call, not the
arithmetic, is the time): the batched 4-point solve of more than
``FEW_HOMOGRAPHIES`` quads is one ``np.linalg.solve`` over all of them, a
shared set of points goes through many homographies in one
``np.tensordot``; one homography (a few points, or the refiner's thousands
of template points every step), and each of a batch of up to
``FEW_HOMOGRAPHIES``, is OpenCV's ``perspectiveTransform`` /
``getPerspectiveTransform`` (from float32 corners: about 1e-5 px at 1000
px), 5-15x faster than numpy on small arrays;
3 x 3 determinants and inverses are written out, and an affine fit is one
product with a solver cached per set of grid points.
"""
from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

PREVIOUS_CORNER = [3, 0, 1, 2]  # of each corner of a quad (np.roll by one, without its cost)
NEXT_CORNER = [1, 2, 3, 0]
CORNERS_FROM = np.array([[(corner + k) % 4 for corner in range(4)] for k in range(4)])  # row k: corner k first
FEW_HOMOGRAPHIES = 4  # up to this many, batched solves and projections go one homography at a time through OpenCV
MIN_DETERMINANT = 1e-12  # below it a 4-point system is degenerate (three corners on a line)


def mean_side_px(quads: np.ndarray) -> np.ndarray:
    """Mean side length of quads (..., 4, 2) in pixels, shape (...): (M,) for M quads, 0-d for one."""
    quads = np.asarray(quads, dtype=np.float64)
    sides = quads - quads[..., PREVIOUS_CORNER, :]
    return np.sqrt((sides * sides).sum(axis=-1)).mean(axis=-1)


def from_quads(grid_corners: np.ndarray, image_corners: np.ndarray) -> np.ndarray:
    """Batched 4-point homographies grid -> image.

    grid_corners: (4, 2) grid (u, v) of the quad corners (shared by all).
    image_corners: (M, 4, 2) pixel corners of M quads, same order.
    Returns (M, 3, 3) float64 with H[2, 2] = 1 (NaN for degenerate quads).
    """
    q = np.asarray(image_corners, dtype=np.float64).reshape(-1, 4, 2)
    m = len(q)
    if m <= FEW_HOMOGRAPHIES:  # OpenCV's solve quad by quad: 1.4-3x faster than the batched one on so few
        return np.stack([from_quad(grid_corners, quad) for quad in q]) if m else np.zeros((0, 3, 3))
    u, v = grid_corners[:, 0], grid_corners[:, 1]
    x, y = q[..., 0], q[..., 1]
    # x = (h0 u + h1 v + h2) / (h6 u + h7 v + 1), y likewise with h3..h5:
    # h0 u + h1 v + h2 - x h6 u - x h7 v = x  and  h3 u + h4 v + h5 - y h6 u - y h7 v = y
    a = np.zeros((m, 8, 8))
    a[:, 0:4, 0] = u
    a[:, 0:4, 1] = v
    a[:, 0:4, 2] = 1.0
    a[:, 0:4, 6] = -x * u
    a[:, 0:4, 7] = -x * v
    a[:, 4:8, 3] = u
    a[:, 4:8, 4] = v
    a[:, 4:8, 5] = 1.0
    a[:, 4:8, 6] = -y * u
    a[:, 4:8, 7] = -y * v
    b = np.concatenate([x, y], axis=1)
    h = np.full((m, 9), np.nan)
    ok = np.abs(np.linalg.det(a)) > MIN_DETERMINANT
    if ok.any():
        h[ok, :8] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
        h[ok, 8] = 1.0
    return h.reshape(m, 3, 3)


def from_quad(grid_corners: np.ndarray, image_corners: np.ndarray) -> np.ndarray:
    """(3, 3) homography grid -> image of one quad, H[2, 2] = 1, NaN if degenerate.

    grid_corners, image_corners: (4, 2), same order. OpenCV solves it from
    float32 corners (about 1e-5 px at 1000 px): a start for an iterative fit.
    """
    try:
        H = cv2.getPerspectiveTransform(grid_corners.astype(np.float32), image_corners.astype(np.float32))
    except cv2.error:
        return np.full((3, 3), np.nan)
    if not np.isfinite(H).all() or abs(det3(H)) < MIN_DETERMINANT or abs(H[2, 2]) < MIN_DETERMINANT:
        return np.full((3, 3), np.nan)
    return H / H[2, 2]


def fit(grid_points: np.ndarray, image_points: np.ndarray) -> np.ndarray:
    """(3, 3) least-squares homography grid -> image from K >= 4 point pairs (K, 2), H[2, 2] = 1; NaN if none fits.

    The normalised direct linear transform (Hartley): both point sets moved to their centroid and
    scaled to a mean distance of sqrt(2), then the unit vector h minimising |A h| (the eigenvector of
    A^T A with the smallest eigenvalue). It minimises the algebraic error, not the reprojection error
    that ``cv2.findHomography`` polishes with Levenberg-Marquardt (2x slower on a dozen points); on
    circle centres the two differ by far less than the centres' own noise, and the callers refine
    on the edges after.
    """
    g = np.asarray(grid_points, dtype=np.float64)
    p = np.asarray(image_points, dtype=np.float64)
    k = len(g)
    if k < 4:
        return np.full((3, 3), np.nan)
    # (sums over k rather than np.mean: the same numbers, without its per-call cost)
    g_centre, p_centre = g.sum(axis=0) / k, p.sum(axis=0) / k
    g, p = g - g_centre, p - p_centre
    g_spread = float(np.sqrt((g * g).sum(axis=1)).sum()) / k
    p_spread = float(np.sqrt((p * p).sum(axis=1)).sum()) / k
    if not (g_spread > 0 and p_spread > 0):
        return np.full((3, 3), np.nan)
    g *= math.sqrt(2.0) / g_spread
    p *= math.sqrt(2.0) / p_spread
    # x = (h0 u + h1 v + h2) / (h6 u + h7 v + h8): h0 u + h1 v + h2 - x (h6 u + h7 v + h8) = 0, y likewise
    A = np.zeros((2 * k, 9))
    A[:k, 0:2] = g
    A[:k, 2] = 1.0
    A[k:, 3:5] = g
    A[k:, 5] = 1.0
    A[:k, 6:8] = -p[:, :1] * g
    A[:k, 8] = -p[:, 0]
    A[k:, 6:8] = -p[:, 1:] * g
    A[k:, 8] = -p[:, 1]
    _, vectors = np.linalg.eigh(A.T @ A)
    Hn = vectors[:, 0].reshape(3, 3)
    # undo the normalisations: H = T_image^-1 Hn T_grid
    gs, ps = math.sqrt(2.0) / g_spread, p_spread / math.sqrt(2.0)
    T_grid = np.array([[gs, 0.0, -gs * g_centre[0]], [0.0, gs, -gs * g_centre[1]], [0.0, 0.0, 1.0]])
    T_image_inv = np.array([[ps, 0.0, p_centre[0]], [0.0, ps, p_centre[1]], [0.0, 0.0, 1.0]])
    H = T_image_inv @ Hn @ T_grid
    if not np.isfinite(H).all() or abs(H[2, 2]) < MIN_DETERMINANT or abs(det3(H)) < MIN_DETERMINANT:
        return np.full((3, 3), np.nan)
    return H / H[2, 2]


def det3(H: np.ndarray) -> float:
    """Determinant of one (3, 3) matrix (cofactors along the first row; np.linalg.det's LU costs more)."""
    (a, b, c), (d, e, f), (g, h, i) = H.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def inv3(H: np.ndarray) -> np.ndarray:
    """Inverse of one invertible (3, 3) matrix: its adjugate over its determinant (np.linalg.inv costs more)."""
    (a, b, c), (d, e, f), (g, h, i) = H.tolist()
    co_a, co_b, co_c = e * i - f * h, f * g - d * i, d * h - e * g
    return np.array([[co_a, c * h - b * i, b * f - c * e],
                     [co_b, a * i - c * g, c * d - a * f],
                     [co_c, b * g - a * h, a * e - b * d]]) / (a * co_a + b * co_b + c * co_c)


def fit_affine(grid_points: np.ndarray, image_points: np.ndarray) -> np.ndarray:
    """(3, 3) least-squares affine map grid -> image from K >= 3 point pairs (K, 2), as a homography."""
    g = np.ascontiguousarray(grid_points, dtype=np.float64)
    H = np.zeros((3, 3))
    H[:2] = (_affine_solver(g.tobytes(), len(g)) @ image_points).T
    H[2, 2] = 1.0
    return H


@lru_cache(maxsize=256)
def _affine_solver(grid_bytes: bytes, k: int) -> np.ndarray:
    """(3, K): the least-squares affine map of K grid points (given as bytes of (K, 2) float64) is this
    times the image points. Normal equations of [x y] = [u v 1] A (3 x 2): A = (D^T D)^-1 D^T [x y], D = [u v 1];
    cached: the grouping fits the same few sets of layout circles again and again."""
    design = np.column_stack([np.frombuffer(grid_bytes).reshape(k, 2), np.ones(k)])
    solver = np.linalg.solve(design.T @ design, design.T)
    solver.flags.writeable = False
    return solver


def project(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Points through homographies.

    H (3, 3), uv (..., 2) -> (..., 2) of uv's float type (OpenCV; a point at
        the horizon, |w| <= FLT_EPSILON, comes out at (0, 0));
    H (M, 3, 3), uv (K, 2) shared -> (M, K, 2);  H (M, 3, 3), uv (M, K, 2) one
        set each -> (M, K, 2) (points at the horizon are inf or NaN).
    A NaN homography projects to NaN.
    """
    if H.ndim == 2:
        if uv.dtype != np.float32:
            uv = np.asarray(uv, dtype=np.float64)
        if math.isnan(H[2, 2]):  # a homography that could not be built (all NaN)
            return np.full(uv.shape, np.nan, uv.dtype)
        if uv.size == 0:
            return uv.copy()
        return cv2.perspectiveTransform(uv.reshape(1, -1, 2), H).reshape(uv.shape)
    uv = np.asarray(uv, dtype=np.float64)
    if len(H) <= FEW_HOMOGRAPHIES and uv.shape[-2] > 0:
        # OpenCV per homography (5-10x faster than the batched numpy below for one); its points at the
        # horizon come out at exactly (0, 0): NaN here, as numpy's would be inf or NaN
        out = (project(H[0], uv if uv.ndim == 2 else uv[0])[None] if len(H) == 1
               else np.stack([project(h, uv if uv.ndim == 2 else uv[m]) for m, h in enumerate(H)]))
        if not out.all():  # some coordinate is exactly 0 (rare): find the points at (0, 0)
            out[(out[..., 0] == 0.0) & (out[..., 1] == 0.0)] = np.nan
        return out
    with np.errstate(divide="ignore", invalid="ignore"):
        if uv.ndim == 3:
            p = np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], axis=2) @ np.transpose(H, (0, 2, 1))
            return p[..., :2] / p[..., 2:3]
        uv1 = np.concatenate([uv, np.ones((len(uv), 1))], axis=1)
        p = np.tensordot(H, uv1, axes=([2], [1]))  # (M, 3, K): one BLAS call (einsum/matmul broadcasting are 3-10x slower)
        return (p[:, :2] / p[:, 2:3]).transpose(0, 2, 1)


UNIT_STEPS = np.array([[1.0, 0.0], [0.0, 1.0]])  # one cell along u and along v


def project_with_cell_px(H: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, float]:
    """Image positions (K, 2) of grid points uv (K, 2) through one H (3, 3), and the size of one
    cell in pixels at the first point (square root of the area its unit square maps to; NaN if unknown)."""
    points = project(H, np.concatenate([uv, uv[0] + UNIT_STEPS]))
    if not np.isfinite(points).all():
        return points[:-2], np.nan
    return points[:-2], cell_px_at(points[0], points[-2], points[-1])


def cell_px_at(origin, step_u, step_v) -> float:
    """The size of one cell in pixels where grid point g maps to origin and g + (1, 0), g + (0, 1) to
    step_u, step_v (image points (2,)): sqrt(|a x b|), a = step_u - origin, b = step_v - origin; NaN if zero."""
    (x0, y0), (x1, y1), (x2, y2) = origin.tolist(), step_u.tolist(), step_v.tolist()
    cell_px = math.sqrt(abs((x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)))
    return cell_px if cell_px > 0 else math.nan


def fit_error_cells(H: np.ndarray, grid_points: np.ndarray, points_px: np.ndarray) -> float:
    """RMS distance between image points (K, 2) and their grid points (K, 2) mapped by H (3, 3),
    in cells (at the first point); inf when it cannot be measured."""
    projected, cell_px = project_with_cell_px(H, grid_points)
    with np.errstate(divide="ignore", invalid="ignore"):
        error = np.sqrt(np.mean(np.sum((projected - points_px) ** 2, axis=1))) / cell_px
    return float(error) if np.isfinite(error) else np.inf


def fit_errors_cells(H: np.ndarray, grid_points: np.ndarray, points_px: np.ndarray, tail: int) -> tuple[float, float]:
    """``fit_error_cells`` of all K point pairs (K, 2) and of their last ``tail`` alone (each in cells at
    its own first point), from one projection."""
    k = len(grid_points)
    points = project(H, np.concatenate([grid_points, grid_points[0] + UNIT_STEPS, grid_points[k - tail] + UNIT_STEPS]))
    if not np.isfinite(points).all():
        return math.inf, math.inf
    squared = np.sum((points[:k] - points_px) ** 2, axis=1)
    errors = [math.sqrt(float(np.mean(squared[first:]))) / cell_px_at(points[first], points[steps], points[steps + 1])
              for first, steps in ((0, k), (k - tail, k + 2))]
    return tuple(error if math.isfinite(error) else math.inf for error in errors)
