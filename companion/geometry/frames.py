"""Every frame of reference, axis convention and fixed transform, in one place.

No other module swaps axes: they call the functions and constants here.

Frames (all right-handed, metres, see ``docs/frames.md`` for the figure):

* **camera** (OpenCV): origin at the optical centre, x right in the image,
  y down in the image, z forward along the optical axis.
* **camera FRD**: the same origin, x forward along the optical axis, y right,
  z down in the image. Only used to state a camera's mounting as
  roll/pitch/yaw like any other body (``R_CAMFRD_CAMERA``).
* **body** (FRD): the vehicle's body frame, x forward, y right, z down,
  origin at the vehicle's reference point (the flight controller's).
* **map**: the facility's frame, z up; its x axis points at a stated bearing
  from true north (``x_bearing_deg``, clockwise as on a compass), so its
  y axis points at ``x_bearing_deg - 90``.
* **NED**: MAVLink local NED (north, east, down), origin at the map origin
  (the EKF origin set with SET_GPS_GLOBAL_ORIGIN).
* **geodetic**: latitude, longitude (degrees, WGS-84) and altitude above mean
  sea level, to and from NED by ArduPilot's flat-earth rule
  (``ned_from_geodetic``, ``geodetic_from_ned``), as its simulator and EKF do.
* **marker**: origin at the centre of the marker's inner black square,
  x toward the marker's right (TL -> TR), y toward its top (BL -> TL),
  z out of the printed face toward the viewer.

Rigid transforms are 4x4 homogeneous matrices named ``T_to_from``:
``p_to = T_to_from @ p_from``; rotations are 3x3 ``R_to_from``; the columns of
``R_to_from`` are the ``from`` axes written in the ``to`` frame.

Euler angles are Z-Y-X (3-2-1, "yaw, pitch, roll", intrinsic) as MAVLink uses
them: ``R_to_from = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. Quaternions are
Hamilton ``(w, x, y, z)``, scalar first, with ``w >= 0`` on output.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

# Columns are the OpenCV camera axes (x right, y down, z forward) in camera FRD.
R_CAMFRD_CAMERA = np.array(
    [[0.0, 0.0, 1.0],
     [1.0, 0.0, 0.0],
     [0.0, 1.0, 0.0]]
)

# Map's z is up, NED's is down: the map's "up" is NED (0, 0, -1).
MAP_UP_IN_NED = np.array([0.0, 0.0, -1.0])


# ---------------------------------------------------------------- rotations
#
# scipy's Rotation does the arithmetic; these functions fix the conventions
# (axis order, scalar-first quaternions, w >= 0, angle ranges). Matrices given
# to them are products of rotations, so scipy's orthogonality check (and its
# SVD re-orthogonalisation) is skipped: it triples the cost of a call on the
# per-frame pose path.

def _from_matrix(R: np.ndarray) -> Rotation:
    return Rotation.from_matrix(np.asarray(R, dtype=float), assume_valid=True)


def rot_x(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about +x (right-hand rule)."""
    return Rotation.from_euler("x", angle_rad).as_matrix()


