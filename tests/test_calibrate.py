"""Calibration recovers the intrinsics of a rendered camera from chessboard views."""
import subprocess
import sys

import cv2
import numpy as np
import pytest

from companion.geometry import frames
from companion.geometry.calibration import Board, CalibrationError, calibrate
from companion.geometry.camera import load_camera
from companion.sim.raster import Renderer, TexturedQuad, make_texture, rectangle_corners

K_TRUE = np.array([[520.0, 0.0, 322.0], [0.0, 518.0, 236.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.12, 0.03, 0.0, 0.0, 0.0])
BOARD = Board(columns=8, rows=5, square_m=0.03)


def chessboard_quad(board: Board, px_per_square: int = 40) -> TexturedQuad:
    squares = np.indices((board.rows + 1, board.columns + 1)).sum(axis=0) % 2
    image = np.kron(squares, np.ones((px_per_square, px_per_square))).astype(np.uint8) * 255
    image = np.pad(image, px_per_square, constant_values=255)
    width_m = (board.columns + 3) * board.square_m
    height_m = (board.rows + 3) * board.square_m
    return TexturedQuad(rectangle_corners(np.eye(4), width_m, height_m), make_texture(image), gain=0.8, offset=20)


def look_at(eye_m, target_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_camera_world of an OpenCV camera at `eye_m` looking at `target_m` (world y up)."""
    z = np.subtract(target_m, eye_m)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R_world_camera = np.column_stack([x, np.cross(z, x), z])
    return frames.invert_transform(frames.make_transform(R_world_camera, eye_m))


def rendered_views(count: int = 10) -> dict[str, np.ndarray]:
    renderer = Renderer(K_TRUE, DIST_TRUE, 640, 480)
    quad = chessboard_quad(BOARD)
    rng = np.random.default_rng(3)
    views = {}
    for i in range(count):
        eye = np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.15, 0.15), rng.uniform(0.35, 0.55)])
        target = rng.uniform(-0.05, 0.05, size=3) * [1, 1, 0]
        image = renderer.render([quad], look_at(eye, target), background=90.0).image
        views[f"view{i}.png"] = cv2.GaussianBlur(image, (0, 0), 0.7)
    return views


@pytest.fixture(scope="module")
def views():
    return rendered_views()


def test_recovers_intrinsics_and_distortion(views):
    result = calibrate(views, BOARD)
    assert len(result.views) >= 8
    np.testing.assert_allclose(result.K, K_TRUE, rtol=0.01, atol=2.0)
    assert result.dist[0] == pytest.approx(DIST_TRUE[0], abs=0.03)
    assert result.rms_px < 0.3


def test_too_few_views_is_a_clear_error(views):
    with pytest.raises(CalibrationError, match="at least 5 views"):
        calibrate(dict(list(views.items())[:2]), BOARD)


def test_cli_writes_a_file_the_camera_model_reads(views, tmp_path):
    for name, image in views.items():
        cv2.imwrite(str(tmp_path / name), image)
    out = tmp_path / "camera.yaml"
    run = subprocess.run([sys.executable, "-m", "companion", "calibrate", str(tmp_path), "--board", "8x5",
                          "--square-mm", "30", "--out", str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    camera = load_camera(out)
    assert (camera.width, camera.height) == (640, 480)
    np.testing.assert_allclose(camera.K, K_TRUE, rtol=0.01, atol=2.0)


def test_cli_rejects_a_missing_folder(tmp_path):
    run = subprocess.run([sys.executable, "-m", "companion", "calibrate", str(tmp_path / "nowhere")],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "no such file or directory" in run.stderr
