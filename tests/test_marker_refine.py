"""Whole-marker sub-pixel alignment on rendered frames: accuracy against ArUco, fallbacks, partial views, lens."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from companion.geometry import frames
from companion.sim import degrade
from companion.sim import raster
from companion.sim import scenes
from companion.geometry.camera import CameraModel, intrinsics_from_hfov
from companion.markers.dictionary import load_dictionary
from companion.markers.layout import MarkerLayout
from companion.params import ParamsError
from companion.detect.refine import MarkerRefiner, MarkerRefineError, RefineParams

W, H = 640, 480
SIZE_M = 0.15


@pytest.fixture(scope="module")
def layout():
    return MarkerLayout(parity=2)


@pytest.fixture(scope="module")
def textures(layout):
    return {i: raster.rs_marker_texture(layout, i) for i in range(50)}


def aruco_detector() -> cv2.aruco.ArucoDetector:
    """What the detector's square path runs: SUBPIX corners, no border margin."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.minDistanceToBorder = 0
    return cv2.aruco.ArucoDetector(load_dictionary("6x6").aruco(), params)


def detected_markers(textures, seed: int, conditions, scenes_each: int, inner_px_range):
    """[(image, id, ArUco corners, truth)] for fully visible markers ArUco found, over rendered scenes."""
    rng = np.random.default_rng(seed)
    detector = aruco_detector()
    found = []
    for condition in conditions:
        for _ in range(scenes_each):
            ids = [int(i) for i in rng.choice(50, 3, replace=False)]
            scene = scenes.random_marker_scene(rng, (W, H), [textures[i] for i in ids], inner_px_range, condition,
                                               max_tilt_deg=60.0)
            corners, detected_ids, _ = detector.detectMarkers(scene.image)
            if detected_ids is None:
                continue
            by_id = {int(i): np.asarray(c, float).reshape(4, 2) for c, i in zip(corners, detected_ids.ravel())}
            for truth in scene.truths:
                marker_id = ids[truth.key]
                if truth.fully_visible and marker_id in by_id:
                    found.append((scene.image, marker_id, by_id[marker_id], truth))
    return found


def mean_corner_error(corners, truth_px) -> float:
    return float(np.linalg.norm(corners - truth_px, axis=1).mean())


def facing_pose(distance_m: float, centre_px, spin_deg: float = 0.0, tilt_deg: float = 0.0) -> np.ndarray:
    """T_camera_marker of a marker whose centre projects to ``centre_px``, spun and tilted."""
    K = intrinsics_from_hfov(W, H, 70.0)
    R = (frames.rot_y(math.radians(tilt_deg)) @ frames.rot_z(math.radians(spin_deg))
         @ frames.R_camera_marker_face_on())
    return frames.make_transform(R, distance_m * np.linalg.solve(K, [centre_px[0], centre_px[1], 1.0]))


def render_one(texture, T_camera_marker, dist=np.zeros(5), seed=0):
    """(image, truth) of one marker in front of a plain background, light blur and noise."""
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), np.asarray(dist, float), W, H)
    quad = raster.marker_quad(texture, SIZE_M, T_camera_marker, gain=0.85, offset=15.0)
    rendering = renderer.render([quad], np.eye(4), 120.0)
    image = degrade.sensor_noise(degrade.gaussian_blur(rendering.image, 0.6), np.random.default_rng(seed), 1.0, 0.02)
    return image, raster.marker_truth(renderer, rendering, texture, SIZE_M, T_camera_marker, np.eye(4), 0)


# ------------------------------------------------------------------ accuracy

@pytest.fixture(scope="module")
def refined_scenes(layout, textures):
    markers = detected_markers(textures, seed=5, conditions=("clean", "gaussian_blur", "noise", "jpeg"),
                               scenes_each=3, inner_px_range=(20.0, 150.0))
    refiner = MarkerRefiner(layout)
    return [(m, refiner.refine(m[0], m[1], m[2])) for m in markers]


