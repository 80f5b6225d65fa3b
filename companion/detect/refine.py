"""Detector stage: align a decoded marker's whole printed pattern to the image, sub-pixel.

    refiner = MarkerRefiner(layout)                  # one per detector (it caches templates)
    fit = refiner.refine(gray, marker_id, corners_px)
    fit.corners_px, fit.H_image_grid, fit.circles_px, fit.refined, fit.residual

Once a marker is decoded, every cell of it is known (``MarkerLayout.cells``
and the corner circles), so the whole grid can be matched to the image, not
only its four corners: every edge of the border, data, parity bands and
circles pulls on one homography. A corner detector (``cv2.cornerSubPix``)
sees one blurred L-junction and is pulled into the black square by blur
(0.3-1 px on 20-70 px markers); matching the model has no such bias.

The method is inverse-compositional Lucas-Kanade (Baker & Matthews 2004) on
a sparse template:

* the template is the marker drawn by ``companion.markers.layout.marker_image`` at
  about the image's own scale (pixels per cell = the marker's cell size in
  the image, rounded, clipped to a range), so its pixel-box edges look like
  the camera's; only template pixels on or next to an edge are kept (flat
  cells say nothing about geometry);
* template coordinates are grid cells scaled to [-1, 1]; the
  steepest-descent images and the inverse 8 x 8 Gauss-Newton matrix are
  computed once per (marker id, scale) and cached;
* each step reads the image at the template points through the current
  homography (one ``cv2.remap``), fits the marker's own black and white
  levels (image = black + contrast * template, least squares), and composes
  the inverse of the step into the homography;
* the fit is kept only if its misfit is no larger than at the initial
  corners and small in itself (the model matches), the marker kept its
  contrast and no corner moved two cells or more; otherwise the initial
  corners come back (``refined`` False, ``status`` says why).

Measured (``benchmarks/bench_refine.py``, 20-150 px markers, tilts to 60
degrees, clean / blur / motion blur / noise / low light / JPEG): median
corner error 0.02 px, p90 0.05-0.08 px, from ArUco's 0.3-0.8 px; about
0.2 ms per marker (7-10 x ``cv2.cornerSubPix``), plus about 2 ms once per
(marker id, scale) to build its template.

Points outside the image read as NaN and are left out, so a marker partly
outside the frame is aligned on what is visible (its corners on the cut
side come out to about 0.15 px). A marker is a homography of
its grid only in an undistorted image: give the refiner the camera
(``CameraModel``) and it aligns in the ideal pinhole image, reading the frame
where OpenCV's lens model (all 14 coefficients) puts each ideal point: its
undistortion map (``cv2.initUndistortRectifyMap``, once per camera and frame
size) is looked up at the template points with one ``cv2.remap`` per step. Without it, lens
distortion bends large markers (k1 = -0.05: refined corners 0.04 px instead
of 0.01 px; k1 = -0.3: worse than ArUco's on large markers near the image
edge; ``benchmarks/bench_refine.py``).

Occluders are not modelled: on a marker partly hidden by something in front
of it (the detector's circles path) the least-squares fit is pulled by the
occluder while its misfit still drops, so call this on square-path
detections only.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Literal
from weakref import WeakKeyDictionary

import cv2
import numpy as np

from companion.detect import homography
from companion.markers.layout import MarkerLayout, marker_image
from companion.params import require

RefineStatus = Literal["refined", "worse", "mismatch", "diverged", "low_contrast", "not_visible", "degenerate"]
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # OpenCV's lens model: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tau_x tau_y]]]]
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9)
OUTSIDE_PX = -1e6  # a frame position that reads as outside any frame
IDEAL_MARGIN = 0.25  # the ideal image is looked up at most this share of the frame's size beyond it
# The corner covariance's model of what the template does not match (``MarkerFit.corner_cov_px2``), in the
# misfit's units (a share of the contrast), calibrated with benchmarks/bench_corner_sigma.py against rendered
# truth: a floor (the template's pixel grid against the image's) and a smear term per unit of the gradient's
# anisotropy (a motion smear the sharp template does not model moves the fit along it).
TEMPLATE_MISMATCH = 0.0375
SMEAR_MISMATCH = 0.28


class MarkerRefineError(ValueError):
    """Bad input to the refinement stage (the message says what is wrong)."""


@dataclass(frozen=True)
class RefineParams:
    """Settings of the whole-marker alignment.

    min_px_per_cell, max_px_per_cell: template scale range (pixels per cell);
        the template is drawn at the marker's image cell size within it.
    max_iterations: Gauss-Newton steps at most (3-4 are used from ArUco corners).
    tolerance_px: stop when a step moves the marker by less than this.
    max_shift_cells: refined corners this far (in cells) or further from the
        initial ones are a divergence: the initial corners are kept.
    min_contrast_gray: white - black gray levels the fitted marker must keep.
    max_residual_fraction: the largest misfit (``MarkerFit.residual``, a share
        of the fitted contrast) of a fit that is kept; above it the model does
        not match the image (a wrong lock; correct fits measure 0.1-0.45,
        wrong locks 0.9 and more).
    min_visible_fraction: of the template points that must lie in the image.
    cache_size: templates (marker id x scale) kept.
    """

    min_px_per_cell: int = 3
    max_px_per_cell: int = 6
    max_iterations: int = 6
    tolerance_px: float = 0.005
    max_shift_cells: float = 2.0
    min_contrast_gray: float = 5.0
    max_residual_fraction: float = 0.6
    min_visible_fraction: float = 0.3
    cache_size: int = 64

    def __post_init__(self):
        require(2 <= self.min_px_per_cell <= self.max_px_per_cell <= 32, "min_px_per_cell",
                "in [2, max_px_per_cell], with max_px_per_cell <= 32", (self.min_px_per_cell, self.max_px_per_cell))
        require(self.max_iterations >= 1, "max_iterations", ">= 1", self.max_iterations)
        for key in ("tolerance_px", "max_shift_cells", "min_contrast_gray", "max_residual_fraction"):
            require(getattr(self, key) > 0, key, "> 0", getattr(self, key))
        require(0 < self.min_visible_fraction <= 1, "min_visible_fraction", "in (0, 1]", self.min_visible_fraction)
        require(self.cache_size >= 1, "cache_size", ">= 1", self.cache_size)


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class MarkerFit:
    """One marker's refined geometry (or its initial corners if the refinement did not hold).

    corners_px: (4, 2) float64 inner-square corners TL, TR, BR, BL in frame
        pixels (``companion.types`` conventions; distorted, like the frame).
    H_image_grid: (3, 3) float64 grid (u, v) in cells -> pixels, H[2, 2] = 1:
        frame pixels, or undistorted (ideal pinhole, same K) pixels when the
        refiner has a camera. From the initial corners when ``refined`` is False.
    circles_px: (12, 2) float64 corner-circle centres the homography
        predicts, frame pixels, in the layout's order (``MarkerLayout.circles``).
    circles_in_image: (12,) bool, that centre lies inside the frame.
    refined: the alignment held (else the geometry is the initial corners').
    status: "refined", or why the initial corners were kept: "worse" (the
        misfit grew), "mismatch" (the misfit stayed above ``max_residual_fraction``),
        "diverged" (moved two cells or more, or a step failed),
        "low_contrast", "not_visible", "degenerate" (corners not a quad).
    residual: RMS misfit between the marker model and the image over the
        template points read, as a fraction of the fitted contrast, at the
        returned corners (clean 20-150 px markers: 0.1-0.2; blur or noise
        raise it). NaN if it could not be measured.
    initial_residual: the same at the initial corners.
    contrast: fitted white - black gray levels (NaN if not measured).
    iterations: Gauss-Newton steps taken.
    corner_cov_px2: (8, 8) float64 covariance of ``corners_px`` flattened
        (x_TL, y_TL, x_TR, y_TR, x_BR, y_BR, x_BL, y_BL), frame pixels^2: the
        alignment's own parameter covariance over the template points read,
        through corner = H(model corner), from what this marker's image
        shows: ``(sigma_noise^2 + TEMPLATE_MISMATCH^2 + SMEAR_MISMATCH^2
        (s_max / s_min - 1)^2) B (J^T J) B^T``, B = (J^T J_image)^-1.
        sigma_noise: the misfit's noise, from the differences of the misfit
        at neighbours along an edge (same template value and gradient: the
        template's mismatch is the same there, the noise is not; the whole
        misfit is mostly that mismatch, which hardly moves the corners).
        J_image: the steepest descent with the image's own gradient, A times
        the template's, A (2 x 2) fitted from the two (blur and a motion
        smear lower the information the image holds, in their direction);
        s_max / s_min: A's singular values' ratio, the smear. The four
        corners come from one homography, so their errors are strongly
        correlated. The detector scales it by a constant calibrated on
        rendered truth (``detector.SQUARE_COV_SCALE``). None when
        ``refined`` is False.
    """

    corners_px: np.ndarray
    H_image_grid: np.ndarray
    circles_px: np.ndarray
    circles_in_image: np.ndarray
    refined: bool
    status: RefineStatus
    residual: float
    initial_residual: float
    contrast: float
    iterations: int
    corner_cov_px2: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class _Template:
    """The edge points of one marker drawn at one scale, ready for inverse-compositional steps.

    points: (1, P, 2) float32 normalised grid coordinates.
    values: (P,) float32 template intensity, 0 black .. 1 white.
    steepest: (P, 8) float32 grad T . dW/dp (the steepest-descent images).
    hessian_inverse: (8, 8) float64 (steepest^T steepest)^-1.
    sum, sum_squares: of the values (the level fit when every point is read).
    """

    points: np.ndarray
    values: np.ndarray
    steepest: np.ndarray
    hessian_inverse: np.ndarray
    sum: float
    sum_squares: float


@dataclass(frozen=True, eq=False)
class _Sample:
    """The image read at the template points through one homography, levels fitted.

    residual: (Q,) float32 (image - black) / contrast - template over the
        points read; None when the contrast is below the minimum.
    used: (P,) bool points read (inside the image), None if all of them.
    """

    residual: np.ndarray | None
    used: np.ndarray | None
    rms: float
    contrast: float


@dataclass(frozen=True, eq=False)
class _IdealFrame:
    """Where each ideal (undistorted) pixel lies in the frame: OpenCV's undistortion map of one camera.

    map_xy: (h, w, 2) float32, the frame position (x, y) of ideal pixel
    (lo_x + i, lo_y + j) at [j, i], (lo_x, lo_y) = ``lo_px``, over the ideal
    pixels the frame's pixels map to, at most ``IDEAL_MARGIN`` of the frame's
    size beyond it on each side (a lens can send its corners far out). Built
    once per camera and frame size: 8 bytes per ideal pixel, 2.5-9 MB at
    640x480, at most 4.5 times the frame's pixels.
    """

    lo_px: tuple[float, float]
    map_xy: np.ndarray

    @classmethod
    def of(cls, camera, shape: tuple[int, int], to_ideal) -> _IdealFrame:
        """For frames of ``shape`` (H, W); ``to_ideal``: (K, 2) frame pixels -> ideal pixels."""
        height, width = shape
        side = np.linspace(0.0, 1.0, 65)[:, None]
        outline = np.concatenate([side * [width - 1, 0], [width - 1, 0] + side * [0, height - 1],
                                  side * [width - 1, 0] + [0, height - 1], side * [0, height - 1]])
        ideal = to_ideal(outline)
        size_px = np.array([width, height])
        lo = np.maximum(np.floor(ideal.min(axis=0)) - 1, -IDEAL_MARGIN * size_px)
        hi = np.minimum(np.ceil(ideal.max(axis=0)) + 1, (1 + IDEAL_MARGIN) * size_px)
        # ideal pixel lo + (i, j) -> frame pixel: OpenCV's map for the pinhole K with its principal point moved by -lo
        P = np.asarray(camera.K, dtype=np.float64).copy()
        P[:2, 2] -= lo
        size = (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
        map_x, map_y = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, P, size, cv2.CV_32FC1)
        return cls((float(lo[0]), float(lo[1])), np.dstack([map_x, map_y]))

    def to_frame(self, ideal_xy: np.ndarray, shift_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """(1, P, 2) float32 ideal pixels -> frame pixels + ``shift_px``, read off the map (bilinear: exact with
        OpenCV 5, at 1/32-pixel steps with OpenCV 4's ``cv2.remap``); far outside any frame where the map has no value.

        (The shifts are ``cv2.add`` with a per-channel scalar: 5x faster than numpy's broadcast on (1, P, 2).)
        """
        map_xy = cv2.add(ideal_xy, (-self.lo_px[0], -self.lo_px[1], 0.0, 0.0))
        frame_xy = cv2.remap(self.map_xy, map_xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=(OUTSIDE_PX, OUTSIDE_PX))
        return cv2.add(frame_xy, (shift_px[0], shift_px[1], 0.0, 0.0))


@dataclass(frozen=True, eq=False)
class _View:
    """The frame around one marker as float32, read at template points.

    crop: (h, w) float32. S_crop_image: (3, 3) frame pixels -> crop pixels (a shift).
    ideal: with a camera, where the ideal pixels the template is placed in lie in the frame.
    """

    crop: np.ndarray
    S_crop_image: np.ndarray
    ideal: _IdealFrame | None

    def read(self, template: _Template, M: np.ndarray) -> np.ndarray:
        """(P,) float32 frame intensities at the template points through M (NaN outside the frame)."""
        if self.ideal is None:
            xy = homography.project(self.S_crop_image @ M, template.points)
        else:
            xy = self.ideal.to_frame(homography.project(M, template.points), self.S_crop_image[:2, 2])
        return cv2.remap(self.crop, xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=np.nan)[0]

class MarkerRefiner:
    """Refines decoded markers of one layout. Not thread-safe (it caches templates): one per thread.

    camera: optional ``companion.geometry.camera.CameraModel`` (anything with
    ``K`` (3, 3) and OpenCV's ``dist`` (4, 5, 8, 12 or 14 coefficients)); with
    it the alignment runs in the ideal (undistorted) image, through OpenCV's
    lens model.
    """

    def __init__(self, layout: MarkerLayout, params: RefineParams | None = None, camera=None):
        self.layout = layout
        self.params = params or RefineParams()
        camera = None if camera is None else _checked_camera(camera)
        # a lens without distortion maps ideal pixels to themselves: nothing to look up
        self.camera = camera if camera is not None and np.any(np.asarray(camera.dist) != 0) else None
        self._ideal_frames: dict[tuple[int, int], _IdealFrame] = {}
        n = layout.n_cells
        # grid (u, v) -> normalised (grid centre at 0, grid edges at -1 and +1)
        self.N_norm_grid = np.array([[2.0 / n, 0.0, -1.0], [0.0, 2.0 / n, -1.0], [0.0, 0.0, 1.0]])
        self._N_grid_norm = np.linalg.inv(self.N_norm_grid)
        self._corners_grid = layout.inner_corners_cells
        self._circles_grid = np.asarray(layout.circles, dtype=float)[:, :2]
        self._corners_and_circles_grid = np.concatenate([self._corners_grid, self._circles_grid])
        # where the model corners sit in the template's normalised coordinates, and how a step dp moves them
        self._corners_norm = homography.project(self.N_norm_grid, self._corners_grid)
        self._corners_dW_dp = _warp_jacobian(self._corners_norm)
        # the grid's outline one cell out (the template reaches half a cell into the quiet zone)
        side = np.linspace(-1.0, n + 1.0, 5)
        ends = np.full(5, -1.0), np.full(5, n + 1.0)
        self._outline_grid = np.concatenate([np.column_stack([side, ends[0]]), np.column_stack([ends[1], side]),
                                             np.column_stack([side, ends[1]]), np.column_stack([ends[0], side])])
        self._templates: OrderedDict[tuple[int, int], _Template] = OrderedDict()
        self._lattices: WeakKeyDictionary[_Template, _Lattice] = WeakKeyDictionary()

    def refine(self, gray: np.ndarray, marker_id: int, corners_px: np.ndarray) -> MarkerFit:
        """Align marker ``marker_id`` to an (H, W) uint8 frame, starting from its corners.

        corners_px: (4, 2) initial inner-square corners TL, TR, BR, BL in the
        marker's upright orientation (rotation already corrected by the decode).
        """
        gray, initial = self._check(gray, marker_id, corners_px)
        initial_ideal = self._to_ideal(initial)
        H0 = homography.from_quad(self._corners_grid, initial_ideal)
        if np.isnan(H0[2, 2]):
            return self._fit(gray, initial, None, "degenerate")
        cell_px = _cell_px(initial_ideal, self.layout.inner_cells)
        px_per_cell = min(max(round(cell_px), self.params.min_px_per_cell), self.params.max_px_per_cell)
        view = self._view(gray, H0)
        if view is None:
            return self._fit(gray, initial, H0, "not_visible")
        template = self._template(int(marker_id), px_per_cell)
        # M: normalised template coordinates -> ideal pixels
        M0 = H0 @ self._N_grid_norm
        M, first, last, steps = self._align(view, M0, template, cell_px)
        if first is None:
            return self._fit(gray, initial, H0, "not_visible")
        if first.residual is None:
            return self._fit(gray, initial, H0, "low_contrast", contrast=first.contrast)
        kept = dict(residual=first.rms, initial_residual=first.rms, contrast=first.contrast, steps=steps)
        if last is None or not np.all(np.isfinite(M)):
            return self._fit(gray, initial, H0, "diverged", **kept)
        H = M @ self.N_norm_grid
        H = H / H[2, 2]
        points = self._to_frame(homography.project(H, self._corners_and_circles_grid))
        corners, circles = points[:4], points[4:]
        status = self._verdict(first, last, corners, initial, cell_px)
        if status != "refined":
            return self._fit(gray, initial, H0, status, **kept)
        fit = self._fit(gray, corners, H, "refined", residual=last.rms, initial_residual=first.rms,
                        contrast=last.contrast, steps=steps, circles=circles)
        return replace(fit, corner_cov_px2=self._corner_cov_px2(M, template, last, corners))

    def _corner_cov_px2(self, M: np.ndarray, template: _Template, last: _Sample,
                        corners_px: np.ndarray) -> np.ndarray:
        """(8, 8) covariance of the 4 corners in frame pixels^2 (see ``MarkerFit.corner_cov_px2``)."""
        lattice = self._lattices.get(template)
        if lattice is None:
            lattice = self._lattices[template] = _Lattice.of(template)
        cov_p = _parameter_cov(template, lattice, last)
        # a step dp moves the model corner by -dW/dp dp (inverse composition), then M projects it
        J = _projection_jacobian(M, self._corners_norm) @ self._corners_dW_dp  # (4, 2, 8) ideal pixels per dp
        if self.camera is not None:
            J = self._lens_jacobian(corners_px) @ J
        J = J.reshape(8, 8)
        cov = J @ cov_p @ J.T
        return 0.5 * (cov + cov.T)

    def _lens_jacobian(self, corners_px: np.ndarray) -> np.ndarray:
        """(4, 2, 2) d(frame pixels)/d(ideal pixels) at the corners (central differences, 0.01 px)."""
        ideal = self._to_ideal(corners_px)
        step = 0.01
        offsets = np.array([[step, 0.0], [-step, 0.0], [0.0, step], [0.0, -step]])
        moved = self._to_frame((ideal[:, None, :] + offsets[None]).reshape(-1, 2)).reshape(4, 4, 2)
        return np.stack([(moved[:, 0] - moved[:, 1]) / (2 * step), (moved[:, 2] - moved[:, 3]) / (2 * step)],
                        axis=2)

    # ------------------------------------------------------------------ steps

    def _align(self, view: _View, M: np.ndarray, template: _Template, cell_px: float):
        """Gauss-Newton on M; returns (M, first sample, last sample, steps).

        The first sample is read at the initial M; the last at the returned M,
        or within ``tolerance_px`` of it (the final step, below the tolerance,
        is not read again). ``last`` is None if the image could not be read.
        """
        # a step dp moves template points by about |dp| normalised units = |dp| n / 2 cells
        tolerance = self.params.tolerance_px / (cell_px * self.layout.n_cells / 2)
        first = sample = self._sample(view, M, template)
        if first is None or first.residual is None:
            return M, first, first, 0
        steps = 0
        for steps in range(1, self.params.max_iterations + 1):
            if sample.used is None:
                dp = template.hessian_inverse @ (template.steepest.T @ sample.residual)
            else:
                steepest = template.steepest[sample.used]
                try:
                    dp = np.linalg.solve(steepest.T.astype(np.float64) @ steepest, steepest.T @ sample.residual)
                except np.linalg.LinAlgError:
                    return M, first, None, steps
            # inverse composition: W(x; p) <- W(x; p) o W(x; dp)^-1, with W(x; dp) = (I + D(dp)) x
            D = np.eye(3)
            D.flat[:8] += dp
            M = M @ homography.inv3(D)
            M /= M[2, 2]
            if np.abs(dp).max() < tolerance:
                break
            sample = self._sample(view, M, template)
            if sample is None or sample.residual is None:
                return M, first, sample, steps
        return M, first, sample, steps

    def _sample(self, view: _View, M: np.ndarray, template: _Template) -> _Sample | None:
        """Read the frame at the template points and fit its levels; None if too little is in the frame."""
        image = view.read(template, M)
        inside = np.isfinite(image)
        count, total = int(np.count_nonzero(inside)), len(image)
        if count < self.params.min_visible_fraction * total:
            return None
        if count == total:
            used, T, I = None, template.values, image
            sum_t, sum_tt = template.sum, template.sum_squares
        else:
            used, T, I = inside, template.values[inside], image[inside]
            sum_t, sum_tt = float(T.sum()), float(T @ T)
        # image = black + contrast * template: the least-squares line through (T, I)
        n, sum_i, sum_ti = float(count), float(I.sum()), float(T @ I)
        denominator = n * sum_tt - sum_t * sum_t
        if denominator <= 0:
            return None
        contrast = (n * sum_ti - sum_t * sum_i) / denominator
        if not contrast >= self.params.min_contrast_gray:
            return _Sample(None, used, np.nan, contrast)
        black = (sum_i - contrast * sum_t) / n
        residual = (I - np.float32(black)) * np.float32(1.0 / contrast) - T
        return _Sample(residual, used, float(np.sqrt(residual @ residual / n)), contrast)

    def _verdict(self, first: _Sample, last: _Sample, corners: np.ndarray, initial: np.ndarray,
                 cell_px: float) -> RefineStatus:
        if not last.contrast >= self.params.min_contrast_gray:
            return "low_contrast"
        shift_px = np.linalg.norm(corners - initial, axis=1).max()
        if not shift_px < self.params.max_shift_cells * cell_px:
            return "diverged"
        if not last.rms <= first.rms:
            return "worse"
        if not last.rms <= self.params.max_residual_fraction:
            return "mismatch"
        return "refined"

    # ---------------------------------------------------------------- helpers

    def _check(self, gray, marker_id, corners_px) -> tuple[np.ndarray, np.ndarray]:
        gray = np.asarray(gray)
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise MarkerRefineError(f"refine() needs an (H, W) uint8 grayscale image, got {gray.shape} {gray.dtype}")
        markers = len(self.layout.dictionary.bits)
        if not 0 <= int(marker_id) < markers:
            raise MarkerRefineError(f"marker_id {marker_id!r} is not in the {markers}-marker dictionary")
        corners = np.asarray(corners_px, dtype=np.float64)
        if corners.shape != (4, 2) or not np.all(np.isfinite(corners)):
            raise MarkerRefineError(f"corners_px must be a finite (4, 2) array, got shape {corners.shape}")
        return gray, corners

    def _to_frame(self, ideal_px: np.ndarray) -> np.ndarray:
        """(K, 2) ideal pixels -> frame pixels (float64), through the camera's lens model."""
        if self.camera is None:
            return ideal_px
        K = self.camera.K
        # the ray of ideal pixel (x, y) is K^-1 (x, y, 1); OpenCV distorts and projects it
        rays = np.column_stack([(ideal_px - K[:2, 2]) / np.diag(K)[:2], np.ones(len(ideal_px))])
        frame_px, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, self.camera.dist)
        return frame_px.reshape(-1, 2)

    def _to_ideal(self, frame_px: np.ndarray) -> np.ndarray:
        """(K, 2) frame pixels -> ideal pixels (float64), OpenCV's iterative undistortion to 1e-9."""
        if self.camera is None:
            return frame_px
        return cv2.undistortPoints(frame_px.reshape(-1, 1, 2), self.camera.K, self.camera.dist, R=None,
                                   P=self.camera.K, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)

    def _view(self, gray: np.ndarray, H: np.ndarray) -> _View | None:
        """The frame around the marker (grid H: grid -> ideal pixels), None if it is all outside."""
        ideal = None if self.camera is None else self._ideal_frame(gray.shape)
        outline = homography.project(H, self._outline_grid)
        if not np.all(np.isfinite(outline)):
            return None
        if ideal is not None:  # a box with a margin: the map's bilinear reading will do
            outline = ideal.to_frame(outline.astype(np.float32)[None])[0]
        height, width = gray.shape
        margin = 2
        (low_x, low_y), (high_x, high_y) = outline.min(axis=0).tolist(), outline.max(axis=0).tolist()
        x0, y0 = max(math.floor(low_x) - margin, 0), max(math.floor(low_y) - margin, 0)
        x1, y1 = min(math.ceil(high_x) + margin, width - 1), min(math.ceil(high_y) + margin, height - 1)
        if x1 - x0 < 2 or y1 - y0 < 2:
            return None
        S = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        return _View(gray[y0:y1 + 1, x0:x1 + 1].astype(np.float32), S, ideal)

    def _ideal_frame(self, shape: tuple[int, int]) -> _IdealFrame:
        if shape not in self._ideal_frames:
            self._ideal_frames[shape] = _IdealFrame.of(self.camera, shape, self._to_ideal)
        return self._ideal_frames[shape]

    def _template(self, marker_id: int, px_per_cell: int) -> _Template:
        key = (marker_id, px_per_cell)
        template = self._templates.get(key)
        if template is None:
            template = edge_template(self.layout, marker_id, px_per_cell, self.N_norm_grid)
            self._templates[key] = template
            if len(self._templates) > self.params.cache_size:
                self._templates.popitem(last=False)
        else:
            self._templates.move_to_end(key)
        return template

    def _fit(self, gray: np.ndarray, corners: np.ndarray, H: np.ndarray | None, status: RefineStatus,
             residual: float = np.nan, initial_residual: float = np.nan, contrast: float = np.nan,
             steps: int = 0, circles: np.ndarray | None = None) -> MarkerFit:
        """circles: (12, 2) frame pixels of the circle centres if known, else projected through H."""
        if H is None:
            H = np.full((3, 3), np.nan)
            circles = np.full((len(self._circles_grid), 2), np.nan)
        elif circles is None:
            circles = self._to_frame(homography.project(H, self._circles_grid))
        height, width = gray.shape
        with np.errstate(invalid="ignore"):
            inside = ((circles[:, 0] >= -0.5) & (circles[:, 0] <= width - 0.5)
                      & (circles[:, 1] >= -0.5) & (circles[:, 1] <= height - 0.5))
        return MarkerFit(corners_px=np.array(corners, dtype=np.float64), H_image_grid=H, circles_px=circles,
                         circles_in_image=inside, refined=status == "refined", status=status,
                         residual=float(residual), initial_residual=float(initial_residual),
                         contrast=float(contrast), iterations=int(steps))


def _checked_camera(camera):
    """The camera, if its ``K`` and ``dist`` are usable by OpenCV's lens model."""
    K = np.asarray(camera.K, dtype=np.float64)
    dist = np.asarray(camera.dist, dtype=np.float64).ravel()
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise MarkerRefineError(f"camera.K must be a finite (3, 3) intrinsic matrix, got {K.tolist()}")
    if len(dist) not in DISTORTION_LENGTHS or not np.all(np.isfinite(dist)):
        raise MarkerRefineError(f"camera.dist must be {', '.join(map(str, DISTORTION_LENGTHS[1:]))} finite "
                                f"coefficients (OpenCV's lens model), got {dist.tolist()}")
    return camera


def edge_template(layout: MarkerLayout, marker_id: int, px_per_cell: int, N_norm_grid: np.ndarray) -> _Template:
    """The marker's edge points at ``px_per_cell``, with their steepest-descent images.

    Template pixels whose 3 x 3 neighbourhood has a nonzero gradient, inside
    the grid plus half a cell of quiet zone (beyond it the background is unknown).
    N_norm_grid: (3, 3) grid cells -> normalised template coordinates (a scaling and shift).
    """
    quiet = 1
    image = marker_image(layout, marker_id, px_per_cell, quiet_zone_cells=quiet).astype(np.float32) / 255.0
    # central differences per template pixel
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=1) * 0.5
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=1) * 0.5
    edges = ((np.abs(gx) + np.abs(gy)) > 1e-4).astype(np.uint8)
    rows, columns = np.nonzero(cv2.dilate(edges, np.ones((3, 3), np.uint8)))
    # template pixel (x, y) has its centre at grid u = (x + 0.5) / px_per_cell - quiet
    uv = np.column_stack([(columns + 0.5) / px_per_cell - quiet, (rows + 0.5) / px_per_cell - quiet])
    n = layout.n_cells
    keep = ((uv >= -0.5) & (uv <= n + 0.5)).all(axis=1)
    rows, columns, uv = rows[keep], columns[keep], uv[keep]
    xy = homography.project(N_norm_grid, uv)
    # dT/d(normalised) = dT/d(template pixel) * template pixels per normalised unit
    scale = px_per_cell / N_norm_grid[0, 0]
    grad = np.column_stack([gx[rows, columns], gy[rows, columns]]).astype(np.float64) * scale
    dW_dp = _warp_jacobian(xy)
    steepest = grad[:, :1] * dW_dp[:, 0] + grad[:, 1:] * dW_dp[:, 1]
    values = image[rows, columns].astype(np.float32)
    points = xy.astype(np.float32)
    return _Template(points=points[None], values=values,
                     steepest=steepest.astype(np.float32),
                     hessian_inverse=np.linalg.inv(steepest.T @ steepest), sum=float(values.sum()),
                     sum_squares=float(values @ values))


