"""Vehicle trajectories for the simulator: body poses in the map frame over time.

A trajectory answers ``pose_at(t_s) -> T_map_body`` (4x4, body FRD -> map)
for any time in ``[0, duration_s]``. Built-in patterns (hover, waypoints,
lawnmower, figure eight) are smooth position and heading curves; the body
tilts the way a multicopter must to follow them (pitch and roll from the
horizontal acceleration). A CSV of timestamped poses is interpolated
(linear position, spherical rotation).

Headings are in the map frame, degrees counter-clockwise from map +x about
map +z (the same sense as a map marker's ``facing``).

CSV format (the leading columns of ``groundtruth.csv``, which therefore reads
back as a trajectory): ``t_ns,x_m,y_m,z_m,qw,qx,qy,qz`` with a header line;
extra columns (and a ``frame`` column) are ignored.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from companion.geometry import frames

GRAVITY_M_S2 = 9.81
CSV_COLUMNS = ("t_ns", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz")
SAME_PLACE_M = 1e-3  # waypoints nearer each other than this are at one place
# A path's spline and speed profile are tabulated at 2 mm and 1 ms up to this many samples (a 2 km path, a
# 1000 s flight), more coarsely beyond: a long flight costs no more memory than that.
MAX_PATH_SAMPLES = 1_000_000


class TrajectoryError(ValueError):
    """A trajectory file or pattern parameter is invalid; the message says where."""


def R_map_body_from_attitude(heading_deg: float, pitch_rad: float = 0.0, roll_rad: float = 0.0) -> np.ndarray:
    """(3, 3) body FRD -> map for a body heading ``heading_deg`` (map frame, ccw from +x).

    Composed from ``companion.geometry.frames``: in a map whose x axis points north,
    NED yaw is the heading measured clockwise, i.e. ``-heading``.
    """
    R_ned_body = frames.rotation_from_euler_321(roll_rad, pitch_rad, -math.radians(heading_deg))
    return frames.R_ned_map(0.0).T @ R_ned_body


class Trajectory:
    """Base: ``duration_s``, ``pose_at(t_s)``, and a description for sequence.yaml."""

    duration_s: float

    def pose_at(self, t_s: float) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def describe(self) -> dict:  # pragma: no cover - interface
        raise NotImplementedError


@dataclass
class PathTrajectory(Trajectory):
    """A smooth path: position (3,) and heading (degrees) as functions of time.

    The body pitches and rolls with the horizontal acceleration (a level
    multicopter tilts toward where it accelerates): pitch = -atan(a_fwd / g),
    roll = atan(a_right / g).
    """

    position_m: Callable[[float], np.ndarray]
    heading_deg: Callable[[float], float]
    duration_s: float
    description: dict
    tilt_from_acceleration: bool = True

    def pose_at(self, t_s: float) -> np.ndarray:
        p = np.asarray(self.position_m(t_s), dtype=float)
        heading = float(self.heading_deg(t_s))
        pitch = roll = 0.0
        if self.tilt_from_acceleration:
            dt = 0.02
            # central second difference: a = (p(t+dt) - 2 p(t) + p(t-dt)) / dt^2
            a = (np.asarray(self.position_m(t_s + dt)) - 2 * p + np.asarray(self.position_m(t_s - dt))) / dt**2
            h = math.radians(heading)
            forward = np.array([math.cos(h), math.sin(h), 0.0])
            # the right of a heading, seen from above with z up, is 90 degrees clockwise
            right = np.array([math.sin(h), -math.cos(h), 0.0])
            pitch = -math.atan2(float(a @ forward), GRAVITY_M_S2)
            roll = math.atan2(float(a @ right), GRAVITY_M_S2)
        return frames.make_transform(R_map_body_from_attitude(heading, pitch, roll), p)

    def describe(self) -> dict:
        return dict(self.description)


@dataclass
class SampledTrajectory(Trajectory):
    """Poses at given times, interpolated (linear position, slerp rotation), held at the ends.

    t_s: (N,) increasing seconds from 0; T_map_body: (N, 4, 4).
    """

    t_s: np.ndarray
    T_map_body: np.ndarray
    description: dict

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    def pose_at(self, t_s: float) -> np.ndarray:
        t = float(np.clip(t_s, self.t_s[0], self.t_s[-1]))
        i = int(np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2))
        t0, t1 = self.t_s[i], self.t_s[i + 1]
        w = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
        T0, T1 = self.T_map_body[i], self.T_map_body[i + 1]
        p = (1 - w) * T0[:3, 3] + w * T1[:3, 3]
        # slerp: R = R0 exp(w log(R0^T R1))
        R = T0[:3, :3] @ frames.rotation_from_rotvec(w * frames.rotvec_from_rotation(T0[:3, :3].T @ T1[:3, :3]))
        return frames.make_transform(R, p)

    def describe(self) -> dict:
        return dict(self.description)


# ---------------------------------------------------------------- patterns

def _minimum_jerk(s: float) -> float:
    """Smooth 0 -> 1 for s in [0, 1], zero velocity and acceleration at both ends."""
    s = min(max(s, 0.0), 1.0)
    # 10 s^3 - 15 s^4 + 6 s^5
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def hover(center_m: Sequence[float], heading_deg: float, duration_s: float, drift_m: float = 0.04,
          seed: int = 0) -> PathTrajectory:
    """Hold position with a hovering drone's slow wander (about ``drift_m``) and heading wobble."""
    c = np.asarray(center_m, dtype=float).reshape(3)
    rng = np.random.default_rng(seed)
    periods = rng.uniform(1.5, 5.0, (3, 3))
    phases = rng.uniform(0, 2 * np.pi, (3, 3))
    weights = np.array([1.0, 0.6, 0.3]) / 1.9
    yaw_period, yaw_phase = rng.uniform(3.0, 6.0), rng.uniform(0, 2 * np.pi)

    def position(t: float) -> np.ndarray:
        wander = (weights[None, :] * np.sin(2 * np.pi * t / periods + phases)).sum(axis=1)
        return c + drift_m * wander * np.array([1.0, 1.0, 0.5])

    def heading(t: float) -> float:
        return heading_deg + 1.0 * math.sin(2 * np.pi * t / yaw_period + yaw_phase)

    return PathTrajectory(position, heading, float(duration_s),
                          {"pattern": "hover", "center_m": c.tolist(), "heading_deg": heading_deg,
                           "duration_s": duration_s, "drift_m": drift_m, "seed": seed})