def test_refined_corners_far_closer_to_the_truth_than_arucos(refined_scenes):
    assert len(refined_scenes) >= 25
    initial = np.array([mean_corner_error(m[2], m[3].corners_px) for m, _ in refined_scenes])
    refined = np.array([mean_corner_error(fit.corners_px, m[3].corners_px) for m, fit in refined_scenes])
    # measured: ArUco 0.3-1 px, refined 0.01-0.04 px
    assert np.median(refined) <= 0.25 * np.median(initial)
    assert np.median(refined) < 0.06
    assert np.percentile(refined, 90) < 0.2
    assert np.mean(refined < initial) >= 0.9
    assert np.mean([fit.refined for _, fit in refined_scenes]) >= 0.9


def test_a_kept_fit_fits_better_than_the_initial_corners(refined_scenes):
    for (image, _, initial, _), fit in refined_scenes:
        if fit.refined:
            assert fit.residual <= fit.initial_residual
            assert fit.residual <= RefineParams().max_residual_fraction
            assert fit.iterations >= 1
        else:
            np.testing.assert_array_equal(fit.corners_px, initial)


def test_homography_and_circles_follow_the_refined_fit(layout, refined_scenes):
    errors = []
    for (_, _, _, truth), fit in refined_scenes:
        if not fit.refined:
            continue
        grid = np.column_stack([layout.inner_corners_cells, np.ones(4)]) @ fit.H_image_grid.T
        np.testing.assert_allclose(grid[:, :2] / grid[:, 2:], fit.corners_px, atol=1e-6)
        assert fit.circles_px.shape == (12, 2)
        assert fit.circles_in_image.all()  # the scenes keep whole markers in the frame
        errors.append(np.linalg.norm(fit.circles_px - truth.circles_px, axis=1))
    assert np.median(np.concatenate(errors)) < 0.06


# ------------------------------------------------------------------ fallbacks

def test_a_blank_frame_keeps_the_initial_corners(layout):
    image = np.full((H, W), 128, np.uint8)
    image += np.random.default_rng(1).integers(0, 3, image.shape, dtype=np.uint8)
    initial = np.array([[300.0, 200.0], [360.0, 205.0], [355.0, 265.0], [295.0, 260.0]])
    fit = MarkerRefiner(layout).refine(image, 7, initial)
    assert not fit.refined
    assert fit.status == "low_contrast"
    np.testing.assert_array_equal(fit.corners_px, initial)
    grid = np.column_stack([layout.inner_corners_cells, np.ones(4)]) @ fit.H_image_grid.T
    np.testing.assert_allclose(grid[:, :2] / grid[:, 2:], initial, atol=1e-3)


@pytest.mark.parametrize("offset_cells", [(2.0, 0.0), (0.0, 3.0), (2.5, 2.5)])
def test_corners_cells_away_from_the_marker_are_not_replaced(layout, textures, offset_cells):
    image, truth = render_one(textures[11], facing_pose(0.9, (320, 240), spin_deg=20, tilt_deg=25))
    cell_px = truth.inner_px / layout.inner_cells
    initial = truth.corners_px + np.array(offset_cells) * cell_px
    fit = MarkerRefiner(layout).refine(image, 11, initial)
    assert not fit.refined, fit.status
    assert fit.status in ("worse", "mismatch", "diverged", "low_contrast")
    np.testing.assert_array_equal(fit.corners_px, initial)


def test_occluded_markers_never_come_back_with_a_larger_misfit(layout, textures):
    """Strips over the border (the circles path's markers): the fit is kept only when it fits better."""
    rng = np.random.default_rng(3)
    refiner = MarkerRefiner(layout)
    fits = []
    for _ in range(4):
        ids = [int(i) for i in rng.choice(50, 3, replace=False)]
        scene = scenes.random_marker_scene(rng, (W, H), [textures[i] for i in ids], (40.0, 120.0), "strip_1_4",
                                           max_tilt_deg=40.0)
        for truth in scene.truths:
            initial = truth.corners_px + rng.normal(0.0, 0.4, (4, 2))
            fits.append((initial, refiner.refine(scene.image, ids[truth.key], initial)))
    assert len(fits) >= 8
    for initial, fit in fits:
        if fit.refined:
            assert fit.residual <= fit.initial_residual
        else:
            np.testing.assert_array_equal(fit.corners_px, initial)
    assert any(not fit.refined for _, fit in fits)