@dataclass(frozen=True, eq=False)
class _Lattice:
    """One template's points on its pixel lattice, for the corner covariance (built once per template).

    pairs: (R, 2) int points two template pixels apart along an edge (the same template value and gradient).
    neighbours: (4, N) int the right, left, lower and upper lattice neighbours of the N points that have
        all four; grad_template: (N, 2) float64 the template's central
        differences there (x, y); transfer: (2, N) float64 (G^T G)^-1 G^T, G = grad_template (None if G
        has not both directions).
    transfer_of_residual: (4, P) float64, where every point was read: A^T - I (flattened) = this @ the
        misfit at the P template points (``_gradient_transfer``: transfer @ the misfit's central
        differences, both linear in it, folded into one matrix); None with ``transfer``.
    cross: (2, 2, 8, 8) float64 sum_i s_i g_a,i dW_b,i^T over all points (s the steepest descent, g_a the
        template's gradient component a, dW_b the warp's row b): J^T J_image = sum_ab A_ba cross_ab.
    normal: (8, 8) float64 J^T J over all points.
    """

    pairs: np.ndarray
    neighbours: np.ndarray
    grad_template: np.ndarray
    transfer: np.ndarray | None
    transfer_of_residual: np.ndarray | None
    cross: np.ndarray
    normal: np.ndarray

    @classmethod
    def of(cls, template: _Template) -> _Lattice:
        xy = template.points[0].astype(np.float64)
        # the lattice step: the smallest gap between points (neighbours in a row lie one step apart)
        gaps = np.abs(np.diff(xy[:, 0]))
        step = float(gaps[gaps > 1e-9].min())
        pad = 2
        column = np.round((xy[:, 0] - xy[:, 0].min()) / step).astype(np.intp) + pad
        row = np.round((xy[:, 1] - xy[:, 1].min()) / step).astype(np.intp) + pad
        index = np.full((int(row.max()) + 1 + pad, int(column.max()) + 1 + pad), -1, np.intp)
        index[row, column] = np.arange(len(xy))

        def neighbour(down: int, right: int) -> np.ndarray:
            return index[row + down, column + right]

        steepest = template.steepest.astype(np.float64)
        # the template's own gradient: steepest columns 2 and 5 (dW/dp2 = (1, 0), dW/dp5 = (0, 1))
        gradient = steepest[:, [2, 5]]
        profile = np.column_stack([template.values, gradient])
        pairs = []
        for down, right in ((0, 2), (2, 0)):
            other = neighbour(down, right)
            i = np.nonzero(other >= 0)[0]
            j = other[i]
            same = np.all(np.abs(profile[i] - profile[j]) < 1e-6, axis=1)
            pairs.append(np.column_stack([i[same], j[same]]))
        neighbours = np.stack([neighbour(0, 1), neighbour(0, -1), neighbour(1, 0), neighbour(-1, 0)])
        neighbours = neighbours[:, np.all(neighbours >= 0, axis=0)]
        values = template.values.astype(np.float64)
        grad_template = np.column_stack([values[neighbours[0]] - values[neighbours[1]],
                                         values[neighbours[2]] - values[neighbours[3]]])
        transfer = _least_squares(grad_template)
        return cls(np.concatenate(pairs), neighbours, grad_template, transfer,
                   None if transfer is None else _transfer_of_residual(transfer, neighbours, len(xy)),
                   _cross(steepest, gradient, xy), steepest.T @ steepest)