def _check_points(points) -> np.ndarray:
    wp = np.asarray(points, dtype=float)
    if wp.ndim != 2 or wp.shape[1] != 4 or len(wp) < 2:
        raise TrajectoryError(f"waypoints must be at least two rows of x,y,z,heading_deg, got shape {wp.shape}")
    if not np.isfinite(wp).all():
        row = int(np.argmin(np.isfinite(wp).all(axis=1)))
        raise TrajectoryError(f"waypoint {row + 1} ({_row_text(wp[row])}) is not four finite numbers")
    return wp


def _check_limits(speed_m_s: float, max_accel_m_s2: float) -> None:
    if not (math.isfinite(speed_m_s) and speed_m_s > 0 and math.isfinite(max_accel_m_s2) and max_accel_m_s2 > 0):
        raise TrajectoryError(f"speed_m_s and max_accel_m_s2 must be positive, got {speed_m_s}, {max_accel_m_s2}")


def _check_path_moves(wp: np.ndarray) -> None:
    """A path flown through its waypoints without stopping cannot stay or turn on the spot."""
    steps = np.linalg.norm(np.diff(wp[:, :3], axis=0), axis=1)
    if (steps < SAME_PLACE_M).any():
        i = int(np.argmax(steps < SAME_PLACE_M))
        raise TrajectoryError(f"waypoints {i + 1} and {i + 2} are both at {_row_text(wp[i, :3])}: a path flies "
                              "through its waypoints without stopping, so each must be somewhere else than the "
                              "one before (the waypoints pattern stops, and turns on the spot)")


def _check_flight_moves(wp: np.ndarray, headings: np.ndarray) -> None:
    """Waypoints flown stop by stop must go somewhere or turn: not all one place and heading."""
    if np.ptp(wp[:, :3], axis=0).max() < SAME_PLACE_M and np.ptp(headings) < 0.01:
        raise TrajectoryError(f"every waypoint is {_row_text(wp[0])}: there is nothing to fly (a hover holds a "
                              "position)")


