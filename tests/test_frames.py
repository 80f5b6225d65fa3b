"""Frame conventions: hand-computed cases and round trips."""
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.geometry import frames

angle = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
pitch_angle = st.floats(min_value=-1.55, max_value=1.55, allow_nan=False)
coordinate = st.floats(min_value=-100.0, max_value=100.0, allow_nan=False)


def is_rotation(R):
    return np.allclose(R @ R.T, np.eye(3), atol=1e-12) and math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-12)


# ------------------------------------------------------------ hand cases

@pytest.mark.parametrize(
    "bearing_deg, p_map, p_ned",
    [
        (0.0, [1, 2, 3], [1, -2, -3]),     # x north, y west, z up
        (90.0, [1, 2, 3], [2, 1, -3]),     # x east, y north
        (180.0, [1, 2, 3], [-1, 2, -3]),   # x south, y east
        (-90.0, [1, 2, 3], [-2, -1, -3]),  # x west, y south
    ],
)
def test_map_to_ned_by_hand(bearing_deg, p_map, p_ned):
    T = frames.T_ned_map(bearing_deg)
    np.testing.assert_allclose(frames.transform_points(T, p_map), p_ned, atol=1e-12)


def test_map_x_bearing_30_degrees():
    # x at bearing 30: north cos30, east sin30; y at bearing -60.
    R = frames.R_ned_map(30.0)
    np.testing.assert_allclose(R[:, 0], [math.sqrt(3) / 2, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], [0.5, -math.sqrt(3) / 2, 0.0], atol=1e-12)
    assert is_rotation(R)


def test_euler_yaw_90_points_forward_east():
    R = frames.rotation_from_euler_321(0.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [-1, 0, 0], atol=1e-12)


def test_euler_pitch_up_raises_the_nose():
    R = frames.rotation_from_euler_321(0.0, math.radians(30), 0.0)
    # NED down is +z, so the nose going up has a negative down component.
    np.testing.assert_allclose(R @ [1, 0, 0], [math.cos(math.radians(30)), 0, -0.5], atol=1e-12)