def _transfer_of_residual(transfer: np.ndarray, neighbours: np.ndarray, points: int) -> np.ndarray:
    """(4, P) T with (transfer @ misfit).ravel() = T @ residual, misfit (N, 2) the residual's central
    differences (right - left, lower - upper) at the ``neighbours`` (4, N) of (2, N) ``transfer``."""
    folded = np.zeros((2, 2, points))
    for a in range(2):
        for b, (plus, minus) in enumerate((neighbours[0:2], neighbours[2:4])):
            np.add.at(folded[a, b], plus, transfer[a])
            np.add.at(folded[a, b], minus, -transfer[a])
    return folded.reshape(4, points)


def _cross(steepest: np.ndarray, gradient: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(2, 2, 8, 8) sum_i s_i g_a,i dW_b,i^T (see ``_Lattice.cross``).

    dW/dp at p = 0 for W(x; p) = (I + D(p)) x: x row (x, y, 1, 0, 0, 0, -x^2, -xy), y row (0, 0, 0, x, y, 1,
    -xy, -y^2): both from the sums against (x, y, 1, x^2, xy, y^2)."""
    x, y = xy[:, 0], xy[:, 1]
    monomials = np.column_stack([x, y, np.ones_like(x), x * x, x * y, y * y])
    cross = np.zeros((2, 2, 8, 8))
    for a in range(2):
        c = (steepest * gradient[:, a:a + 1]).T @ monomials  # (8, 6)
        cross[a, 0, :, :3], cross[a, 0, :, 6], cross[a, 0, :, 7] = c[:, :3], -c[:, 3], -c[:, 4]
        cross[a, 1, :, 3:6], cross[a, 1, :, 6], cross[a, 1, :, 7] = c[:, :3], -c[:, 4], -c[:, 5]
    return cross


def _parameter_cov(template: _Template, lattice: _Lattice, last: _Sample) -> np.ndarray:
    """(8, 8) covariance of the alignment's parameters (see ``MarkerFit.corner_cov_px2``), template units."""
    if last.used is None:
        residual = last.residual.astype(np.float64)
        cross, normal = lattice.cross, lattice.normal
    else:  # the misfit at every template point, NaN where not read
        residual = np.full(len(template.values), np.nan)
        residual[last.used] = last.residual
        steepest = template.steepest[last.used].astype(np.float64)
        cross = _cross(steepest, steepest[:, [2, 5]], template.points[0][last.used].astype(np.float64))
        normal = steepest.T @ steepest
    # sigma_noise^2 = mean((r_i - r_j)^2) / 2 over along-edge pairs (the template's mismatch cancels)
    differences = residual[lattice.pairs[:, 0]] - residual[lattice.pairs[:, 1]]
    differences = differences[np.isfinite(differences)]
    total = last.rms ** 2
    noise = min(float(differences @ differences / (2 * len(differences))), total) if len(differences) >= 20 else total
    A, smear = _gradient_transfer(lattice, residual)
    # sigma^2 = sigma_noise^2 + the template's mismatch: its floor and the smear it does not model
    variance = noise + TEMPLATE_MISMATCH ** 2 + (SMEAR_MISMATCH * (smear - 1.0)) ** 2
    # dp = (J^T J_image)^-1 J^T r: Cov(p) = sigma^2 B (J^T J) B^T, B = (J^T J_image)^-1, J^T J_image = sum A_ba cross_ab
    try:
        # sum_ab A_ba cross_ab: A^T flattened against cross's (a, b) pairs, one product
        B = np.linalg.inv((A.T.reshape(4) @ cross.reshape(4, 64)).reshape(8, 8))
    except np.linalg.LinAlgError:
        B = np.linalg.pinv(normal)
    return variance * B @ normal @ B.T


def _gradient_transfer(lattice: _Lattice, residual: np.ndarray) -> tuple[np.ndarray, float]:
    """(A (2, 2), smear s_max / s_min >= 1 of A): the image's gradient ~ A the template's, fitted (least
    squares) on lattice central differences of both at the points whose four neighbours were read; the
    identity and 1 where A cannot be fitted."""
    # the image at the template points in template units (levels fitted) is the template + the misfit, so
    # its central differences are the template's + the misfit's: A^T = I + (G^T G)^-1 G^T dR
    every_point_read = bool(np.isfinite(residual).all())
    if every_point_read and lattice.transfer_of_residual is not None:
        return _singular_ratio((np.eye(2) + (lattice.transfer_of_residual @ residual).reshape(2, 2)).T)
    r = residual[lattice.neighbours]  # (4, N)
    misfit = np.column_stack([r[0] - r[1], r[2] - r[3]])
    transfer = lattice.transfer
    if not every_point_read:  # the points whose four neighbours were read
        keep = np.all(np.isfinite(misfit), axis=1)
        transfer = _least_squares(lattice.grad_template[keep]) if np.count_nonzero(keep) >= 20 else None
        misfit = misfit[keep]
    if transfer is None:
        return np.eye(2), 1.0
    return _singular_ratio((np.eye(2) + transfer @ misfit).T)


def _singular_ratio(A: np.ndarray) -> tuple[np.ndarray, float]:
    """(A, s_max / s_min of the (2, 2) A); the identity and 1 where A is about singular."""
    # A's singular values: s^2 = (t +- sqrt(t^2 - 4 det^2)) / 2, t = sum of A's squares
    t, det = float(np.sum(A * A)), abs(float(A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]))
    root = np.sqrt(max(t * t - 4.0 * det * det, 0.0))
    s_max, s_min = np.sqrt((t + root) / 2.0), np.sqrt(max((t - root) / 2.0, 0.0))
    if not s_min > 1e-3 * s_max:
        return np.eye(2), 1.0
    return A, float(s_max / s_min)