def rot_y(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about +y (right-hand rule)."""
    return Rotation.from_euler("y", angle_rad).as_matrix()


def rot_z(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about +z (right-hand rule)."""
    return Rotation.from_euler("z", angle_rad).as_matrix()


def rotation_from_euler_321(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """(3, 3) ``R_to_from`` from Z-Y-X Euler angles (radians).

    The ``from`` frame is reached by yawing about z, then pitching about the
    new y, then rolling about the newest x (MAVLink's body -> NED attitude).
    """
    # R = Rz(yaw) Ry(pitch) Rx(roll): intrinsic rotations, upper-case axes in scipy
    return Rotation.from_euler("ZYX", [yaw_rad, pitch_rad, roll_rad]).as_matrix()


def euler_321_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """(roll_rad, pitch_rad, yaw_rad) of a (3, 3) rotation, Z-Y-X order.

    pitch is in [-pi/2, pi/2], roll and yaw in [-pi, pi]. At gimbal lock
    (pitch within 1e-7 rad of +-pi/2) only yaw -/+ roll is observable: roll
    is reported as 0 and yaw carries the rotation.
    """
    # scipy's rule at gimbal lock is ours: the third angle (roll) is set to 0.
    yaw, pitch, roll = _from_matrix(R).as_euler("ZYX", suppress_warnings=True)
    return float(roll), float(pitch), float(yaw)


def roll_pitch_321(R: np.ndarray) -> tuple[float, float]:
    """(roll_rad, pitch_rad) of a (3, 3) rotation, Z-Y-X order, as ``euler_321_from_rotation``.

    Closed form (the pose stage calls it per hypothesis): with
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``, ``R[2, 0] = -sin(pitch)``,
    ``R[2, 1] = cos(pitch) sin(roll)``, ``R[2, 2] = cos(pitch) cos(roll)``.
    """
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    return roll, pitch


def down_in_body(R_ned_body: np.ndarray) -> np.ndarray:
    """(3,) NED's down (gravity's direction) in body FRD axes: ``R_ned_body^T (0, 0, 1)``, its third row."""
    return R_ned_body[2]


def down_in_body_at(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """(3,) ``down_in_body`` at this roll and pitch, Z-Y-X order (see ``roll_pitch_321``), whatever the yaw."""
    cos_pitch = math.cos(pitch_rad)
    return np.array([-math.sin(pitch_rad), cos_pitch * math.sin(roll_rad), cos_pitch * math.cos(roll_rad)])


def roll_pitch_321_jacobian(R: np.ndarray) -> np.ndarray:
    """(2, 3) derivative of (roll, pitch) of ``R`` by a small rotation ``theta`` applied as ``R' = exp(theta) R``.

    ``theta`` is on the axes of the ``to`` frame (NED for ``R_ned_body``). With
    ``R = Rz(yaw) Ry(pitch) Rx(roll)`` the rotation rate on those axes is
    ``w = roll' R e_x + pitch' Rz(yaw) e_y + yaw' e_z``, so
    ``roll' = (w_x cos yaw + w_y sin yaw) / cos pitch`` and
    ``pitch' = -w_x sin yaw + w_y cos yaw`` (undefined at pitch = +-90 degrees).
    """
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    cos_pitch = math.hypot(float(R[0, 0]), float(R[1, 0]))
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c / cos_pitch, s / cos_pitch, 0.0], [-s, c, 0.0]])


def rotation_from_quaternion(q_wxyz) -> np.ndarray:
    """(3, 3) rotation from a quaternion (w, x, y, z); normalised first.

    Raises ValueError for a zero or non-finite quaternion.
    """
    q = np.asarray(q_wxyz, dtype=float).reshape(4)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quaternion {q.tolist()} has no direction (norm {norm})")
    return Rotation.from_quat(q, scalar_first=True).as_matrix()


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (w, x, y, z), w >= 0, of a (3, 3) rotation."""
    return _from_matrix(R).as_quat(canonical=True, scalar_first=True)


def rotation_from_rotvec(rotvec) -> np.ndarray:
    """(3, 3) rotation from a (3,) axis-angle vector (radians), as cv2.Rodrigues."""
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=float).reshape(3)).as_matrix()


def rotvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """(3,) axis-angle vector (radians, angle in [0, pi]) of a (3, 3) rotation."""
    return _from_matrix(R).as_rotvec()


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> float | np.ndarray:
    """Angle (radians, [0, pi]) of the rotation taking R_b to R_a.

    (3, 3) rotations give a float; stacks (..., 3, 3) broadcast to (...) angles.
    """
    # the magnitude of R_a R_b^T
    R_a, R_b = np.asarray(R_a, dtype=float), np.asarray(R_b, dtype=float)
    angle = _from_matrix(R_a @ np.swapaxes(R_b, -1, -2)).magnitude()
    return float(angle) if np.ndim(angle) == 0 else angle


def skew(v) -> np.ndarray:
    """(3, 3) cross-product matrix: ``skew(a) @ b == np.cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


# --------------------------------------------------------------- transforms

def make_transform(R: np.ndarray, t_m) -> np.ndarray:
    """(4, 4) homogeneous transform from a (3, 3) rotation and (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t_m, dtype=float).reshape(3)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """(4, 4) inverse of a rigid transform: ``T_b_a`` from ``T_a_b``."""
    R = T[:3, :3]
    # T^-1 = [R^T, -R^T t]
    return make_transform(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points) -> np.ndarray:
    """(N, 3) points mapped by a (4, 4) transform; ``points`` is (N, 3) or (3,)."""
    p = np.asarray(points, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def transform_from_rotvec(rvec, tvec) -> np.ndarray:
    """(4, 4) transform from OpenCV's (rvec, tvec) pair (any shapes of 3)."""
    return make_transform(rotation_from_rotvec(rvec), np.asarray(tvec, dtype=float).reshape(3))


