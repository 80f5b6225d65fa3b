"""Vehicle pose from the mapped markers seen in one frame (no filtering).

``PoseSolver(facility_map, camera).solve_detailed(detections, t_ns, prior, attitude)``
returns a ``PoseSolution`` whose ``measurement`` is the pose (or None, with
the reason in ``status``). The steps:

1. Correspondences: for every detection of a mapped marker, its four inner
   corners and, for the circles path, its corner-circle centres, as map-frame
   points against image points. Each point's noise is the detection's own
   ``corner_sigma_px`` (what the detector measured), else
   ``PoseParams.corner_sigma_px``, with ``model_sigma_px`` added in
   quadrature; the four corners' joint (8, 8) covariance where the detection
   states one (``Detection.corner_cov_px2``: the square path's corners come
   from one alignment, their errors correlated); the map's own error (the marker's ``sd`` in the map, else
   ``map_sd_m``, ``map_sd_deg``) moves all of a marker's points together, so a marker's errors are weighed by the
   inverse of their joint covariance. Every squared error below is in those
   units (chi-square). Markers whose map entry states its own position sd (a
   survey writes one for each) were placed through each other and err
   together: with no exactly known marker (an anchor) in view to measure it
   against, the smallest of their position variances in the frame is a
   shift they share, which moves them and the camera alike; the pose is
   solved without it in the weights (with it, a marker surveyed a little
   less well than another counts for much less, and the pose leans on the
   best one alone), the chi-square tests keep it, and the covariance
   counts it (step 6).
2. Attitude: the flight controller's roll and pitch at the capture time
   (``companion.geometry.attitude``), when given, join every fit as a prior
   of standard deviation ``attitude_sd_deg``: two more residuals, so a
   weakly constrained fit (one small or far marker) is in effect solved for
   x, y, z and yaw, and a fit that tilts the body away from the measured
   attitude costs what it should.
3. Hypotheses: with a recent prior pose (the caller's or the last accepted
   one), one fit refined from it, kept if it explains every marker. Else
   ``SOLVEPNP_IPPE_SQUARE`` on each marker's corners gives its two IPPE
   poses, the second kept only if it is not clearly worse (its squared
   error, attitude included, within ``ambiguity_chi2`` of the first), and
   ``SOLVEPNP_SQPNP`` over all points of all markers gives one more. Each
   hypothesis gathers the markers it reprojects loosely, is refined jointly
   over all their points (Gauss-Newton with Levenberg-Marquardt damping and
   the analytic Jacobian), and keeps the markers whose own squared errors
   then pass a chi-square test: the per-marker pose-disagreement test.
4. Choice: most agreeing markers, then the lowest squared error. Markers
   left out must be a minority of at least two agreeing markers, else the
   frame is rejected as inconsistent; the whole fit must pass the same
   chi-square test and ``max_rms_px`` (on what the map's stated error
   does not explain). A pose whose body is tilted beyond
   ``max_tilt_deg`` is implausible for a flying vehicle and never chosen.
   If the fit with the attitude fails these tests, the frame is solved again
   without it (an attitude that disagrees with the markers is not trusted).
5. Ambiguity: a distinct pose (another IPPE branch) whose squared error is
   within ``ambiguity_chi2`` of the best makes the result ambiguous; then
   the candidate nearest a prior pose is taken, and without a prior the
   frame is rejected (a flipped single-marker pose is metres and tens of
   degrees off). With the attitude most flips cost far more than that. A
   pose chosen with every rival ruled out and no prior is marked
   ``unambiguous``: the Kalman filter takes it as a fix without waiting for
   more frames.
6. Covariance: ``(J^T W J + A^T W_a A)^-1``, J the Jacobian of the
   reprojection residuals with respect to the body pose, W the points'
   inverse covariance (their noise and the map's error), A and W_a the
   attitude prior's: it includes the attitude's uncertainty; plus the
   surveyed markers' shared shift, through the pose it moves. Rotated into
   NED. Nothing consistent is withheld for being uncertain: the covariance
   says how good the pose is.

All axis conventions come from ``companion.geometry.frames``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import ClassVar

import cv2
import numpy as np
from scipy.stats import chi2

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, MapMarker
from companion.types import AttitudeSample, Detection, PoseMeasurement

NS_PER_S = 1_000_000_000
MAX_ITERATIONS = 12
STEP_TOLERANCE = 1e-9  # radians and metres: a smaller step ends the refinement
ATTITUDE_DOF = 2


@dataclass(frozen=True)
class PoseParams:
    """Thresholds of the pose solver (pixels, degrees, metres, seconds).

    corner_sigma_px: standard deviation of a detected point's x and y for
        detections that do not state their own (``Detection.corner_sigma_px``).
    model_sigma_px: added in quadrature to every point's noise: what the
        detector's own estimate leaves out (video compression, the camera
        calibration).
    map_sd_m, map_sd_deg: standard deviation of each marker's mapped
        position (each axis) and orientation (about each axis): the map's own
        error, which moves all of a marker's points together (0.005 m and
        0.2 degrees: a survey, as ``companion survey`` measures it; 0.02 m and
        2 degrees: a tape measure; 0: an exact map, as in a simulation), for
        the markers whose map entry states no ``sd`` of its own
        (``MapMarker.sd_position_m``, ``sd_angle_deg``: those are used as given).
    gate_probability: probability that corner noise alone passes the
        chi-square tests (0.999: one honest marker in a thousand fails; 1.0
        turns them off).
    max_rms_px: reject any fit whose RMS point error beyond what the
        map's stated error explains is above this (a bound on the points'
        own noise whatever the detector states).
    hypothesis_gate_px: loose RMS gate to gather markers before refining a
        hypothesis made from one marker.
    ambiguity_chi2: a distinct pose whose chi-square exceeds the best's by
        less than this makes the result ambiguous.
    max_tilt_deg: largest plausible body roll/pitch (ArduPilot's ANGLE_MAX
        defaults to 30 degrees); it rejects many flipped IPPE branches.
    attitude_sd_deg: standard deviation of the flight controller's roll and
        of its pitch, each (its estimate's error plus the camera mount's).
    distinct_rotation_deg, distinct_position_m: two poses closer than both
        are the same solution.
    prior_max_age_s: the last accepted pose serves as prior this long (0: never).
    accept_ambiguous_without_prior: return the best ambiguous pose anyway.
    max_markers: use at most this many markers (largest in the image first);
        1 gives single-marker PnP, None uses all (joint PnP).
    """

    corner_sigma_px: float = 0.5
    model_sigma_px: float = 0.02
    map_sd_m: float = 0.005
    map_sd_deg: float = 0.2
    gate_probability: float = 0.999
    max_rms_px: float = 2.0
    hypothesis_gate_px: float = 30.0
    ambiguity_chi2: float = 25.0
    max_tilt_deg: float = 35.0
    attitude_sd_deg: float = 0.5
    distinct_rotation_deg: float = 3.0
    distinct_position_m: float = 0.05
    prior_max_age_s: float = 1.0
    accept_ambiguous_without_prior: bool = False
    max_markers: int | None = None

    # Config keys that were replaced: the old key is an error naming the new one.
    RENAMED_KEYS: ClassVar[dict[str, str]] = {
        "gate_z": "gate_probability, the chi-square tests' probability (gate_z 3.09 was 0.999)",
        "max_position_sd_m": "the covariance sent with every pose (nothing consistent is withheld for being "
                             "uncertain); remove the key",
    }

    def __post_init__(self) -> None:
        def number(value) -> bool:
            return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

        if not (number(self.gate_probability) and 0.0 < self.gate_probability <= 1.0):
            raise ValueError(f"pose parameter gate_probability must be in (0, 1], got {self.gate_probability!r}")
        for name in ("corner_sigma_px", "attitude_sd_deg", "max_rms_px", "hypothesis_gate_px", "ambiguity_chi2",
                     "distinct_rotation_deg", "distinct_position_m"):
            value = getattr(self, name)
            if not (number(value) and value > 0):
                raise ValueError(f"pose parameter {name} must be a positive number, got {value!r}")
        for name in ("model_sigma_px", "map_sd_m", "map_sd_deg", "prior_max_age_s"):  # prior_max_age_s 0: no prior
            value = getattr(self, name)
            if not (number(value) and value >= 0):
                raise ValueError(f"pose parameter {name} must be a number >= 0, got {value!r}")
        if not (number(self.max_tilt_deg) and 0 < self.max_tilt_deg <= 90):
            raise ValueError(f"pose parameter max_tilt_deg must be in (0, 90], got {self.max_tilt_deg!r}")
        if not isinstance(self.accept_ambiguous_without_prior, bool):
            raise ValueError("pose parameter accept_ambiguous_without_prior must be true or false, got "
                             f"{self.accept_ambiguous_without_prior!r}")
        if self.max_markers is not None and not (isinstance(self.max_markers, int) and
                                                 not isinstance(self.max_markers, bool) and self.max_markers >= 1):
            raise ValueError(f"pose parameter max_markers must be an integer >= 1 or null (all), got "
                             f"{self.max_markers!r}")


@dataclass(frozen=True)
class MarkerObservation:
    """One mapped marker seen in the frame.

    points_map: (K, 3) map-frame points (4 corners TL, TR, BR, BL, then circle centres).
    points_px: (K, 2) their image positions.
    sigma_px: standard deviation of each point's x and y.
    corner_cov_px2: (8, 8) joint covariance of the 4 corners (x, y each,
        TL first), the detection's ``corner_cov_px2``, or None (then
        ``sigma_px`` for them too).
    """

    marker: MapMarker
    detection: Detection
    points_map: np.ndarray
    points_px: np.ndarray
    sigma_px: float
    corner_cov_px2: np.ndarray | None = None

    @property
    def side_px(self) -> float:
        """Mean side length of the marker's inner square in the image."""
        corners = self.detection.corners_px
        sides = corners - corners[[3, 0, 1, 2]]
        return float(np.sqrt((sides * sides).sum(axis=1)).mean())