# ------------------------------------------------------------------ partial views, lens

def test_a_marker_partly_outside_the_frame(layout, textures):
    # centre 25 px from the right edge: the grid's right part and the inner square's right corners are outside
    image, truth = render_one(textures[23], facing_pose(0.75, (W - 25.0, 250.0), spin_deg=8, tilt_deg=15))
    outside = truth.corners_px[:, 0] > W - 0.5
    assert outside.any() and not outside.all()
    centre = truth.corners_px.mean(axis=0)
    # ArUco-like start: pulled 0.4 px toward the centre, plus noise
    inward = (centre - truth.corners_px) / np.linalg.norm(centre - truth.corners_px, axis=1, keepdims=True)
    initial = truth.corners_px + 0.4 * inward + np.random.default_rng(2).normal(0.0, 0.2, (4, 2))
    fit = MarkerRefiner(layout).refine(image, 23, initial)
    assert fit.refined, fit.status
    error = np.linalg.norm(fit.corners_px - truth.corners_px, axis=1)
    # measured: 0.03 px inside; the corners outside, extrapolated through the homography, 0.16 px
    assert error[~outside].max() < 0.05
    assert error.max() < 0.25
    assert error.mean() < 0.4 * np.linalg.norm(initial - truth.corners_px, axis=1).mean()
    circles_inside = (truth.circles_px[:, 0] >= -0.5) & (truth.circles_px[:, 0] <= W - 0.5)
    assert 0 < circles_inside.sum() < 12
    np.testing.assert_array_equal(fit.circles_in_image, circles_inside)
    # the covariance is made of the points read: the corners extrapolated beyond them are stated less sure
    assert np.linalg.eigvalsh(fit.corner_cov_px2).min() > 0
    variance = np.diag(fit.corner_cov_px2).reshape(4, 2).sum(axis=1)
    assert variance[outside].min() > 2 * variance[~outside].max()


def camera_with(dist) -> CameraModel:
    return CameraModel(intrinsics_from_hfov(W, H, 70.0), np.asarray(dist, float), W, H, np.eye(4))


def test_all_fourteen_lens_coefficients_are_modelled(layout, textures):
    """Rational, thin-prism and tilted-sensor terms too: the renderer draws them with OpenCV, the refiner
    (with the camera) must align on them as well as on a plain radial lens."""
    dist = np.array([-0.25, 0.08, 0.001, -0.001, 0.0, 0.02, -0.01, 0.005, 0.003, -0.002, 0.002, 0.001, 0.01, -0.008])
    image, truth = render_one(textures[8], facing_pose(0.6, (450.0, 330.0), spin_deg=-20, tilt_deg=25), dist)
    assert truth.fully_visible and truth.inner_px > 80
    initial, _, _ = aruco_detector().detectMarkers(image)
    initial = np.asarray(initial[0], float).reshape(4, 2)
    fit = MarkerRefiner(layout, camera=camera_with(dist)).refine(image, 8, initial)
    assert fit.refined, fit.status
    error = mean_corner_error(fit.corners_px, truth.corners_px)
    assert error < 0.05
    assert error < 0.5 * mean_corner_error(MarkerRefiner(layout).refine(image, 8, initial).corners_px,
                                           truth.corners_px)


def test_with_the_camera_a_strongly_distorted_large_marker_is_refined(layout, textures):
    dist = np.array([-0.3, 0.1, 0.001, -0.001, 0.0])
    camera = camera_with(dist)
    image, truth = render_one(textures[5], facing_pose(0.55, (470.0, 340.0), spin_deg=30, tilt_deg=20), dist)
    assert truth.fully_visible and truth.inner_px > 100
    initial, _, _ = aruco_detector().detectMarkers(image)
    initial = np.asarray(initial[0], float).reshape(4, 2)
    with_camera = MarkerRefiner(layout, camera=camera).refine(image, 5, initial)
    without = MarkerRefiner(layout).refine(image, 5, initial)
    assert with_camera.refined
    error = mean_corner_error(with_camera.corners_px, truth.corners_px)
    assert error < 0.05
    assert error < 0.5 * mean_corner_error(without.corners_px, truth.corners_px)
    assert np.median(np.linalg.norm(with_camera.circles_px - truth.circles_px, axis=1)) < 0.08