# -------------------------------------------------------- named transforms

def R_ned_map(x_bearing_deg: float) -> np.ndarray:
    """(3, 3) rotation map -> NED for a map whose x axis points at ``x_bearing_deg``.

    The bearing is measured from true north, clockwise seen from above
    (a compass bearing: 90 = east). The map's y axis is 90 degrees
    counter-clockwise from x seen from above (bearing - 90), its z is up.
    """
    b = math.radians(x_bearing_deg)
    x_axis = [math.cos(b), math.sin(b), 0.0]
    # bearing - 90: (cos(b - 90), sin(b - 90)) = (sin b, -cos b)
    y_axis = [math.sin(b), -math.cos(b), 0.0]
    return np.column_stack([x_axis, y_axis, MAP_UP_IN_NED])


def T_ned_map(x_bearing_deg: float) -> np.ndarray:
    """(4, 4) map -> NED; both frames share the map origin (the EKF origin)."""
    return make_transform(R_ned_map(x_bearing_deg), np.zeros(3))


# ---------------------------------------------------------------- geodetic
#
# ArduPilot's Location class (libraries/AP_Common/Location.cpp): north and
# east offsets are degE7 differences times LOCATION_SCALING_FACTOR, the east
# one also times the cosine of the mean latitude. Its simulator moves the
# vehicle and its EKF measures positions with this rule, so converting with
# the same one puts SITL's vehicle exactly where its EKF believes it is.

# metres per 1e-7 degree of latitude: ArduPilot's RADIUS_OF_EARTH (6378100 m) * pi / 180 * 1e-7
LOCATION_SCALING_FACTOR_M = 0.011131884502145034
DEG_E7 = 1e7


def _longitude_scale(latitude_deg: float) -> float:
    """ArduPilot's longitude_scale: cos(latitude), at least 0.01."""
    return max(math.cos(math.radians(latitude_deg)), 0.01)


def ned_from_geodetic(latitude_deg: float, longitude_deg: float, altitude_m: float,
                      origin_latitude_deg: float, origin_longitude_deg: float, origin_altitude_m: float) -> np.ndarray:
    """(3,) north, east, down (m) of a geodetic position from an origin (altitudes above mean sea level)."""
    d_lat_e7 = (latitude_deg - origin_latitude_deg) * DEG_E7
    # longitude difference wrapped into [-180, 180) degrees
    d_lon_e7 = ((longitude_deg - origin_longitude_deg + 180.0) % 360.0 - 180.0) * DEG_E7
    # north = dlat * F, east = dlon * F * cos((lat + lat0) / 2), down = alt0 - alt
    north_m = d_lat_e7 * LOCATION_SCALING_FACTOR_M
    east_m = d_lon_e7 * LOCATION_SCALING_FACTOR_M * _longitude_scale((latitude_deg + origin_latitude_deg) / 2)
    return np.array([north_m, east_m, origin_altitude_m - altitude_m])


def geodetic_from_ned(ned_m, origin_latitude_deg: float, origin_longitude_deg: float,
                      origin_altitude_m: float) -> tuple[float, float, float]:
    """(latitude_deg, longitude_deg, altitude_m) of a (3,) NED offset from an origin: ``ned_from_geodetic`` inverted."""
    north_m, east_m, down_m = np.asarray(ned_m, dtype=float).reshape(3)
    latitude_deg = origin_latitude_deg + north_m / LOCATION_SCALING_FACTOR_M / DEG_E7
    scale = _longitude_scale((latitude_deg + origin_latitude_deg) / 2)
    longitude_deg = origin_longitude_deg + east_m / (LOCATION_SCALING_FACTOR_M * scale) / DEG_E7
    longitude_deg = (longitude_deg + 180.0) % 360.0 - 180.0
    return float(latitude_deg), float(longitude_deg), float(origin_altitude_m - down_m)


def map_heading_deg(direction_map) -> float:
    """The heading of a direction given in the map frame: degrees counter-clockwise from the map's +x seen from
    above, in (-180, 180] (its horizontal part; as the map file gives headings)."""
    x, y = float(direction_map[0]), float(direction_map[1])
    return math.degrees(math.atan2(y, x))