@dataclass(frozen=True, eq=False)
class _Points:
    """The points of a frame's observations, stacked once.

    map: (K, 3); px: (K, 2); marker: (K,) index of each point's observation;
    starts, counts: (M,) each observation's first point and number of
    points; marker_ids: (M,) their map ids; sigma_px: (M,) each
    observation's point noise (the detection's and the model's); centres:
    (M, 3) the markers' centres in the map; corner_cov_px2: per observation,
    its corners' (8, 8) covariance with the model's noise added, or None;
    map_var: (M, 6) the variances of each marker's mapped pose, [position m^2 (3),
    orientation rad^2 (3)] (``PoseSolver._map_variances``); surveyed: (M,) bool, the marker's map entry
    states its own position sd above 0 (``companion survey`` writes one for every marker it placed):
    such markers err together (see ``common_shift_var``).
    """

    map: np.ndarray
    px: np.ndarray
    marker: np.ndarray
    starts: np.ndarray
    counts: np.ndarray
    marker_ids: np.ndarray
    sigma_px: np.ndarray
    centres: np.ndarray
    corner_cov_px2: tuple[np.ndarray | None, ...] = ()
    map_var: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    surveyed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    @classmethod
    def of(cls, observations: list[MarkerObservation], params: PoseParams,
           map_var: dict[int, np.ndarray]) -> _Points:
        counts = np.array([len(o.points_map) for o in observations])
        # sigma^2 = sigma_detection^2 + sigma_model^2
        sigma_px = np.sqrt(np.array([o.sigma_px for o in observations]) ** 2 + params.model_sigma_px ** 2)
        # Sigma_corners = Sigma_detection + sigma_model^2 I
        model_px2 = params.model_sigma_px ** 2 * np.eye(8)
        corner_cov_px2 = tuple(None if o.corner_cov_px2 is None else o.corner_cov_px2 + model_px2
                               for o in observations)
        return cls(np.vstack([o.points_map for o in observations]), np.vstack([o.points_px for o in observations]),
                   np.repeat(np.arange(len(observations)), counts), np.cumsum(counts) - counts, counts,
                   np.array([o.marker.id for o in observations]), sigma_px,
                   np.array([o.marker.T_map_marker[:3, 3] for o in observations]), corner_cov_px2,
                   np.array([map_var[o.marker.id] for o in observations]),
                   np.array([bool(o.marker.sd_position_m) for o in observations]))

    def of_markers(self, members: np.ndarray) -> _Points:
        """The points of the observations ``members`` (indices, ascending)."""
        if len(members) == len(self.counts):
            return self
        keep = np.isin(self.marker, members)
        counts = self.counts[members]
        return _Points(self.map[keep], self.px[keep], np.repeat(np.arange(len(members)), counts),
                       np.cumsum(counts) - counts, counts, self.marker_ids[members], self.sigma_px[members],
                       self.centres[members], tuple(self.corner_cov_px2[m] for m in members), self.map_var[members],
                       self.surveyed[members])

    @functools.cached_property
    def common_shift_var(self) -> float:
        """The variance (m^2, each axis) of the shift the surveyed markers among these share: the smallest of
        their position variances (0 without any, and 0 with a marker known exactly among these: an anchor,
        against which the shift is measured). A survey places markers through each other, so those seen
        together err alike (bench_survey's aisle: six surveyed markers all 2.5-5.3 mm off the same way);
        their errors' common part moves them and the camera together."""
        if not self.surveyed.any() or (self.map_var[:, :3] == 0.0).all(axis=1).any():
            return 0.0
        return float(self.map_var[self.surveyed, :3].min())

    def without_common_shift(self) -> _Points:
        """These points with the surveyed markers' position variances less ``common_shift_var``."""
        common = self.common_shift_var
        if common == 0.0:
            return self
        map_var = self.map_var.copy()
        map_var[self.surveyed, :3] -= common
        return replace(self, map_var=map_var)

    @property
    def correlated(self) -> bool:
        """Some observation's corners have a joint covariance (not sigma^2 I)."""
        return any(cov is not None for cov in self.corner_cov_px2)

    def noise_px2(self, m: int) -> np.ndarray:
        """(2n, 2n) covariance of observation m's own point noise (x, y of each point in turn)."""
        noise = self.sigma_px[m] ** 2 * np.eye(2 * self.counts[m])
        if self.corner_cov_px2[m] is not None:
            noise[:8, :8] = self.corner_cov_px2[m]
        return noise