def _row_text(values) -> str:
    return ",".join(f"{v:g}" for v in values)


def waypoints(points: Sequence[Sequence[float]], speed_m_s: float = 1.0, pause_s: float = 0.0,
              max_accel_m_s2: float = 1.0, description: dict | None = None) -> PathTrajectory:
    """Fly from waypoint to waypoint (x, y, z, heading_deg), stopping at each.

    Each leg follows a minimum-jerk profile no faster than ``speed_m_s`` at its
    peak, no harder than ``max_accel_m_s2``, turning at most 45 deg/s;
    ``pause_s`` hovers at each waypoint.
    """
    wp = _check_points(points)
    _check_limits(speed_m_s, max_accel_m_s2)
    headings = np.degrees(np.unwrap(np.radians(wp[:, 3])))
    _check_flight_moves(wp, headings)
    legs = []
    for a, b, ha, hb in zip(wp[:-1, :3], wp[1:, :3], headings[:-1], headings[1:]):
        d = float(np.linalg.norm(b - a))
        # minimum jerk over T: peak speed 1.875 d / T, peak acceleration 5.77 d / T^2
        duration = max(1.875 * d / speed_m_s, math.sqrt(5.77 * d / max_accel_m_s2), abs(hb - ha) / 45.0, 1.0)
        legs.append((a, b, ha, hb, duration))
    starts = np.cumsum([0.0] + [leg[4] + pause_s for leg in legs])
    total = float(starts[-1])

    def leg_at(t: float):
        i = int(np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(legs) - 1))
        a, b, ha, hb, duration = legs[i]
        s = _minimum_jerk((t - starts[i]) / duration)
        return a + s * (b - a), ha + s * (hb - ha)

    desc = description or {"pattern": "waypoints", "points": wp.tolist(), "speed_m_s": speed_m_s,
                           "pause_s": pause_s, "max_accel_m_s2": max_accel_m_s2}
    return PathTrajectory(lambda t: leg_at(t)[0], lambda t: leg_at(t)[1], total, desc)


def smooth_path(points: Sequence[Sequence[float]], speed_m_s: float = 1.0,
                max_accel_m_s2: float = 0.8) -> PathTrajectory:
    """Fly smoothly through waypoints (x, y, z, heading_deg) without stopping.

    The path is a Catmull-Rom spline through the points (chord-length knots);
    it is flown at ``speed_m_s`` with smooth speed-up and slow-down at the
    ends (peak acceleration ``max_accel_m_s2``); the heading follows the
    same spline over the distance flown.
    """
    wp = _check_points(points)
    _check_limits(speed_m_s, max_accel_m_s2)
    _check_path_moves(wp)
    wp[:, 3] = np.degrees(np.unwrap(np.radians(wp[:, 3])))
    chords = np.maximum(np.linalg.norm(np.diff(wp[:, :3], axis=0), axis=1), 1e-3)
    knots = np.concatenate([[0.0], np.cumsum(chords)])
    # dense samples of the spline, then arc length along them
    u = np.linspace(0.0, knots[-1], min(max(int(knots[-1] / 0.002), 200), MAX_PATH_SAMPLES))
    dense = _catmull_rom(knots, wp, u)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense[:, :3], axis=0), axis=1))])
    length = float(arc[-1])
    # speed ramps over ramp_s with a minimum-jerk profile: peak acceleration 1.875 v / ramp_s
    ramp_s = 1.875 * speed_m_s / max_accel_m_s2
    cruise_speed = speed_m_s
    if length < speed_m_s * ramp_s:  # too short to reach the speed
        cruise_speed = math.sqrt(length * max_accel_m_s2 / 1.875)
        ramp_s = 1.875 * cruise_speed / max_accel_m_s2
    duration = length / cruise_speed + ramp_s
    t_grid = np.linspace(0.0, duration, min(int(duration * 1000) + 2, MAX_PATH_SAMPLES))
    speed = cruise_speed * np.minimum(_min_jerk_array(t_grid / ramp_s), _min_jerk_array((duration - t_grid) / ramp_s))
    distance = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2 * np.diff(t_grid))])
    distance *= length / distance[-1]

    columns = [np.ascontiguousarray(dense[:, k]) for k in range(4)]  # np.interp copies a strided column each call

    def state(t: float) -> np.ndarray:
        s = float(np.interp(t, t_grid, distance))
        return np.array([np.interp(s, arc, column) for column in columns])

    return PathTrajectory(lambda t: state(t)[:3], lambda t: float(state(t)[3]), float(duration), {
        "pattern": "path", "points": wp.tolist(), "speed_m_s": speed_m_s, "max_accel_m_s2": max_accel_m_s2})