def yaw_ned_from_map_heading_deg(heading_deg: float, x_bearing_deg: float) -> float:
    """NED yaw (compass heading, degrees in [0, 360)) of a body heading ``heading_deg`` in the map.

    The map heading is counter-clockwise from map +x seen from above; the map's
    +x is at compass bearing ``x_bearing_deg``, so yaw = bearing - heading.
    """
    return (x_bearing_deg - heading_deg) % 360.0


def R_body_camera_from_mount(roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """(3, 3) camera (OpenCV) -> body FRD for a camera mounted at these angles.

    The angles are the camera FRD frame's Z-Y-X Euler angles relative to the
    body: all zero is a camera looking forward with its image upright;
    ``pitch_deg = -20`` looks forward and 20 degrees down; ``pitch_deg = -90``
    looks straight down with the image top toward the vehicle's front.
    """
    R_body_camfrd = rotation_from_euler_321(
        math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg)
    )
    return R_body_camfrd @ R_CAMFRD_CAMERA


def R_map_marker_on_wall(facing_deg: float) -> np.ndarray:
    """(3, 3) marker -> map for an upright marker on a vertical wall.

    ``facing_deg``: direction the printed face looks toward (the wall's
    outward normal), counter-clockwise from map +x about map +z
    (0 faces +x, 90 faces +y). The marker's top points to map +z.
    """
    h = math.radians(facing_deg)
    z_axis = np.array([math.cos(h), math.sin(h), 0.0])
    y_axis = np.array([0.0, 0.0, 1.0])
    # x = y cross z: the viewer's right
    return np.column_stack([np.cross(y_axis, z_axis), y_axis, z_axis])


def R_map_marker_facing_up() -> np.ndarray:
    """(3, 3) marker -> map for a floor marker (face up), marker x along map +x."""
    return np.eye(3)


def R_map_marker_facing_down() -> np.ndarray:
    """(3, 3) marker -> map for a ceiling marker (face down), marker x along map +x."""
    return rot_x(math.pi)


def R_camera_marker_face_on() -> np.ndarray:
    """(3, 3) marker -> OpenCV camera for an upright marker seen face-on (marker x = image right, y = image up).

    A level body looking along map +x (yaw 0 in a map whose x points north),
    a forward camera, a wall marker facing -x.
    """
    R_map_camera = R_ned_map(0.0).T @ R_body_camera_from_mount()
    return R_map_camera.T @ R_map_marker_on_wall(180.0)


# ----------------------------------------------------------------- marker

def grid_to_marker_m(uv_cells, inner_origin_cells: float, inner_cells: float, size_m: float) -> np.ndarray:
    """(N, 3) marker-frame points (metres, z = 0) of (N, 2) grid coordinates.

    Grid coordinates (u, v) are in cells from the grid's outer top-left
    corner, u right, v down; the inner black square spans
    [o, o + c] x [o, o + c] with o = ``inner_origin_cells``,
    c = ``inner_cells`` (a marker layout's ``inner_origin`` and
    ``inner_cells``: n + 2 for an n x n dictionary) and side ``size_m``.
    """
    uv = np.asarray(uv_cells, dtype=float).reshape(-1, 2)
    cell_m = size_m / inner_cells
    centre = inner_origin_cells + inner_cells / 2.0
    # x = (u - (o + c/2)) cell_m, y = ((o + c/2) - v) cell_m
    x = (uv[:, 0] - centre) * cell_m
    y = (centre - uv[:, 1]) * cell_m
    return np.column_stack([x, y, np.zeros(len(uv))])


def marker_inner_corners_m(size_m: float) -> np.ndarray:
    """(4, 3) inner black square corners TL, TR, BR, BL in the marker frame, metres (z = 0)."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


# ------------------------------------------------------------- covariance

def rotate_pose_covariance(cov_6x6: np.ndarray, R_new_old: np.ndarray) -> np.ndarray:
    """(6, 6) covariance over [position (3), small-angle rotation (3)] re-expressed.

    Both blocks are vectors in the ``old`` frame's axes; the result has them
    in the ``new`` frame's axes: ``C' = B C B^T`` with ``B = diag(R, R)``.
    """
    B = np.zeros((6, 6))
    B[:3, :3] = R_new_old
    B[3:, 3:] = R_new_old
    return B @ cov_6x6 @ B.T
