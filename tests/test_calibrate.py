"""Calibration recovers the intrinsics of a rendered camera from chessboard views; the command's options are
checked before the work, and Ctrl-C on a recording writes nothing."""
import csv
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import cli
from companion.geometry import frames
from companion.geometry.calibration import Board, CalibrationError, CharucoBoard, calibrate
from companion.geometry.camera import load_camera
from companion.markers.charuco import CharucoSpec
from companion.sim.board_views import BoardCamera, view_poses
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


def test_a_view_of_another_size_is_named_and_left_out_whichever_sorts_first(views):
    odd = {"aaa.png": cv2.resize(views["view0.png"], (1280, 960))}
    result = calibrate({**odd, **views}, BOARD)
    assert ("aaa.png", "1280x960, not 640x480 like most views") in result.rejected
    np.testing.assert_allclose(result.K, K_TRUE, rtol=0.01, atol=2.0)


def test_cli_names_an_empty_folder(tmp_path):
    run = subprocess.run([sys.executable, "-m", "companion", "calibrate", str(tmp_path)], capture_output=True, text=True)
    assert run.returncode == 2 and f"{tmp_path}: no images in the folder (.bmp, " in run.stderr


# ------------------------------------------------------------ the command's options

@pytest.fixture
def images(tmp_path) -> Path:
    folder = tmp_path / "images"
    folder.mkdir()
    for name in ("one.png", "two.png"):
        cv2.imwrite(str(folder / name), np.full((120, 160), 200, np.uint8))
    return folder


@pytest.mark.parametrize("options, message", [
    (["--coverage", "2"], "--coverage must be more than 0 and at most 1 (the share of the image covered: 0.7 is 70 %), "
                          "not 2"),
    (["--coverage", "nan"], "--coverage must be more than 0 and at most 1 (the share of the image covered: 0.7 is "
                            "70 %), not nan"),
    (["--min-views", "0"], "--min-views must be 5 to 50 (a calibration needs 5 views, capture stops at 50), not 0"),
    (["--min-views", "80"], "--min-views must be 5 to 50 (a calibration needs 5 views, capture stops at 50), not 80"),
    (["--width", "-5"], "--width must be a positive number of pixels, not -5"),
    (["--height", "0"], "--height must be a positive number of pixels, not 0"),
    (["--square-mm", "inf"], "--square-mm must be a positive number of millimetres, not inf"),
    (["--board", "9x6", "--marker-mm", "16"], "--marker-mm: for a ChArUco board only, not a chessboard (--board)"),
])
def test_an_option_out_of_range_is_refused_before_the_camera_is_opened(tmp_path, capsys, options, message):
    """--coverage 2 ('200 % of the image covered') was a goal never met, --min-views 0 and --width -5 were taken."""
    out = tmp_path / "camera.yaml"
    assert cli.main(["calibrate", "--device", "/dev/video97", *options, "--out", str(out)]) == 2
    assert capsys.readouterr().err == f"companion calibrate: {message}\n"
    assert not out.exists()


@pytest.mark.parametrize("options, message", [
    (["--coverage", "0.5"], "--coverage: for live capture (--device) only, not images or videos"),
    (["--min-views", "20", "--width", "1280", "--height", "720"], "--min-views, --width, --height: for live capture "
                                                                  "(--device) only, not images or videos"),
    (["--save-views", "{tmp}/views"], "--save-views: for views taken live (--device) or from videos, not images "
                                      "(they are the views)"),
])
def test_a_live_capture_option_with_images_is_refused_not_ignored(tmp_path, images, capsys, options, message):
    out = tmp_path / "camera.yaml"
    options = [option.format(tmp=tmp_path) for option in options]
    assert cli.main(["calibrate", str(images), *options, "--out", str(out)]) == 2
    assert capsys.readouterr().err == f"companion calibrate: {message}\n"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["images"]  # no camera file, no views folder


# ------------------------------------------------------------ Ctrl-C

LENS = (np.array([[478.0, 0.0, 322.5], [0.0, 478.0, 236.0], [0.0, 0.0, 1.0]]), np.array([-0.10, 0.02, 0, 0, 0]))


