"""The RS marker detector on rendered frames: both paths, occlusions, rotations, rejections."""
from __future__ import annotations

import json
import math
import threading
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.geometry import frames
from companion.sim import degrade
from companion.sim import occluders
from companion.sim import raster
from companion.sim import scenes
from companion.geometry.camera import CameraModel, intrinsics_from_hfov
from companion.detect import homography
from companion.detect.circles import CircleParams
from companion.detect.detector import Detector, DetectorError, DetectorParams
from companion.detect.smear import Smear, SmearParams, deconvolve
from companion.detect.square import SquareParams
from companion.markers.codec import GridDecoder
from companion.markers.layout import UNKNOWN, MarkerLayout
from companion.params import ParamsError

W, H = 640, 480
SIZE_M = 0.15
GOLDEN = sorted((Path(__file__).parent / "data" / "detector").glob("*.json"))
# max corner error against the renderer's ground truth: the square path reads its
# corners from the edges; the circles path extrapolates hidden corners
GOLDEN_TOLERANCE_PX = {"square": 0.4, "circles": 0.75}


def facing_pose(distance_m: float, spin_deg: float = 0.0, tilt_deg: float = 0.0,
                offset_px=(0.0, 0.0)) -> np.ndarray:
    """T_camera_marker of an upright marker ahead of the camera, spun about its normal, then tilted."""
    K = intrinsics_from_hfov(W, H, 70.0)
    R = (frames.rot_y(math.radians(tilt_deg)) @ frames.rot_z(math.radians(spin_deg))
         @ frames.R_camera_marker_face_on())
    centre = distance_m * np.linalg.solve(K, [K[0, 2] + offset_px[0], K[1, 2] + offset_px[1], 1.0])
    return frames.make_transform(R, centre)


def render_scene(textures_and_poses, occluders=(), background=150.0, blur_sigma_px=0.6, seed=0, dist=np.zeros(5)):
    """Render markers (and occluder quads) with one camera (lens ``dist``); returns (image, truths)."""
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), dist, W, H)
    quads, placed = [], []
    for texture, T in textures_and_poses:
        quads.append(raster.marker_quad(texture, SIZE_M, T, gain=0.9, offset=10.0))
        placed.append((texture, T, len(quads) - 1))
    quads.extend(occluders)
    rendering = renderer.render(quads, np.eye(4), background)
    truths = [raster.marker_truth(renderer, rendering, t, SIZE_M, T, np.eye(4), i) for t, T, i in placed]
    rng = np.random.default_rng(seed)
    image = degrade.sensor_noise(degrade.gaussian_blur(rendering.image, blur_sigma_px), rng, 1.0, 0.02)
    return image, truths


@pytest.fixture(scope="module")
def layout():
    return MarkerLayout(parity=2)


@pytest.fixture(scope="module")
def detector():
    return Detector()


def by_id(detections):
    return {d.id: d for d in detections}


# --------------------------------------------------------------- square path

@pytest.mark.parametrize("spin_deg", [0, 90, 180, 270, 33])
def test_square_path_reads_id_and_upright_corners_at_every_rotation(layout, detector, spin_deg):
    texture = raster.rs_marker_texture(layout, 17)
    image, (truth,) = render_scene([(texture, facing_pose(1.2, spin_deg, tilt_deg=25))])
    (d,) = detector.detect(image)
    assert (d.id, d.symbol, d.path, d.corrected) == (17, "R", "square", 0)
    assert np.abs(d.corners_px - truth.corners_px).max() < 0.6
    assert d.quality > 0.95
    assert d.circles_px.shape == (0, 2) and d.circle_ids.shape == (0,)


def test_square_path_finds_several_markers_of_parity_4():
    layout4 = MarkerLayout(parity=4)
    textures = [raster.rs_marker_texture(layout4, i) for i in (3, 41)]
    image, truths = render_scene([(textures[0], facing_pose(1.4, 10, offset_px=(-150, 0))),
                                  (textures[1], facing_pose(1.4, -80, offset_px=(150, 20)))])
    found = by_id(Detector(DetectorParams(parity=4)).detect(image))
    assert sorted(found) == [3, 41]
    for truth in truths:
        assert np.abs(found[truth.marker_id].corners_px - truth.corners_px).max() < 0.6


def test_blob_on_the_data_is_corrected_through_the_parity_ring(layout, detector):
    texture = raster.rs_marker_texture(layout, 5)
    T = facing_pose(1.3, 12)
    blob = occluders.blob_occluder(SIZE_M, T, np.random.default_rng(3), radius_fraction=0.2, level=25.0)
    image, (truth,) = render_scene([(texture, T)], occluders=[blob])
    (d,) = detector.detect(image)
    assert (d.id, d.path) == (5, "square")
    assert d.corrected >= 1
    assert np.abs(d.corners_px - truth.corners_px).max() < 0.6


