"""ChArUco boards: the printed PDF at exact scale, and calibration from rendered views of known cameras
(70 and 120 degree lenses), from image folders and live from a frame source."""
from __future__ import annotations

import csv
import math
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.capture.replay import replay_source
from companion.geometry import frames
from companion.geometry.calibration import (Board, CalibrationError, CaptureGoal, CharucoBoard, calibrate,
                                            calibrate_points, capture_live)
from companion.geometry.camera import load_camera
from companion.markers.charuco import CharucoError, CharucoSpec, charuco_pdf
from companion.sim.board_views import BoardCamera, hfov_deg, look_at, view_poses

SPEC = CharucoSpec()                 # 8x11 squares of 22 mm, markers 16 mm, DICT_5X5_100
# (K, dist): 640x480 cameras whose horizontal field of view is 70 and 120 degrees with their distortion
# (test_the_lenses_have_the_fields_of_view_they_are_named_for), principal points off centre; the
# 120 degree lens is strongly barrel-shaped yet monotonic over the whole image, as a real lens is.
LENS_70 = (np.array([[478.0, 0.0, 322.5], [0.0, 478.0, 236.0], [0.0, 0.0, 1.0]]), np.array([-0.10, 0.02, 0, 0, 0]))
LENS_120 = (np.array([[248.0, 0.0, 318.0], [0.0, 248.6, 243.0], [0.0, 0.0, 1.0]]),
            np.array([-0.22, 0.045, 0.0, 0.0, 0.0]))


CAMERAS = {}


def render(lens, T_camera_world, noise_seed=None) -> np.ndarray:
    """The board seen through ``lens`` (one renderer per lens: its distortion map is built once)."""
    if id(lens) not in CAMERAS:
        CAMERAS[id(lens)] = BoardCamera(SPEC, lens)
    return CAMERAS[id(lens)].render(T_camera_world, noise_seed)


def truth_of(lens) -> dict[str, float]:
    K, dist = lens
    return {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "k1": dist[0]}


def assert_meets_the_target(calibration, lens) -> None:
    """fx, fy, cx, cy within 0.5 % and k1 within 0.01 of the rendered camera's."""
    values = calibration.parameters()
    for name, truth in truth_of(lens).items():
        if name == "k1":
            assert abs(values[name] - truth) < 0.01, (name, values[name], truth)
        else:
            assert abs(values[name] - truth) / truth < 0.005, (name, values[name], truth)


def test_the_lenses_have_the_fields_of_view_they_are_named_for():
    assert hfov_deg(LENS_70) == pytest.approx(70.0, abs=1.0)
    assert hfov_deg(LENS_120) == pytest.approx(120.0, abs=1.0)


# ------------------------------------------------------------------ printing

