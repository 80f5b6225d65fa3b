"""Vehicle pose from the mapped markers seen in one frame (no filtering).

``PoseSolver(facility_map, camera).solve(detections, t_ns)`` returns a
``PoseMeasurement`` or None. The steps:

1. Correspondences: for every detection of a mapped marker, its four inner
   corners and, for the circles path, its corner-circle centres, as map-frame
   points against image points.
2. Hypotheses: ``SOLVEPNP_IPPE_SQUARE`` on each marker's corners gives its
   two IPPE camera poses; ``SOLVEPNP_SQPNP`` over all points of all markers
   gives one more. Each hypothesis gathers the markers it reprojects
   loosely, is refined jointly over all their points (Levenberg-Marquardt),
   and keeps the markers whose own squared errors then pass a chi-square
   test at the expected corner noise ``corner_sigma_px``: this is the
   per-marker pose-disagreement test, done in the image where the noise is
   known rather than in metres where it grows with range.
3. Choice: most agreeing markers, then the lowest squared error. Markers
   left out must be a minority of at least two agreeing markers, else the
   frame is rejected as inconsistent; the whole fit must pass the same
   chi-square test and ``max_rms_px``. A pose whose body is tilted beyond
   ``max_tilt_deg`` is implausible for a flying vehicle and never chosen.
4. Ambiguity: a distinct pose (another IPPE branch) whose squared error is
   within ``ambiguity_chi2`` sigma^2 of the best makes the result ambiguous;
   then the candidate nearest a prior pose is taken (the caller's, or the
   solver's last accepted pose if recent), and without a prior the frame is
   rejected (a flipped single-marker pose is typically metres and tens of
   degrees off).
5. Covariance: ``sigma^2 (J^T J)^-1``, J the Jacobian of the reprojection
   residuals with respect to the body pose, sigma^2 the residual variance,
   floored at ``corner_sigma_px^2``: part of a detector's corner error moves
   the pose instead of showing as residual (with one marker, 8 residuals fit
   6 parameters), so the residuals alone understate it. Rotated into NED.
6. Uncertainty: a pose whose position standard deviation (largest axis)
   exceeds ``max_position_sd_m`` is rejected: a small far marker fits its
   corners well yet fixes the pose to within metres.

All axis conventions come from ``companion.geometry.frames``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import ClassVar

import cv2
import numpy as np
from scipy.stats import chi2

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, MapMarker
from companion.types import Detection, PoseMeasurement

NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class PoseParams:
    """Thresholds of the pose solver (pixels, degrees, metres, seconds).

    corner_sigma_px: expected standard deviation of a detected point's x and
        y (detector noise); the consistency gates are chi-square tests at it.
    gate_probability: probability that corner noise alone passes those tests
        (0.999: one honest marker in a thousand fails; 1.0 turns them off).
    max_rms_px: reject any fit whose RMS point error is above this.
    hypothesis_gate_px: loose RMS gate to gather markers before refining a
        hypothesis made from one marker.
    ambiguity_chi2: a distinct pose whose sum of squared errors exceeds the
        best by less than this many sigma^2 makes the result ambiguous.
    max_position_sd_m: reject a pose whose position standard deviation along
        its worst axis is above this (metres).
    max_tilt_deg: largest plausible body roll/pitch (ArduPilot's ANGLE_MAX
        defaults to 30 degrees); it rejects many flipped IPPE branches.
    distinct_rotation_deg, distinct_position_m: two poses closer than both
        are the same solution.
    prior_max_age_s: the last accepted pose serves as prior this long.
    accept_ambiguous_without_prior: return the best ambiguous pose anyway.
    max_markers: use at most this many markers (largest in the image first);
        1 gives single-marker PnP, None uses all (joint PnP).
    """

    corner_sigma_px: float = 0.5
    gate_probability: float = 0.999
    max_rms_px: float = 2.0
    hypothesis_gate_px: float = 30.0
    ambiguity_chi2: float = 25.0
    max_position_sd_m: float = 0.10
    max_tilt_deg: float = 35.0
    distinct_rotation_deg: float = 3.0
    distinct_position_m: float = 0.05
    prior_max_age_s: float = 1.0
    accept_ambiguous_without_prior: bool = False
    max_markers: int | None = None

    # Config keys that were replaced: the old key is an error naming the new one.
    RENAMED_KEYS: ClassVar[dict[str, str]] = {
        "gate_z": "gate_probability, the chi-square tests' probability (gate_z 3.09 was 0.999)",
    }

    def __post_init__(self) -> None:
        if not (isinstance(self.gate_probability, (int, float)) and 0.0 < self.gate_probability <= 1.0):
            raise ValueError(f"pose parameter gate_probability must be in (0, 1], got {self.gate_probability!r}")


@dataclass(frozen=True)
class MarkerObservation:
    """One mapped marker seen in the frame.

    points_map: (K, 3) map-frame points (4 corners TL, TR, BR, BL, then circle centres).
    points_px: (K, 2) their image positions.
    """

    marker: MapMarker
    detection: Detection
    points_map: np.ndarray
    points_px: np.ndarray

    @property
    def side_px(self) -> float:
        """Mean side length of the marker's inner square in the image."""
        corners = self.detection.corners_px
        return float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))