def board_recording(folder: Path, poses: int = 10, still_frames: int = 6, tail_frames: int = 1500) -> Path:
    """A sequence folder of the ChArUco board held still at ``poses`` places (``still_frames`` each), then at the
    last one for ``tail_frames`` frames more: the run goes on well after its last view. One PNG per pose,
    named again in timestamps.csv for each frame of it."""
    camera, spec = BoardCamera(CharucoSpec(), LENS), CharucoSpec()
    rendered = (camera.render(T) for T in view_poses(LENS, 30, seed=1))
    images = [image for image in rendered if not isinstance(CharucoBoard(spec).find(image), str)][:poses]
    folder.mkdir()
    names = []
    for k, image in enumerate(images):
        cv2.imwrite(str(folder / f"pose{k}.png"), image)
        names += [f"pose{k}.png"] * still_frames
    names += [names[-1]] * tail_frames
    with open(folder / "timestamps.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(("frame", "t_ns", "file"))
        writer.writerows((index, index * 33_333_333, name) for index, name in enumerate(names))
    return folder


def as_video(sequence: Path, video: Path) -> Path:
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480), isColor=False)
    with open(sequence / "timestamps.csv", newline="") as handle:
        for row in csv.DictReader(handle):
            writer.write(cv2.imread(str(sequence / row["file"]), cv2.IMREAD_GRAYSCALE))
    writer.release()
    return video


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("recordings")
    sequence = board_recording(folder / "walk")
    return {"sequence": sequence, "video": as_video(sequence, folder / "board.avi")}


@pytest.mark.parametrize("kind", ["video", "sequence"])
def test_ctrl_c_on_a_recording_stops_and_writes_nothing(tmp_path, recordings, kind):
    """Ctrl-C after six views of a recording (live capture's 'stop with the views so far' before) calibrated on
    them, overwrote the camera file, saved the views and exited 0 without a word about it."""
    out, views = tmp_path / "good.yaml", tmp_path / "views"
    out.write_text("the camera file of an earlier calibration\n")
    # Ctrl-C at a terminal reaches a foreground process, whose SIGINT is at its default; a test run started in the
    # background of a script (`pytest &`) would pass it on ignored, and calibrate then rightly ignores it too
    process = subprocess.Popen([sys.executable, "-m", "companion", "calibrate", str(recordings[kind]), "--out", str(out),
                                "--save-views", str(views)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    taken = 0
    for line in process.stdout:
        taken += ": view" in line
        if taken == 6:
            process.send_signal(signal.SIGINT)
            break
    stdout, stderr = process.communicate(timeout=120)
    assert taken == 6, stdout
    assert (process.returncode, stderr) == (130, "companion calibrate: interrupted\n")
    assert "->" not in stdout  # no result
    assert out.read_text() == "the camera file of an earlier calibration\n" and not views.exists()


def test_ctrl_c_in_live_capture_still_calibrates_on_the_views_so_far(tmp_path, recordings, monkeypatch, capsys):
    """The documented --device behaviour, kept: Ctrl-C stops the capture and calibrates on the views taken (a
    camera played by the recording, interrupted after its sixth view)."""
    from companion.capture import v4l2
    from companion.capture.replay import replay_source

    class Camera:
        """The recording as a started camera; Ctrl-C (SIGINT to this process) once 6 views' frames were given."""

        def __init__(self):
            self.replay, self.given = replay_source(recordings["sequence"], realtime=False), 0
            self.connected, self.lost_reason = type("Connected", (), {"wait": lambda self, timeout: True})(), None

        def start(self):
            self.replay.start()

        def get(self, timeout_s):
            self.given += 1
            if self.given == 6 * 6 + 2:
                signal.raise_signal(signal.SIGINT)
            return self.replay.get(timeout_s)

        def close(self):
            self.replay.close()

        @property
        def finished(self):
            return self.replay.finished

    device = tmp_path / "video0"
    device.write_text("")
    monkeypatch.setattr(v4l2, "device_path", lambda name: str(device))
    monkeypatch.setattr(v4l2, "v4l2_source", lambda *args, **kwargs: Camera())
    unhandled = []
    previous = signal.signal(signal.SIGINT, lambda *_: unhandled.append(True))  # not a KeyboardInterrupt in pytest
    try:
        code = cli.main(["calibrate", "--device", str(device), "--save-views", str(tmp_path / "views"),
                         "--out", str(tmp_path / "camera.yaml")])
    finally:
        signal.signal(signal.SIGINT, previous)
    stdout = capsys.readouterr().out
    assert (code, unhandled) == (0, []), stdout
    assert "6 views taken" in stdout and "6 of 6 views" not in stdout and "-> " in stdout
    assert load_camera(tmp_path / "camera.yaml").width == 640
    assert len(list((tmp_path / "views").glob("*.png"))) == 6