@dataclass(frozen=True, eq=False)
class _Weights:
    """How a frame's point errors are weighed: per marker, ``Sigma^-1/2`` of its (2n, 2n) error covariance.

    ``Sigma = N + G S G^T``: the points' own noise N (sigma^2 I, or with the
    corners' joint covariance from the detector's alignment in its first
    8 x 8 block), and the map's error of the marker's pose,
    S = diag(sd_m^2 (3), sd_rad^2 (3)) (the marker's own sd in the map, else
    map_sd_m and map_sd_deg), seen through
    G = d(pixels)/d(the marker's pose in the map), which moves all its
    points together. ``inverse_roots`` is None without map error and
    without joint corner covariances (then ``Sigma^-1/2 = I / sigma``).
    """

    points: _Points
    inverse_roots: list[np.ndarray] | None
    map_px2: np.ndarray | None = None  # (M,) per marker: trace(G S G^T), its map error in squared pixels
    map_roots: list[np.ndarray] | None = None  # per marker: (2n, 6) Sigma^-1/2 G S^1/2, its map error whitened

    def whiten(self, values: np.ndarray) -> np.ndarray:
        """(K, 2, ...) point errors (or their derivatives) -> whitened, the same shape."""
        points = self.points
        if self.inverse_roots is None:
            return values / np.repeat(points.sigma_px, points.counts).reshape((-1,) + (1,) * (values.ndim - 1))
        out = np.empty_like(values)
        for start, count, root in zip(points.starts, points.counts, self.inverse_roots):
            block = values[start:start + count]
            out[start:start + count] = (root @ block.reshape(2 * count, -1)).reshape(block.shape)
        return out

    def marker_chi2(self, errors_px: np.ndarray) -> np.ndarray:
        """(M,) each marker's chi-square from its (K, 2) point errors."""
        return np.add.reduceat(np.sum(self.whiten(errors_px) ** 2, axis=1), self.points.starts)

    def of_markers(self, members: np.ndarray) -> _Weights:
        """The weights of the observations ``members`` (indices, ascending)."""
        roots = None if self.inverse_roots is None else [self.inverse_roots[m] for m in members]
        return _Weights(self.points.of_markers(members), roots, None if self.map_px2 is None else self.map_px2[members],
                        None if self.map_roots is None else [self.map_roots[m] for m in members])


@dataclass(frozen=True)
class Fit:
    """A camera pose fitted to a set of markers.

    T_camera_map: (4, 4) map -> camera.
    inliers: indices (into the observations) of the markers that agree.
    marker_chi2: (M,) chi-square (squared point errors over their variances)
        of every observed marker (inf if a point falls behind the camera).
    chi2: over the inliers' points; attitude_chi2: the attitude prior's
        (0 without an attitude); sse_px2, n_points: squared point errors in
        pixels^2 and point count over the inliers; map_px2: the squared pixel
        errors the inliers' stated map error explains (its expectation).
    """

    T_camera_map: np.ndarray
    inliers: tuple[int, ...]
    marker_chi2: np.ndarray
    chi2: float
    attitude_chi2: float
    sse_px2: float
    n_points: int
    with_attitude: bool = False
    map_px2: float = 0.0

    @property
    def unexplained_rms_px(self) -> float:
        """RMS point error over the inliers beyond what the map's stated error explains (their expected
        squared pixel errors from it, ``map_px2``, taken out)."""
        return math.sqrt(max(self.sse_px2 - self.map_px2, 0.0) / self.n_points)

    @property
    def rms_px(self) -> float:
        """RMS point reprojection error over the inliers."""
        return math.sqrt(self.sse_px2 / self.n_points)

    @property
    def dof(self) -> int:
        """Residual degrees of freedom: 2 per point, 2 for the attitude, minus 6 pose parameters."""
        return max(2 * self.n_points + (ATTITUDE_DOF if self.with_attitude else 0) - 6, 1)

    @property
    def cost(self) -> float:
        """Total chi-square: points and attitude."""
        return self.chi2 + self.attitude_chi2


@dataclass(frozen=True)
class MarkerOffset:
    """How far a marker the consistency gate left out sits from its map entry: its own corners (the IPPE
    branch nearest the accepted pose) seen from the pose the other markers agree on.

    position_m: its centre's distance from the mapped one; angle_deg: its turn against the mapped orientation.
    """

    marker_id: int
    position_m: float
    angle_deg: float


@dataclass(frozen=True)
class PoseSolution:
    """Everything the solver decided for one frame.

    measurement: the accepted pose, or None.
    status: "ok", or why there is no pose: "no mapped markers",
        "reprojection", "inconsistent markers", "implausible attitude",
        "ambiguous".
    ambiguous: another pose fitted nearly as well (resolved by the prior if
        ``used_prior``).
    used_attitude: the flight controller's roll and pitch were part of the fit.
    marker_ids: ids of the markers used (without a pose: of the fit it came
        nearest with; none with "inconsistent markers"); rejected_ids: mapped
        markers seen but left out as inconsistent, with "inconsistent markers"
        every mapped marker seen;
        rejected_offsets: how far off its map entry each of them was seen,
        in the same order (with "inconsistent markers": seen from the best fit
        that left it out, NaN where none did); unmapped_ids:
        detections not in the map (or seen twice, or with corners not finite).
    """

    measurement: PoseMeasurement | None
    status: str
    ambiguous: bool = False
    used_prior: bool = False
    used_attitude: bool = False
    marker_ids: tuple[int, ...] = ()
    rejected_ids: tuple[int, ...] = ()
    rejected_offsets: tuple[MarkerOffset, ...] = ()
    unmapped_ids: tuple[int, ...] = ()
    fits: tuple[Fit, ...] = field(default=(), repr=False)


@dataclass(frozen=True)
class _Choice:
    status: str
    fit: Fit | None = None
    ambiguous: bool = False
    used_prior: bool = False