def _min_jerk_array(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def _catmull_rom(knots: np.ndarray, values: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(M, D) cubic Hermite spline through (N, D) ``values`` at ``knots``, tangents from neighbours
    (zero at the two ends), evaluated at (M,) ``u``."""
    n = len(knots)
    tangents = np.zeros_like(values)
    for i in range(1, n - 1):
        tangents[i] = (values[i + 1] - values[i - 1]) / (knots[i + 1] - knots[i - 1])
    i = np.clip(np.searchsorted(knots, u, side="right") - 1, 0, n - 2)
    h = (knots[i + 1] - knots[i])[:, None]
    s = ((u - knots[i]) / h[:, 0])[:, None]
    # Hermite basis: h00 = 2s^3 - 3s^2 + 1, h10 = s^3 - 2s^2 + s, h01 = -2s^3 + 3s^2, h11 = s^3 - s^2
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * values[i] + h10 * h * tangents[i] + h01 * values[i + 1] + h11 * h * tangents[i + 1]


def lawnmower(start_m: Sequence[float], end_m: Sequence[float], sweep_m: float, passes: int,
              heading_deg: float, speed_m_s: float = 1.0, max_accel_m_s2: float = 1.0) -> PathTrajectory:
    """Back-and-forth passes parallel to start -> end, stepping ``sweep_m`` sideways between passes.

    The side step is toward the left of start -> end (seen from above); a
    negative ``sweep_m`` steps to the right. The heading stays fixed.
    """
    a, b = np.asarray(start_m, float).reshape(3), np.asarray(end_m, float).reshape(3)
    along = b - a
    if np.linalg.norm(along[:2]) < 1e-6:
        raise TrajectoryError(f"start and end are both at x,y {_row_text(a[:2])}: a lawnmower's passes run "
                              "between them, so they must be apart in x/y")
    if passes < 1:
        raise TrajectoryError(f"a lawnmower needs at least one pass, not {passes}")
    left = np.array([-along[1], along[0], 0.0]) / np.linalg.norm(along[:2])
    points = []
    for k in range(passes):
        offset = left * (sweep_m * k / max(passes - 1, 1))
        p, q = (a, b) if k % 2 == 0 else (b, a)
        points += [(*(p + offset), heading_deg), (*(q + offset), heading_deg)]
    return waypoints(points, speed_m_s, 0.3, max_accel_m_s2, description={
        "pattern": "lawnmower", "start_m": a.tolist(), "end_m": b.tolist(), "sweep_m": sweep_m,
        "passes": passes, "heading_deg": heading_deg, "speed_m_s": speed_m_s, "max_accel_m_s2": max_accel_m_s2})


def figure_eight(center_m: Sequence[float], size_m: Sequence[float], period_s: float, heading_deg: float,
                 duration_s: float, look_along_path_deg: float | None = None) -> PathTrajectory:
    """A figure eight (lemniscate of Gerono) of half-extents ``size_m`` = (along, across) in the map x/y.

    The eight's long axis is map x rotated by ``heading_deg``; the body faces
    ``heading_deg`` fixed, or, with ``look_along_path_deg`` set, the path's
    direction plus that offset. The eight starts at its centre (at rest it
    would jump: the first second ramps the speed up).
    """
    c = np.asarray(center_m, float).reshape(3)
    sx, sy = size_m
    h = math.radians(heading_deg)
    axis_x = np.array([math.cos(h), math.sin(h), 0.0])
    axis_y = np.array([-math.sin(h), math.cos(h), 0.0])
    ramp_s = min(1.0, duration_s / 4)

    def phase(t: float) -> float:
        # speed ramps up over the first ramp_s seconds: phase = w (t - ramp/2) after the ramp
        w = 2 * np.pi / period_s
        if t < ramp_s:
            return w * t * t / (2 * ramp_s)
        return w * (t - ramp_s / 2)

    def position(t: float) -> np.ndarray:
        s = phase(t)
        # Gerono: x = sin(s), y = sin(s) cos(s)
        return c + sx * math.sin(s) * axis_x + sy * math.sin(s) * math.cos(s) * axis_y

    def heading(t: float) -> float:
        if look_along_path_deg is None:
            return heading_deg
        v = position(t + 0.05) - position(t - 0.05)
        return math.degrees(math.atan2(v[1], v[0])) + look_along_path_deg

    return PathTrajectory(position, heading, float(duration_s), {
        "pattern": "figure8", "center_m": c.tolist(), "size_m": [sx, sy], "period_s": period_s,
        "heading_deg": heading_deg, "duration_s": duration_s, "look_along_path_deg": look_along_path_deg})


# --------------------------------------------------------------------- CSV

def read_trajectory_csv(path) -> SampledTrajectory:
    """Read ``t_ns,x_m,y_m,z_m,qw,qx,qy,qz`` rows (T_map_body); times are shifted to start at 0."""
    path = str(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as error:
        raise TrajectoryError(f"{path}: cannot read trajectory: {error.strerror}") from None
    if not rows:
        raise TrajectoryError(f"{path}: no poses (expected a header {','.join(CSV_COLUMNS)} and rows)")
    missing = [c for c in CSV_COLUMNS if c not in rows[0]]
    if missing:
        raise TrajectoryError(f"{path}: missing column(s) {', '.join(missing)}; need {','.join(CSV_COLUMNS)}")
    times, poses = [], []
    for line, row in enumerate(rows, start=2):
        values = [_csv_number(path, line, row, column) for column in CSV_COLUMNS]
        try:
            R = frames.rotation_from_quaternion(values[4:8])
        except ValueError as error:
            raise TrajectoryError(f"{path}:{line}: qw..qz: {error}") from None
        times.append(values[0] * 1e-9)
        poses.append(frames.make_transform(R, values[1:4]))
    t = np.asarray(times) - times[0]
    if len(t) < 2 or np.any(np.diff(t) <= 0):
        raise TrajectoryError(f"{path}: t_ns must increase strictly over at least two rows")
    return SampledTrajectory(t, np.asarray(poses), {"pattern": "csv", "file": path})


def _csv_number(path: str, line: int, row: dict, column: str) -> float:
    """The finite number in ``column`` of a CSV row; TrajectoryError naming the file, line and column."""
    text = row[column]
    try:
        value = float(text)
    except (TypeError, ValueError):
        value = None
    if value is None or not math.isfinite(value):
        shown = "missing" if text is None else repr(text)
        raise TrajectoryError(f"{path}:{line}: {column} is {shown}, not a finite number")
    return value


def write_trajectory_csv(path, trajectory: Trajectory, fps: float) -> None:
    """Sample a trajectory at ``fps`` into a CSV that ``read_trajectory_csv`` reads."""
    n = int(math.floor(trajectory.duration_s * fps + 1e-9)) + 1
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        for i in range(n):
            t_ns = int(round(i * 1e9 / fps))
            T = trajectory.pose_at(t_ns * 1e-9)
            q = frames.quaternion_from_rotation(T[:3, :3])
            writer.writerow([t_ns, *(f"{v:.6f}" for v in T[:3, 3]), *(f"{v:.9f}" for v in q)])


def trajectory_from_description(desc: dict, base_dir: Path | None = None) -> Trajectory:
    """Rebuild a trajectory from its ``describe()`` dict (as stored in sequence.yaml)."""
    pattern = desc.get("pattern")
    args = {k: v for k, v in desc.items() if k != "pattern"}
    if pattern == "hover":
        return hover(**args)
    if pattern == "waypoints":
        return waypoints(**args)
    if pattern == "lawnmower":
        return lawnmower(**args)
    if pattern == "figure8":
        return figure_eight(**args)
    if pattern == "path":
        return smooth_path(**args)
    if pattern == "csv":
        file = Path(args["file"])
        if base_dir is not None and not file.is_absolute() and not file.exists():
            file = base_dir / file
        return read_trajectory_csv(file)
    raise TrajectoryError(f"unknown trajectory pattern {pattern!r}")