# ------------------------------------------------------------------ inputs

def test_bad_inputs_are_named(layout):
    refiner = MarkerRefiner(layout)
    corners = np.array([[10.0, 10.0], [50.0, 10.0], [50.0, 50.0], [10.0, 50.0]])
    with pytest.raises(MarkerRefineError, match="uint8"):
        refiner.refine(np.zeros((H, W), np.float32), 0, corners)
    with pytest.raises(MarkerRefineError, match=r"\(4, 2\)"):
        refiner.refine(np.zeros((H, W), np.uint8), 0, corners[:3])
    with pytest.raises(MarkerRefineError, match="marker_id"):
        refiner.refine(np.zeros((H, W), np.uint8), 50, corners)
    with pytest.raises(ParamsError, match="max_iterations"):
        RefineParams(max_iterations=0)
    with pytest.raises(MarkerRefineError, match="dist"):
        MarkerRefiner(layout, camera=camera_with(np.zeros(7)))


def test_degenerate_corners_are_returned_as_given(layout):
    image = np.full((H, W), 100, np.uint8)
    collapsed = np.array([[100.0, 100.0], [100.0, 100.0], [140.0, 140.0], [140.0, 140.0]])
    fit = MarkerRefiner(layout).refine(image, 3, collapsed)
    assert fit.status == "degenerate" and not fit.refined
    np.testing.assert_array_equal(fit.corners_px, collapsed)
    assert not fit.circles_in_image.any()


def test_the_template_cache_is_bounded(layout, textures):
    image, truth = render_one(textures[0], facing_pose(0.8, (320, 240)))
    refiner = MarkerRefiner(layout, RefineParams(cache_size=2))
    for marker_id in (0, 1, 2, 0):
        refiner.refine(image, marker_id, truth.corners_px)
    assert len(refiner._templates) == 2


def test_the_robust_layout_is_refined_too():
    layout = MarkerLayout(parity=4)  # 18 x 18 grid
    texture = raster.rs_marker_texture(layout, 31)
    image, truth = render_one(texture, facing_pose(1.2, (300.0, 220.0), spin_deg=-35, tilt_deg=35))
    corners, ids, _ = aruco_detector().detectMarkers(image)
    assert ids is not None and 31 in ids.ravel()
    initial = np.asarray(corners[list(ids.ravel()).index(31)], float).reshape(4, 2)
    fit = MarkerRefiner(layout).refine(image, 31, initial)
    assert fit.refined
    assert mean_corner_error(fit.corners_px, truth.corners_px) < 0.3 * mean_corner_error(initial, truth.corners_px)
    assert np.median(np.linalg.norm(fit.circles_px - truth.circles_px, axis=1)) < 0.08


# ------------------------------------------------------------ corner covariance

def test_the_corner_covariance_has_the_shape_of_the_corners_scatter(layout, textures):
    """One tilted marker under 200 independent noise draws: the stated (8, 8) corner covariance's correlations
    are those of the refined corners' scatter (its scale is the misfit's, which blur's model error dominates)."""
    T = facing_pose(1.6, (300, 250), spin_deg=20, tilt_deg=40)
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), np.zeros(5), W, H)
    rendering = renderer.render([raster.marker_quad(textures[7], SIZE_M, T, gain=0.85, offset=15.0)], np.eye(4), 120.0)
    truth = raster.marker_truth(renderer, rendering, textures[7], SIZE_M, T, np.eye(4), 0)
    blurred = degrade.gaussian_blur(rendering.image, 0.6)
    refiner = MarkerRefiner(layout)
    corners, covariances = [], []
    for seed in range(200):
        fit = refiner.refine(degrade.sensor_noise(blurred, np.random.default_rng(seed), 6.0, 0.0), 7,
                             truth.corners_px + 0.3)
        assert fit.refined and fit.corner_cov_px2.shape == (8, 8)
        np.testing.assert_allclose(fit.corner_cov_px2, fit.corner_cov_px2.T, atol=1e-15)
        assert np.linalg.eigvalsh(fit.corner_cov_px2).min() > 0
        corners.append(fit.corners_px.reshape(8))
        covariances.append(fit.corner_cov_px2)

    def correlations(cov):
        sd = np.sqrt(np.diag(cov))
        return (cov / np.outer(sd, sd))[np.triu_indices(8, 1)]

    stated, scattered = correlations(np.mean(covariances, axis=0)), correlations(np.cov(np.array(corners).T))
    assert np.abs(stated).max() > 0.1  # there is a structure to compare
    assert np.corrcoef(stated, scattered)[0, 1] > 0.6
    assert np.abs(stated - scattered).max() < 0.25


