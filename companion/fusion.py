"""Kalman fusion of per-frame poses into the estimate sent to the flight controller.

The only module that imports filterpy. State (8,), in the flight controller's
local NED frame (a fixed rotation of the map frame, ``companion.geometry.frames``)::

    x = [north_m, east_m, down_m, yaw_rad, vn_m_s, ve_m_s, vd_m_s, yaw_rate_rad_s]

a constant-velocity model for position and for yaw, driven by white-noise
acceleration, stepped with the variable dt between capture times. Each
PoseMeasurement brings its own covariance; measurements whose Mahalanobis
distance to the prediction exceeds a chi-square gate are rejected and counted.

Losing and re-acquiring the markers:

* TRACKING: the newest frame gave an accepted pose.
* COASTING: no accepted pose, for at most ``max_coast_s`` since the last one:
  the prediction is still returned (growing covariance) so single-frame
  dropouts do not interrupt the stream.
* ACQUIRING: before the first fix, and once coasting has run out: nothing is
  returned (the daemon stops sending; the flight controller's own IMU
  prediction is better than ours). A fix needs ``confirm_frames`` mutually
  consistent poses, so a lone ambiguous pose (a yaw flip) never gets through,
  unless the pose stage ruled out every other pose itself
  (``PoseMeasurement.unambiguous``: by the image or the flight controller's
  attitude): then that one pose is the fix.
  If the re-acquired pose is more than ``reset_distance_m`` or
  ``reset_yaw_rad`` away from the last estimate returned, ``reset_counter``
  is incremented so the flight controller snaps to it instead of dragging.

The covariance sent: the filter averages frames as if their errors were
independent. The share of a pose's error that comes from the map
(``PoseMeasurement.map_covariance_ned``: a marker hung 2 cm from its entry
puts every frame that sees it 2 cm off) does not shrink that way, so the
estimate's position and yaw covariance is never below the last accepted
pose's map share (``covering``).

When coasting runs out, ``PoseFilter.loss`` says why at that frame
(``TrackLoss``): a gap in the frames longer than ``max_coast_s`` (a stalled
camera), or poses that stopped coming or passing the gate.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2

from companion.geometry import frames
from companion.types import Estimate, PoseMeasurement

# Indices into the state vector.
POS = slice(0, 3)
YAW = 3
VEL = slice(4, 7)
YAW_RATE = 7
STATE_DIM = 8
# Measurement z = [north, east, down, yaw]: rows/cols of covariance_ned used.
MEASURED_COV_INDICES = [0, 1, 2, 5]
MEASUREMENT_DIM = 4
# H picks position and yaw out of the state.
H = np.zeros((MEASUREMENT_DIM, STATE_DIM))
H[0:3, 0:3] = np.eye(3)
H[3, YAW] = 1.0


class FusionError(ValueError):
    """Invalid fusion parameters."""


class TrackState(enum.Enum):
    ACQUIRING = "acquiring"
    TRACKING = "tracking"
    COASTING = "coasting"


@dataclass(frozen=True)
class FusionParams:
    """Tuning of the filter and of the lost/re-acquire policy."""

    accel_noise_m_s2: float = 3.0
    yaw_accel_noise_rad_s2: float = 3.0
    # A pose consistent with the track passes the Mahalanobis gate with this
    # probability (the chi-square quantile with 4 degrees of freedom: 18.47 at 0.999).
    gate_probability: float = 0.999
    max_coast_s: float = 0.25
    confirm_frames: int = 3
    reset_distance_m: float = 0.25
    reset_yaw_rad: float = math.radians(10.0)
    initial_velocity_std_m_s: float = 2.0
    initial_yaw_rate_std_rad_s: float = 1.0

    # Config keys that were replaced: the old key is an error naming the new one.
    RENAMED_KEYS: ClassVar[dict[str, str]] = {
        "gate_chi2": "gate_probability, the gate as a probability (gate_chi2 18.47 was 0.999)",
    }

    def __post_init__(self) -> None:
        positive = ("accel_noise_m_s2", "yaw_accel_noise_rad_s2",
                    "reset_distance_m", "reset_yaw_rad",
                    "initial_velocity_std_m_s", "initial_yaw_rate_std_rad_s")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value > 0):
                raise FusionError(f"fusion parameter {name} must be a positive number, got {value!r}")
        if not (isinstance(self.gate_probability, (int, float)) and 0 < self.gate_probability <= 1):
            raise FusionError(f"fusion parameter gate_probability must be in (0, 1], got {self.gate_probability!r}")
        if not (isinstance(self.max_coast_s, (int, float)) and 0 <= self.max_coast_s <= 5):
            raise FusionError(f"fusion parameter max_coast_s must be in [0, 5] s, got {self.max_coast_s!r}")
        if not (isinstance(self.confirm_frames, int) and not isinstance(self.confirm_frames, bool)
                and self.confirm_frames >= 1):
            raise FusionError(f"fusion parameter confirm_frames must be an integer >= 1, got {self.confirm_frames!r}")


@dataclass(frozen=True)
class TrackLoss:
    """Why the filter gave up its track at a frame.

    without_fix_s: time since its last fix, past ``max_coast_s``.
    frame_gap_s: how much of it came before this frame with no frame at all.
    no_frames: that gap alone was longer than ``max_coast_s`` (the frames stopped); else the poses stopped
        coming or passing the gate.
    """

    without_fix_s: float
    frame_gap_s: float
    no_frames: bool


@dataclass
class FusionCounters:
    """What the filter did with the measurements it was given."""

    accepted: int = 0
    rejected: int = 0          # failed the Mahalanobis gate
    coasted: int = 0           # frames answered with a prediction only
    out_of_order: int = 0      # capture time not after the previous one
    lost: int = 0              # times coasting ran out
    acquisitions: int = 0      # fixes after ACQUIRING (first one included)
    resets: int = 0            # reset_counter increments


def wrap_angle_rad(angle_rad: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def measurement_vector(measurement: PoseMeasurement) -> tuple[np.ndarray, np.ndarray, float, float]:
    """z (4,), R (4, 4), roll_rad, pitch_rad of one pose measurement."""
    T = measurement.T_ned_body
    roll, pitch, yaw = frames.euler_321_from_rotation(T[:3, :3])
    z = np.array([T[0, 3], T[1, 3], T[2, 3], yaw])
    R = measurement.covariance_ned[np.ix_(MEASURED_COV_INDICES, MEASURED_COV_INDICES)]
    return z, R, roll, pitch


def map_share(measurement: PoseMeasurement) -> np.ndarray:
    """(4, 4) the map's share of R (``measurement_vector``): zero for an exact map."""
    share = measurement.map_covariance_ned
    if share is None:
        return np.zeros((MEASUREMENT_DIM, MEASUREMENT_DIM))
    return share[np.ix_(MEASURED_COV_INDICES, MEASURED_COV_INDICES)]