def _least_squares(G: np.ndarray) -> np.ndarray | None:
    """(2, N) (G^T G)^-1 G^T of (N, 2) G, None unless G has 20 rows or more in both directions
    (det(G^T G) not ~0 against its trace^2)."""
    gram = G.T @ G
    if len(G) < 20 or not np.linalg.det(gram) > 1e-6 * np.trace(gram) ** 2:
        return None
    return np.linalg.inv(gram) @ G.T


def _warp_jacobian(xy: np.ndarray) -> np.ndarray:
    """(K, 2, 8) dW/dp at p = 0 for W(x; p) = (I + D(p)) x, D = [[p0 p1 p2] [p3 p4 p5] [p6 p7 0]], at (K, 2) points."""
    x, y = xy[:, 0], xy[:, 1]
    zero, one = np.zeros_like(x), np.ones_like(x)
    return np.stack([np.stack([x, y, one, zero, zero, zero, -x * x, -x * y], axis=1),
                     np.stack([zero, zero, zero, x, y, one, -x * y, -y * y], axis=1)], axis=1)


def _projection_jacobian(M: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K, 2, 2) d project(M, x)/dx at the (K, 2) points xy, M a (3, 3) homography."""
    h = np.column_stack([xy, np.ones(len(xy))]) @ M.T  # (K, 3)
    w = h[:, 2:3]
    u = h[:, :2] / w
    # d(h_i / w)/dx_j = (M_ij - u_i M_2j) / w
    return (M[None, :2, :2] - u[:, :, None] * M[None, 2:3, :2]) / w[:, :, None]


def _cell_px(corners_px: np.ndarray, inner_cells: int) -> float:
    """The marker's cell size in the image: square root of the inner square's area over its cells."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = corners_px.tolist()
    # quadrilateral area = half the cross product of its diagonals
    area = 0.5 * abs((x2 - x0) * (y3 - y1) - (y2 - y0) * (x3 - x1))
    return float(np.sqrt(area) / inner_cells)