@dataclass(frozen=True)
class Fit:
    """A camera pose fitted to a set of markers.

    T_camera_map: (4, 4) map -> camera.
    inliers: indices (into the observations) of the markers that agree.
    marker_sse_px2: (M,) sum of squared point errors of every observed marker
        (inf if a point falls behind the camera).
    sse_px2, n_points: sum of squared point errors and point count over the inliers.
    """

    T_camera_map: np.ndarray
    inliers: tuple[int, ...]
    marker_sse_px2: np.ndarray
    sse_px2: float
    n_points: int

    @property
    def rms_px(self) -> float:
        """RMS point reprojection error over the inliers."""
        return math.sqrt(self.sse_px2 / self.n_points)

    @property
    def dof(self) -> int:
        """Residual degrees of freedom: 2 coordinates per point minus 6 pose parameters."""
        return max(2 * self.n_points - 6, 1)


@dataclass(frozen=True)
class PoseSolution:
    """Everything the solver decided for one frame.

    measurement: the accepted pose, or None.
    status: "ok", or why there is no pose: "no mapped markers",
        "reprojection", "inconsistent markers", "implausible attitude",
        "ambiguous", "uncertain".
    ambiguous: another pose fitted nearly as well (resolved by the prior if
        ``used_prior``).
    marker_ids: ids of the markers used; rejected_ids: mapped markers seen
        but left out as inconsistent; unmapped_ids: detections not in the map
        (or seen twice).
    """

    measurement: PoseMeasurement | None
    status: str
    ambiguous: bool = False
    used_prior: bool = False
    marker_ids: tuple[int, ...] = ()
    rejected_ids: tuple[int, ...] = ()
    unmapped_ids: tuple[int, ...] = ()
    fits: tuple[Fit, ...] = field(default=(), repr=False)


@dataclass(frozen=True)
class _Choice:
    status: str
    fit: Fit | None = None
    ambiguous: bool = False
    used_prior: bool = False