def covering(P: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(n, n) a covariance not below P nor M: M where M is the larger, P elsewhere.

    P (n, n) positive definite, M (n, n) positive semi-definite. With P = L L^T and L^-1 M L^-T = V diag(w) V^T,
    it is L V diag(max(w, 1)) V^T L^T: P itself when M is below it, M when M is above it in every direction.
    """
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return P + M
    L_inv = np.linalg.inv(L)
    w, V = np.linalg.eigh(L_inv @ M @ L_inv.T)
    B = L @ V
    return (B * np.maximum(w, 1.0)) @ B.T


@dataclass(frozen=True)
class _Innovation:
    """A measurement against a track's prediction.

    z: (4,) with its yaw unwrapped next to the state's; R: (4, 4);
    roll_rad, pitch_rad: the measured attitude's (not filtered);
    d_sq: squared Mahalanobis distance to the prediction.
    """

    z: np.ndarray
    R: np.ndarray
    roll_rad: float
    pitch_rad: float
    d_sq: float


class _Track:
    """One Kalman filter over the 8-state model, started from one measurement."""

    def __init__(self, params: FusionParams, measurement: PoseMeasurement):
        z, R, self.roll_rad, self.pitch_rad = measurement_vector(measurement)
        self.params = params
        self.kf = KalmanFilter(dim_x=STATE_DIM, dim_z=MEASUREMENT_DIM)
        self.kf.H = H
        self.kf.x = np.zeros((STATE_DIM, 1))
        self.kf.x[0:4, 0] = z
        P = np.zeros((STATE_DIM, STATE_DIM))
        P[0:4, 0:4] = R
        P[VEL, VEL] = np.eye(3) * params.initial_velocity_std_m_s ** 2
        P[YAW_RATE, YAW_RATE] = params.initial_yaw_rate_std_rad_s ** 2
        self.kf.P = P
        self.t_ns = measurement.t_ns
        self.t_last_fix_ns = measurement.t_ns
        self.rotation_cov = measurement.covariance_ned[3:6, 3:6].copy()
        self.map_share = map_share(measurement)

    def predict_to(self, t_ns: int) -> None:
        dt = (t_ns - self.t_ns) * 1e-9
        if dt <= 0:
            return
        F = np.eye(STATE_DIM)
        F[0:4, 4:8] = np.eye(4) * dt
        self.kf.predict(F=F, Q=process_noise(dt, self.params))
        self.t_ns = t_ns

    def innovation(self, measurement: PoseMeasurement) -> _Innovation:
        z, R, roll_rad, pitch_rad = measurement_vector(measurement)
        x_yaw = float(self.kf.x[YAW, 0])
        # Compare yaw modulo 2 pi: the state's yaw is continuous (unwrapped).
        z[3] = x_yaw + wrap_angle_rad(z[3] - x_yaw)
        y = z - (H @ self.kf.x)[:, 0]
        # S = H P H' + R;  d^2 = y' S^-1 y
        S = H @ self.kf.P @ H.T + R
        d_sq = float(y @ np.linalg.solve(S, y))
        return _Innovation(z, R, roll_rad, pitch_rad, d_sq)

    def update(self, measurement: PoseMeasurement, innovation: _Innovation) -> None:
        self.kf.update(innovation.z.reshape(MEASUREMENT_DIM, 1), R=innovation.R)
        self.roll_rad, self.pitch_rad = innovation.roll_rad, innovation.pitch_rad
        self.rotation_cov = measurement.covariance_ned[3:6, 3:6].copy()
        self.map_share = map_share(measurement)
        self.t_last_fix_ns = measurement.t_ns

    def position_ned_m(self) -> np.ndarray:
        return self.kf.x[POS, 0].copy()

    def yaw_rad(self) -> float:
        return wrap_angle_rad(float(self.kf.x[YAW, 0]))

    def estimate(self, reset_counter: int, tracking: bool) -> Estimate:
        P = self.kf.P
        # over [north, east, down, yaw] (the state's first four)
        sent = covering(P[0:4, 0:4], self.map_share)
        cov = np.zeros((6, 6))
        cov[0:3, 0:3] = sent[0:3, 0:3]
        cov[0:3, 5] = cov[5, 0:3] = sent[0:3, 3]
        cov[3:5, 3:5] = self.rotation_cov[0:2, 0:2]
        cov[5, 5] = sent[3, 3]
        return Estimate(
            t_ns=self.t_ns,
            position_ned_m=self.position_ned_m(),
            velocity_ned_m_s=self.kf.x[VEL, 0].copy(),
            roll_rad=self.roll_rad,
            pitch_rad=self.pitch_rad,
            yaw_rad=self.yaw_rad(),
            covariance_ned=cov,
            reset_counter=reset_counter,
            tracking=tracking,
            velocity_covariance_ned=P[VEL, VEL].copy(),
        )


def process_noise(dt: float, params: FusionParams) -> np.ndarray:
    """(8, 8) discrete white-noise-acceleration Q for one step of dt seconds.

    filterpy's per-axis block [[dt^4/4, dt^3/2], [dt^3/2, dt^2]] in the
    state's order (north, east, down, yaw, then their rates), each axis
    scaled by its acceleration variance.
    """
    # sigma_a of each state's axis
    sigma = np.tile([params.accel_noise_m_s2] * 3 + [params.yaw_accel_noise_rad_s2], 2)
    unit = Q_discrete_white_noise(dim=2, dt=dt, var=1.0, block_size=4, order_by_dim=False)
    # Q_ij = unit_ij sigma_i sigma_j: unit couples a state only with its own axis's rate
    return unit * np.outer(sigma, sigma)


class PoseFilter:
    """Fuses PoseMeasurements (one per frame, or None) into Estimates.

    Call ``step(t_ns, measurement)`` once per frame in capture order; it
    returns the Estimate to send, or None while nothing should be sent.
    """

    def __init__(self, params: FusionParams | None = None):
        self.params = params or FusionParams()
        # Squared Mahalanobis distance passed with probability gate_probability.
        self.gate_chi2 = float(chi2.ppf(self.params.gate_probability, MEASUREMENT_DIM))
        self.counters = FusionCounters()
        self.state = TrackState.ACQUIRING
        self.reset_counter = 0
        self._track: _Track | None = None
        self._candidate: _Track | None = None
        self._candidate_count = 0
        self._last_t_ns: int | None = None
        self._frame_gap_s = 0.0   # between the last two frames' capture times
        self._last_sent: Estimate | None = None
        self.loss: TrackLoss | None = None  # the track's loss at the last step (None: not lost there)

    def step(self, t_ns: int, measurement: PoseMeasurement | None) -> Estimate | None:
        """Advance to capture time ``t_ns`` with this frame's pose (or None)."""
        self.loss = None
        if self._last_t_ns is not None and t_ns <= self._last_t_ns:
            self.counters.out_of_order += 1
            return None
        self._frame_gap_s = 0.0 if self._last_t_ns is None else (t_ns - self._last_t_ns) * 1e-9
        self._last_t_ns = t_ns
        if self.state is TrackState.ACQUIRING:
            estimate = self._acquire(measurement)
        else:
            estimate = self._track_step(t_ns, measurement)
        if estimate is not None:
            self._last_sent = estimate
        return estimate

    def _track_step(self, t_ns: int, measurement: PoseMeasurement | None) -> Estimate | None:
        track = self._track
        # Stale before this frame's pose is weighed: after a gap in the frames the prediction's covariance has
        # grown enough to pass any jump, which would then reach the autopilot with no reset.
        if self._is_stale(track, t_ns):
            return self._lose_track(t_ns, measurement)
        track.predict_to(t_ns)
        if measurement is not None:
            innovation = track.innovation(measurement)
            if innovation.d_sq <= self.gate_chi2:
                track.update(measurement, innovation)
                self.counters.accepted += 1
                self.state = TrackState.TRACKING
                return track.estimate(self.reset_counter, tracking=True)
            self.counters.rejected += 1
        if self._is_stale(track, t_ns):
            return self._lose_track(t_ns, measurement)
        self.counters.coasted += 1
        self.state = TrackState.COASTING
        return track.estimate(self.reset_counter, tracking=False)

    def _lose_track(self, t_ns: int, measurement: PoseMeasurement | None) -> Estimate | None:
        """No fix for ``max_coast_s``: acquire again, starting with this frame's pose (if any)."""
        self.loss = TrackLoss((t_ns - self._track.t_last_fix_ns) * 1e-9, self._frame_gap_s,
                              no_frames=self._frame_gap_s > self.params.max_coast_s)
        self.counters.lost += 1
        self.state = TrackState.ACQUIRING
        self._track = None
        return self._acquire(measurement) if measurement is not None else None

    def _acquire(self, measurement: PoseMeasurement | None) -> Estimate | None:
        if measurement is None:
            return None
        candidate = self._candidate
        if candidate is None or self._is_stale(candidate, measurement.t_ns):
            self._start_candidate(measurement)
        else:
            candidate.predict_to(measurement.t_ns)
            innovation = candidate.innovation(measurement)
            if innovation.d_sq <= self.gate_chi2:
                candidate.update(measurement, innovation)
                self._candidate_count += 1
            else:
                self.counters.rejected += 1
                self._start_candidate(measurement)
        needed = 1 if measurement.unambiguous else self.params.confirm_frames
        if self._candidate_count < needed:
            return None
        return self._promote_candidate()

    def _is_stale(self, track: _Track, t_ns: int) -> bool:
        return (t_ns - track.t_last_fix_ns) * 1e-9 > self.params.max_coast_s

    def _start_candidate(self, measurement: PoseMeasurement) -> None:
        self._candidate = _Track(self.params, measurement)
        self._candidate_count = 1

    def _promote_candidate(self) -> Estimate:
        track = self._candidate
        self._track, self._candidate, self._candidate_count = track, None, 0
        self.state = TrackState.TRACKING
        self.counters.accepted += 1
        self.counters.acquisitions += 1
        if self._last_sent is not None and self._jumped_from(self._last_sent, track):
            self.reset_counter += 1
            self.counters.resets += 1
        return track.estimate(self.reset_counter, tracking=True)

    def _jumped_from(self, previous: Estimate, track: _Track) -> bool:
        distance_m = float(np.linalg.norm(track.position_ned_m() - previous.position_ned_m))
        yaw_change_rad = abs(wrap_angle_rad(track.yaw_rad() - previous.yaw_rad))
        return distance_m > self.params.reset_distance_m or yaw_change_rad > self.params.reset_yaw_rad