def test_data_that_disagrees_with_its_parity_ring_is_rejected(layout, detector):
    # marker 9's parity ring around marker 30's data: ArUco reads id 30 from the inner square,
    # but the RS parity contradicts it, so nothing may be reported
    cells = layout.cells(9)
    inner = slice(layout.inner_origin, layout.inner_origin + layout.inner_cells)
    cells[inner, inner] = layout.cells(30)[inner, inner]
    px_per_cell, quiet = 16, 1
    image = np.where(np.kron(np.pad(cells, quiet), np.ones((px_per_cell, px_per_cell))) > 0, 0, 255).astype(np.uint8)
    corners = (layout.inner_corners_cells + quiet) * px_per_cell - 0.5
    texture = raster.MarkerTexture(image, corners, np.zeros((0, 2)), 30)
    image, _ = render_scene([(texture, facing_pose(1.2, 20))])
    aruco_ids = cv2.aruco.ArucoDetector(layout.dictionary.aruco()).detectMarkers(image)[1]
    assert aruco_ids is not None and 30 in aruco_ids.ravel()
    assert detector.detect(image) == []


def test_marker_free_frame_yields_nothing(detector):
    background = scenes.clutter_image(np.random.default_rng(4), (W, H))
    assert detector.detect(background) == []


def test_stage_times_are_reported(layout, detector):
    image, _ = render_scene([(raster.rs_marker_texture(layout, 1), facing_pose(1.0))])
    detector.detect(image)
    assert {"square", "square_decode"} <= set(detector.last_stage_ms)
    assert all(ms >= 0 for ms in detector.last_stage_ms.values())


def test_with_the_camera_a_distorted_lens_gives_corners_as_accurate_as_an_undistorted_one(layout):
    """k1 = -0.3, large tilted markers towards the image corners: the detector given the camera aligns the
    corners through the lens; against the renderer's ground truth they are at least as good as the same
    scenes through an undistorted lens (and far better than without the camera)."""
    scenes_poses = [[(3, facing_pose(0.7, 20, 25, (-190, -120))), (17, facing_pose(0.7, -30, -20, (190, 120)))],
                    [(8, facing_pose(0.6, 50, 30, (200, -110))), (41, facing_pose(0.65, 10, -30, (-200, 115)))],
                    [(25, facing_pose(0.8, -70, 15, (-220, 20))), (33, facing_pose(0.75, 80, 35, (210, 0)))]]
    K = intrinsics_from_hfov(W, H, 70.0)

    def mean_corner_error_px(dist, detector):
        errors = []
        for seed, poses in enumerate(scenes_poses):
            textures = [(raster.rs_marker_texture(layout, i), T) for i, T in poses]
            image, truths = render_scene(textures, seed=seed, dist=dist)
            found = by_id(detector.detect(image))
            assert sorted(found) == sorted(i for i, _ in poses)
            errors += [np.linalg.norm(found[i].corners_px - t.corners_px, axis=1).mean()
                       for (i, _), t in zip(poses, truths)]
        return float(np.mean(errors))

    plain, distorted = np.zeros(5), np.array([-0.3, 0.0, 0.0, 0.0, 0.0])
    undistorted_px = mean_corner_error_px(plain, Detector(camera=CameraModel(K, plain, W, H, np.eye(4))))
    distorted_px = mean_corner_error_px(distorted, Detector(camera=CameraModel(K, distorted, W, H, np.eye(4))))
    without_camera_px = mean_corner_error_px(distorted, Detector())
    # measured: 0.025 px undistorted, 0.008 px distorted with the camera, 0.54 px without it
    assert distorted_px <= undistorted_px
    assert distorted_px < 0.1 * without_camera_px


# ------------------------------------------------------------ golden frames

def test_golden_frames_exist_for_every_case():
    notes = {path.stem for path in GOLDEN}
    assert {"square_rotations", "circles_rotations", "strip_1_8", "strip_1_4", "strip_1_4_parity4", "blob",
            "marker_free_clutter", "other_families", "too_occluded", "side_corners", "clean_beside_occluded",
            "motion_blur", "motion_blur_small", "dim_small", "thin_oblique_blurred", "round_blur",
            "noisy_small", "dim_oblique", "walk_smeared_small", "walk_smeared_deconvolved"} <= notes