class PoseSolver:
    """Turns one frame's detections into the vehicle pose in the map and NED.

    Holds one piece of state: the last accepted pose, used as the prior for
    ambiguous frames within ``params.prior_max_age_s``.
    """

    def __init__(self, facility_map: FacilityMap, camera: CameraModel, params: PoseParams | None = None):
        self.facility_map = facility_map
        self.camera = camera
        self.params = params or PoseParams()
        self._layout = None
        self._last: tuple[int, np.ndarray] | None = None  # (t_ns, T_map_body)

    def solve(self, detections: list[Detection], t_ns: int, prior_T_map_body: np.ndarray | None = None) -> PoseMeasurement | None:
        """The pose from this frame's detections, or None (see ``solve_detailed``)."""
        return self.solve_detailed(detections, t_ns, prior_T_map_body).measurement

    def solve_detailed(self, detections: list[Detection], t_ns: int, prior_T_map_body: np.ndarray | None = None) -> PoseSolution:
        """The pose and the reasons behind it.

        prior_T_map_body: (4, 4) a recent body pose in the map, used only to
        resolve an ambiguous frame; defaults to the last accepted pose if it
        is at most ``prior_max_age_s`` older than ``t_ns``.
        """
        observations, unmapped = self.observations(detections)
        if not observations:
            return PoseSolution(None, "no mapped markers", unmapped_ids=unmapped)
        fits = self._hypothesis_fits(observations)
        choice = self._choose(fits, len(observations), self._prior(t_ns, prior_T_map_body))
        used = choice.fit.inliers if choice.fit is not None else ()
        common = dict(ambiguous=choice.ambiguous, marker_ids=tuple(observations[i].marker.id for i in used),
                      unmapped_ids=unmapped, fits=tuple(fits))
        if choice.status != "ok":
            return PoseSolution(None, choice.status, **common)
        measurement = self._measurement(choice.fit, observations, t_ns)
        if position_sd_m(measurement) > self.params.max_position_sd_m:
            return PoseSolution(None, "uncertain", **common)
        self._last = (t_ns, measurement.T_map_body)
        rejected = tuple(o.marker.id for i, o in enumerate(observations) if i not in used)
        return PoseSolution(measurement, "ok", used_prior=choice.used_prior, rejected_ids=rejected, **common)

    def _choose(self, fits: list[Fit], observed: int, prior: np.ndarray | None) -> "_Choice":
        """The fit to report, or why none: plausibility, consistency, ambiguity."""
        plausible = [f for f in fits if self._plausible(f)]
        if fits and not plausible:
            return _Choice("implausible attitude")
        best = _best(plausible)
        status = self._check_consistency(best, observed)
        if status != "ok":
            return _Choice(status, best)
        rivals = self._rivals(best, plausible)
        if not rivals:
            return _Choice("ok", best)
        if prior is not None:
            return _Choice("ok", _nearest_to_prior([best] + rivals, prior, self.camera.T_camera_body), True, True)
        if self.params.accept_ambiguous_without_prior:
            return _Choice("ok", best, True)
        return _Choice("ambiguous", best, True)

    # ------------------------------------------------------ correspondences

    def observations(self, detections: list[Detection]) -> tuple[list[MarkerObservation], tuple[int, ...]]:
        """Mapped markers seen once each (largest first), and the ids left out.

        A marker detected twice in one frame cannot be both places: both
        detections are left out.
        """
        counts: dict[int, int] = {}
        for detection in detections:
            counts[detection.id] = counts.get(detection.id, 0) + 1
        observations, left_out = [], []
        for detection in detections:
            marker = self.facility_map.markers.get(detection.id)
            if marker is None or counts[detection.id] > 1:
                left_out.append(detection.id)
                continue
            observations.append(self._observation(marker, detection))
        observations.sort(key=lambda o: -o.side_px)
        if self.params.max_markers is not None:
            observations = observations[: self.params.max_markers]
        return observations, tuple(sorted(set(left_out)))

    def _observation(self, marker: MapMarker, detection: Detection) -> MarkerObservation:
        points_marker = [marker.corners_marker()]
        points_px = [np.asarray(detection.corners_px, dtype=float).reshape(4, 2)]
        if len(detection.circle_ids):
            circles_uv = self._circles_uv()
            ids = np.asarray(detection.circle_ids, dtype=int).reshape(-1)
            valid = (ids >= 0) & (ids < len(circles_uv))  # a detector bug must not stop the pipeline
            layout = self._marker_layout()
            points_marker.append(frames.grid_to_marker_m(circles_uv[ids[valid]], layout.inner_origin, layout.inner_cells, marker.size_m))
            points_px.append(np.asarray(detection.circles_px, dtype=float).reshape(-1, 2)[valid])
        points_map = frames.transform_points(marker.T_map_marker, np.vstack(points_marker))
        return MarkerObservation(marker, detection, points_map, np.vstack(points_px))

    def _marker_layout(self):
        if self._layout is None:
            from companion.markers.layout import MarkerLayout

            self._layout = MarkerLayout(parity=self.facility_map.parity, dictionary=self.facility_map.dictionary)
        return self._layout

    def _circles_uv(self) -> np.ndarray:
        """(12, 2) circle centres (u, v) in grid cells."""
        return np.asarray(self._marker_layout().circles, dtype=float)[:, :2]

    # ----------------------------------------------------------- hypotheses

    def _hypothesis_fits(self, observations: list[MarkerObservation]) -> list[Fit]:
        """Refined fits from every marker's IPPE poses and from all markers at once, duplicates removed."""
        starts = [T for o in observations for T in self._ippe_poses(o)]
        if len(observations) > 1:
            starts.append(self._all_markers_pose(observations))
        fits: list[Fit] = []
        for T_camera_map in starts:
            fit = self._grow_and_refine(T_camera_map, observations)
            if fit is not None and not self._same_pose_as_any(fit, fits):
                fits.append(fit)
        return fits

    def _all_markers_pose(self, observations: list[MarkerObservation]) -> np.ndarray:
        """T_camera_map from SQPnP (globally optimal) over all points of all markers.

        Many markers small in the image, each with a poor pose of its own, can
        still give a good joint pose.
        """
        points_map = np.vstack([o.points_map for o in observations])
        points_px = np.vstack([o.points_px for o in observations])
        _, rvec, tvec = cv2.solvePnP(points_map, points_px, self.camera.K, self.camera.dist, flags=cv2.SOLVEPNP_SQPNP)
        return frames.transform_from_rotvec(rvec, tvec)

    def _ippe_poses(self, observation: MarkerObservation) -> list[np.ndarray]:
        """IPPE_SQUARE poses (T_camera_map) of one marker from its corners.

        The second solution is kept only if it is not clearly worse on this
        marker's points (the same test as for ambiguity); a clearly wrong
        branch cannot become the best fit and costs a refinement.
        """
        square = observation.marker.corners_marker()
        corners_px = observation.points_px[:4].reshape(4, 1, 2)
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            square, corners_px, self.camera.K, self.camera.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        T_marker_map = frames.invert_transform(observation.marker.T_map_marker)
        poses = [frames.transform_from_rotvec(rvecs[i], tvecs[i]) @ T_marker_map for i in range(count)]
        sse = [float(self._marker_sse(T, [observation])[0]) for T in poses]
        limit_px2 = min(sse) + self.params.ambiguity_chi2 * self.params.corner_sigma_px ** 2
        return [T for T, e in zip(poses, sse) if e <= limit_px2]

    def _grow_and_refine(self, T_camera_map: np.ndarray, observations: list[MarkerObservation]) -> Fit | None:
        """Refine a hypothesis on the markers it explains; None if it explains none."""
        sse = self._marker_sse(T_camera_map, observations)
        counts = np.array([len(o.points_map) for o in observations])
        members = np.flatnonzero(sse < counts * self.params.hypothesis_gate_px ** 2)
        for _ in range(3):
            if len(members) == 0:
                return None
            T_camera_map = self._refine(T_camera_map, [observations[i] for i in members])
            sse = self._marker_sse(T_camera_map, observations)
            agreeing = np.flatnonzero([self._within_noise(e, 2 * n) for e, n in zip(sse, counts)])
            if np.array_equal(agreeing, members):
                break
            members = agreeing
        if len(members) == 0:
            return None
        return Fit(T_camera_map, tuple(int(i) for i in members), sse, float(sse[members].sum()), int(counts[members].sum()))

    def _within_noise(self, sse_px2: float, dof: int) -> bool:
        """Chi-square test: squared errors explained by corner noise at ``corner_sigma_px``."""
        return sse_px2 / self.params.corner_sigma_px ** 2 < chi2_quantile(self.params.gate_probability, dof)

    def _refine(self, T_camera_map: np.ndarray, observations: list[MarkerObservation]) -> np.ndarray:
        """Levenberg-Marquardt over all points of these markers, from T_camera_map."""
        points_map = np.vstack([o.points_map for o in observations])
        points_px = np.vstack([o.points_px for o in observations])
        rvec = frames.rotvec_from_rotation(T_camera_map[:3, :3]).reshape(3, 1)
        tvec = T_camera_map[:3, 3].reshape(3, 1).copy()
        rvec, tvec = cv2.solvePnPRefineLM(points_map, points_px, self.camera.K, self.camera.dist, rvec, tvec)
        return frames.transform_from_rotvec(rvec, tvec)

    def _residuals(self, T_camera_map: np.ndarray, observations: list[MarkerObservation]) -> np.ndarray:
        """(K, 2) projected minus observed pixels over the markers' points (NaN behind the camera)."""
        points_map = np.vstack([o.points_map for o in observations])
        points_px = np.vstack([o.points_px for o in observations])
        return self.camera.project_from(T_camera_map, points_map) - points_px

    def _marker_sse(self, T_camera_map: np.ndarray, observations: list[MarkerObservation]) -> np.ndarray:
        """(M,) sum of squared point errors of each marker under the pose (inf if behind the camera)."""
        squared = np.sum(self._residuals(T_camera_map, observations) ** 2, axis=1)
        starts = np.cumsum([0] + [len(o.points_map) for o in observations[:-1]])
        sse = np.add.reduceat(squared, starts)
        return np.where(np.isfinite(sse), sse, np.inf)

    # --------------------------------------------------------------- choice

    def _plausible(self, fit: Fit) -> bool:
        """Body roll and pitch within ``max_tilt_deg`` (in the map, z up)."""
        T_map_body = _body_pose(fit.T_camera_map, self.camera.T_camera_body)
        # The body's down axis (FRD z) against the map's down direction.
        cos_tilt = float(-T_map_body[2, 2])
        return cos_tilt >= math.cos(math.radians(self.params.max_tilt_deg))

    def _check_consistency(self, best: Fit | None, observed: int) -> str:
        if best is None:
            return "reprojection"
        outliers = observed - len(best.inliers)
        if outliers and (len(best.inliers) < 2 or len(best.inliers) <= outliers):
            return "inconsistent markers"
        if best.rms_px > self.params.max_rms_px or not self._within_noise(best.sse_px2, best.dof):
            return "reprojection"
        return "ok"

    def _rivals(self, best: Fit, fits: list[Fit]) -> list[Fit]:
        """Distinct fits to the same markers whose squared error is not clearly worse."""
        sigma2 = max(self.params.corner_sigma_px ** 2, best.sse_px2 / best.dof)
        limit_px2 = best.sse_px2 + self.params.ambiguity_chi2 * sigma2
        return [
            f for f in fits
            if f is not best and f.inliers == best.inliers and f.sse_px2 < limit_px2 and not self._same_pose_as_any(f, [best])
        ]

    def _same_pose_as_any(self, fit: Fit, others: list[Fit]) -> bool:
        """Whether one of the others is the same camera pose: closer than both distinct_rotation_deg and distinct_position_m."""
        if not others:
            return False
        # one vectorised call: this runs for every pair of hypotheses
        R_others = np.stack([other.T_camera_map[:3, :3] for other in others])
        angles_deg = np.degrees(frames.rotation_angle_rad(R_others, fit.T_camera_map[:3, :3]))
        positions_m = np.linalg.norm(np.stack([_camera_position_m(other) for other in others]) - _camera_position_m(fit), axis=1)
        same = (angles_deg < self.params.distinct_rotation_deg) & (positions_m < self.params.distinct_position_m)
        return bool(same.any())

    def _prior(self, t_ns: int, prior_T_map_body: np.ndarray | None) -> np.ndarray | None:
        if prior_T_map_body is not None:
            return prior_T_map_body
        if self._last is not None and 0 <= t_ns - self._last[0] <= self.params.prior_max_age_s * NS_PER_S:
            return self._last[1]
        return None

    # ---------------------------------------------------------- measurement

    def _measurement(self, fit: Fit, observations: list[MarkerObservation], t_ns: int) -> PoseMeasurement:
        used = [observations[i] for i in fit.inliers]
        T_map_body = _body_pose(fit.T_camera_map, self.camera.T_camera_body)
        covariance_map = self._covariance_map(T_map_body, used)
        T_ned_map = self.facility_map.T_ned_map
        return PoseMeasurement(
            t_ns=t_ns,
            T_map_body=T_map_body,
            T_ned_body=T_ned_map @ T_map_body,
            covariance_ned=frames.rotate_pose_covariance(covariance_map, T_ned_map[:3, :3]),
            marker_ids=tuple(o.marker.id for o in used),
            reprojection_rms_px=fit.rms_px,
        )

    def _covariance_map(self, T_map_body: np.ndarray, observations: list[MarkerObservation]) -> np.ndarray:
        """(6, 6) covariance of [body position (3), small rotation (3)], both on map axes.

        C = sigma^2 (J^T J)^-1, J = d(residuals)/d(pose), sigma^2 = r.r / (2K - 6)
        floored at corner_sigma_px^2.
        """
        J = self._pose_jacobian(T_map_body, observations)
        residuals = self._residuals(self._T_camera_map(T_map_body), observations).reshape(-1)
        dof = max(residuals.size - 6, 1)
        sigma2 = max(float(residuals @ residuals) / dof, self.params.corner_sigma_px ** 2)
        return sigma2 * np.linalg.pinv(J.T @ J)

    def _pose_jacobian(self, T_map_body: np.ndarray, observations: list[MarkerObservation]) -> np.ndarray:
        """(2K, 6) derivative of the projected pixels by [dp_map (3), dtheta_map (3)].

        Perturbed pose: R' = exp(dtheta) R, p' = p + dp (map axes). A map
        point X is seen at X_c = R_cm (X - p) + t_cb with R_cm = R_cb R^T, so
        to first order dX_c = R_cm (-dp + (X - p) x dtheta); the camera
        gives d(pixels)/dX_c (OpenCV's projectPoints).
        """
        points_map = np.vstack([o.points_map for o in observations])
        T_camera_map = self._T_camera_map(T_map_body)
        # A_i = d(pixels_i)/dX_c R_cm: (K, 2, 3)
        A = self.camera.projection_jacobian(frames.transform_points(T_camera_map, points_map)) @ T_camera_map[:3, :3]
        # d(pixels_i)/d(dp) = -A_i
        d_position = -A
        # d(pixels_i)/d(dtheta) = A_i skew(X_i - p): row a of it is a x (X_i - p)
        d_rotation = np.cross(A, (points_map - T_map_body[:3, 3])[:, None, :])
        return np.concatenate([d_position, d_rotation], axis=2).reshape(-1, 6)

    def _T_camera_map(self, T_map_body: np.ndarray) -> np.ndarray:
        # T_camera_map = T_camera_body T_body_map
        return self.camera.T_camera_body @ frames.invert_transform(T_map_body)