def test_euler_roll_right_lowers_the_right_wing():
    R = frames.rotation_from_euler_321(math.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_euler_order_is_yaw_then_pitch_then_roll():
    # Yaw 90 (facing east) puts the right wing south; pitching the nose up 90
    # about that wing points forward straight up and leaves the wing south.
    R = frames.rotation_from_euler_321(0.0, math.pi / 2, math.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [-1, 0, 0], atol=1e-12)


def test_quaternion_by_hand():
    q = frames.quaternion_from_rotation(frames.rot_z(math.pi / 2))
    np.testing.assert_allclose(q, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-12)
    q = frames.quaternion_from_rotation(frames.rot_x(math.pi))
    np.testing.assert_allclose(q, [0, 1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(frames.rotation_from_quaternion([0, 0, 1, 0]), np.diag([-1, 1, -1]), atol=1e-12)


def test_zero_quaternion_is_rejected():
    with pytest.raises(ValueError, match="norm"):
        frames.rotation_from_quaternion([0, 0, 0, 0])


def test_camera_forward_axes():
    R = frames.R_body_camera_from_mount()
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # optical axis forward
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # image right = body right
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-12)  # image down = body down


def test_camera_tilted_down_20_degrees():
    R = frames.R_body_camera_from_mount(pitch_deg=-20.0)
    t = math.radians(20)
    np.testing.assert_allclose(R @ [0, 0, 1], [math.cos(t), 0, math.sin(t)], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_camera_looking_down_has_image_top_forward():
    R = frames.R_body_camera_from_mount(pitch_deg=-90.0)
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R @ [0, -1, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_camera_looking_right():
    R = frames.R_body_camera_from_mount(yaw_deg=90.0)
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [-1, 0, 0], atol=1e-12)


@pytest.mark.parametrize(
    "facing_deg, normal, right",
    [
        (0.0, [1, 0, 0], [0, 1, 0]),
        (90.0, [0, 1, 0], [-1, 0, 0]),
        (180.0, [-1, 0, 0], [0, -1, 0]),
        (-90.0, [0, -1, 0], [1, 0, 0]),
    ],
)
def test_wall_marker_axes(facing_deg, normal, right):
    R = frames.R_map_marker_on_wall(facing_deg)
    np.testing.assert_allclose(R[:, 2], normal, atol=1e-12)
    np.testing.assert_allclose(R[:, 0], right, atol=1e-12)
    np.testing.assert_allclose(R[:, 1], [0, 0, 1], atol=1e-12)
    assert is_rotation(R)


def test_floor_and_ceiling_markers():
    up, down = frames.R_map_marker_facing_up(), frames.R_map_marker_facing_down()
    np.testing.assert_allclose(up[:, 2], [0, 0, 1])
    np.testing.assert_allclose(down[:, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(down[:, 0], [1, 0, 0], atol=1e-12)
    assert is_rotation(up) and is_rotation(down)


def test_camera_frd_is_a_pure_axis_swap():
    R = frames.R_CAMFRD_CAMERA
    assert is_rotation(R)
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0])  # optical axis is camera-FRD forward


def test_wall_marker_seen_by_a_camera_facing_it_is_upright():
    # Camera at the map origin, forward body facing map +x (bearing of body = map x),
    # looking at a marker on the wall at x = 2 facing -x: its right must project to image right.
    R_map_marker = frames.R_map_marker_on_wall(180.0)
    T_map_marker = frames.make_transform(R_map_marker, [2.0, 0.0, 0.0])
    # Body FRD in map (z up): forward = +x, right = -y, down = -z.
    R_map_body = np.column_stack([[1, 0, 0], [0, -1, 0], [0, 0, -1]]).astype(float)
    T_map_camera = frames.make_transform(R_map_body @ frames.R_body_camera_from_mount(), [0, 0, 0])
    T_camera_marker = frames.invert_transform(T_map_camera) @ T_map_marker
    corners = np.array([[-0.1, 0.1, 0], [0.1, 0.1, 0], [0.1, -0.1, 0], [-0.1, -0.1, 0]])
    p = frames.transform_points(T_camera_marker, corners)
    uv = p[:, :2] / p[:, 2:]
    assert uv[1, 0] > uv[0, 0]  # TR right of TL
    assert uv[3, 1] > uv[0, 1]  # BL below TL


# ------------------------------------------------------------ round trips

@settings(max_examples=200, deadline=None)
@given(angle, pitch_angle, angle)
def test_euler_round_trip(roll, pitch, yaw):
    R = frames.rotation_from_euler_321(roll, pitch, yaw)
    assert is_rotation(R)
    back = frames.euler_321_from_rotation(R)
    np.testing.assert_allclose(frames.rotation_from_euler_321(*back), R, atol=1e-9)
    assert math.isclose(back[1], pitch, abs_tol=1e-9)


def test_euler_at_gimbal_lock_reproduces_rotation():
    R = frames.rotation_from_euler_321(0.3, math.pi / 2, 1.0)
    roll, pitch, yaw = frames.euler_321_from_rotation(R)
    assert roll == 0.0
    np.testing.assert_allclose(frames.rotation_from_euler_321(roll, pitch, yaw), R, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(angle, pitch_angle, angle)
def test_quaternion_round_trip(roll, pitch, yaw):
    R = frames.rotation_from_euler_321(roll, pitch, yaw)
    q = frames.quaternion_from_rotation(R)
    assert q[0] >= 0 and math.isclose(np.linalg.norm(q), 1.0, abs_tol=1e-12)
    np.testing.assert_allclose(frames.rotation_from_quaternion(q), R, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(angle, pitch_angle, angle)
def test_rotvec_matches_opencv_rodrigues(roll, pitch, yaw):
    R = frames.rotation_from_euler_321(roll, pitch, yaw)
    rvec = frames.rotvec_from_rotation(R)
    np.testing.assert_allclose(frames.rotation_from_rotvec(rvec), R, atol=1e-9)
    np.testing.assert_allclose(cv2.Rodrigues(rvec)[0], R, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(angle, pitch_angle, angle, coordinate, coordinate, coordinate)
def test_transform_inverse_round_trip(roll, pitch, yaw, x, y, z):
    T = frames.make_transform(frames.rotation_from_euler_321(roll, pitch, yaw), [x, y, z])
    np.testing.assert_allclose(frames.invert_transform(T) @ T, np.eye(4), atol=1e-9)
    p = np.array([[1.0, -2.0, 3.0]])
    back = frames.transform_points(frames.invert_transform(T), frames.transform_points(T, p))
    np.testing.assert_allclose(back, p, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(st.floats(min_value=-720, max_value=720, allow_nan=False), coordinate, coordinate, coordinate)
def test_map_ned_round_trip_preserves_up(bearing_deg, x, y, z):
    T = frames.T_ned_map(bearing_deg)
    assert is_rotation(T[:3, :3])
    p_ned = frames.transform_points(T, [x, y, z])
    assert math.isclose(p_ned[2], -z, abs_tol=1e-9)
    np.testing.assert_allclose(frames.transform_points(frames.invert_transform(T), p_ned), [x, y, z], atol=1e-9)


def test_map_yaw_becomes_ned_yaw_with_bearing():
    # A body yawed by psi in the map (counter-clockwise about z up, level) has
    # NED yaw = bearing - psi (clockwise from north).
    bearing, psi = 40.0, 25.0
    R_map_body_level = np.diag([1.0, -1.0, -1.0])  # FRD with forward = map +x
    R_map_body = frames.rot_z(math.radians(psi)) @ R_map_body_level
    R_ned_body = frames.R_ned_map(bearing) @ R_map_body
    roll, pitch, yaw = frames.euler_321_from_rotation(R_ned_body)
    assert math.isclose(math.degrees(yaw), bearing - psi, abs_tol=1e-9)
    assert math.isclose(roll, 0.0, abs_tol=1e-12) and math.isclose(pitch, 0.0, abs_tol=1e-12)


def test_rotate_pose_covariance():
    cov = np.diag([1.0, 4.0, 9.0, 0.01, 0.04, 0.09])
    R = frames.R_ned_map(0.0)  # x -> north, y -> west, z -> up
    out = frames.rotate_pose_covariance(cov, R)
    np.testing.assert_allclose(np.diag(out), np.diag(cov), atol=1e-12)
    out = frames.rotate_pose_covariance(cov, frames.R_ned_map(90.0))  # x -> east, y -> north
    np.testing.assert_allclose(np.diag(out), [4.0, 1.0, 9.0, 0.04, 0.01, 0.09], atol=1e-12)


def test_rotation_angle():
    assert math.isclose(frames.rotation_angle_rad(frames.rot_z(0.3), np.eye(3)), 0.3, abs_tol=1e-12)
    assert math.isclose(frames.rotation_angle_rad(frames.rot_x(math.pi), np.eye(3)), math.pi, abs_tol=1e-7)


def test_grid_to_marker_inner_corners():
    # 6x6 data, p = 2, g = 1: o = 3, the inner square is 8 cells, u, v in [3, 11].
    uv = [[3, 3], [11, 3], [11, 11], [3, 11], [7, 7]]
    points = frames.grid_to_marker_m(uv, 3.0, 8, 0.16)
    expected = [[-0.08, 0.08, 0], [0.08, 0.08, 0], [0.08, -0.08, 0], [-0.08, -0.08, 0], [0, 0, 0]]
    np.testing.assert_allclose(points, expected, atol=1e-12)
    # One cell right and one cell down of the centre: +cell_m in x, -cell_m in y.
    np.testing.assert_allclose(frames.grid_to_marker_m([[8, 8]], 3.0, 8, 0.16), [[0.02, -0.02, 0]], atol=1e-12)


@pytest.mark.parametrize("inner_cells, cell_m", [(7, 0.15 / 7), (10, 0.015)], ids=["5x5", "8x8"])
def test_grid_to_marker_other_dictionaries(inner_cells, cell_m):
    # 5x5 data: a 7-cell inner square; 8x8: 10 cells. With o = 5 and a 0.15 m square:
    # its corners at +-0.075 m, the centre at u = v = o + c/2, one cell = 0.15 / c.
    o, c = 5.0, inner_cells
    uv = [[o, o], [o + c, o + c], [o + c / 2, o + c / 2], [o + c / 2 + 1, o + c / 2 - 2], [o - 2, o - 2]]
    expected = [[-0.075, 0.075, 0], [0.075, -0.075, 0], [0, 0, 0], [cell_m, 2 * cell_m, 0],
                [-0.075 - 2 * cell_m, 0.075 + 2 * cell_m, 0]]
    np.testing.assert_allclose(frames.grid_to_marker_m(uv, o, c, 0.15), expected, atol=1e-12)