@pytest.mark.parametrize("golden", GOLDEN, ids=lambda path: path.stem)
def test_golden_frame(golden):
    expected = json.loads(golden.read_text())
    image = cv2.imread(str(golden.with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
    params = {None: DetectorParams, "for_footage": DetectorParams.for_footage}[expected.get("params")]
    detector = Detector(params(parity=expected["parity"]))
    found = detector.detect(image)
    assert sorted(d.id for d in found) == sorted(m["id"] for m in expected["markers"]), expected["note"]
    layout = detector.layout
    for marker in expected["markers"]:
        d = by_id(found)[marker["id"]]
        assert (d.symbol, d.path) == (marker["symbol"], marker["path"])
        error = np.abs(d.corners_px - np.array(marker["corners"])).max()
        assert error < GOLDEN_TOLERANCE_PX[d.path], (marker["symbol"], error)
        if marker["occlusion"] != "none":
            # a 1/8 strip may hide one parity copy only
            assert d.corrected >= 1 or marker["occlusion"] in ("strip_1_8", "side_1_8")
        if d.path == "circles":
            assert_circles_consistent(d, layout)


def assert_circles_consistent(d, layout):
    """circle_ids are distinct layout circles on 2+ corners, and circles_px lie where the
    detection's own corners put them (within a quarter cell)."""
    ids = np.asarray(d.circle_ids)
    assert len(ids) >= 5 and len(set(ids.tolist())) == len(ids) and ids.min() >= 0 and ids.max() < 12
    assert len(set((ids // 3).tolist())) >= 2
    H_grid, _ = cv2.findHomography(layout.inner_corners_cells, d.corners_px, 0)
    expected = cv2.perspectiveTransform(layout.circles[ids, :2].reshape(1, -1, 2), H_grid)[0]
    cell_px = np.linalg.norm(d.corners_px[1] - d.corners_px[0]) / layout.inner_cells
    assert np.linalg.norm(expected - d.circles_px, axis=1).max() < 0.25 * cell_px


# ------------------------------------------------------------- motion smear

def golden(name: str):
    path = Path(__file__).parent / "data" / "detector" / f"{name}.json"
    return cv2.imread(str(path.with_suffix(".png")), cv2.IMREAD_GRAYSCALE), json.loads(path.read_text())


def test_a_small_smeared_marker_is_found_only_with_the_smear_undone():
    # 38 px marker under a 9 px smear: ArUco finds no quad for it; the 67 px one beside it shows the smear
    image, expected = golden("motion_blur_small")
    small = expected["markers"][1]
    without = Detector(DetectorParams(smear=SmearParams(recover=False))).detect(image)
    assert small["id"] not in by_id(without)
    found = by_id(Detector().detect(image))
    assert small["id"] in found
    assert np.abs(found[small["id"]].corners_px - np.array(small["corners"])).max() < GOLDEN_TOLERANCE_PX["square"]


def test_a_dim_frame_is_thresholded_with_a_lower_offset():
    # mean gray 20, the marker's contrast 24: ArUco's usual 7-gray offset finds no quad for it
    image, expected = golden("dim_small")
    marker = expected["markers"][0]
    assert cv2.mean(image)[0] < SquareParams().dim_frame_mean_gray
    without = Detector(DetectorParams(square=SquareParams(dim_frame_mean_gray=0.0))).detect(image)
    assert marker["id"] not in by_id(without)
    found = by_id(Detector().detect(image))
    assert marker["id"] in found
    assert np.abs(found[marker["id"]].corners_px - np.array(marker["corners"])).max() < GOLDEN_TOLERANCE_PX["square"]


@pytest.mark.parametrize("name", ["noisy_small", "dim_oblique"])
def test_a_noisy_or_dim_frame_is_read_again_with_a_small_threshold_window(name):
    # grain (sd 12) or a dim frame (mean gray 20) breaks up a small marker's quad at the usual 15 px window
    image, expected = golden(name)
    marker = expected["markers"][0]
    without = Detector(DetectorParams(square=SquareParams(small_window_px=15))).detect(image)
    assert marker["id"] not in by_id(without)
    found = by_id(Detector().detect(image))
    assert marker["id"] in found
    assert np.abs(found[marker["id"]].corners_px - np.array(marker["corners"])).max() < GOLDEN_TOLERANCE_PX["square"]


def test_the_survey_detector_reads_every_frame_again_with_the_small_window():
    # a walk's 20 px marker smeared by about 2 px in a frame that looks neither blurred, dim nor noisy
    image, expected = golden("walk_smeared_small")
    clean, smeared = expected["markers"]
    default = Detector()
    assert set(by_id(default.detect(image))) == {clean["id"]}
    assert "small_window" not in default.last_stage_ms
    assert not DetectorParams().square.small_window_every_frame
    footage = Detector(DetectorParams.for_footage())
    found = by_id(footage.detect(image))
    assert set(found) == {clean["id"], smeared["id"]}
    assert "small_window" in footage.last_stage_ms
    assert np.abs(found[smeared["id"]].corners_px - np.array(smeared["corners"])).max() < GOLDEN_TOLERANCE_PX["square"]


def test_the_survey_detector_reads_a_deconvolved_frame_with_the_small_window_too():
    # a 21 px marker of a walk, found on neither the frame nor its deconvolution with the usual window alone
    image, expected = golden("walk_smeared_deconvolved")
    clean, smeared = expected["markers"]
    footage = DetectorParams.for_footage()
    found = by_id(Detector(footage).detect(image))
    assert set(found) == {clean["id"], smeared["id"]}
    assert np.abs(found[smeared["id"]].corners_px - np.array(smeared["corners"])).max() < GOLDEN_TOLERANCE_PX["square"]
    no_smear = replace(footage, smear=replace(footage.smear, recover=False))
    assert set(by_id(Detector(no_smear).detect(image))) == {clean["id"]}
    no_small_window = replace(footage, square=replace(footage.square, small_window_every_frame=False))
    assert set(by_id(Detector(no_small_window).detect(image))) == {clean["id"]}


def test_with_expected_places_the_small_window_pass_runs_only_for_a_missing_marker_while_few_are_found():
    # in noisy_small the usual window finds LEFT (38) and the small window UP (36)
    image, expected = golden("noisy_small")
    corners = {m["id"]: np.array(m["corners"]) for m in expected["markers"]}
    both_expected = np.stack([corners[38], corners[36]])
    detector = Detector()
    assert set(by_id(detector.detect(image, expected_px=corners[38][None]))) == {38}
    assert "small_window" not in detector.last_stage_ms
    assert set(by_id(detector.detect(image, expected_px=both_expected))) == {36, 38}
    assert "small_window" in detector.last_stage_ms
    one_is_enough = Detector(DetectorParams(square=SquareParams(small_window_enough_markers=1)))
    assert set(by_id(one_is_enough.detect(image, expected_px=both_expected))) == {38}
    assert set(by_id(one_is_enough.detect(image))) == {36, 38}


def test_only_a_noisy_frame_is_called_noisy(layout):
    finder = Detector().square
    noisy, _ = golden("noisy_small")
    assert finder.is_noisy(noisy)
    for name in ("dim_small", "round_blur", "square_rotations", "marker_free_clutter", "motion_blur"):
        assert not finder.is_noisy(golden(name)[0]), name
    texture = raster.rs_marker_texture(layout, 7)
    clean, _ = render_scene([(texture, facing_pose(0.7, spin_deg=20, tilt_deg=15))])
    assert not finder.is_noisy(clean)
    grain = np.random.default_rng(3).normal(0.0, 12.0, clean.shape)
    assert finder.is_noisy(np.clip(clean + grain, 0, 255).astype(np.uint8))


def test_the_smear_is_measured_on_a_found_marker(detector):
    # the golden frame was smeared 9 px at 60 degrees (tests/data/detector/generate.py)
    image, expected = golden("motion_blur_small")
    large = expected["markers"][0]
    smear = detector.smear.estimate(image, large["id"], np.array(large["corners"]))
    assert abs(smear.length_px - 9.0) <= 1.0
    assert abs(math.degrees(smear.angle_rad) - 60.0) <= 6.0


def test_a_sharp_marker_shows_no_smear(layout, detector):
    texture = raster.rs_marker_texture(layout, 7)
    image, truths = render_scene([(texture, facing_pose(0.7, spin_deg=20, tilt_deg=15))])
    assert detector.smear.estimate(image, 7, truths[0].corners_px) is None
    cell_px = np.linalg.norm(truths[0].corners_px[1] - truths[0].corners_px[0]) / layout.inner_cells
    H_grid = homography.from_quad(layout.inner_corners_cells, truths[0].corners_px)
    assert np.nanmax(detector.edges.step_widths_px(image, H_grid, cell_px)) < SmearParams().min_edge_width_px


def test_deconvolution_undoes_a_known_smear(layout):
    texture = raster.rs_marker_texture(layout, 3)
    sharp, truths = render_scene([(texture, facing_pose(1.0, spin_deg=10))], blur_sigma_px=0.0)
    smeared = degrade.motion_blur(sharp, 9.0, math.radians(35))  # the simulator's own kernel
    restored = deconvolve(smeared, Smear(9.0, math.radians(35), 1.0), SmearParams().noise_to_signal)
    x0, y0 = truths[0].corners_px.min(axis=0).astype(int) - 10
    x1, y1 = truths[0].corners_px.max(axis=0).astype(int) + 10
    marker = (slice(y0, y1), slice(x0, x1))
    before = np.abs(smeared.astype(float) - sharp)[marker].mean()
    after = np.abs(restored.astype(float) - sharp)[marker].mean()
    assert after < 0.5 * before


# ------------------------------------------------------------- circles path

DICTIONARIES = ("5x5", "6x6", "8x8")
# one bound for every dictionary (measured max, 6x6: square 0.07 px, circles 0.32 px; 5x5 and 8x8: 0.05, 0.47)
SQUARE_TOLERANCE_PX, CIRCLES_TOLERANCE_PX = 0.2, 0.6


@pytest.mark.parametrize("dictionary", DICTIONARIES)
@pytest.mark.parametrize("parity", [2, 4])
def test_every_dictionary_reads_as_accurately_on_both_paths(dictionary, parity):
    """5x5 and 8x8 markers (13-20 cell grids) meet the 6x6 markers' corner accuracy against the renderer's
    ground truth: square path at five rotations, circles path with a strip over each side band (quiet zone,
    parity band and gap: 1/4 of a 6x6 p = 2 texture, the benchmark's strip_1_4)."""
    layout = MarkerLayout(parity, dictionary)
    detector = Detector(DetectorParams(parity=parity, dictionary=dictionary))
    for spin_deg in (0, 90, 180, 270, 33):
        image, (truth,) = render_scene([(raster.rs_marker_texture(layout, 17), facing_pose(1.2, spin_deg, 25))])
        (d,) = detector.detect(image)
        assert (d.id, d.path, d.corrected) == (17, "square", 0), (dictionary, spin_deg)
        assert np.abs(d.corners_px - truth.corners_px).max() < SQUARE_TOLERANCE_PX, (dictionary, spin_deg)
    band_fraction = (1 + layout.inner_origin) / (layout.n_cells + 2)  # of the texture (grid and quiet zone)
    for seed, (spin_deg, side) in enumerate(((30, "left"), (-20, "top"), (110, "right"), (200, "bottom"))):
        texture = raster.rs_marker_texture(layout, 40)
        T = facing_pose(1.0, spin_deg, 15, offset_px=(60, 20))
        strip = occluders.strip_occluder(texture, SIZE_M, T, band_fraction, side, np.random.default_rng(seed),
                                         level=60)
        image, (truth,) = render_scene([(texture, T)], occluders=[strip], seed=seed)
        (d,) = detector.detect(image)
        assert (d.id, d.path) == (40, "circles") and d.corrected >= 1, (dictionary, side)
        assert np.abs(d.corners_px - truth.corners_px).max() < CIRCLES_TOLERANCE_PX, (dictionary, side)
        assert_circles_consistent(d, layout)


def test_circles_path_reads_a_marker_cut_by_the_image_edge(layout, detector):
    # a quarter of the grid lies left of the frame: its cells are erasures, not errors
    texture = raster.rs_marker_texture(layout, 21)
    image, (truth,) = render_scene([(texture, facing_pose(0.9, 15, 10, offset_px=(-300, 0)))])
    assert not truth.corners_visible.all()
    (d,) = detector.detect(image)
    assert (d.id, d.path) == (21, "circles") and d.corrected >= 1
    visible = truth.corners_visible
    assert np.abs(d.corners_px[visible] - truth.corners_px[visible]).max() < 0.5
    assert_circles_consistent(d, layout)


def clean_and_strip_scene(layout):
    """Marker 3 clean on the left, marker 40 under a strip over a quarter of it on the right:
    (image, the strip's texture, its pose, the strip, the two markers' truths)."""
    clean_texture, strip_texture = raster.rs_marker_texture(layout, 3), raster.rs_marker_texture(layout, 40)
    T_strip = facing_pose(1.0, 30, 15, offset_px=(150, 0))
    strip = occluders.strip_occluder(strip_texture, SIZE_M, T_strip, 0.25, "left", np.random.default_rng(0), level=60)
    image, truths = render_scene([(clean_texture, facing_pose(1.0, -10, 10, offset_px=(-150, 0))),
                                  (strip_texture, T_strip)], occluders=[strip])
    return image, strip_texture, T_strip, strip, truths


@pytest.fixture(params=[1, 2], ids=["one_thread", "two_threads"])
def opencv_threads(request):
    """OpenCV on one thread (the blob search runs after the square path, at half resolution once it found a
    marker) or two (it runs at full resolution while ArUco runs on a second thread)."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(request.param)
    yield request.param
    cv2.setNumThreads(before)


def test_occluded_marker_beside_a_clean_one_is_found_by_default(layout, opencv_threads):
    # one clean marker and one under a strip: by default the circles path also runs beside the
    # square path's finds; "when_square_empty" runs it only in frames where the square path found
    # nothing; "never" never runs it
    image, strip_texture, T_strip, strip, _ = clean_and_strip_scene(layout)
    found = {mode: {(d.id, d.path) for d in Detector(DetectorParams(circles=CircleParams(run=mode))).detect(image)}
             for mode in ("always", "when_square_empty", "never")}
    assert {(d.id, d.path) for d in Detector().detect(image)} == found["always"] == {(3, "square"), (40, "circles")}
    assert found["when_square_empty"] == found["never"] == {(3, "square")}
    strip_only, _ = render_scene([(strip_texture, T_strip)], occluders=[strip])
    assert [(d.id, d.path) for d in Detector(DetectorParams(circles=CircleParams(run="when_square_empty")))
            .detect(strip_only)] == [(40, "circles")]
    assert Detector(DetectorParams(circles=CircleParams(run="never"))).detect(strip_only) == []


def test_aruco_runs_on_the_calling_thread_when_its_own_has_not_started_it(layout):
    # two threads: ArUco goes to the detector's second thread while the blob search runs here; on a
    # loaded machine that thread may not have started it by the time the search is done, and then it
    # runs here instead: the same markers either way; close() ends the thread
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        image = clean_and_strip_scene(layout)[0]
        threads_before = set(threading.enumerate())
        detector = Detector()
        both = {(3, "square"), (40, "circles")}
        assert {(d.id, d.path) for d in detector.detect(image)} == both
        (thread,) = [t for t in set(threading.enumerate()) - threads_before if t.name.startswith("detector-aruco")]
        release = threading.Event()
        busy = detector._aruco_worker.submit(release.wait, 30)  # the thread is held up elsewhere
        try:
            assert {(d.id, d.path) for d in detector.detect(image)} == both
            assert not busy.done()  # the frame did not wait for the thread
        finally:
            release.set()
        assert busy.result() is True
        assert thread.is_alive()
        detector.close()
        assert not thread.is_alive()
        assert {(d.id, d.path) for d in detector.detect(image)} == both  # a new thread after close
        detector.close()
    finally:
        cv2.setNumThreads(before)


def test_a_small_occluded_marker_alone_is_found_on_one_thread_and_on_two(layout, opencv_threads):
    # 34 px, under circles.min_side_beside_found_px (40): a frame where the square path found nothing is
    # searched down to circles.min_side_px (20), on one thread after it, on two beside ArUco; at 40 it is missed
    texture = raster.rs_marker_texture(layout, 40)
    T = facing_pose(2.0, 25, 20, offset_px=(60, -30))
    strip = occluders.strip_occluder(texture, SIZE_M, T, 0.25, "left", np.random.default_rng(0), level=60)
    image, (truth,) = render_scene([(texture, T)], occluders=[strip])
    assert 30 < truth.inner_px < 40
    assert [(d.id, d.path) for d in Detector().detect(image)] == [(40, "circles")]
    assert Detector(DetectorParams(circles=CircleParams(min_side_px=40))).detect(image) == []


def test_footage_settings_look_for_small_occluded_markers_beside_found_ones_too(layout, opencv_threads):
    # a 28 px marker under a strip beside a clean one: on one thread the search beside found markers
    # runs at half resolution by default (circles.min_side_beside_found_px 40) and misses it; on two the
    # search beside ArUco runs at full resolution before the square path's outcome is known; the
    # survey's settings (DetectorParams.for_footage) search at full resolution on both
    clean_texture, strip_texture = raster.rs_marker_texture(layout, 3), raster.rs_marker_texture(layout, 40)
    T_strip = facing_pose(2.5, 25, 20, offset_px=(120, -30))
    strip = occluders.strip_occluder(strip_texture, SIZE_M, T_strip, 0.25, "left", np.random.default_rng(0), level=60)
    image, (_, truth) = render_scene([(clean_texture, facing_pose(1.0, -10, 10, offset_px=(-150, 0))),
                                      (strip_texture, T_strip)], occluders=[strip])
    assert 20 < truth.inner_px < 40
    both = {(3, "square"), (40, "circles")}
    assert {(d.id, d.path) for d in Detector().detect(image)} == ({(3, "square")} if opencv_threads == 1 else both)
    assert {(d.id, d.path) for d in Detector(DetectorParams.for_footage()).detect(image)} == both


def test_either_blob_method_finds_the_occluded_markers(layout, opencv_threads):
    """Connected components (the default: shape tests on each blob's bounding box) and outer contours
    (moment ellipses at any angle) find the same markers under strips, a hidden side and a hidden corner,
    tilted up to 50 degrees and turned at any angle, and no wrong one."""
    textures = [raster.rs_marker_texture(layout, i) for i in range(50)]
    rng = np.random.default_rng(11)
    detectors = {method: Detector(DetectorParams(circles=CircleParams(blob_method=method)))
                 for method in ("components", "contours")}
    found = {method: 0 for method in detectors}
    markers = 0
    for condition in ("strip_1_8", "side_1_4", "corner") * 4:
        ids = [int(i) for i in rng.choice(50, 2, replace=False)]
        scene = scenes.random_marker_scene(rng, (640, 480), [textures[i] for i in ids], (50.0, 120.0), condition)
        truth_ids = {ids[t.key] for t in scene.truths}
        markers += len(truth_ids)
        for method, detector in detectors.items():
            ids_found = {d.id for d in detector.detect(scene.image)}
            assert ids_found <= truth_ids, (method, condition)
            found[method] += len(ids_found)
    assert markers >= 20
    assert found["components"] == found["contours"] >= markers - 1


def test_expected_places_limit_the_circles_search_once_the_square_path_found_a_marker(layout):
    # the daemon tells the detector where mapped markers should be: the occluded one is found where it is
    # expected (a prediction 8 px off), not where nothing is expected; with nothing found by the square
    # path the whole frame is searched whatever is expected
    image, strip_texture, T_strip, strip, truths = clean_and_strip_scene(layout)
    clean_px, strip_px = truths[0].corners_px, truths[1].corners_px
    detector = Detector()

    def found(expected_px):
        return {(d.id, d.path) for d in detector.detect(image, expected_px=expected_px)}

    assert found(np.stack([clean_px, strip_px + [8.0, -8.0]])) == {(3, "square"), (40, "circles")}
    assert found(clean_px[None]) == found(np.zeros((0, 4, 2))) == {(3, "square")}
    assert found(np.stack([clean_px, clean_px + [0.0, 200.0]])) == {(3, "square")}
    strip_only, _ = render_scene([(strip_texture, T_strip)], occluders=[strip])
    assert [(d.id, d.path) for d in detector.detect(strip_only, expected_px=np.zeros((0, 4, 2)))] == [(40, "circles")]


def test_a_60_px_marker_in_an_8000_by_6000_image_is_found(layout, detector):
    """The smallest marker is an absolute size in pixels (square.min_side_px), not a share of the image."""
    texture = raster.rs_marker_texture(layout, 17)
    renderer = raster.Renderer(intrinsics_from_hfov(400, 300, 70.0), np.zeros(5), 400, 300)
    # 60 px face-on at 400 px wide: f s / z = 60
    T = facing_pose(1.0, 20, 15)
    T[:3, 3] *= renderer.K[0, 0] * SIZE_M / 60.0 / T[2, 3]
    rendering = renderer.render([raster.marker_quad(texture, SIZE_M, T, gain=0.9, offset=10.0)], np.eye(4), 150.0)
    truth = raster.marker_truth(renderer, rendering, texture, SIZE_M, T, np.eye(4), 0)
    large = np.full((6000, 8000), 150, np.uint8)
    large[4100:4400, 5200:5600] = degrade.gaussian_blur(rendering.image, 0.6)
    (d,) = detector.detect(large)
    assert 55 < truth.inner_px < 62
    assert (d.id, d.path) == (17, "square")
    assert np.abs(d.corners_px - (truth.corners_px + [5200, 4100])).max() < 0.2


# ------------------------------------------------------------------- decoder

def test_decoder_corrects_scattered_damage_and_refuses_random_cells(layout):
    decoder = GridDecoder(layout)
    rng = np.random.default_rng(1)
    grid = np.rot90(layout.cells(12).astype(np.int8), -3)
    damaged = grid.copy()
    data = np.argwhere(layout.codeword_mask)
    for r, c in data[rng.choice(len(data), 6, replace=False)]:
        damaged[r, c] = 1 - damaged[r, c]
    erased = damaged.copy()
    for r, c in data[rng.choice(len(data), 10, replace=False)]:
        erased[r, c] = UNKNOWN
    results = decoder.decode(np.stack([damaged, erased]))
    assert [(r.id, r.rotation) for r in results] == [(12, 3), (12, 3)]
    assert results[0].mismatched_cells == 6
    noise = rng.integers(0, 2, (500, layout.n_cells, layout.n_cells)).astype(np.int8)
    assert all(r is None for r in decoder.decode(noise))


def test_decoder_radius_shrinks_with_erasures(layout):
    radius = GridDecoder(layout).radius_by_known
    assert radius[-1] == (GridDecoder(layout).min_distance - 1) // 2 - 2
    assert np.all(np.diff(radius) >= 0)
    assert radius[40] == -1  # too few known cells: never accept


# -------------------------------------------------------------------- inputs

@pytest.mark.parametrize("shape", [(1, 1), (5, 5), (3, 640), (640, 3), (11, 11), (1, 10000)])
def test_a_frame_too_small_for_any_marker_has_none_and_raises_nothing(detector, shape):
    """Noise frames narrower than the smallest inner square either path reads (12 px): OpenCV's filters raised
    on the empty rows of their reduced copies (`companion detect` on a 5 x 5 image printed a traceback)."""
    image = np.random.default_rng(3).integers(0, 256, shape, dtype=np.uint8)
    assert detector.detect(image) == []
    assert detector.detect(image, expected_px=np.array([[[1.0, 1.0], [9.0, 1.0], [9.0, 9.0], [1.0, 9.0]]])) == []


def test_bad_image_and_bad_params_raise_clear_errors(detector):
    with pytest.raises(DetectorError, match="uint8"):
        detector.detect(np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ParamsError, match="parity"):
        DetectorParams(parity=3)
    with pytest.raises(ParamsError, match="dictionary"):
        DetectorParams(dictionary="7x7")
    with pytest.raises(ParamsError, match="run"):
        CircleParams(run="sometimes")
    with pytest.raises(TypeError):
        DetectorParams(**{"no_such_key": 1})


def test_params_from_a_mapping_name_the_dotted_key():
    params = DetectorParams.from_mapping({"parity": 4, "circles": {"run": "never", "max_blobs": 100},
                                          "refine": {"max_iterations": 3}})
    assert (params.parity, params.circles.run, params.circles.max_blobs, params.refine.max_iterations) == \
        (4, "never", 100, 3)
    assert params.circles.min_area_px == CircleParams().min_area_px
    assert DetectorParams.from_mapping({}) == DetectorParams() == DetectorParams.from_mapping(None)
    for mapping, message in [({"parity": 3}, "parity: must be 2 or 4, got 3"),
                             ({"square": {"aruco_threshold_windows_px": [6, 27, 20]}},
                              "square.aruco_threshold_windows_px: must be [min, max, step] integers"),
                             ({"square": {"min_side_pix": 3}}, "square.min_side_pix: unknown key"),
                             ({"edges": {"square_samples": 2.5}}, "edges.square_samples: must be an integer"),
                             ({"decoder": {"algebraic": "yes"}}, "decoder.algebraic: must be true or false"),
                             ({"sampling": {"min_contrast_gray": -1}}, "sampling.min_contrast_gray: must be > 0"),
                             ({"circles": {"min_side_beside_found_px": 10}},
                              "circles.min_side_beside_found_px: must be >= min_level_side_px (20.0) > 0")]:
        with pytest.raises(ParamsError) as error:
            DetectorParams.from_mapping(mapping)
        assert str(error.value).startswith(message), error.value


# ---------------------------------------------------------------- homography

def test_the_homography_helper_agrees_with_opencv():
    rng = np.random.default_rng(2)
    grid = np.array([[3.0, 3.0], [11.0, 3.0], [11.0, 11.0], [3.0, 11.0]])
    quads = grid[None] * rng.uniform(8, 12, (5, 1, 1)) + rng.uniform(-6, 6, (5, 4, 2)) + 100
    H = homography.from_quads(grid, quads)
    points = rng.uniform(0, 14, (20, 2))
    expected = np.stack([cv2.perspectiveTransform(points[None], cv2.getPerspectiveTransform(
        grid.astype(np.float32), q.astype(np.float32)).astype(np.float64))[0] for q in quads])
    np.testing.assert_allclose(homography.project(H, points), expected, atol=1e-3)  # float32 corners in OpenCV
    np.testing.assert_allclose(homography.project(H, grid), quads, atol=1e-9)
    np.testing.assert_allclose(homography.project(H[1], points), homography.project(H, points)[1], atol=1e-9)
    each = np.stack([points + k for k in range(5)])
    np.testing.assert_allclose(homography.project(H, each)[3], homography.project(H[3], points + 3), atol=1e-9)
    assert np.isnan(homography.from_quads(grid, np.zeros((1, 4, 2)))).all()  # degenerate quad
    assert np.isnan(homography.project(np.full((3, 3), np.nan), points)).all()  # and it projects to NaN
    # a least-squares fit through exact points, and its error in cells: a 2-cell shift of one of 8 points
    fitted = homography.fit(points[:8], homography.project(H[0], points[:8]))
    np.testing.assert_allclose(homography.project(fitted, points), homography.project(H[0], points), atol=1e-6)
    _, cell_px = homography.project_with_cell_px(H[0], points[:1])
    moved = homography.project(H[0], points[:8])
    moved[0] += [2 * cell_px, 0.0]
    assert homography.fit_error_cells(H[0], points[:8], moved) == pytest.approx(2 / np.sqrt(8), rel=1e-6)


def test_square_path_detections_state_their_corners_joint_covariance():
    """The aligned corners' (8, 8) covariance comes with each square-path detection, at the detection's own
    sigma (its diagonal's mean is corner_sigma_px^2), symmetric and positive definite."""
    detector = Detector()
    textures = [raster.rs_marker_texture(detector.layout, i, 16) for i in range(3)]
    rng = np.random.default_rng(4)
    scene = scenes.random_marker_scene(rng, (640, 480), textures, (40.0, 90.0), scenes.CONDITIONS["clean"],
                                       max_tilt_deg=40)
    square = [d for d in detector.detect(scene.image) if d.path == "square"]
    assert square
    for d in square:
        assert d.corner_cov_px2.shape == (8, 8)
        np.testing.assert_allclose(np.trace(d.corner_cov_px2) / 8, d.corner_sigma_px ** 2, rtol=1e-9)
        np.testing.assert_allclose(d.corner_cov_px2, d.corner_cov_px2.T, atol=1e-15)
        assert np.linalg.eigvalsh(d.corner_cov_px2).min() > 0


@pytest.mark.parametrize("angle_deg, neighbour_px", [(45, (-10, 10)), (135, (10, 10))])
def test_a_turned_oblique_circle_passes_the_ring_test_whichever_way_it_is_turned(angle_deg, neighbour_px):
    """An elongated dark blob (a circle seen obliquely) turned either way, a dark square off its narrow
    side clear of its ring. Connected components give its box and area, not the sign of its turn: the
    ring test tries both (with the wrong one the ring runs over the square and both ends of the blob).
    Contours read the turn from the blob's moments."""
    from companion.detect.circles import find_blobs

    image = np.full((240, 320), 220, np.uint8)
    cv2.ellipse(image, (160, 120), (9, 3), angle_deg, 0, 360, 30, -1, lineType=cv2.LINE_AA)
    x, y = 160 + neighbour_px[0], 120 + neighbour_px[1]
    cv2.rectangle(image, (x - 3, y - 3), (x + 3, y + 3), 30, -1)
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    for method in ("components", "contours"):
        blobs = find_blobs(image, CircleParams(blob_method=method))
        assert len(blobs) == 2, method  # the blob and the square
        assert np.linalg.norm(blobs.centres_px - [160, 120], axis=1).min() < 0.5, method


def test_the_blob_table_agrees_with_opencv_on_drawn_shapes():
    """The contour table (Pick's and Green's theorems over the compressed contours, vectorised) against
    OpenCV on the same regions: areas and centres against its connected components, second moments
    against cv2.moments of each outer contour's polygon (plus a pixel's own 1/12 px^2). Filled ellipses
    at several sizes and angles, a rotated rectangle, a single pixel and a straight run."""
    from companion.detect.circles import PIXEL_VARIANCE_PX2, _contour_table

    binary = np.zeros((200, 300), np.uint8)
    for centre, axes, angle in [((40, 40), (12, 12), 0), ((100, 40), (14, 6), 30), ((160, 45), (9, 4), 75),
                                ((230, 50), (20, 11), 130), ((50, 120), (5, 5), 0), ((120, 130), (3, 2), 45)]:
        cv2.ellipse(binary, centre, axes, angle, 0, 360, 255, -1)
    cv2.fillConvexPoly(binary, cv2.boxPoints(((220, 140), (40, 18), 20)).round().astype(np.int32), 255)
    binary[180, 20] = 255            # a single pixel
    binary[185, 60:70] = 255         # a straight run: a contour polygon of no area
    table = _contour_table(binary, max_area_px=binary.size)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    assert len(table.areas) == count - 1 == len(contours) == 9
    for label in range(1, count):
        row = int(np.argmin(np.linalg.norm(table.centres - centroids[label], axis=1)))
        assert table.areas[row] == stats[label, cv2.CC_STAT_AREA]  # Pick: exactly the pixel count
        np.testing.assert_allclose(table.centres[row], centroids[label], atol=0.05)
    for contour in contours:
        m = cv2.moments(contour)
        if m["m00"] == 0:
            continue  # the pixel and the run: no polygon
        row = int(np.argmin(np.linalg.norm(table.centres - [m["m10"] / m["m00"], m["m01"] / m["m00"]], axis=1)))
        expected = np.array([m["mu20"], m["mu02"], m["mu11"]]) / m["m00"] + [PIXEL_VARIANCE_PX2, PIXEL_VARIANCE_PX2, 0]
        np.testing.assert_allclose(table.moments[row], expected, rtol=1e-9, atol=1e-9)
    single = int(np.argmin(np.linalg.norm(table.centres - [20, 180], axis=1)))
    np.testing.assert_allclose(table.moments[single], [PIXEL_VARIANCE_PX2, PIXEL_VARIANCE_PX2, 0], atol=1e-12)