def _stated_and_scattered(refiner, image, truth, noise_dn: float, draws: int = 60):
    """(8,) mean stated corner variance and (8,) variance of the refined corners over independent noise draws."""
    corners, variances = [], []
    for seed in range(draws):
        fit = refiner.refine(degrade.sensor_noise(image, np.random.default_rng(seed), noise_dn, 0.0), 7,
                             truth.corners_px + 0.3)
        assert fit.refined
        corners.append(fit.corners_px.reshape(8))
        variances.append(np.diag(fit.corner_cov_px2))
    return np.mean(variances, axis=0), np.var(np.array(corners), axis=0)


@pytest.fixture(scope="module")
def tilted_marker(textures):
    """(image blurred like a camera's, truth) of marker 7, 1.6 m away, spun 20 and tilted 40 degrees."""
    T = facing_pose(1.6, (300, 250), spin_deg=20, tilt_deg=40)
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), np.zeros(5), W, H)
    rendering = renderer.render([raster.marker_quad(textures[7], SIZE_M, T, gain=0.85, offset=15.0)], np.eye(4), 120.0)
    truth = raster.marker_truth(renderer, rendering, textures[7], SIZE_M, T, np.eye(4), 0)
    return degrade.gaussian_blur(rendering.image, 0.6), truth


def test_the_stated_corner_variance_grows_with_the_images_noise_as_the_scatter_does(layout, tilted_marker):
    """From 2 to 12 DN of sensor noise the corners' scatter grows ~30x; the stated variance grows by about as much
    (the misfit's noise is measured along the marker's edges, apart from the template's mismatch)."""
    image, truth = tilted_marker
    refiner = MarkerRefiner(layout)
    stated_low, scattered_low = _stated_and_scattered(refiner, image, truth, 2.0)
    stated_high, scattered_high = _stated_and_scattered(refiner, image, truth, 12.0)
    assert scattered_high.mean() > 10 * scattered_low.mean()
    grown = (stated_high.mean() - stated_low.mean()) / (scattered_high.mean() - scattered_low.mean())
    assert 0.4 < grown < 1.5


def test_a_motion_smear_widens_the_stated_variance_along_it(layout, tilted_marker):
    """A 6 px horizontal smear: the refined corners scatter more in x than in y, against the unsmeared marker,
    and the stated variances say so by about as much (the image's own gradient, not the sharp template's)."""
    image, truth = tilted_marker
    refiner = MarkerRefiner(layout)
    ratios = {}
    for name, frame in (("sharp", image), ("smeared", degrade.motion_blur(image, 6.0, 0.0))):
        stated, scattered = _stated_and_scattered(refiner, frame, truth, 4.0)
        ratios[name] = (stated[0::2].mean() / stated[1::2].mean(), scattered[0::2].mean() / scattered[1::2].mean())
    (stated_sharp, scattered_sharp), (stated_smeared, scattered_smeared) = ratios["sharp"], ratios["smeared"]
    assert scattered_smeared > 2 * scattered_sharp  # the smear is there to see
    assert stated_smeared > 2 * stated_sharp
    for stated, scattered in ratios.values():
        assert 0.6 < stated / scattered < 1.6


def test_a_fit_that_did_not_hold_states_no_covariance(layout):
    blank = np.full((H, W), 128, np.uint8)
    fit = MarkerRefiner(layout).refine(blank, 3, np.array([[100.0, 100], [160, 100], [160, 160], [100, 160]]))
    assert not fit.refined and fit.corner_cov_px2 is None
