"""Bundle adjustment of a survey: every marker and camera pose over every corner and circle seen.

Unknowns: each frame's camera pose ``T_camera_map`` and each free marker's
``T_map_marker``, both as small corrections to their current values
(a rotation ``R = exp(dtheta) R0`` on the left, on the outer frame's axes, and
a translation ``t = t0 + dt``), so a marker's correction ``[dp (3), dtheta (3)]``
is on map axes, as its covariance is reported. Fixed markers (anchors) do
not move.

Residuals, all in standard deviations:

* every point of every sighting: (projected - detected pixels) / ``sigma_px``;
* "hangs on a vertical wall" priors: the horizontal part of the marker's
  y axis (map x, y) / ``wall_sd_rad`` (zero when the y axis is vertical);
* soft anchors (to test how well several anchors agree): the position
  difference / ``anchor_sd_m`` and the rotation difference (rotation vector) / ``anchor_sd_rad``.

``scipy.optimize.least_squares`` solves it (trust region reflective, LSMR
on the sparse Jacobian given by ``jac_sparsity``: a point depends on one
camera and one marker), with a Huber loss so that a few bad corners cannot
pull the map. Each free marker's covariance is ``s^2 (J^T J)^-1`` reduced to
its 6x6 block by the Schur complement of the camera poses (each camera's
block is 6x6), ``s^2`` the residuals' variance in standard deviations.
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.survey.observations import SurveyFrame

HUBER_SIGMAS = 3.0        # residuals beyond this many standard deviations count linearly
MIN_DEPTH_M = 1e-3        # a point behind the camera is projected as if just in front (a large error)


@dataclass(frozen=True)
class Priors:
    """What is known besides the images.

    on_wall: marker ids whose y axis is vertical, to within ``wall_sd_rad``.
    soft_anchors: marker id -> stated T_map_marker (4, 4), held to within ``anchor_sd_m`` and ``anchor_sd_rad``.
    """

    on_wall: frozenset[int] = frozenset()
    wall_sd_rad: float = math.radians(0.2)
    soft_anchors: dict[int, np.ndarray] = field(default_factory=dict)
    anchor_sd_m: float = 0.01
    anchor_sd_rad: float = math.radians(1.0)


@dataclass(frozen=True)
class Adjustment:
    """The adjusted poses and their uncertainty.

    markers: id -> T_map_marker (4, 4), fixed and free; cameras: (F, 4, 4) T_camera_map of the frames.
    covariance: free marker id -> (6, 6) over [position m (3), small rotation rad (3)], map axes.
    sighting_rms_px: (S,) RMS point error of each sighting, in ``sightings`` order (frame k, marker id).
    sigma_px: the point noise the residuals show (RMS over all points).
    """

    markers: dict[int, np.ndarray]
    cameras: np.ndarray
    covariance: dict[int, np.ndarray]
    sightings: list[tuple[int, int]]
    sighting_rms_px: np.ndarray
    sigma_px: float
    iterations: int


class BundleAdjustment:
    """One adjustment problem: frames (each with its sightings), initial poses, which markers are free."""

    def __init__(self, survey_frames: list[SurveyFrame], camera: CameraModel, markers: dict[int, np.ndarray],
                 cameras: np.ndarray, free_ids: list[int], priors: Priors = Priors(), sigma_px: float = 0.5):
        self.frames, self.camera, self.priors, self.sigma_px = survey_frames, camera, priors, sigma_px
        self.ids = sorted(markers)
        self.slot = {m: k for k, m in enumerate(self.ids)}
        self.free_ids = list(free_ids)
        self.free_slot = {m: k for k, m in enumerate(self.free_ids)}
        self.R0_marker = np.array([markers[m][:3, :3] for m in self.ids])
        self.p0_marker = np.array([markers[m][:3, 3] for m in self.ids])
        self.R0_camera = np.array(cameras)[:, :3, :3]
        self.t0_camera = np.array(cameras)[:, :3, 3]
        self._index_points()

    def _index_points(self) -> None:
        """Flat (P, ...) arrays over every point: its frame, marker slot, marker-frame position and pixels."""
        frame_of, slot_of, points, pixels, self.sightings, starts = [], [], [], [], [], [0]
        for k, frame in enumerate(self.frames):
            for s in frame.sightings:
                n = len(s.points_px)
                frame_of.append(np.full(n, k))
                slot_of.append(np.full(n, self.slot[s.marker_id]))
                points.append(s.points_marker_m)
                pixels.append(s.points_px)
                self.sightings.append((k, s.marker_id))
                starts.append(starts[-1] + n)
        self.point_frame = np.concatenate(frame_of)
        self.point_slot = np.concatenate(slot_of)
        self.points_marker = np.vstack(points)
        self.points_px = np.vstack(pixels)
        self.sighting_starts = np.array(starts)
        self.wall_ids = [m for m in self.free_ids if m in self.priors.on_wall]
        self.anchor_ids = [m for m in self.free_ids if m in self.priors.soft_anchors]

    # --------------------------------------------------------------- model

    @property
    def n_params(self) -> int:
        return 6 * (len(self.frames) + len(self.free_ids))

    def poses(self, x: np.ndarray):
        """(R_camera (F, 3, 3), t_camera (F, 3), R_marker (M, 3, 3), p_marker (M, 3)) at parameters x."""
        F = len(self.frames)
        d_camera = x[:6 * F].reshape(F, 6)
        # R = exp(dtheta) R0, t = t0 + dt
        R_camera = Rotation.from_rotvec(d_camera[:, :3]).as_matrix() @ self.R0_camera
        t_camera = self.t0_camera + d_camera[:, 3:]
        R_marker, p_marker = self.R0_marker.copy(), self.p0_marker.copy()
        if self.free_ids:
            d_marker = x[6 * F:].reshape(-1, 6)
            free = [self.slot[m] for m in self.free_ids]
            # p = p0 + dp, R = exp(dtheta) R0
            p_marker[free] += d_marker[:, :3]
            R_marker[free] = Rotation.from_rotvec(d_marker[:, 3:]).as_matrix() @ self.R0_marker[free]
        return R_camera, t_camera, R_marker, p_marker

    def point_errors_px(self, x: np.ndarray) -> np.ndarray:
        """(P, 2) projected minus detected pixels of every point."""
        R_camera, t_camera, R_marker, p_marker = self.poses(x)
        # X_map = R_map_marker X + p;  X_camera = R_camera_map X_map + t
        X_map = np.einsum("pij,pj->pi", R_marker[self.point_slot], self.points_marker) + p_marker[self.point_slot]
        X_camera = np.einsum("pij,pj->pi", R_camera[self.point_frame], X_map) + t_camera[self.point_frame]
        X_camera[:, 2] = np.maximum(X_camera[:, 2], MIN_DEPTH_M)
        projected, _ = cv2.projectPoints(X_camera.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.camera.K,
                                         self.camera.dist)
        return projected.reshape(-1, 2) - self.points_px

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(2P + 2W + 6A,) every residual in standard deviations (see the module docstring)."""
        parts = [self.point_errors_px(x).ravel() / self.sigma_px]
        if self.wall_ids or self.anchor_ids:
            _, _, R_marker, p_marker = self.poses(x)
        if self.wall_ids:
            y_axes = R_marker[[self.slot[m] for m in self.wall_ids], :, 1]
            parts.append(y_axes[:, :2].ravel() / self.priors.wall_sd_rad)
        for m in self.anchor_ids:
            T_stated = self.priors.soft_anchors[m]
            k = self.slot[m]
            parts.append((p_marker[k] - T_stated[:3, 3]) / self.priors.anchor_sd_m)
            parts.append(frames.rotvec_from_rotation(R_marker[k] @ T_stated[:3, :3].T) / self.priors.anchor_sd_rad)
        return np.concatenate(parts)

    def sparsity(self) -> sp.csr_matrix:
        """Which parameters each residual depends on: a point on its camera (6) and its marker if free (6)."""
        F = len(self.frames)
        rows, cols = [], []
        point_rows = np.arange(2 * len(self.point_frame)).reshape(-1, 2)
        for axis in range(2):
            r = point_rows[:, axis]
            rows.append(np.repeat(r, 6))
            cols.append((6 * self.point_frame[:, None] + np.arange(6)).ravel())
            free_slot = np.array([self.free_slot.get(m, -1) for m in self.ids])[self.point_slot]
            moving = free_slot >= 0
            rows.append(np.repeat(r[moving], 6))
            cols.append((6 * F + 6 * free_slot[moving][:, None] + np.arange(6)).ravel())
        row = 2 * len(self.point_frame)
        for m in self.wall_ids:
            for _ in range(2):
                rows.append(np.full(6, row))
                cols.append(6 * F + 6 * self.free_slot[m] + np.arange(6))
                row += 1
        for m in self.anchor_ids:
            for _ in range(6):
                rows.append(np.full(6, row))
                cols.append(6 * F + 6 * self.free_slot[m] + np.arange(6))
                row += 1
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(row, self.n_params))

    # --------------------------------------------------------------- solve

    def solve(self, max_iterations: int = 60, progress: bool = False, description: str = "adjusting") -> Adjustment:
        bar = tqdm(total=max_iterations, unit="step", desc=description, disable=not progress, file=sys.stderr)

        def step(intermediate_result) -> None:  # the name asks scipy for the OptimizeResult
            bar.update(1)
            bar.set_postfix(cost=f"{intermediate_result.cost:.4g}")

        try:
            result = least_squares(self.residuals, np.zeros(self.n_params), jac_sparsity=self.sparsity(),
                                   method="trf", tr_solver="lsmr", loss="huber", f_scale=HUBER_SIGMAS,
                                   x_scale="jac", max_nfev=max_iterations, callback=step)
        finally:
            bar.close()
        return self._adjustment(result)

    def _adjustment(self, result) -> Adjustment:
        R_camera, t_camera, R_marker, p_marker = self.poses(result.x)
        markers = {m: frames.make_transform(R_marker[k], p_marker[k]) for m, k in self.slot.items()}
        cameras = np.array([frames.make_transform(R, t) for R, t in zip(R_camera, t_camera)])
        errors = self.point_errors_px(result.x)
        squared = np.sum(errors ** 2, axis=1)
        counts = np.diff(self.sighting_starts)
        sighting_rms = np.sqrt(np.add.reduceat(squared, self.sighting_starts[:-1]) / counts)
        dof = max(2 * len(errors) - self.n_params, 1)
        # the residuals' variance in standard deviations: (sum of squared point errors / sigma^2) / dof
        variance = float(np.sum(squared)) / self.sigma_px ** 2 / dof
        covariance = self._marker_covariance(result.jac, variance)
        return Adjustment(markers, cameras, covariance, self.sightings, sighting_rms,
                          math.sqrt(float(np.sum(squared)) / (2 * len(errors))), int(result.nfev))

    def _marker_covariance(self, J, variance: float) -> dict[int, np.ndarray]:
        """Free marker id -> (6, 6) covariance: s^2 times the inverse of the Schur complement of the cameras.

        H = J^T J = [[A, B], [B^T, C]] (cameras first); the markers' block of H^-1
        is (C - B^T A^-1 B)^-1, and A is block diagonal (6x6 per camera).
        """
        if not self.free_ids:
            return {}
        J = sp.csr_matrix(J)
        n_camera = 6 * len(self.frames)
        H = (J.T @ J).tocsr()
        A = H[:n_camera, :n_camera].tobsr(blocksize=(6, 6))
        B = H[:n_camera, n_camera:]
        C = H[n_camera:, n_camera:].toarray()
        blocks = A.data
        A_inverse = sp.bsr_matrix((np.linalg.pinv(blocks), A.indices, A.indptr), shape=A.shape)
        schur = C - (B.T @ (A_inverse @ B)).toarray()
        covariance = variance * np.linalg.pinv(schur)
        return {m: covariance[6 * k:6 * k + 6, 6 * k:6 * k + 6] for m, k in self.free_slot.items()}