def test_the_printed_board_is_detected_whole_at_exact_scale(tmp_path):
    """pdftoppm renders the PDF at 300 dpi: OpenCV finds all 70 corners, 22 mm apart to 0.1 %."""
    pdf = tmp_path / "board.pdf"
    pdf.write_bytes(charuco_pdf(SPEC, "a4"))
    subprocess.run(["pdftoppm", "-r", "300", "-gray", "-png", str(pdf), str(tmp_path / "page")], check=True)
    page = cv2.imread(str(next(tmp_path.glob("page*.png"))), cv2.IMREAD_GRAYSCALE)
    ids, corners = CharucoBoard(SPEC).detect(page)
    assert sorted(ids) == list(range(SPEC.corners))
    px_per_mm = 300 / 25.4
    # corner i is at (i % 7 + 1, i // 7 + 1) squares from the board's top-left corner (OpenCV's numbering)
    board_mm = np.array([((i % 7 + 1) * 22.0, (i // 7 + 1) * 22.0) for i in ids])
    H, _ = cv2.findHomography(board_mm, corners)
    H /= H[2, 2]
    # a pure scale (no rotation, shear or perspective) of exactly 300 dpi, to 0.1 %
    np.testing.assert_allclose(H[:2, :2], np.eye(2) * px_per_mm, atol=0.001 * px_per_mm)
    assert abs(H[2, 0]) < 1e-5 and abs(H[2, 1]) < 1e-5
    # centred on the page horizontally: the board is 176 mm wide on a 210 mm sheet
    assert H[0, 2] / px_per_mm == pytest.approx((210 - 176) / 2, abs=0.2)


def test_markers_cli_writes_the_board_and_names_its_calibrate_options(tmp_path):
    run = subprocess.run([sys.executable, "-m", "companion", "markers", "--charuco", "6x8", "--square-mm", "30",
                          "--marker-mm", "22", "--out", str(tmp_path)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "charuco-6x8-30mm-22mm-a4.pdf").is_file()
    assert "--charuco 6x8 --square-mm 30 --marker-mm 22" in run.stdout and "35 corners" in run.stdout


@pytest.mark.parametrize("options, message", [
    (["--charuco", "12x16", "--square-mm", "30"], "more than one A4 page offers"),
    (["--charuco", "--marker-mm", "25"], "must be positive and smaller than the square"),
    (["--charuco", "--aruco-dictionary", "DICT_9X9"], "unknown OpenCV dictionary"),
    (["--charuco", "20x20", "--square-mm", "5", "--marker-mm", "3"], "more than the 100 of DICT_5X5_100"),
])
def test_a_board_that_cannot_be_printed_is_a_one_line_error(tmp_path, options, message):
    run = subprocess.run([sys.executable, "-m", "companion", "markers", *options, "--out", str(tmp_path)],
                         capture_output=True, text=True)
    assert run.returncode == 2 and message in run.stderr and run.stderr.count("\n") == 1


def test_spec_rejects_a_marker_larger_than_its_square():
    with pytest.raises(CharucoError):
        CharucoSpec(marker_mm=30.0)


# --------------------------------------------------------------- calibration

@pytest.mark.parametrize("lens", [LENS_70, LENS_120], ids=["70deg", "120deg"])
def test_calibration_recovers_the_rendered_camera(lens):
    views = {f"view{i:02d}": render(lens, T) for i, T in enumerate(view_poses(lens, 30, seed=1))}
    calibration = calibrate(views, CharucoBoard(SPEC))
    assert_meets_the_target(calibration, lens)
    assert calibration.rms_px < 0.3 and len(calibration.views) >= 10
    # every view is used or named with its reason; partial views count
    assert set(calibration.views) | {name for name, _ in calibration.rejected} == set(views)
    assert all("corners found" in reason for _, reason in calibration.rejected)
    assert min(len(p) for p, _ in [CharucoBoard(SPEC).find(views[v]) for v in calibration.views]) < SPEC.corners
    # the fit's own uncertainty of the pinhole parameters is honest: the truth within 5 standard deviations
    for name in ("fx", "fy", "cx", "cy"):
        assert abs(calibration.parameters()[name] - truth_of(lens)[name]) < 5 * calibration.std[name], name


def test_a_partial_view_counts_for_charuco_but_not_for_a_chessboard():
    # the camera looks past the board's edge: a third of it is out of the image
    T = look_at([0.0, 0.0, 0.25], [0.0, 0.0, 0.0])
    T = frames.make_transform(frames.rot_y(math.radians(-25)), np.zeros(3)) @ T
    image = render(LENS_70, T)
    image_points, board_points = CharucoBoard(SPEC).find(image)
    assert 20 <= len(image_points) < SPEC.corners
    assert isinstance(Board(7, 10, 0.022).find(image), str)
    # the board points are where OpenCV's board says those corners are
    assert set(np.round(board_points[:, :2] / 0.022).astype(int).ravel()) <= set(range(1, 11))


def test_a_warped_view_is_left_out_as_an_outlier_and_named():
    """A sheet that is not flat (or a rolling shutter's wobble): a 2 px ripple across one view."""
    views = {f"view{i:02d}": render(LENS_70, T) for i, T in enumerate(view_poses(LENS_70, 30, seed=1))}
    corners = {name: len(result[0]) for name in views
               if not isinstance(result := CharucoBoard(SPEC).find(views[name]), str)}
    warped = max(corners, key=corners.get)   # the view with the most corners
    x, y = np.meshgrid(np.arange(640, dtype=np.float32), np.arange(480, dtype=np.float32))
    ripple_x = (x + 2.0 * np.sin(y / 40.0)).astype(np.float32)
    views[warped] = cv2.remap(views[warped], ripple_x, y, cv2.INTER_LINEAR, borderValue=90)
    calibration = calibrate(views, CharucoBoard(SPEC))
    reasons = dict(calibration.rejected)
    assert warped in reasons and "reprojection error" in reasons[warped], reasons.get(warped)
    assert_meets_the_target(calibration, LENS_70)


def test_a_mislocated_corner_is_dropped_before_it_pulls_the_fit():
    board = CharucoBoard(SPEC)
    views = {f"view{i:02d}": render(LENS_120, T) for i, T in enumerate(view_poses(LENS_120, 30, seed=1))}
    found = {name: result for name, image in views.items() if not isinstance(result := board.find(image), str)}
    name = next(iter(found))
    image_points, board_points = found[name]
    image_points = image_points.copy()
    image_points[0] += (30.0, -20.0)   # one corner read at the wrong place
    found[name] = (image_points, board_points)
    calibration = calibrate_points(found, (640, 480), board)
    assert calibration.dropped_corners == 1 and name in calibration.views
    assert_meets_the_target(calibration, LENS_120)


def test_too_few_views_names_the_reasons():
    views = {"blank": np.full((480, 640), 90, np.uint8)}
    with pytest.raises(CalibrationError, match=r"found in 0 of 1 images.*blank: 0 ChArUco corners found"):
        calibrate(views, CharucoBoard(SPEC))


def test_cli_calibrates_from_a_folder_and_prints_every_coefficient_with_its_uncertainty(tmp_path):
    folder = tmp_path / "views"
    folder.mkdir()
    for i, T in enumerate(view_poses(LENS_120, 30, seed=1)):
        cv2.imwrite(str(folder / f"view{i:02d}.png"), render(LENS_120, T))
    (folder / "notes.txt").write_text("not an image")
    out = tmp_path / "camera.yaml"
    run = subprocess.run([sys.executable, "-m", "companion", "calibrate", str(folder), "--charuco", "8x11",
                          "--square-mm", "22", "--marker-mm", "16", "--out", str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"):
        assert any(line.split()[:1] == [name] and "±" in line for line in run.stdout.splitlines()), name
    assert "left out" in run.stdout and "RMS" in run.stdout
    camera = load_camera(out)
    np.testing.assert_allclose([camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]],
                               [248.0, 248.6, 318.0, 243.0], rtol=0.005)


# ----------------------------------------------------------------- live

def write_live_sequence(folder: Path, lens, poses: list[np.ndarray], still_frames: int = 6) -> None:
    """A camera's frames: the board held still at each pose (sensor noise on every frame), moved between."""
    (folder / "frames").mkdir(parents=True)
    rows, index = [], 0

    def emit(T, seed):
        nonlocal index
        name = f"frames/{index:05d}.png"
        cv2.imwrite(str(folder / name), render(lens, T, noise_seed=seed))
        rows.append((index, index * 33_333_333, name))
        index += 1

    for k, T in enumerate(poses):
        for _ in range(still_frames):
            emit(T, seed=index)
        if k + 1 < len(poses):    # two frames in motion toward the next pose
            for fraction in (0.33, 0.66):
                step = frames.make_transform(np.eye(3), fraction * (poses[k + 1][:3, 3] - T[:3, 3]))
                emit(step @ T, seed=index)
    with open(folder / "timestamps.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(("frame", "t_ns", "file"))
        writer.writerows(rows)


def test_live_capture_takes_one_view_per_still_pose_and_stops_at_the_goal(tmp_path):
    poses = [T for T in view_poses(LENS_70, 40, seed=1)
             if not isinstance(CharucoBoard(SPEC).find(render(LENS_70, T)), str)][:16]
    write_live_sequence(tmp_path / "live", LENS_70, poses)
    source = replay_source(tmp_path / "live", realtime=False)
    source.start()
    events = []
    try:
        goal = CaptureGoal(min_views=12, coverage=0.5, max_views=16)
        calibration, images = capture_live(source, CharucoBoard(SPEC), goal, on_event=events.append)
    finally:
        source.close()
    taken = [e for e in events if e.kind == "view"]
    # never a moving frame, never the same pose twice: at most one view per still pose
    assert 12 <= len(taken) <= len(poses) and len(images) == len(taken)
    assert events[-1].kind == "done"
    tried = [e for e in events if e.kind == "calibration"]
    assert tried and all("views: RMS" in e.message for e in tried)
    assert_meets_the_target(calibration, LENS_70)


def test_live_capture_with_too_few_views_is_an_error(tmp_path):
    poses = [T for T in view_poses(LENS_70, 20, seed=2)
             if not isinstance(CharucoBoard(SPEC).find(render(LENS_70, T)), str)][:3]
    write_live_sequence(tmp_path / "live", LENS_70, poses)
    source = replay_source(tmp_path / "live", realtime=False)
    source.start()
    try:
        with pytest.raises(CalibrationError, match="at least 5 views are needed"):
            capture_live(source, CharucoBoard(SPEC), CaptureGoal(min_views=12))
    finally:
        source.close()
    shutil.rmtree(tmp_path / "live")


def test_cli_calibrates_from_a_video_and_a_sequence_folder_taking_the_still_views(tmp_path):
    """A recording of the board held still at 16 poses, moved between: as a sequence folder (PNG frames) and
    as a video (MJPG), each calibrates through the command, one view per still pose (none of a moving
    frame), the views named after the recording and saved with --save-views."""
    poses = [T for T in view_poses(LENS_70, 40, seed=1)
             if not isinstance(CharucoBoard(SPEC).find(render(LENS_70, T)), str)][:16]
    write_live_sequence(tmp_path / "walk", LENS_70, poses)
    video = tmp_path / "board.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480), isColor=False)
    for path in sorted((tmp_path / "walk" / "frames").glob("*.png")):
        writer.write(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    writer.release()
    for recording in (tmp_path / "walk", video):
        out, views = tmp_path / f"{recording.name}.yaml", tmp_path / f"{recording.name}-views"
        run = subprocess.run([sys.executable, "-m", "companion", "calibrate", str(recording), "--out", str(out),
                              "--save-views", str(views)], capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        taken = [line for line in run.stdout.splitlines() if line.startswith(f"{recording.name}: view")]
        assert 12 <= len(taken) <= len(poses), run.stdout
        assert len(list(views.glob(f"{recording.name}-view*.png"))) == len(taken)
        camera = load_camera(out)
        K, truth = camera.K, LENS_70[0]
        tolerance = 0.005 if recording.is_dir() else 0.01  # JPEG-compressed frames: a little looser
        np.testing.assert_allclose([K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                                   [truth[0, 0], truth[1, 1], truth[0, 2], truth[1, 2]], rtol=tolerance)


def test_cli_views_from_a_video_need_a_charuco_board_seen_still(tmp_path):
    video = tmp_path / "board.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480), isColor=False)
    for _ in range(10):
        writer.write(np.full((480, 640), 128, np.uint8))
    writer.release()

    def calibrate(*options: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "companion", "calibrate", str(video), *options,
                               "--out", str(tmp_path / "c.yaml")], capture_output=True, text=True, timeout=60)

    run = calibrate("--board", "9x6")
    assert run.returncode == 2 and run.stderr == f"companion calibrate: {video}: views from a video need a ChArUco board, not --board\n"
    run = calibrate()
    assert run.returncode == 2 and run.stdout == "board.avi: 0 views in 10 frames\n"
    assert run.stderr == f"companion calibrate: {video}: the board never rested in view (a view: its corners still for 4 frames, somewhere new)\n"
    assert not (tmp_path / "c.yaml").exists()
