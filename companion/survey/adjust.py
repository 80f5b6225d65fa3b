"""Bundle adjustment of a survey: every marker and camera pose over every corner and circle seen.

Unknowns: each frame's camera pose ``T_camera_map`` and each free marker's
``T_map_marker``. A step changes them by small corrections on the outer
frame's axes (a rotation ``R = exp(dtheta) R0`` on the left and a translation
``t = t0 + dt``), so a marker's correction ``[dp (3), dtheta (3)]`` is on map
axes, as its covariance is reported. Fixed markers (anchors) do not move.

Residuals, all in standard deviations:

* every point of every sighting: (projected - detected pixels) / its noise:
  its kind's (``POINT_KINDS``: a square-path corner is aligned on the whole
  printed pattern, a few hundredths of a pixel; the circles path's corners
  and circle centres are tenths) times what the detector states for that
  sighting relative to the kind's median (``Sighting.sigma_px``: a large,
  sharp marker seen face-on weighs more than a small, blurred or oblique
  one), under a Huber loss at ``HUBER_SIGMAS`` so that a few bad points
  cannot pull the map; the four corners of a square-path sighting share one
  more error, along their aspect (the quadrilateral's width read long against
  its height), ``ASPECT_VARIANCE_FACTOR`` times as large as their noise says:
  those residuals are whitened with it (``_AspectModes``);
* "hangs on a vertical wall" priors: the horizontal part of the marker's
  y axis (map x, y) / ``wall_sd_rad`` (zero when the y axis is vertical);
* soft anchors (to test how well several anchors agree): the position
  difference / ``anchor_sd_m`` and the rotation difference (rotation vector) / ``anchor_sd_rad``.

The solver is Levenberg-Marquardt with exact steps: the normal equations are
reduced to the markers by the Schur complement of the cameras (each camera's
block is 6x6, the markers' system is dense and small: 6 per free marker) and
solved exactly, with the Huber loss as iteratively reweighted least squares.
An inexact iterative step (LSMR) stalls along the weak directions of a
survey, the slow bending of a long chain of markers, while the residuals
already look converged; an exact step does not. Each free marker's
covariance is ``s^2 S^-1`` at the solution, ``S`` the same reduced system
(the cameras marginalised out), ``s^2`` the residuals' variance in standard deviations
(priors, which hold as stated whatever the images' residuals, count unscaled: ``S^-1 (s^2 S_images +
P) S^-1``, ``P`` their information),
plus the detector's systematic error's (``SYSTEMATIC_POINT_PX``: each point of
each marker off by a constant in every frame; it does not shrink with the
number of frames): ``SYSTEMATIC_POINT_PX^2 X X^T``, X = S^-1 times the
reduced gradient of each such offset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.progress import progress_bar
from companion.survey.observations import POINT_KINDS, SurveyFrame

HUBER_SIGMAS = 3.0        # a point's error beyond this many standard deviations counts linearly
MIN_DEPTH_M = 1e-3        # a point behind the camera is projected as if just in front (a large error)
RELATIVE_DECREASE = 1e-10  # converged when a step lowers the cost by less than this fraction
MAX_DAMPING = 1e10
# The detector's systematic error: each point of a marker (corner, circle centre) is read off by a constant of
# about this much (one standard deviation, px, along each of the marker's image axes), the same in every frame
# the marker is seen in, so it does not average out over frames as the noise does. Measured on bench_survey's
# walks against the renderer's true corners (markers.csv): per marker and corner, the mean detected - true over
# all its frames is 0.020 px RMS on the quick walk, 0.014 px on the full 640x480 walk (noise explains 0.002-0.003
# px of it); the larger is taken since part of it has one sign on every marker (0.007 px: blurred markers read
# short, docs/survey.md), which adds up along a chain where independent offsets would partly cancel.
SYSTEMATIC_POINT_PX = 0.02
# A square-path sighting's aspect: its four corners' error along ``aspect_modes``. Measured against the renderer's
# true corners (benchmarks/bench_survey_budget.py; docs/survey.md, "A sighting's aspect"): in units of each
# sighting's stated noise its variance is 2.5 on bench_survey's 640x480 walk and 6.2 on its 1280x720 walk (larger
# markers, median corner spread 40 -> 72 px: the aspect error grows with them, the stated noise hardly, 0.015 ->
# 0.018 px), the other modes' 0.3-2.3 but the scale's (2.0, 5.7; weighed like the aspect, it made the map worse).
# It is not noise: it repeats from frame to frame (a motion smear stretches a marker along it, a small marker's
# pattern biases it) and much of it has one sign (the walk's markers read wider than tall). A marker on a wall
# turns only about the vertical, which a view from the side sees as aspect: weighed as noise, these errors turned
# the 640x480 one-anchor map (6.1 mm median).
# 6 is taken, the larger walk's: against 3, bench_survey's maps went 3.6 -> 3.5 and 1.7 -> 1.7 mm median (640x480,
# one and three anchors), 2.3 -> 2.5 and 0.9 -> 0.7 mm (1280x720), and a rendering of the 640x480 walk with other
# seeds, which played no part in choosing it, 3.9 -> 2.5 mm (one anchor) and 2.4 -> 1.8 mm (three).
ASPECT_VARIANCE_FACTOR = 6.0


@dataclass(frozen=True)
class Priors:
    """What is known besides the images.

    on_wall: marker ids whose y axis is vertical, to within ``wall_sd_rad``.
    soft_anchors: marker id -> stated T_map_marker (4, 4), held to within ``anchor_sd_m`` and ``anchor_sd_rad``,
    or the marker's own (m, rad) in ``anchor_sd``.
    """

    on_wall: frozenset[int] = frozenset()
    wall_sd_rad: float = math.radians(0.2)
    soft_anchors: dict[int, np.ndarray] = field(default_factory=dict)
    anchor_sd_m: float = 0.01
    anchor_sd_rad: float = math.radians(1.0)
    anchor_sd: dict[int, tuple[float, float]] = field(default_factory=dict)

    def sd_of_anchor(self, marker_id: int) -> tuple[float, float]:
        """(position m, angle rad) a soft anchor is held to."""
        return self.anchor_sd.get(marker_id, (self.anchor_sd_m, self.anchor_sd_rad))


@dataclass(frozen=True)
class Adjustment:
    """The adjusted poses and their uncertainty.

    markers: id -> T_map_marker (4, 4), fixed and free; cameras: (F, 4, 4) T_camera_map of the frames.
    covariance: free marker id -> (6, 6) over [position m (3), small rotation rad (3)], map axes.
    sighting_rms_px: (S,) RMS point error of each sighting, in ``sightings`` order (frame k, marker id).
    sigma_px: the point noise the residuals show (RMS over all points).
    noise_px: point kind -> the noise of one coordinate of that kind of point the residuals show (RMS,
        corrected for the parameters fitted to them), for the kinds present; points_of_kind: how many points.
    iterations: steps taken; converged: the last step no longer lowered the cost.
    cost: half the sum of squared residuals in standard deviations (Huber on the points) at the solution;
    variance: the residuals' variance in standard deviations, s^2 (the covariance's factor).
    point_errors_px: (P, 2) projected minus detected pixels of every point, sighting by sighting;
    point_kinds: (P,) index into POINT_KINDS; sighting_starts: (S + 1,) each sighting's first point;
    point_factors: (P,) each point's noise over its kind's (its sighting's stated sigma over the kind's median).
    aspect_px2: (S,) each square-path sighting's corner errors along its aspect mode, squared (px^2; 0 for the
        others), the part its chi-square counts ``1 / ASPECT_VARIANCE_FACTOR`` of.
    """

    markers: dict[int, np.ndarray]
    cameras: np.ndarray
    covariance: dict[int, np.ndarray]
    sightings: list[tuple[int, int]]
    sighting_rms_px: np.ndarray
    sigma_px: float
    noise_px: dict[str, float]
    points_of_kind: dict[str, int]
    iterations: int
    converged: bool
    point_errors_px: np.ndarray
    point_kinds: np.ndarray
    sighting_starts: np.ndarray
    point_factors: np.ndarray
    aspect_px2: np.ndarray
    cost: float = math.nan
    variance: float = math.nan

    def sighting_chi2(self, noise_px: dict[str, float]) -> np.ndarray:
        """(S,) each sighting's squared point errors in units of its points' noise (chi-square, 2 K dof), the
        aspect of its corners at its larger variance."""
        noise = np.array([noise_px[kind] for kind in POINT_KINDS])[self.point_kinds] * self.point_factors
        first = self.sighting_starts[:-1]
        chi2 = np.add.reduceat(np.sum(self.point_errors_px ** 2, axis=1) / noise ** 2, first)
        return chi2 - _aspect_share_lost() * self.aspect_px2 / noise[first] ** 2


@dataclass
class _Poses:
    """Every pose of the problem: cameras (F, 3, 3) and (F, 3), markers (M, 3, 3) and (M, 3) by slot."""

    R_camera: np.ndarray
    t_camera: np.ndarray
    R_marker: np.ndarray
    p_marker: np.ndarray


@dataclass
class _Normal:
    """The normal equations J^T J dx = -J^T r in blocks, and the cost they were taken at.

    A: (F, 6, 6) each camera's block; g_camera: (F, 6). B: (S, 6, 6) camera-marker block of each sighting
    of a free marker (zero for the others); C: (Mf, 6, 6) each free marker's block; g_marker: (Mf, 6).
    C_prior: (Mf, 6, 6) the priors' part of C (their information, J^T J).
    """

    cost: float
    A: np.ndarray
    g_camera: np.ndarray
    B: np.ndarray
    C: np.ndarray
    g_marker: np.ndarray
    C_prior: np.ndarray


@dataclass
class _Jacobians:
    """Every point's whitened residual r (P, 2) and its derivatives by the camera's and the marker's corrections,
    J_camera and J_marker (P, 2, 6); point_cost: the points' Huber cost; scale: (P,) each point's whitening,
    sqrt(Huber weight) / noise; pixels_per_m: (P, 2, 3) d(pixels)/dX_camera, unweighted."""

    r: np.ndarray
    point_cost: float
    scale: np.ndarray
    pixels_per_m: np.ndarray
    J_camera: np.ndarray
    J_marker: np.ndarray


def _aspect_share_lost() -> float:
    """The share of a residual's squared part along its aspect mode that the aspect's variance discounts:
    1 - 1 / ``ASPECT_VARIANCE_FACTOR`` (read at each call: tests set the factor)."""
    return 1.0 - 1.0 / ASPECT_VARIANCE_FACTOR


def aspect_modes(corners_px: np.ndarray) -> np.ndarray:
    """(S, 8) unit vectors over the (x, y) errors of S quadrilaterals' corners (S, 4, 2) that read each one wider
    and shorter: every corner (x, -y) from the corners' centre, image axes."""
    centred = corners_px - corners_px.mean(axis=1, keepdims=True)
    modes = (centred * [1.0, -1.0]).reshape(len(corners_px), 8)
    return modes / np.maximum(np.linalg.norm(modes, axis=1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class _AspectModes:
    """The aspect mode of every square-path sighting's four corners, and the whitening of its residuals.

    points: (S, 4) the corners' point indices; modes: (S, 8) their ``aspect_modes`` (from the detected corners);
    sightings: (S,) their indices.
    A residual r of those corners, in units of their noise, has covariance I + (F - 1) u u^T (F =
    ``ASPECT_VARIANCE_FACTOR``): whitened, r - (1 - 1 / sqrt(F)) u (u . r), and its squared norm loses
    (1 - 1 / F) (u . r)^2.
    """

    points: np.ndarray
    modes: np.ndarray
    sightings: np.ndarray

    @classmethod
    def of(cls, points_px: np.ndarray, point_kind: np.ndarray, sighting_starts: np.ndarray) -> "_AspectModes":
        first = sighting_starts[:-1]
        square = np.flatnonzero((np.diff(sighting_starts) >= 4) & (point_kind[first] == POINT_KINDS.index("corner")))
        points = first[square, None] + np.arange(4)
        return cls(points, aspect_modes(points_px[points]), square)

    def along(self, r: np.ndarray) -> np.ndarray:
        """(S,) each sighting's residual along its mode, r (P, 2)."""
        return np.einsum("sk,sk->s", self.modes, r[self.points].reshape(len(self.points), 8))

    def whitened(self, r: np.ndarray) -> np.ndarray:
        """r (P, 2) or a Jacobian (P, 2, n) with each sighting's mode scaled by 1 / sqrt(F)."""
        if len(self.points) == 0:
            return r
        shrink = 1.0 - 1.0 / math.sqrt(ASPECT_VARIANCE_FACTOR)
        blocks = r[self.points].reshape(len(self.points), 8, -1)
        blocks = blocks - shrink * self.modes[:, :, None] * np.einsum("sk,skj->sj", self.modes, blocks)[:, None, :]
        out = r.copy()
        out[self.points] = blocks.reshape(r[self.points].shape)
        return out

    def lost(self, r: np.ndarray) -> float:
        """Half of what the squared norm of residuals r (P, 2) loses by the whitening."""
        return 0.5 * _aspect_share_lost() * float(np.sum(self.along(r) ** 2))


class BundleAdjustment:
    """One adjustment problem: frames (each with its sightings), initial poses, which markers are free.

    noise_px: the expected noise of one coordinate of a point, by kind (``POINT_KINDS``), or one value for all;
    a sighting whose detector states its noise (``Sighting.sigma_px``) has its points' scaled by that over the
    median of their kind's.
    """

    def __init__(self, survey_frames: list[SurveyFrame], camera: CameraModel, markers: dict[int, np.ndarray],
                 cameras: np.ndarray, free_ids: list[int], priors: Priors = Priors(),
                 noise_px: dict[str, float] | float = 0.5):
        self.frames, self.camera, self.priors = survey_frames, camera, priors
        self.noise_px = noise_px if isinstance(noise_px, dict) else {kind: float(noise_px) for kind in POINT_KINDS}
        self.ids = sorted(markers)
        self.slot = {m: k for k, m in enumerate(self.ids)}
        self.free_ids = list(free_ids)
        self.free_slot = {m: k for k, m in enumerate(self.free_ids)}
        cameras = np.asarray(cameras)
        self.start = _Poses(cameras[:, :3, :3].copy(), cameras[:, :3, 3].copy(),
                            np.array([markers[m][:3, :3] for m in self.ids]),
                            np.array([markers[m][:3, 3] for m in self.ids]))
        self._index_points()

    def _index_points(self) -> None:
        """Flat (P, ...) arrays over every point (frame by frame, sighting by sighting), and the sightings."""
        frame_of, slot_of, kind_of, points, pixels, self.sightings, starts = [], [], [], [], [], [], [0]
        sides, sigmas = [], []
        for k, frame in enumerate(self.frames):
            for s in frame.sightings:
                n = len(s.points_px)
                sigmas.append(np.full(n, np.nan if s.sigma_px is None else s.sigma_px))
                sides.append(np.full(n, np.ptp(s.points_marker_m[:4, 0])))
                frame_of.append(np.full(n, k))
                slot_of.append(np.full(n, self.slot[s.marker_id]))
                kind_of.append(s.point_kinds())
                points.append(s.points_marker_m)
                pixels.append(s.points_px)
                self.sightings.append((k, s.marker_id))
                starts.append(starts[-1] + n)
        self.point_frame = np.concatenate(frame_of)
        self.point_slot = np.concatenate(slot_of)
        self.point_kind = np.concatenate(kind_of)
        self.points_marker = np.vstack(points)
        self.points_px = np.vstack(pixels)
        self.point_side_m = np.concatenate(sides)
        self.sighting_starts = np.array(starts)
        self.point_factor = self._point_factors(sigmas)
        self.point_noise_px = np.array([self.noise_px[POINT_KINDS[k]] for k in self.point_kind]) * self.point_factor
        self.sighting_frame = np.array([k for k, _ in self.sightings])
        self.sighting_free = np.array([self.free_slot.get(m, -1) for _, m in self.sightings])
        self.point_sighting = np.repeat(np.arange(len(self.sightings)), np.diff(self.sighting_starts))
        # each distinct point of each marker (a corner, a circle centre), by the marker and where it is on it
        where = np.round(self.points_marker[:, :2] / self.point_side_m[:, None] * 1000).astype(int)
        _, self.point_key = np.unique(np.column_stack([self.point_slot, where]), axis=0, return_inverse=True)
        self.point_key = self.point_key.reshape(-1)
        self.point_keys = int(self.point_key.max()) + 1 if len(self.point_key) else 0
        # pairs of sightings of free markers in one frame (both orders, and each with itself): the Schur complement's terms
        pairs = [(a, b) for k in range(len(self.frames))
                 for a in self._free_sightings_of(k) for b in self._free_sightings_of(k)]
        self.pairs = np.array(pairs, dtype=int).reshape(-1, 2)
        self.frame_starts = np.concatenate([[0], np.cumsum(np.bincount(self.point_frame, minlength=len(self.frames)))])
        self.aspect = _AspectModes.of(self.points_px, self.point_kind, self.sighting_starts)
        self.wall_ids = [m for m in self.free_ids if m in self.priors.on_wall]
        self.anchor_ids = [m for m in self.free_ids if m in self.priors.soft_anchors]

    def _point_factors(self, sigmas) -> np.ndarray:
        """(P,) each point's noise relative to its kind's: the detector's sigma of its sighting over the median
        of its kind's (1 where the detector states none)."""
        sigma = np.concatenate(sigmas) if sigmas else np.zeros(0)
        factor = np.ones(len(sigma))
        for k in range(len(POINT_KINDS)):
            stated = (self.point_kind == k) & np.isfinite(sigma) & (sigma > 0)
            if stated.any():
                factor[stated] = sigma[stated] / np.median(sigma[stated])
        return factor

    def _sightings_of(self, k: int) -> range:
        return range(np.searchsorted(self.sighting_frame, k), np.searchsorted(self.sighting_frame, k, side="right"))

    def _free_sightings_of(self, k: int) -> list[int]:
        return [s for s in self._sightings_of(k) if self.sighting_free[s] >= 0]

    @property
    def n_params(self) -> int:
        return 6 * (len(self.frames) + len(self.free_ids))

    # --------------------------------------------------------------- model

    def _camera_points(self, poses: _Poses) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(X_camera, R_camera X_map, R_marker X_marker), each (P, 3), of every point."""
        slot, frame = self.point_slot, self.point_frame
        # X_map = R_map_marker X + p;  X_camera = R_camera_map X_map + t
        rotated_marker = np.einsum("pij,pj->pi", poses.R_marker[slot], self.points_marker)
        X_map = rotated_marker + poses.p_marker[slot]
        rotated_map = np.einsum("pij,pj->pi", poses.R_camera[frame], X_map)
        X_camera = rotated_map + poses.t_camera[frame]
        X_camera[:, 2] = np.maximum(X_camera[:, 2], MIN_DEPTH_M)
        return X_camera, rotated_map, rotated_marker

    def point_errors_px(self, poses: _Poses | None = None) -> np.ndarray:
        """(P, 2) projected minus detected pixels of every point (at the start poses by default)."""
        X_camera, _, _ = self._camera_points(poses or self.start)
        return self.camera.project(X_camera) - self.points_px

    def _robust(self, errors_px: np.ndarray) -> tuple[np.ndarray, float]:
        """(per-point IRLS weights (P,), Huber cost of the points) of point errors (P, 2).

        s = |error| / noise; cost rho(s) = s^2 up to k, 2 k s - k^2 beyond; weight rho'(s) / (2 s) = min(1, k / s).
        """
        s = np.linalg.norm(errors_px, axis=1) / self.point_noise_px
        k = HUBER_SIGMAS
        rho = np.where(s <= k, s ** 2, 2 * k * s - k ** 2)
        return np.minimum(1.0, k / np.maximum(s, 1e-12)), 0.5 * float(np.sum(rho))

    def _prior_residuals(self, poses: _Poses) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(free slot, residuals (n,), their Jacobian by [dp, dtheta] (n, 6)) of every prior."""
        terms = []
        for m in self.wall_ids:
            y_axis = poses.R_marker[self.slot[m], :, 1]
            J = np.zeros((2, 6))
            # d(y)/d(dtheta) = -[y]x  (dy = dtheta x y)
            J[:, 3:] = -frames.skew(y_axis)[:2] / self.priors.wall_sd_rad
            terms.append((self.free_slot[m], y_axis[:2] / self.priors.wall_sd_rad, J))
        for m in self.anchor_ids:
            T_stated = self.priors.soft_anchors[m]
            sd_m, sd_rad = self.priors.sd_of_anchor(m)
            k = self.slot[m]
            r = np.concatenate([(poses.p_marker[k] - T_stated[:3, 3]) / sd_m,
                                frames.rotvec_from_rotation(poses.R_marker[k] @ T_stated[:3, :3].T) / sd_rad])
            # small differences: d(rotvec(exp(dtheta) R R_s^T))/d(dtheta) ~ identity
            J = np.diag([1 / sd_m] * 3 + [1 / sd_rad] * 3)
            terms.append((self.free_slot[m], r, J))
        return terms

    def cost(self, poses: _Poses) -> float:
        """Half the sum of squared residuals (Huber on the points)."""
        errors = self.point_errors_px(poses)
        weights, point_cost = self._robust(errors)
        point_cost -= self.aspect.lost(errors * (np.sqrt(weights) / self.point_noise_px)[:, None])
        return point_cost + 0.5 * sum(float(r @ r) for _, r, _ in self._prior_residuals(poses))

    def _jacobians(self, poses: _Poses) -> _Jacobians:
        """Every point's residual and its derivatives at ``poses``, weighted by its noise and the Huber loss."""
        X_camera, rotated_map, rotated_marker = self._camera_points(poses)
        errors = self.camera.project(X_camera) - self.points_px
        weights, point_cost = self._robust(errors)
        # each point's residual and Jacobian scaled by sqrt(weight) / noise
        scale = np.sqrt(weights) / self.point_noise_px
        pixels_per_m = self.camera.projection_jacobian(X_camera)                 # (P, 2, 3) d(pixels)/dX_camera
        P = pixels_per_m * scale[:, None, None]                                   # (P, 2, 3) d(residual)/dX_camera
        # camera: dX_camera = -[R X_map]x dtheta + dt
        J_camera = np.concatenate([-P @ _skews(rotated_map), P], axis=2)
        # marker: dX_camera = R_camera (dp - [R_marker X]x dtheta)
        P_map = P @ poses.R_camera[self.point_frame]
        J_marker = np.concatenate([P_map, -P_map @ _skews(rotated_marker)], axis=2)
        r = errors * scale[:, None]
        return _Jacobians(self.aspect.whitened(r), point_cost - self.aspect.lost(r), scale, pixels_per_m,
                          self.aspect.whitened(J_camera), self.aspect.whitened(J_marker))

    def _normal(self, poses: _Poses) -> _Normal:
        """The normal equations at ``poses``, points weighted by their noise and the Huber loss."""
        jacobians = self._jacobians(poses)
        r, point_cost, J_camera, J_marker = jacobians.r, jacobians.point_cost, jacobians.J_camera, jacobians.J_marker
        A = np.add.reduceat(np.einsum("pki,pkj->pij", J_camera, J_camera), self.frame_starts[:-1])
        g_camera = np.add.reduceat(np.einsum("pki,pk->pi", J_camera, r), self.frame_starts[:-1])
        starts = self.sighting_starts[:-1]
        free = self.sighting_free >= 0
        B = np.add.reduceat(np.einsum("pki,pkj->pij", J_camera, J_marker), starts) * free[:, None, None]
        C_sighting = np.add.reduceat(np.einsum("pki,pkj->pij", J_marker, J_marker), starts)
        g_sighting = np.add.reduceat(np.einsum("pki,pk->pi", J_marker, r), starts)
        n_free = len(self.free_ids)
        C, g_marker = np.zeros((n_free, 6, 6)), np.zeros((n_free, 6))
        np.add.at(C, self.sighting_free[free], C_sighting[free])
        np.add.at(g_marker, self.sighting_free[free], g_sighting[free])
        prior_cost, C_prior = 0.0, np.zeros_like(C)
        for k, r_prior, J_prior in self._prior_residuals(poses):
            C_prior[k] += J_prior.T @ J_prior
            g_marker[k] += J_prior.T @ r_prior
            prior_cost += 0.5 * float(r_prior @ r_prior)
        return _Normal(point_cost + prior_cost, A, g_camera, B, C + C_prior, g_marker, C_prior)

    def _reduced(self, normal: _Normal, damping: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A^-1 (F, 6, 6), S (6Mf, 6Mf), A^-1 g_camera (F, 6)): the cameras eliminated.

        H = [[A, B], [B^T, C]] (cameras first), damped on its diagonal (Marquardt): the markers' system
        is S = C - B^T A^-1 B, with one term per pair of free markers seen in one frame.
        """
        eye = np.eye(6)
        A = normal.A * (1.0 + damping * eye)          # diag(A) (1 + damping): Marquardt's scaling
        A_inverse = np.linalg.inv(A)
        n_free = len(self.free_ids)
        S = np.zeros((n_free, n_free, 6, 6))
        S[np.arange(n_free), np.arange(n_free)] = normal.C * (1.0 + damping * eye)
        if len(self.pairs):
            a, b = self.pairs[:, 0], self.pairs[:, 1]
            # S[m(a), m(b)] -= B_a^T A^-1 B_b
            terms = np.einsum("sji,sjk,skl->sil", normal.B[a], A_inverse[self.sighting_frame[a]], normal.B[b])
            np.add.at(S, (self.sighting_free[a], self.sighting_free[b]), -terms)
        S = S.transpose(0, 2, 1, 3).reshape(6 * n_free, 6 * n_free)
        return A_inverse, S, np.einsum("fij,fj->fi", A_inverse, normal.g_camera)

    def _step(self, normal: _Normal, damping: float) -> tuple[np.ndarray, np.ndarray]:
        """The damped Gauss-Newton step (cameras (F, 6), free markers (Mf, 6)), solved exactly.

        H dx = -g: d_marker = S^-1 (-g_marker + B^T A^-1 g_camera), d_camera = A^-1 (-g_camera - B d_marker).
        """
        A_inverse, S, Ainv_g = self._reduced(normal, damping)
        free = self.sighting_free >= 0
        n_free = len(self.free_ids)
        rhs = -normal.g_marker.copy()
        np.add.at(rhs, self.sighting_free[free],
                  np.einsum("sji,sj->si", normal.B[free], Ainv_g[self.sighting_frame[free]]))
        d_marker = np.linalg.solve(S, rhs.ravel()).reshape(n_free, 6) if n_free else np.zeros((0, 6))
        coupling = np.zeros_like(normal.g_camera)
        np.add.at(coupling, self.sighting_frame[free],
                  np.einsum("sij,sj->si", normal.B[free], d_marker[self.sighting_free[free]]))
        d_camera = -np.einsum("fij,fj->fi", A_inverse, normal.g_camera + coupling)
        return d_camera, d_marker

    def _moved(self, poses: _Poses, d_camera: np.ndarray, d_marker: np.ndarray) -> _Poses:
        """The poses after a step: R = exp(dtheta) R0, t = t0 + dt (markers: p = p0 + dp)."""
        R_marker, p_marker = poses.R_marker.copy(), poses.p_marker.copy()
        if len(self.free_ids):
            free = [self.slot[m] for m in self.free_ids]
            p_marker[free] += d_marker[:, :3]
            R_marker[free] = Rotation.from_rotvec(d_marker[:, 3:]).as_matrix() @ R_marker[free]
        R_camera = Rotation.from_rotvec(d_camera[:, :3]).as_matrix() @ poses.R_camera
        return _Poses(R_camera, poses.t_camera + d_camera[:, 3:], R_marker, p_marker)

    # --------------------------------------------------------------- solve

    def solve(self, max_iterations: int = 50, progress: bool = False, description: str = "adjusting") -> Adjustment:
        """Levenberg-Marquardt from the start poses until a step no longer lowers the cost."""
        poses, damping, converged, steps = self.start, 1e-4, False, 0
        normal = self._normal(poses)
        with progress_bar(max_iterations, "step", progress, description) as bar:
            while steps < max_iterations and not converged:
                steps += 1
                bar.update(1)
                while damping < MAX_DAMPING:
                    candidate = self._moved(poses, *self._step(normal, damping))
                    cost = self.cost(candidate)
                    if cost < normal.cost:
                        break
                    damping *= 10.0
                else:
                    converged = True  # no step lowers the cost: at the minimum (to rounding)
                    break
                converged = normal.cost - cost < RELATIVE_DECREASE * normal.cost
                poses, damping = candidate, max(damping / 10.0, 1e-9)
                normal = self._normal(poses)
                bar.set_postfix(cost=f"{normal.cost:.6g}")
        return self._adjustment(poses, normal, steps, converged)

    def _adjustment(self, poses: _Poses, normal: _Normal, steps: int, converged: bool) -> Adjustment:
        markers = {m: frames.make_transform(poses.R_marker[k], poses.p_marker[k]) for m, k in self.slot.items()}
        cameras = np.array([frames.make_transform(R, t) for R, t in zip(poses.R_camera, poses.t_camera)])
        errors = self.point_errors_px(poses)
        squared = np.sum(errors ** 2, axis=1)
        counts = np.diff(self.sighting_starts)
        sighting_rms = np.sqrt(np.add.reduceat(squared, self.sighting_starts[:-1]) / counts)
        n_residuals = 2 * len(errors)
        dof = max(n_residuals - self.n_params, 1)
        # the residuals' variance in standard deviations: (sum of squared point errors / noise^2) / dof
        in_sd = errors / self.point_noise_px[:, None]
        variance = (float(np.sum(in_sd ** 2)) - 2.0 * self.aspect.lost(in_sd)) / dof
        aspect_px2 = np.zeros(len(self.sightings))
        aspect_px2[self.aspect.sightings] = self.aspect.along(errors) ** 2
        # each kind's noise: its RMS (each point's error over its factor), scaled up for the parameters fitted
        relative = squared / self.point_factor ** 2
        noise = {kind: math.sqrt(float(np.mean(relative[self.point_kind == k])) / 2 * n_residuals / dof)
                 for k, kind in enumerate(POINT_KINDS) if np.any(self.point_kind == k)}
        counts_of_kind = {kind: int(np.sum(self.point_kind == k)) for k, kind in enumerate(POINT_KINDS)}
        covariance = self._marker_covariance(poses, normal, variance)
        return Adjustment(markers, cameras, covariance, self.sightings, sighting_rms,
                          math.sqrt(float(np.sum(squared)) / n_residuals), noise, counts_of_kind, steps, converged,
                          errors, self.point_kind, self.sighting_starts, self.point_factor, aspect_px2, normal.cost,
                          variance)

    def _marker_covariance(self, poses: _Poses, normal: _Normal, variance: float) -> dict[int, np.ndarray]:
        """Free marker id -> (6, 6) covariance: the noise's, s^2 S^-1 (S the cameras' Schur complement), plus
        the detector's systematic error's, which the frames do not average out.

        One point of one marker read off by 1 px along the image direction of the marker's x (or y) axis in
        every frame it is seen in moves the free markers by X = S^-1 g (up to sign), g the reduced gradient of
        that error (``_systematic_gradients``); every point's offsets independent, SYSTEMATIC_POINT_PX each:
        Cov = SYSTEMATIC_POINT_PX^2 X X^T. It does not shrink with the number of frames, and it reaches the
        markers placed through the biased one.
        """
        if not self.free_ids:
            return {}
        _, S, _ = self._reduced(normal, 0.0)
        S_inverse = np.linalg.pinv(S)
        # S = S_images + P, P the priors' information: the images' noise is s^2 times what their weights
        # say, a prior's is as stated, so Cov = S^-1 (s^2 (S - P) + P) S^-1 (s^2 S^-1 without priors)
        P = np.zeros_like(S)
        for k, block in enumerate(normal.C_prior):
            P[6 * k:6 * k + 6, 6 * k:6 * k + 6] = block
        noise = S_inverse @ (variance * (S - P) + P) @ S_inverse
        X = (S_inverse @ self._systematic_gradients(poses, normal)).reshape(len(self.free_ids), 6, -1)
        systematic = SYSTEMATIC_POINT_PX ** 2 * np.einsum("kic,kjc->kij", X, X)
        return {m: noise[6 * k:6 * k + 6, 6 * k:6 * k + 6] + systematic[k] for m, k in self.free_slot.items()}

    def _systematic_gradients(self, poses: _Poses, normal: _Normal) -> np.ndarray:
        """(6 Mf, 2 N) the free markers' reduced gradient, g_marker - B^T A^-1 g_camera, of one of the N
        points of the markers (a corner or circle of one marker, ``point_key``) read 1 px off along the image
        direction of its marker's x axis (column 2 n) or y axis (2 n + 1) in every frame it is seen in."""
        jacobians = self._jacobians(poses)
        A_inverse = np.linalg.inv(normal.A)
        # R_camera_marker at each point
        R = np.einsum("pij,pjk->pik", poses.R_camera[self.point_frame], poses.R_marker[self.point_slot])
        free_point = self.sighting_free[self.point_sighting]
        own = np.flatnonzero(free_point >= 0)
        # (free sighting a, point p) seen in one frame: an error at p moves that camera, hence a's marker
        a, p = self._coupled_points()
        gradient = np.zeros((len(self.free_ids), 2 * self.point_keys, 6))
        for axis in (0, 1):
            direction = np.einsum("pij,pj->pi", jacobians.pixels_per_m, R[:, :, axis])
            # the point moved 1 px along it, whitened like its residual
            moved = direction / np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
            moved = self.aspect.whitened(moved * jacobians.scale[:, None])
            g_camera = np.einsum("pki,pk->pi", jacobians.J_camera, moved)   # (P, 6)
            g_marker = np.einsum("pki,pk->pi", jacobians.J_marker, moved)
            column = 2 * self.point_key + axis
            np.add.at(gradient, (free_point[own], column[own]), g_marker[own])
            Ainv_g = np.einsum("pij,pj->pi", A_inverse[self.point_frame[p]], g_camera[p])
            np.add.at(gradient, (self.sighting_free[a], column[p]), -np.einsum("pji,pj->pi", normal.B[a], Ainv_g))
        return gradient.transpose(0, 2, 1).reshape(6 * len(self.free_ids), -1)

    def _coupled_points(self) -> tuple[np.ndarray, np.ndarray]:
        """((Q,) free sightings, (Q,) points): every point with every free sighting of its frame."""
        pairs = np.array([(a, b) for k in range(len(self.frames)) for a in self._free_sightings_of(k)
                          for b in self._sightings_of(k)], dtype=int).reshape(-1, 2)
        counts = np.diff(self.sighting_starts)[pairs[:, 1]]
        # the points of sighting b: its first point + 0, 1, ..., count - 1
        offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        return np.repeat(pairs[:, 0], counts), np.repeat(self.sighting_starts[pairs[:, 1]], counts) + offsets


def _skews(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors: ``_skews(a)[i] @ b == np.cross(a[i], b)``."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], axis=1), np.stack([z, zero, -x], axis=1),
                     np.stack([-y, x, zero], axis=1)], axis=1)
