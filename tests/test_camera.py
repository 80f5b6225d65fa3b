"""Camera model: loading (plain YAML and OpenCV FileStorage), mounting, projection, errors."""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.geometry import frames
from companion.geometry.camera import CameraError, CameraModel, load_camera, read_opencv_calibration

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "config" / "camera-example.yaml"

K_TRUE = np.array([[600.0, 0.0, 330.0], [0.0, 590.0, 235.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.21, 0.08, 0.001, -0.0005, -0.01])


def write_opencv_calibration(path, K=K_TRUE, dist=DIST_TRUE, width=640, height=480):
    """Write a calibration exactly as OpenCV's calibration sample does (cv2.FileStorage)."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("calibration_time", "Tue Nov 24 2026")
    storage.write("image_width", width)
    storage.write("image_height", height)
    storage.write("camera_matrix", K)
    storage.write("distortion_coefficients", dist.reshape(-1, 1))
    storage.write("avg_reprojection_error", 0.21)
    storage.release()
    return path


def inline(**overrides):
    section = {"width": 640, "height": 480, "fx_px": 500.0, "fy_px": 500.0, "cx_px": 320.0, "cy_px": 240.0}
    section.update(overrides)
    return {k: v for k, v in section.items() if v is not None}


# ------------------------------------------------------------------ loading

def test_example_config_loads():
    camera = load_camera(EXAMPLE)
    assert (camera.width, camera.height) == (640, 480)
    assert 69.0 < camera.hfov_deg < 71.0
    np.testing.assert_allclose(camera.T_body_camera[:3, 3], [0.10, 0.0, 0.05])
    # Tilted 20 degrees down: the optical axis has a positive (down) body z component.
    axis = camera.T_body_camera[:3, :3] @ [0, 0, 1]
    np.testing.assert_allclose(axis, [math.cos(math.radians(20)), 0, math.sin(math.radians(20))], atol=1e-12)


def test_opencv_calibration_file(tmp_path):
    path = write_opencv_calibration(tmp_path / "calib.yaml")
    assert "!!opencv-matrix" in path.read_text()
    camera = load_camera(path)
    np.testing.assert_allclose(camera.K, K_TRUE)
    np.testing.assert_allclose(camera.dist, DIST_TRUE)
    assert (camera.width, camera.height) == (640, 480)
    np.testing.assert_allclose(camera.T_body_camera[:3, :3], frames.R_body_camera_from_mount())


OPENCV4_CALIBRATION = """%YAML:1.0
---
calibration_time: "Mon 23 Nov 2026 10:00:00 UTC"
image_width: 1280
image_height: 720
board_width: 9
board_height: 6
square_size: 2.4999999441206455e-02
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 9.1234e+02, 0., 6.4012e+02, 0., 9.1098e+02, 3.5977e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ 1.2e-01, -2.5e-01, 1.0e-03, -2.0e-04, 1.1e-01 ]
avg_reprojection_error: 2.8e-01
"""


def test_opencv4_calibration_text(tmp_path):
    path = tmp_path / "out_camera_data.yml"
    path.write_text(OPENCV4_CALIBRATION)
    camera = load_camera(path)
    assert (camera.width, camera.height) == (1280, 720)
    np.testing.assert_allclose(camera.K[0], [912.34, 0.0, 640.12])
    np.testing.assert_allclose(camera.dist, [0.12, -0.25, 0.001, -0.0002, 0.11])


def test_config_section_with_relative_calibration_file(tmp_path):
    write_opencv_calibration(tmp_path / "calib.yaml")
    config = tmp_path / "companion.yaml"
    config.write_text(yaml.safe_dump({"camera": {"calibration_file": "calib.yaml", "mount": {"facing": "down"}}}))
    camera = load_camera(config)
    np.testing.assert_allclose(camera.K, K_TRUE)
    np.testing.assert_allclose(camera.T_body_camera[:3, :3] @ [0, 0, 1], [0, 0, 1], atol=1e-12)


def test_hfov_section():
    camera = CameraModel.from_config(inline(fx_px=None, fy_px=None, cx_px=None, cy_px=None, hfov_deg=70.0), "x.yaml")
    assert math.isclose(camera.hfov_deg, 70.0, abs_tol=1e-9)
    assert camera.K[0, 2] == 319.5 and camera.K[1, 2] == 239.5


def test_to_config_round_trip():
    section = inline(distortion=[0.1, -0.02, 0.0, 0.001, 0.0], mount={"lever_arm_m": [0.1, -0.02, 0.03], "facing": "left", "tilt_down_deg": 15})
    camera = CameraModel.from_config(section, "x.yaml")
    again = CameraModel.from_config(yaml.safe_load(yaml.safe_dump(camera.to_config())), "y.yaml")
    np.testing.assert_allclose(again.K, camera.K)
    np.testing.assert_allclose(again.dist, camera.dist)
    np.testing.assert_allclose(again.T_body_camera, camera.T_body_camera, atol=1e-12)


@pytest.mark.parametrize(
    "mount, axis_in_body, right_in_body",
    [
        ({}, [1, 0, 0], [0, 1, 0]),
        ({"facing": "backward"}, [-1, 0, 0], [0, -1, 0]),
        ({"facing": "right"}, [0, 1, 0], [-1, 0, 0]),
        ({"facing": "left"}, [0, -1, 0], [1, 0, 0]),
        ({"facing": "down"}, [0, 0, 1], [0, 1, 0]),
        ({"facing": "up"}, [0, 0, -1], [0, 1, 0]),
        ({"pitch_deg": -90.0, "yaw_deg": 90.0}, [0, 0, 1], [-1, 0, 0]),
    ],
)
def test_mount_directions(mount, axis_in_body, right_in_body):
    camera = CameraModel.from_config(inline(mount=mount), "x.yaml")
    R = camera.T_body_camera[:3, :3]
    np.testing.assert_allclose(R @ [0, 0, 1], axis_in_body, atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], right_in_body, atol=1e-12)


# --------------------------------------------------------------- projection

def test_project_matches_pinhole_without_distortion():
    camera = CameraModel.from_config(inline(), "x.yaml")
    px = camera.project([[0.2, -0.1, 2.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(px, [[320 + 500 * 0.1, 240 - 500 * 0.05], [320, 240]], atol=1e-9)


def test_points_behind_the_camera_are_nan():
    camera = CameraModel.from_config(inline(), "x.yaml")
    px = camera.project([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    assert np.isnan(px[0]).all() and np.isfinite(px[1]).all()


def test_undistort_inverts_project(tmp_path):
    camera = load_camera(write_opencv_calibration(tmp_path / "calib.yaml"))
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.35, 0.35, 50), np.ones(50)])
    px = camera.project(points)
    assert np.abs(px - CameraModel(K_TRUE, np.zeros(5), 640, 480, np.eye(4)).project(points)).max() > 1.0
    np.testing.assert_allclose(camera.normalized(px), points[:, :2], atol=1e-6)
    np.testing.assert_allclose(camera.undistort_px(px), (points[:, :2] * [600, 590]) + [330, 235], atol=1e-3)


def test_projection_jacobian_by_hand_and_by_differences(tmp_path):
    # Pinhole: u = fx X/Z + cx, v = fy Y/Z + cy, so du/dX = fx/Z, du/dZ = -fx X/Z^2, dv/dY = fy/Z, dv/dZ = -fy Y/Z^2.
    pinhole = CameraModel.from_config(inline(), "x.yaml")
    J = pinhole.projection_jacobian([[0.2, -0.1, 2.0]])
    np.testing.assert_allclose(J[0], [[250.0, 0.0, -25.0], [0.0, 250.0, 12.5]], atol=1e-9)
    # With distortion: central differences of project().
    camera = load_camera(write_opencv_calibration(tmp_path / "calib.yaml"))
    points = np.array([[0.3, -0.2, 1.5], [-0.4, 0.3, 1.0], [0.0, 0.05, 3.0]])
    step = 1e-6
    numeric = np.stack([(camera.project(points + step * e) - camera.project(points - step * e)) / (2 * step)
                        for e in np.eye(3)], axis=2)
    np.testing.assert_allclose(camera.projection_jacobian(points), numeric, rtol=1e-6, atol=1e-6)


def test_project_from_map_frame():
    camera = CameraModel.from_config(inline(), "x.yaml")
    # Camera 2 m in front of a point on its optical axis.
    T_world_camera = frames.make_transform(np.eye(3), [1.0, 2.0, 3.0])
    px = camera.project_from(frames.invert_transform(T_world_camera), [[1.0, 2.0, 5.0]])
    np.testing.assert_allclose(px, [[320, 240]], atol=1e-9)
    assert camera.in_image(px).all()
    assert not camera.in_image([[-3.0, 10.0], [700.0, 10.0]]).any()


# ------------------------------------------------------------------- errors

@pytest.mark.parametrize(
    "section, key, words",
    [
        (inline(width=0), "camera.width", "positive integer"),
        (inline(height=480.5), "camera.height", "positive integer"),
        (inline(fx_px=-1.0), "camera.fx_px", "positive"),
        (inline(cy_px=None), "camera.cy_px", "missing"),
        (inline(cx_px=900.0), "camera.cx_px", "outside"),
        (inline(hfov_deg=70.0), "camera.hfov_deg", "not both"),
        (inline(distortion=[0.1, 0.2]), "camera.distortion", "list of"),
        (inline(distortion=[0.1, 0.2, 0.0, "x"]), "camera.distortion", "finite"),
        (inline(lens="wide"), "camera.lens", "unknown key"),
        (inline(mount={"facing": "sideways"}), "camera.mount.facing", "must be one of"),
        (inline(mount={"facing": "down", "tilt_down_deg": 10}), "camera.mount.tilt_down_deg", "horizontal"),
        (inline(mount={"facing": "forward", "pitch_deg": -10}), "camera.mount.pitch_deg", "not both"),
        (inline(mount={"lever_arm_m": [0.1, 0.2]}), "camera.mount.lever_arm_m", "metres"),
        (inline(mount={"tilt": 3}), "camera.mount.tilt", "unknown key"),
        (inline(calibration_file="c.yaml"), "camera.width", "remove the inline"),
    ],
)
def test_section_errors_name_file_and_key(section, key, words):
    with pytest.raises(CameraError) as info:
        CameraModel.from_config(section, "conf/drone.yaml")
    message = str(info.value)
    assert message.startswith("conf/drone.yaml: ")
    assert f"'{key}'" in message and words in message


def test_calibration_file_errors(tmp_path):
    with pytest.raises(CameraError, match="no such file"):
        read_opencv_calibration(tmp_path / "missing.yaml")
    bad = write_opencv_calibration(tmp_path / "bad_k.yaml", K=np.eye(2))
    with pytest.raises(CameraError, match=r"bad_k.yaml: key 'camera_matrix': must be 3x3"):
        read_opencv_calibration(bad)
    storage = cv2.FileStorage(str(tmp_path / "no_dist.yaml"), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("camera_matrix", K_TRUE)
    storage.release()
    with pytest.raises(CameraError, match=r"no_dist.yaml: key 'distortion_coefficients': missing"):
        read_opencv_calibration(tmp_path / "no_dist.yaml")
    bad = write_opencv_calibration(tmp_path / "bad_size.yaml", width=-5)
    with pytest.raises(CameraError, match=r"key 'image_width'"):
        read_opencv_calibration(bad)


def test_malformed_files(tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("camera: [unclosed\n")
    with pytest.raises(CameraError, match="not valid YAML"):
        load_camera(broken)
    with pytest.raises(CameraError, match="cannot read"):
        load_camera(tmp_path / "nothing.yaml")
    broken.write_text("camera: 5\n")
    with pytest.raises(CameraError, match="broken.yaml: section 'camera'"):
        load_camera(broken)