# ----------------------------------------------------------------- helpers

def position_sd_m(measurement: PoseMeasurement) -> float:
    """Standard deviation of the position along its worst axis, metres."""
    return math.sqrt(max(float(np.linalg.eigvalsh(measurement.covariance_ned[:3, :3])[-1]), 0.0))


def _best(fits: list[Fit]) -> Fit | None:
    """Most agreeing markers, then the lowest RMS."""
    return min(fits, key=lambda f: (-len(f.inliers), f.sse_px2), default=None)


@functools.lru_cache(maxsize=1024)
def chi2_quantile(probability: float, dof: int) -> float:
    """q with P(X <= q) = probability for X chi-square with ``dof`` degrees of freedom.

    Cached: a solve asks for a few small dof many times, and scipy's call costs ~50 us.
    """
    return float(chi2.ppf(probability, dof))


def _camera_position_m(fit: Fit) -> np.ndarray:
    """(3,) the camera's optical centre in the map."""
    return frames.invert_transform(fit.T_camera_map)[:3, 3]


def _body_pose(T_camera_map: np.ndarray, T_camera_body: np.ndarray) -> np.ndarray:
    """(4, 4) T_map_body from the camera pose and the camera mounting."""
    # T_map_body = T_map_camera T_camera_body
    return frames.invert_transform(T_camera_map) @ T_camera_body


def _nearest_to_prior(fits: list[Fit], prior_T_map_body: np.ndarray, T_camera_body: np.ndarray) -> Fit:
    """The fit whose body pose is nearest the prior (metres + radians at 1 m)."""
    def distance(fit: Fit) -> float:
        T_map_body = _body_pose(fit.T_camera_map, T_camera_body)
        position_m = float(np.linalg.norm(T_map_body[:3, 3] - prior_T_map_body[:3, 3]))
        return position_m + frames.rotation_angle_rad(T_map_body[:3, :3], prior_T_map_body[:3, :3])

    return min(fits, key=distance)