@dataclass(frozen=True)
class _Gravity:
    """The attitude prior of one frame on the map frame: measured (roll, pitch) and 1 / sd."""

    roll_rad: float
    pitch_rad: float
    inverse_sd: float
    R_ned_map: np.ndarray

    def residual(self, R_map_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((2,) whitened roll and pitch errors, (2, 3) their derivative by theta on map axes, R' = exp(theta) R)."""
        R_ned_body = self.R_ned_map @ R_map_body
        roll, pitch = frames.roll_pitch_321(R_ned_body)
        error = np.array([math.remainder(roll - self.roll_rad, 2 * math.pi), pitch - self.pitch_rad])
        # theta on NED axes = R_ned_map theta_map
        jacobian = frames.roll_pitch_321_jacobian(R_ned_body) @ self.R_ned_map
        return error * self.inverse_sd, jacobian * self.inverse_sd


class PoseSolver:
    """Turns one frame's detections into the vehicle pose in the map and NED.

    Holds two pieces of state: the last accepted pose, used as the prior for
    the next frames within ``params.prior_max_age_s``; and the markers found
    off their map entry (``loosen``).
    """

    def __init__(self, facility_map: FacilityMap, camera: CameraModel, params: PoseParams | None = None):
        self.facility_map = facility_map
        self.camera = camera
        self.params = params or PoseParams()
        self._layout = None
        self._marker_points: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._last: tuple[int, np.ndarray] | None = None  # (t_ns, T_map_body)
        self._T_camera_body = camera.T_camera_body
        self._R_ned_map = facility_map.T_ned_map[:3, :3]
        self._map_var = self._map_variances()
        self._loose: dict[int, np.ndarray] = {}  # marker id -> its variances once found off the map (``loosen``)

    def solve(self, detections: list[Detection], t_ns: int, prior_T_map_body: np.ndarray | None = None,
              attitude: AttitudeSample | None = None) -> PoseMeasurement | None:
        """The pose from this frame's detections, or None (see ``solve_detailed``)."""
        return self.solve_detailed(detections, t_ns, prior_T_map_body, attitude).measurement

    def solve_detailed(self, detections: list[Detection], t_ns: int, prior_T_map_body: np.ndarray | None = None,
                       attitude: AttitudeSample | None = None) -> PoseSolution:
        """The pose and the reasons behind it.

        prior_T_map_body: (4, 4) a recent body pose in the map, a start for the
        fit and the choice between ambiguous fits; defaults to the last
        accepted pose if it is at most ``prior_max_age_s`` older than ``t_ns``.
        attitude: the flight controller's roll and pitch at ``t_ns``, or None.
        """
        observations, unmapped = self.observations(detections)
        if not observations:
            return PoseSolution(None, "no mapped markers", unmapped_ids=unmapped)
        # markers found off their map entry (``loosen``) are posed on only when no other is seen, and then
        # with their loosened variances: beside others they would add nothing but their error
        trusted = [o for o in observations if o.marker.id not in self._loose]
        solved = trusted or observations
        points = _Points.of(solved, self.params, self._map_var if trusted else {**self._map_var, **self._loose})
        prior = self._prior(t_ns, prior_T_map_body)
        gravity = None if attitude is None else self._gravity(attitude)
        fits, choice = self._solve(points, len(solved), prior, gravity)
        if gravity is not None and choice.status != "ok":
            fits, choice = self._solve(points, len(solved), prior, None)
        used = choice.fit.inliers if choice.fit is not None else ()
        common = dict(ambiguous=choice.ambiguous, marker_ids=tuple(solved[i].marker.id for i in used),
                      unmapped_ids=unmapped, fits=tuple(fits))
        if choice.status == "inconsistent markers":  # every marker seen was left out, none outvoted
            return PoseSolution(None, choice.status, rejected_ids=tuple(o.marker.id for o in observations),
                                rejected_offsets=tuple(self._offset_from_the_others(o, solved, fits)
                                                       for o in observations), **{**common, "marker_ids": ()})
        if choice.status != "ok":
            return PoseSolution(None, choice.status, **common)
        with_attitude = choice.fit.with_attitude
        measurement = self._measurement(choice.fit, points.of_markers(np.array(used)), solved, t_ns,
                                        gravity if with_attitude else None,
                                        unambiguous=not (choice.ambiguous or choice.used_prior))
        self._last = (t_ns, measurement.T_map_body)
        rejected = [o for o in observations if o.marker.id not in common["marker_ids"]]
        return PoseSolution(measurement, "ok", used_prior=choice.used_prior, used_attitude=with_attitude,
                            rejected_ids=tuple(o.marker.id for o in rejected),
                            rejected_offsets=tuple(self._offset(o, choice.fit.T_camera_map) for o in rejected),
                            **common)

    def loosen(self, marker_id: int, sd_m: float, sd_deg: float) -> None:
        """Marker ``marker_id`` was found about ``sd_m`` and ``sd_deg`` off its map entry (the daemon's
        ``MapWatch``): from now on it is left out beside other markers, and posed on alone with its map
        variances raised to these (never lowered), so that its pose comes with a covariance that covers the
        error, not a few millimetres'."""
        loosened = _pose_variances(sd_m, sd_deg)
        self._loose[marker_id] = np.maximum(self._loose.get(marker_id, self._map_var[marker_id]), loosened)

    def loosen_all(self, sd_m: float, sd_deg: float) -> None:
        """The map as a whole was found less accurate than stated (the daemon's ``MapWatch``): every marker's map
        variances are raised to these (never lowered), so that markers may disagree by that much and the
        covariance says so."""
        loosened = _pose_variances(sd_m, sd_deg)
        self._map_var = {marker_id: np.maximum(v, loosened) for marker_id, v in self._map_var.items()}
        self._loose = {marker_id: np.maximum(v, loosened) for marker_id, v in self._loose.items()}

    def _offset_from_the_others(self, observation: MarkerObservation, solved: list[MarkerObservation],
                                fits: list[Fit]) -> MarkerOffset:
        """A marker's offset seen from the best plausible fit that leaves it out (NaN where none does)."""
        index = next((i for i, o in enumerate(solved) if o is observation), None)
        best = _best([f for f in fits if index not in f.inliers and self._plausible(f)])
        if best is None:
            return MarkerOffset(observation.marker.id, math.nan, math.nan)
        return self._offset(observation, best.T_camera_map)

    def _offset(self, observation: MarkerObservation, T_camera_map: np.ndarray) -> MarkerOffset:
        """Where an observed marker's own corners put it, seen from the accepted ``T_camera_map``, against its
        map entry (NaN where its corners give no pose: degenerate)."""
        marker = observation.marker
        poses, _ = self._ippe_square(marker, observation.points_px[:4])
        if not poses:
            return MarkerOffset(marker.id, math.nan, math.nan)
        # of its two IPPE poses T_camera_marker, the one turned least from where the map and the pose put it
        mapped = T_camera_map @ marker.T_map_marker
        T_camera_marker = min(poses, key=lambda T: frames.rotation_angle_rad(T[:3, :3], mapped[:3, :3]))
        # T_map_marker as seen = T_map_camera T_camera_marker
        T_seen = frames.invert_transform(T_camera_map) @ T_camera_marker
        return MarkerOffset(marker.id, float(np.linalg.norm(T_seen[:3, 3] - marker.T_map_marker[:3, 3])),
                            math.degrees(frames.rotation_angle_rad(T_seen[:3, :3], marker.T_map_marker[:3, :3])))

    def _solve(self, points: _Points, observed: int, prior: np.ndarray | None,
               gravity: _Gravity | None) -> tuple[list[Fit], _Choice]:
        """(fits, choice): from the prior alone when it explains every marker, else from every hypothesis."""
        if prior is not None:
            fit = self._grow_and_refine(self._T_camera_map(prior), points, gravity)
            if fit is not None and len(fit.inliers) == observed:
                choice = self._choose([fit], observed, None)
                if choice.status == "ok":
                    return [fit], _Choice("ok", fit, used_prior=True)
        fits = self._hypothesis_fits(points, gravity)
        return fits, self._choose(fits, observed, prior)

    def _choose(self, fits: list[Fit], observed: int, prior: np.ndarray | None) -> _Choice:
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
            return _Choice("ok", _nearest_to_prior([best] + rivals, prior, self._T_camera_body), True, True)
        if self.params.accept_ambiguous_without_prior:
            return _Choice("ok", best, True)
        return _Choice("ambiguous", best, True)

    # ------------------------------------------------------ correspondences

    def observations(self, detections: list[Detection]) -> tuple[list[MarkerObservation], tuple[int, ...]]:
        """Mapped markers seen once each (largest first), and the ids left out.

        A marker detected twice in one frame cannot be both places: both
        detections are left out; so is one whose corners are not all finite
        (no stage of the detector makes one: a guard, since OpenCV's PnP
        raises on them).
        """
        counts: dict[int, int] = {}
        for detection in detections:
            counts[detection.id] = counts.get(detection.id, 0) + 1
        observations, left_out = [], []
        for detection in detections:
            marker = self.facility_map.markers.get(detection.id)
            if marker is None or counts[detection.id] > 1 or not np.isfinite(detection.corners_px).all():
                left_out.append(detection.id)
                continue
            observations.append(self._observation(marker, detection))
        observations.sort(key=lambda o: -o.side_px)
        if self.params.max_markers is not None:
            observations = observations[: self.params.max_markers]
        return observations, tuple(sorted(set(left_out)))

    def _observation(self, marker: MapMarker, detection: Detection) -> MarkerObservation:
        corners_map, circles_map = self._points_of(marker)
        points_map, points_px = corners_map, np.asarray(detection.corners_px, dtype=float).reshape(4, 2)
        if len(detection.circle_ids):
            ids = np.asarray(detection.circle_ids, dtype=int).reshape(-1)
            circles_px = np.asarray(detection.circles_px, dtype=float).reshape(-1, 2)
            # a detector bug must not stop the pipeline
            valid = (ids >= 0) & (ids < len(circles_map)) & np.isfinite(circles_px).all(axis=1)
            points_map = np.vstack([corners_map, circles_map[ids[valid]]])
            points_px = np.vstack([points_px, circles_px[valid]])
        sigma_px = detection.corner_sigma_px
        if sigma_px is None or not (math.isfinite(sigma_px) and sigma_px > 0):
            sigma_px = self.params.corner_sigma_px
        return MarkerObservation(marker, detection, points_map, points_px, float(sigma_px),
                                 _corner_cov_px2(detection.corner_cov_px2))

    def _map_variances(self) -> dict[int, np.ndarray]:
        """Marker id -> (6,) variances of its mapped pose, [m^2 (3), rad^2 (3)]: the map's ``sd`` of the
        marker where it states one, else ``map_sd_m`` / ``map_sd_deg`` (built once per map)."""
        variances = {}
        for marker in self.facility_map.markers.values():
            sd_m = self.params.map_sd_m if marker.sd_position_m is None else marker.sd_position_m
            sd_deg = self.params.map_sd_deg if marker.sd_angle_deg is None else marker.sd_angle_deg
            variances[marker.id] = _pose_variances(sd_m, sd_deg)
        return variances

    def _points_of(self, marker: MapMarker) -> tuple[np.ndarray, np.ndarray]:
        """((4, 3) inner corners, (12, 3) corner-circle centres) of a marker in the map frame, computed once."""
        cached = self._marker_points.get(marker.id)
        if cached is None:
            layout = self._marker_layout()
            circles_uv = np.asarray(layout.circles, dtype=float)[:, :2]
            circles_marker = frames.grid_to_marker_m(circles_uv, layout.inner_origin, layout.inner_cells, marker.size_m)
            cached = (frames.transform_points(marker.T_map_marker, marker.corners_marker()),
                      frames.transform_points(marker.T_map_marker, circles_marker))
            self._marker_points[marker.id] = cached
        return cached

    def _marker_layout(self):
        if self._layout is None:
            from companion.markers.layout import MarkerLayout

            self._layout = MarkerLayout(parity=self.facility_map.parity, dictionary=self.facility_map.dictionary)
        return self._layout

    def _gravity(self, attitude: AttitudeSample) -> _Gravity:
        return _Gravity(attitude.roll_rad, attitude.pitch_rad, 1.0 / math.radians(self.params.attitude_sd_deg),
                        self._R_ned_map)

    # ----------------------------------------------------------- hypotheses

    def _hypothesis_fits(self, points: _Points, gravity: _Gravity | None) -> list[Fit]:
        """Refined fits from every marker's IPPE poses and from all markers at once, duplicates removed."""
        starts = [(T, m) for m in range(len(points.counts)) for T in self._ippe_poses(points, m, gravity)]
        if len(points.counts) > 1:
            starts.append((self._all_markers_pose(points), None))
        fits: list[Fit] = []
        for T_camera_map, seed in starts:
            fit = self._grow_and_refine(T_camera_map, points, gravity, seed)
            if fit is not None and not self._same_pose_as_any(fit, fits):
                fits.append(fit)
        return fits

    def _all_markers_pose(self, points: _Points) -> np.ndarray:
        """T_camera_map from SQPnP (globally optimal) over all points of all markers.

        Many markers small in the image, each with a poor pose of its own, can
        still give a good joint pose.
        """
        _, rvec, tvec = cv2.solvePnP(points.map, points.px, self.camera.K, self.camera.dist, flags=cv2.SOLVEPNP_SQPNP)
        return _transform(cv2.Rodrigues(rvec)[0], tvec)

    def _ippe_poses(self, points: _Points, m: int, gravity: _Gravity | None) -> list[np.ndarray]:
        """IPPE_SQUARE poses (T_camera_map) of marker ``m`` from its corners.

        The second solution is kept only if it is not clearly worse on this
        marker's corners and, with an attitude, on the attitude too (the same
        test as for ambiguity): a clearly wrong branch cannot become the best
        fit and costs a refinement.
        """
        start = points.starts[m]
        corners_px = points.px[start:start + 4]
        marker = self.facility_map.markers[int(points.marker_ids[m])]
        camera_marker, rms_px = self._ippe_square(marker, corners_px)
        if not camera_marker:  # degenerate corners (collapsed, collinear): no pose of its own
            return []
        # T_camera_map = T_camera_marker T_marker_map
        T_marker_map = frames.invert_transform(marker.T_map_marker)
        poses = [T @ T_marker_map for T in camera_marker]
        # OpenCV's RMS is over the 8 coordinates: sse = 8 rms^2, chi-square = sse / sigma^2
        weight = 1.0 / points.sigma_px[m] ** 2
        costs = [8.0 * float(rms) ** 2 * weight for rms in rms_px]
        if gravity is not None:
            costs = [c + float(np.sum(gravity.residual(self._R_map_body(T))[0] ** 2)) for c, T in zip(costs, poses)]
        limit = min(costs) + self.params.ambiguity_chi2
        return [T for T, c in zip(poses, costs) if c <= limit]

    def _ippe_square(self, marker: MapMarker, corners_px: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """IPPE_SQUARE on a marker's (4, 2) inner corners: its T_camera_marker candidates (none for degenerate
        corners) and each one's RMS over the 8 coordinates (px)."""
        count, rvecs, tvecs, rms_px = cv2.solvePnPGeneric(marker.corners_marker(), corners_px.reshape(4, 1, 2),
                                                           self.camera.K, self.camera.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        return ([_transform(cv2.Rodrigues(rvecs[i])[0], tvecs[i]) for i in range(count)],
                np.asarray(rms_px).reshape(-1)[:count])

    def _grow_and_refine(self, T_camera_map: np.ndarray, points: _Points, gravity: _Gravity | None,
                         seed: int | None = None) -> Fit | None:
        """Refine a hypothesis on the markers it explains; None if it explains none.

        seed: the marker the hypothesis came from (its IPPE pose), if one did: when the markers gathered
        pull each other so far that none agrees with their joint fit (two that disagree: too few to leave
        one out), the hypothesis is refined on the seed alone, so that such a frame is said to have
        inconsistent markers, not a bad reprojection."""
        errors = self.camera.project_from(T_camera_map, points.map) - points.px
        sse_m = np.add.reduceat(np.sum(errors ** 2, axis=1), points.starts)
        members = np.flatnonzero(sse_m < points.counts * self.params.hypothesis_gate_px ** 2)
        fit = self._refined(T_camera_map, points, gravity, members)
        if fit is None and seed is not None and not np.array_equal(members, [seed]):
            fit = self._refined(T_camera_map, points, gravity, np.array([seed]))
        return fit

    def _refined(self, T_camera_map: np.ndarray, points: _Points, gravity: _Gravity | None,
                 members: np.ndarray) -> Fit | None:
        """The fit refined on ``members`` (indices), then on the markers that agree with it, up to three
        times; None if none agrees."""
        # the weights at the start: the map error's share changes little while the pose is refined
        weights, solving = self._weights_tested_and_solved(T_camera_map, points)
        for _ in range(3):
            if len(members) == 0:
                return None
            refined = self._refine(T_camera_map, solving.of_markers(members), gravity)
            if refined is None:
                return None
            T_camera_map = refined
            chi2_m, sse_m = self._marker_errors(T_camera_map, points, weights)
            agreeing = np.flatnonzero([self._within_noise(c, 2 * n) for c, n in zip(chi2_m, points.counts)])
            if np.array_equal(agreeing, members):
                break
            members = agreeing if np.isin(members, agreeing).all() or len(members) < 3 else \
                self._consensus(T_camera_map, weights, solving, members, gravity)
        if len(members) == 0:
            return None
        attitude_chi2 = 0.0
        if gravity is not None:
            attitude_chi2 = float(np.sum(gravity.residual(self._R_map_body(T_camera_map))[0] ** 2))
        return Fit(T_camera_map, tuple(int(i) for i in members), chi2_m, float(chi2_m[members].sum()), attitude_chi2,
                   float(sse_m[members].sum()), int(points.counts[members].sum()), gravity is not None,
                   0.0 if weights.map_px2 is None else float(weights.map_px2[members].sum()))

    def _consensus(self, T_camera_map: np.ndarray, weights: _Weights, solving: _Weights, members: np.ndarray,
                   gravity: _Gravity | None) -> np.ndarray:
        """The markers of ``members`` (indices, ascending) that agree on one pose, when a fit to all of them
        leaves some of them out: leave-one-out by chi-square, a consensus over markers as RANSAC's.

        Each marker in turn is left out and the pose fitted to the others; the one whose absence fits the
        others best (lowest chi-square per degree of freedom) goes, until the others all pass the
        per-marker test. The moved marker's pull on a joint fit can make every marker fail it; fitted
        without it, the others agree. At most a minority goes; fewer than three markers cannot outvote one.
        """
        keep_at_least = len(members) // 2 + 1
        while len(members) > max(keep_at_least, 2):
            best = None
            for left_out in range(len(members)):
                rest = np.delete(members, left_out)
                T_rest = self._refine(T_camera_map, solving.of_markers(rest), gravity)
                if T_rest is None:
                    continue
                chi2_rest = self._marker_errors(T_rest, weights.points, weights)[0][rest]
                dof = max(2 * int(weights.points.counts[rest].sum()) - 6, 1)
                if best is None or chi2_rest.sum() / dof < best[0]:
                    best = (chi2_rest.sum() / dof, rest, chi2_rest)
            if best is None:
                break
            _, members, chi2_rest = best
            if all(self._within_noise(c, 2 * n) for c, n in zip(chi2_rest, weights.points.counts[members])):
                break
        return members

    def _within_noise(self, chi2_value: float, dof: int) -> bool:
        """Chi-square test: squared errors explained by the points' noise."""
        return chi2_value < chi2_quantile(self.params.gate_probability, dof)

    def _refine(self, T_camera_map: np.ndarray, weights: _Weights, gravity: _Gravity | None) -> np.ndarray | None:
        """Gauss-Newton (Levenberg-Marquardt damped) on T_camera_map over these points (weighed) and the attitude.

        Perturbation: R' = exp(w) R, t' = t + dt (camera axes), so a map point
        seen at X_c = R X + t moves by dX_c = w x (R X) + dt, and the camera
        gives d(pixels)/dX_c. With the attitude, R_map_body = R^T R_cb moves by
        theta_map = -R^T w. None if a point falls behind the camera.
        """
        points = weights.points
        R, t = T_camera_map[:3, :3], T_camera_map[:3, 3]
        damping, previous = 0.0, None
        for _ in range(MAX_ITERATIONS):
            rotated = points.map @ R.T
            px, dpx_dX = self.camera.project_with_jacobian(rotated + t)
            # d(pixels)/dw: row a of d(pixels)/dX_c gives a . (w x RX) = w . (RX x a)
            d_rotation = _cross(rotated[:, None, :], dpx_dX)
            residual = weights.whiten(px - points.px).reshape(-1)
            J = weights.whiten(np.concatenate([d_rotation, dpx_dX], axis=2)).reshape(-1, 6)
            if gravity is not None:
                error, d_theta = gravity.residual(R.T @ self._T_camera_body[:3, :3])
                residual = np.concatenate([residual, error])
                J = np.vstack([J, np.hstack([-d_theta @ R.T, np.zeros((2, 3))])])
            cost = float(residual @ residual)
            if not math.isfinite(cost):
                return None if previous is None else _transform(*previous[:2])
            if previous is not None and cost > previous[2]:
                # the step made it worse: back to the previous pose, a more cautious step
                R, t, cost, J, residual = previous
                damping = max(10.0 * damping, 1e-4)
            else:
                damping = damping / 10.0 if damping > 1e-8 else 0.0
            previous = (R, t, cost, J, residual)
            H = J.T @ J
            if damping:
                H[np.diag_indices(6)] *= 1.0 + damping
            try:
                step = -np.linalg.solve(H, J.T @ residual)
            except np.linalg.LinAlgError:
                break
            R = cv2.Rodrigues(step[:3])[0] @ R
            t = t + step[3:]
            if np.abs(step).max() < STEP_TOLERANCE:
                break
        return _transform(R, t)

    def _marker_errors(self, T_camera_map: np.ndarray, points: _Points,
                       weights: _Weights) -> tuple[np.ndarray, np.ndarray]:
        """((M,) chi-square, (M,) squared pixel errors) of each marker under the pose (inf if behind the camera)."""
        errors = self.camera.project_from(T_camera_map, points.map) - points.px
        sse = np.add.reduceat(np.sum(errors ** 2, axis=1), points.starts)
        chi2_m = weights.marker_chi2(errors)
        return np.where(np.isfinite(chi2_m), chi2_m, np.inf), np.where(np.isfinite(sse), sse, np.inf)

    def _weights_tested_and_solved(self, T_camera_map: np.ndarray, points: _Points) -> tuple[_Weights, _Weights]:
        """The weights the chi-square tests use (every marker's whole map error) and those the pose is
        solved with (the surveyed markers' common shift left out, ``_Points.common_shift_var``): weighed
        by it, a marker surveyed a little less well than another counts for much less, and the pose leans
        on the best one alone (on bench_survey's aisle the true map, told the survey's sd, flew at
        2.02-2.81 mm against its 1.18 mm told it is exact). The covariance counts the shift
        (``_covariance_map``)."""
        weights = self._weights(T_camera_map, points)
        if points.common_shift_var == 0.0:
            return weights, weights
        return weights, self._weights(T_camera_map, points.without_common_shift())

    def _weights(self, T_camera_map: np.ndarray, points: _Points, with_map_roots: bool = False) -> _Weights:
        """The points' weights at a camera pose (see ``_Weights``); ``map_roots`` only ``with_map_roots`` (the
        covariance's, once per pose: not every hypothesis's)."""
        map_error = bool(points.map_var.any())
        if not map_error and not points.correlated:
            return _Weights(points, None)
        if map_error:
            R, t = T_camera_map[:3, :3], T_camera_map[:3, 3]
            # d(pixels)/dX_map = d(pixels)/dX_c R: (K, 2, 3)
            D = self.camera.projection_jacobian(points.map @ R.T + t) @ R
            # the marker moved by dt and turned by dtheta about its centre c: dX = dt + dtheta x (X - c);
            # row a of D gives a . (dtheta x r) = dtheta . (r x a)
            r = points.map - np.repeat(points.centres, points.counts, axis=0)
            G = np.concatenate([D, _cross(r[:, None, :], D)], axis=2)
        roots: list[np.ndarray | None] = [None] * len(points.counts)
        map_px2 = np.zeros(len(points.counts)) if map_error else None
        map_roots: list[np.ndarray | None] | None = None
        if map_error and with_map_roots:
            map_roots = [None] * len(points.counts)
        for count in np.unique(points.counts):  # one batch per point count (4: every square-path marker)
            markers = np.flatnonzero(points.counts == count)
            noise = np.stack([points.noise_px2(m) for m in markers])
            sigma, floor = noise, 0.0
            if map_error:
                g = np.stack([G[points.starts[m]:points.starts[m] + count].reshape(2 * count, 6) for m in markers])
                # S = diag(each marker's variances of its mapped pose): (n, 1, 6) against g's (n, 2 count, 6)
                S = points.map_var[markers, None, :]
                sigma = noise + (g * S) @ g.transpose(0, 2, 1)
                map_px2[markers] = np.sum(g ** 2 * S, axis=(1, 2))  # trace(G S G^T), S diagonal
                # the smallest variance of the points' own noise: no direction of Sigma is surer than that
                floor = np.linalg.eigvalsh(noise)[:, :1] if points.correlated else points.sigma_px[markers, None] ** 2
            # Sigma = N + G S G^T = V diag(l) V^T; Sigma^-1/2 = V diag(l^-1/2) V^T (l >= the floor: a
            # point behind the camera of a wild hypothesis gives a huge G, and Cholesky would fail)
            values, vectors = np.linalg.eigh(sigma)
            inverse_roots = (vectors / np.sqrt(np.maximum(values, floor))[:, None, :]) @ vectors.transpose(0, 2, 1)
            for m, root in zip(markers, inverse_roots):
                roots[m] = root
            if map_roots is not None:
                for m, map_root in zip(markers, inverse_roots @ (g * np.sqrt(S))):
                    map_roots[m] = map_root
        return _Weights(points, roots, map_px2, map_roots)

    # --------------------------------------------------------------- choice

    def _plausible(self, fit: Fit) -> bool:
        """Body roll and pitch within ``max_tilt_deg`` (in the map, z up)."""
        # The body's down axis (FRD z) against the map's down direction.
        cos_tilt = float(-self._R_map_body(fit.T_camera_map)[2, 2])
        return cos_tilt >= math.cos(math.radians(self.params.max_tilt_deg))

    def _check_consistency(self, best: Fit | None, observed: int) -> str:
        if best is None:
            return "reprojection"
        outliers = observed - len(best.inliers)
        if outliers and (len(best.inliers) < 2 or len(best.inliers) <= outliers):
            return "inconsistent markers"
        if best.unexplained_rms_px > self.params.max_rms_px or not self._within_noise(best.cost, best.dof):
            return "reprojection"
        return "ok"

    def _rivals(self, best: Fit, fits: list[Fit]) -> list[Fit]:
        """Distinct fits to the same markers whose chi-square is not clearly worse.

        Residuals larger than the points' noise widen the margin in proportion.
        """
        scale = max(1.0, best.cost / best.dof)
        limit = best.cost + self.params.ambiguity_chi2 * scale
        return [
            f for f in fits
            if f is not best and f.inliers == best.inliers and f.cost < limit and not self._same_pose_as_any(f, [best])
        ]

    def _same_pose_as_any(self, fit: Fit, others: list[Fit]) -> bool:
        """Whether one of the others is the same camera pose: closer than both distinct_rotation_deg and distinct_position_m."""
        if not others:
            return False
        R_others = np.stack([other.T_camera_map[:3, :3] for other in others])
        # the angle of R_a R_b^T from its trace: cos(angle) = (trace - 1) / 2
        cos_angle = (np.einsum("kij,ij->k", R_others, fit.T_camera_map[:3, :3]) - 1.0) / 2.0
        positions_m = np.linalg.norm(np.stack([_camera_position_m(other) for other in others]) - _camera_position_m(fit), axis=1)
        same = (cos_angle > math.cos(math.radians(self.params.distinct_rotation_deg))) & \
               (positions_m < self.params.distinct_position_m)
        return bool(same.any())

    def _prior(self, t_ns: int, prior_T_map_body: np.ndarray | None) -> np.ndarray | None:
        if prior_T_map_body is not None:
            return prior_T_map_body
        if self._last is not None and 0 <= t_ns - self._last[0] <= self.params.prior_max_age_s * NS_PER_S:
            return self._last[1]
        return None

    # ---------------------------------------------------------- measurement

    def _measurement(self, fit: Fit, points: _Points, observations: list[MarkerObservation], t_ns: int,
                     gravity: _Gravity | None, unambiguous: bool) -> PoseMeasurement:
        T_map_body = _body_pose(fit.T_camera_map, self._T_camera_body)
        covariance_map, map_share = self._covariance_map(T_map_body, points, gravity)
        R_ned_map = self.facility_map.T_ned_map[:3, :3]
        return PoseMeasurement(
            t_ns=t_ns,
            T_map_body=T_map_body,
            T_ned_body=self.facility_map.T_ned_map @ T_map_body,
            covariance_ned=frames.rotate_pose_covariance(covariance_map, R_ned_map),
            map_covariance_ned=frames.rotate_pose_covariance(map_share, R_ned_map),
            marker_ids=tuple(observations[i].marker.id for i in fit.inliers),
            reprojection_rms_px=fit.rms_px,
            unambiguous=unambiguous,
        )

    def _covariance_map(self, T_map_body: np.ndarray, points: _Points,
                        gravity: _Gravity | None) -> tuple[np.ndarray, np.ndarray]:
        """(6, 6) covariance of [body position (3), small rotation (3)], both on map axes, and (6, 6) the map
        error's share of it.

        C = (J^T W J + A^T A)^-1: J = d(pixels)/d(pose), W the points' inverse
        covariance (``_Weights``: their noise and the map's error, as the pose was solved: without the
        surveyed markers' common shift), A = d(whitened roll, pitch)/d(pose) when the attitude was used;
        plus that shift's own share: it moves the surveyed markers' points by G dX (G = d(pixels)/dX_map,
        on their points only) and the pose by K dX, K = C J^T W G, so C += s^2 K K^T (s^2: the shift's
        variance on each axis).

        The map's share: the pose is C J^T W times the point errors, of which the map's are G_m dm for each
        marker m (dm its mapped pose's error, covariance S_m): C (sum_m J_m^T W_m G_m S_m G_m^T W_m J_m) C,
        plus the shift's. It is the part of C that frames seeing the same markers share.
        """
        common = points.common_shift_var
        weights = self._weights(self._T_camera_map(T_map_body), points.without_common_shift(), with_map_roots=True)
        jacobian = self._pose_jacobian(T_map_body, points.map).reshape(-1, 2, 6)
        J = weights.whiten(jacobian).reshape(-1, 6)
        information = J.T @ J
        if gravity is not None:
            A = np.hstack([np.zeros((2, 3)), gravity.residual(T_map_body[:3, :3])[1]])
            information += A.T @ A
        C = np.linalg.pinv(information)
        map_share = np.zeros((6, 6))
        if weights.map_roots is not None:
            J_m = np.split(J, 2 * np.cumsum(points.counts)[:-1])
            # sum_m (J_m^T W_m^1/2 G_m S_m^1/2)(...)^T, W_m^1/2 G_m S_m^1/2 = the marker's map root
            X = np.hstack([J_mi.T @ root for J_mi, root in zip(J_m, weights.map_roots)])
            map_share = C @ X @ X.T @ C
        if common > 0.0:
            # a map point moved by dX moves as the body moved by -dX: G = -d(pixels)/d(position)
            G = -jacobian[..., :3] * np.repeat(points.surveyed, points.counts)[:, None, None]
            K = C @ J.T @ weights.whiten(G).reshape(-1, 3)
            C = C + common * K @ K.T
            map_share = map_share + common * K @ K.T
        return C, map_share

    def _pose_jacobian(self, T_map_body: np.ndarray, points_map: np.ndarray) -> np.ndarray:
        """(2K, 6) derivative of the projected pixels by [dp_map (3), dtheta_map (3)].

        Perturbed pose: R' = exp(dtheta) R, p' = p + dp (map axes). A map
        point X is seen at X_c = R_cm (X - p) + t_cb with R_cm = R_cb R^T, so
        to first order dX_c = R_cm (-dp + (X - p) x dtheta); the camera
        gives d(pixels)/dX_c (OpenCV's projectPoints).
        """
        T_camera_map = self._T_camera_map(T_map_body)
        # A_i = d(pixels_i)/dX_c R_cm: (K, 2, 3)
        A = self.camera.projection_jacobian(frames.transform_points(T_camera_map, points_map)) @ T_camera_map[:3, :3]
        # d(pixels_i)/d(dp) = -A_i
        d_position = -A
        # d(pixels_i)/d(dtheta) = A_i skew(X_i - p): row a of it is a x (X_i - p)
        d_rotation = _cross(A, (points_map - T_map_body[:3, 3])[:, None, :])
        return np.concatenate([d_position, d_rotation], axis=2).reshape(-1, 6)

    def _T_camera_map(self, T_map_body: np.ndarray) -> np.ndarray:
        # T_camera_map = T_camera_body T_body_map
        return self._T_camera_body @ frames.invert_transform(T_map_body)

    def _R_map_body(self, T_camera_map: np.ndarray) -> np.ndarray:
        # R_map_body = R_map_camera R_camera_body
        return T_camera_map[:3, :3].T @ self._T_camera_body[:3, :3]


# ----------------------------------------------------------------- helpers

def position_sd_m(measurement: PoseMeasurement) -> float:
    """Standard deviation of the position along its worst axis, metres."""
    return math.sqrt(max(float(np.linalg.eigvalsh(measurement.covariance_ned[:3, :3])[-1]), 0.0))


def _pose_variances(sd_m: float, sd_deg: float) -> np.ndarray:
    """(6,) variances of a pose, [m^2 (3), rad^2 (3)], from its position and angle sd."""
    return np.array([sd_m ** 2] * 3 + [math.radians(sd_deg) ** 2] * 3)


def _corner_cov_px2(cov_px2) -> np.ndarray | None:
    """A detection's (8, 8) corner covariance if usable (finite, symmetric, positive definite), else None."""
    if cov_px2 is None:
        return None
    cov = np.asarray(cov_px2, dtype=float)
    if cov.shape != (8, 8) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12):
        return None
    if not np.linalg.eigvalsh(cov)[0] > 0:
        return None
    return cov


def _best(fits: list[Fit]) -> Fit | None:
    """Most agreeing markers, then the lowest chi-square."""
    return min(fits, key=lambda f: (-len(f.inliers), f.cost), default=None)


@functools.lru_cache(maxsize=1024)
def chi2_quantile(probability: float, dof: int) -> float:
    """q with P(X <= q) = probability for X chi-square with ``dof`` degrees of freedom.

    Cached: a solve asks for a few small dof many times, and scipy's call costs ~50 us.
    """
    return float(chi2.ppf(probability, dof))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis, broadcast (numpy's cross costs ~50 us a call on these small stacks)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _transform(R: np.ndarray, t) -> np.ndarray:
    """(4, 4) from a rotation and a translation of any shape of 3 (OpenCV's tvec)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def _camera_position_m(fit: Fit) -> np.ndarray:
    """(3,) the camera's optical centre in the map: -R^T t."""
    T = fit.T_camera_map
    return -T[:3, :3].T @ T[:3, 3]


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
