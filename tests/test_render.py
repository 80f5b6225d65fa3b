"""The rendering core: geometry and ground truth, clipping, depth order, degradations, determinism."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from companion.geometry import frames
from companion.markers.layout import MarkerLayout
from companion.sim import degrade
from companion.sim import occluders
from companion.sim import raster
from companion.sim import scenes
from companion.geometry.camera import intrinsics_from_hfov

ARUCO = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_50)
W, H = 640, 480


def aruco_detector() -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.minDistanceToBorder = 0
    return cv2.aruco.ArucoDetector(ARUCO, params)


def detect(image: np.ndarray) -> dict[int, np.ndarray]:
    corners, ids, _ = aruco_detector().detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners)}


def facing_marker_pose(distance_m: float, offset_px=(0.0, 0.0), K=None, spin_deg: float = 0.0,
                       tilt_deg: float = 0.0) -> np.ndarray:
    """T_camera_marker for an upright marker straight ahead (then spun and tilted)."""
    K = intrinsics_from_hfov(W, H, 70.0) if K is None else K
    R = (frames.rot_y(math.radians(tilt_deg)) @ frames.rot_z(math.radians(spin_deg))
         @ frames.R_camera_marker_face_on())
    u, v = K[0, 2] + offset_px[0], K[1, 2] + offset_px[1]
    centre = distance_m * np.linalg.solve(K, [u, v, 1.0])
    return frames.make_transform(R, centre)


def render_markers(renderer, textures_and_poses, size_m=0.15, background=128.0):
    quads, placed = [], []
    for texture, T in textures_and_poses:
        quads.append(raster.marker_quad(texture, size_m, T))
        placed.append((texture, T, len(quads) - 1))
    rendering = renderer.render(quads, np.eye(4), background)
    truths = [raster.marker_truth(renderer, rendering, t, size_m, T, np.eye(4), i) for t, T, i in placed]
    return rendering, truths


# ------------------------------------------------------------- geometry

def test_ground_truth_corners_match_detected_corners_on_random_scenes():
    rng = np.random.default_rng(11)
    markers = [raster.aruco_marker_texture(ARUCO, i) for i in range(3)]
    errors, seen = [], 0
    for _ in range(12):
        scene = scenes.random_marker_scene(rng, (W, H), markers, condition="clean")
        found = detect(scene.image)
        for truth in scene.truths:
            seen += 1
            if truth.marker_id in found:
                error = np.linalg.norm(found[truth.marker_id] - truth.corners_px, axis=1)
                errors.append(error[truth.corners_visible])
    errors = np.concatenate(errors)
    assert len(errors) >= 0.85 * 4 * seen
    assert np.median(errors) < 0.3, np.median(errors)
    assert np.percentile(errors, 90) < 0.8


def test_ground_truth_through_lens_distortion():
    K = intrinsics_from_hfov(W, H, 70.0)
    dist = np.array([-0.28, 0.09, 0.001, -0.0005, 0.0])
    renderer = raster.Renderer(K, dist, W, H)
    texture = raster.aruco_marker_texture(ARUCO, 7)
    # far off-centre, where the distortion moves points by many pixels
    T = facing_marker_pose(1.2, offset_px=(-200.0, 140.0), K=K, spin_deg=17.0)
    rendering, (truth,) = render_markers(renderer, [(texture, T)])
    ideal, _ = raster.Renderer(K, np.zeros(5), W, H).project(frames.marker_inner_corners_m(0.15) @ T[:3, :3].T
                                                              + T[:3, 3], np.eye(4))
    assert np.max(np.linalg.norm(ideal - truth.corners_px, axis=1)) > 10.0  # the lens matters here
    found = detect(rendering.image)
    assert 7 in found
    assert np.max(np.linalg.norm(found[7] - truth.corners_px, axis=1)) < 0.5


def test_distortion_map_inverts_projection():
    K = intrinsics_from_hfov(W, H, 70.0)
    dist = np.array([-0.28, 0.09, 0.001, -0.0005, 0.0])
    renderer = raster.Renderer(K, dist, W, H)
    # pixel -> canvas (the map), canvas -> ray, ray -> projectPoints must return the pixel
    pixels = np.array([[0, 0], [639, 0], [320, 240], [10, 470], [600, 300]])
    canvas = renderer._undistort_map[pixels[:, 1], pixels[:, 0]].astype(float)
    rays = np.column_stack([canvas, np.ones(len(canvas))]) @ np.linalg.inv(renderer.canvas_K).T
    back, in_front = renderer.project(rays, np.eye(4))
    assert in_front.all()
    np.testing.assert_allclose(back, pixels, atol=0.01)


def test_lens_remap_does_not_shift_the_corners_near_the_centre():
    """A 70 degree lens with k1 -0.05 (the survey benchmark's phone): RS markers whose corners lie 60-120 px
    from the principal point, at 24 placements. The lens moves them by 0.05-0.4 px there, a fraction that
    changes slowly across the image; OpenCV's bicubic remap shifted the edges by a share of that fraction,
    and our detector's corners came out 0.014 px towards the centre on average here (0.025 px on the survey
    benchmark's walk; 0.001 px with an exact B-spline remap, 0.003 px with Lanczos). The remap must leave
    them within 0.008 px of the truth on average, radially."""
    from companion.detect.detector import Detector, DetectorParams
    from companion.geometry.camera import CameraModel
    K = intrinsics_from_hfov(W, H, 70.0)
    dist = np.array([-0.05, 0.0, 0.0, 0.0, 0.0])
    renderer = raster.Renderer(K, dist, W, H)
    detector = Detector(DetectorParams(parity=2), camera=CameraModel(K, dist, W, H, np.eye(4)))
    layout = MarkerLayout(parity=2)
    rng = np.random.default_rng(4)
    radial_px = []
    for k in range(24):
        texture = raster.rs_marker_texture(layout, k)
        angle = rng.uniform(0, 2 * math.pi)
        offset = 90.0 * np.array([math.cos(angle), math.sin(angle)]) + rng.uniform(-0.5, 0.5, 2)
        T = facing_marker_pose(rng.uniform(1.6, 2.2), offset_px=offset, K=K, spin_deg=rng.uniform(-40, 40),
                               tilt_deg=rng.uniform(-25, 25))
        rendering, (truth,) = render_markers(renderer, [(texture, T)], size_m=0.15)
        found = [d for d in detector.detect(rendering.image) if d.id == k and d.path == "square"]
        assert found, k
        outward = truth.corners_px - K[:2, 2]
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        radial_px.extend(((found[0].corners_px - truth.corners_px) * outward).sum(axis=1))
    assert abs(np.mean(radial_px)) < 0.008, np.mean(radial_px)


def test_supersampled_render_keeps_ground_truth():
    K = intrinsics_from_hfov(W, H, 70.0)
    renderer = raster.Renderer(K, [], W, H, supersample=2)
    texture = raster.aruco_marker_texture(ARUCO, 3)
    T = facing_marker_pose(1.0, offset_px=(60.0, -30.0), spin_deg=-33.0, tilt_deg=35.0)
    rendering, (truth,) = render_markers(renderer, [(texture, T)])
    assert rendering.image.shape == (H, W)
    found = detect(rendering.image)
    assert np.max(np.linalg.norm(found[3] - truth.corners_px, axis=1)) < 0.5


def test_rendered_square_has_the_projected_area_and_centre():
    """Detector-free check: a black square's darkness integrates to its projected area and centre."""
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    image = np.full((160, 160), 255, np.uint8)
    image[16:144, 16:144] = 0
    lo, hi = 15.5, 143.5
    square = raster.MarkerTexture(image, np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]]), np.zeros((0, 2)), 0)
    for distance in (0.3, 0.7, 1.0, 1.6, 2.5):  # inner side 230 .. 27 px: every mip level
        for offset in ((0.0, 0.0), (0.3, 0.1), (0.5, 0.5), (0.77, 0.25)):
            T = facing_marker_pose(distance, offset)
            rendering, (truth,) = render_markers(renderer, [(square, T)], background=255.0)
            darkness = (255.0 - rendering.image.astype(float)) / 255.0
            area = abs(cv2.contourArea(truth.corners_px.astype(np.float32)))
            side_error_px = (math.sqrt(darkness.sum()) - math.sqrt(area)) / 2
            assert abs(side_error_px) < 0.06, (distance, offset, side_error_px)
            ys, xs = np.mgrid[:H, :W]
            centre = np.array([(darkness * xs).sum(), (darkness * ys).sum()]) / darkness.sum()
            assert np.linalg.norm(centre - truth.corners_px.mean(axis=0)) < 0.08


# ------------------------------------------------------------- clipping

def test_clip_polygon_near():
    square = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 3.0], [-1.0, 0.0, 3.0]])
    clipped = raster.clip_polygon_near(square, 1.0)
    assert len(clipped) == 4
    assert clipped[:, 2].min() == pytest.approx(1.0)
    np.testing.assert_allclose(sorted(map(tuple, clipped)),
                               sorted([(1.0, 0.0, 1.0), (1.0, 0.0, 3.0), (-1.0, 0.0, 3.0), (-1.0, 0.0, 1.0)]))
    assert len(raster.clip_polygon_near(square - [0.0, 0.0, 10.0], 1.0)) == 0
    triangle_corner_in = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    assert len(raster.clip_polygon_near(triangle_corner_in, 1.0)) == 3


def test_floor_partly_behind_camera_is_drawn_only_below_the_horizon():
    K = intrinsics_from_hfov(W, H, 70.0)
    renderer = raster.Renderer(K, [], W, H)
    # camera 1 m above a floor (camera y is down, so the floor is the plane y = +1),
    # the floor reaching 20 m behind and 30 m ahead of the camera
    floor_texture = raster.make_texture(np.full((64, 64), 200, np.uint8))
    corners = np.array([[-50.0, 1.0, 30.0], [50.0, 1.0, 30.0], [50.0, 1.0, -20.0], [-50.0, 1.0, -20.0]])
    rendering = renderer.render([raster.TexturedQuad(corners, floor_texture)], np.eye(4), background=30.0)
    horizon_row = K[1, 2]
    above = rendering.image[: int(horizon_row) - 1]
    assert np.all(above == 30)  # nothing of the part behind the camera folds into the sky
    # below the horizon, the floor is seen out to 30 m: rows with y >= cy + f / 30
    near_rows = rendering.image[int(horizon_row + K[1, 1] / 30.0) + 2:]
    assert np.all(near_rows == 200)
    assert np.all(rendering.label[int(horizon_row + K[1, 1] / 30.0) + 2:] == 0)


def test_quad_wholly_behind_camera_draws_nothing():
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    texture = raster.make_texture(np.full((16, 16), 255, np.uint8))
    corners = np.array([[-1.0, -1.0, -2.0], [1.0, -1.0, -2.0], [1.0, 1.0, -2.0], [-1.0, 1.0, -2.0]])
    rendering = renderer.render([raster.TexturedQuad(corners, texture)], np.eye(4), background=10.0)
    assert np.all(rendering.image == 10) and np.all(rendering.label == -1)


def test_nearest_quad_wins_whatever_the_order():
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    near = raster.TexturedQuad(np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]]),
                               raster.make_texture(np.full((16, 16), 50, np.uint8)))
    # the far quad is tilted so its centroid is nearer than the near quad's in places
    far = raster.TexturedQuad(np.array([[-3.0, -3.0, 1.0], [3.0, -3.0, 7.0], [3.0, 3.0, 7.0], [-3.0, 3.0, 1.0]]),
                              raster.make_texture(np.full((16, 16), 220, np.uint8)))
    for quads, near_index in (([near, far], 0), ([far, near], 1)):
        rendering = renderer.render(quads, np.eye(4))
        assert rendering.image[H // 2, W // 2] == 50
        assert rendering.label[H // 2, W // 2] == near_index


def flat_quad(x0, x1, y0, y1, z, level) -> raster.TexturedQuad:
    """A plain quad facing the camera at depth z (camera frame), x0..x1 by y0..y1 metres."""
    corners = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    return raster.TexturedQuad(corners, raster.make_texture(np.full((16, 16), level, np.uint8)))


def test_what_a_tiled_wall_hides_is_skipped_and_what_it_does_not_is_drawn():
    """A wall of three tiles at 2 m hides a panel behind it; the panel shows wherever the wall does not cover
    it: through a missing tile, beyond the wall's edge, or when it stands in front."""
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    tiles = [flat_quad(x, x + 0.4, -0.4, 0.4, 2.0, 90) for x in (-0.6, -0.2, 0.2)]
    # the panel at 4 m: inside the wall's image (the wall spans +-0.3 x +-0.2 of depth there, scaled by 2)
    behind = flat_quad(-0.8, 0.8, -0.5, 0.5, 4.0, 220)
    whole = renderer.render(tiles + [behind], np.eye(4))
    assert 3 not in whole.label and not np.any(whole.image == 220)
    # the middle tile missing: the panel shows through the gap
    gap = renderer.render([tiles[0], tiles[2], behind], np.eye(4))
    assert gap.label[H // 2, W // 2] == 2 and gap.image[H // 2, W // 2] == 220
    # a panel a little wider than the wall: its rim shows at both sides
    wider = renderer.render(tiles + [flat_quad(-1.3, 1.3, -0.5, 0.5, 4.0, 220)], np.eye(4))
    assert np.count_nonzero(wider.label == 3) > 100
    # the panel in front of the wall: drawn over it
    front = renderer.render(tiles + [flat_quad(-0.2, 0.2, -0.1, 0.1, 1.0, 220)], np.eye(4))
    assert front.label[H // 2, W // 2] == 3


def test_one_sided_quad_is_culled_from_behind():
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    texture = raster.aruco_marker_texture(ARUCO, 1)
    T = facing_marker_pose(1.0)
    quad = raster.marker_quad(texture, 0.15, T)
    assert renderer.render([quad], np.eye(4)).label[H // 2, W // 2] == 0
    flipped = T @ frames.make_transform(frames.rot_y(math.pi), [0.0, 0.0, 0.0])
    assert np.all(renderer.render([raster.marker_quad(texture, 0.15, flipped)], np.eye(4)).label == -1)


# ------------------------------------------------------ texture filtering

FOCAL_PX = 500.0


def tilted_square(texture: np.ndarray, tilt_deg: float, distance_m: float, shift_px: float,
                  side_m: float = 0.4) -> raster.TexturedQuad:
    """A square textured quad straight ahead, turned about the image x axis (foreshortened along y)."""
    shift_m = shift_px * distance_m / FOCAL_PX
    T = frames.make_transform(frames.rot_x(math.radians(tilt_deg)), [shift_m, shift_m, distance_m])
    h = side_m / 2
    corners = frames.transform_points(T, np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0.0]]))
    return raster.TexturedQuad(corners, raster.make_texture(texture))


def area_sampled(quad: raster.TexturedQuad, texture: np.ndarray, K: np.ndarray, background: float,
                 samples: int = 8) -> np.ndarray:
    """(H, W) float32 independent reference: level 0 of the texture warped at 8 x 8 samples a pixel, averaged."""
    c = quad.corners_world
    th, tw = texture.shape
    a, b = c[1] - c[0], c[3] - c[0]
    s = samples
    K_fine = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5], [0, 0, 1]]) @ K
    H_fine = K_fine @ np.column_stack([a / tw, b / th, c[0] + a / (2 * tw) + b / (2 * th)])
    fine = cv2.warpPerspective(texture.astype(np.float32), H_fine, (W * s, H * s), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    return cv2.resize(fine, (W, H), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("tilt_deg", [0.0, 60.0, 70.0])
def test_a_foreshortened_texture_stays_sharp_across(tilt_deg):
    # a black/white step along the texture's x, shrunk 5 texels a pixel: across the step (image x) the
    # area-sampled edge has a variance of 1/12 px^2; a mip level chosen for the quad's mean scale blurred it
    # to 0.7 px^2 face-on and 1.7 px^2 at 70 deg (the foreshortening along y made the level coarser)
    K = np.array([[FOCAL_PX, 0, 319.5], [0, FOCAL_PX, 239.5], [0, 0, 1]])
    renderer = raster.Renderer(K, np.zeros(5), W, H)
    step = np.zeros((512, 512), np.uint8)
    step[:, 256:] = 255
    for shift_px in (0.0, 0.3, 0.6):
        image = renderer.render([tilted_square(step, tilt_deg, 2.0, shift_px)], np.eye(4), 0.0).image
        profile = image[H // 2 - 3: H // 2 + 4, 280:360].astype(float).mean(axis=0)
        weights = np.diff(profile) / np.diff(profile).sum()
        x = np.arange(len(weights))
        mean = weights @ x
        assert weights @ (x - mean) ** 2 < 0.35


@pytest.mark.parametrize("distance_m", [4.0, 8.0, 12.0])
@pytest.mark.parametrize("tilt_deg", [0.0, 60.0, 70.0])
def test_a_shrunken_marker_matches_the_area_sampled_reference(distance_m, tilt_deg):
    # an RS marker 50, 25 and 17 px across, face-on and foreshortened 2x and 3x: neither blurred (the
    # mean-scale mip level: 27-73 DN RMS from the reference) nor aliased into moire by the finer level (10-27)
    K = np.array([[FOCAL_PX, 0, 319.5], [0, FOCAL_PX, 239.5], [0, 0, 1]])
    renderer = raster.Renderer(K, np.zeros(5), W, H)
    marker = raster.rs_marker_texture(MarkerLayout(parity=2), 7).image
    for shift_px in (0.0, 0.35, 0.7):
        quad = tilted_square(marker, tilt_deg, distance_m, shift_px)
        rendering = renderer.render([quad], np.eye(4), 128.0)
        reference = area_sampled(quad, marker, K, 128.0)
        ys, xs = np.nonzero(rendering.label == 0)
        inside = (slice(ys.min() + 2, ys.max() - 1), slice(xs.min() + 2, xs.max() - 1))
        rms_dn = np.sqrt(np.mean((rendering.image[inside].astype(float) - reference[inside]) ** 2))
        assert rms_dn < 30.0


# ------------------------------------------------------------- occluders

def face_on_truth(occluder_factory, marker_id=5):
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    texture = raster.aruco_marker_texture(ARUCO, marker_id)
    T = facing_marker_pose(0.8)
    quads = [raster.marker_quad(texture, 0.15, T), occluder_factory(texture, T)]
    rendering = renderer.render(quads, np.eye(4), 128.0)
    return rendering, raster.marker_truth(renderer, rendering, texture, 0.15, T, np.eye(4), 0)


def test_strip_occluder_hides_the_given_fraction_from_one_side():
    rng = np.random.default_rng(0)
    for side, hidden in (("left", [0, 3]), ("right", [1, 2]), ("top", [0, 1]), ("bottom", [2, 3])):
        _, truth = face_on_truth(lambda t, T: occluders.strip_occluder(t, 0.15, T, 0.25, side, rng))
        expected = np.ones(4, bool)
        expected[hidden] = False
        np.testing.assert_array_equal(truth.corners_visible, expected, err_msg=side)
        assert truth.inner_visible_fraction == pytest.approx(0.75, abs=0.03), side


def test_strip_occluder_defeats_plain_aruco():
    rng = np.random.default_rng(1)
    rendering, truth = face_on_truth(lambda t, T: occluders.strip_occluder(t, 0.15, T, 1 / 8, "left", rng, 200.0))
    assert truth.inner_visible_fraction == pytest.approx(7 / 8, abs=0.03)
    assert 5 not in detect(rendering.image)


def test_side_occluder_hides_a_side_with_both_its_corners_circles_and_runs_far_past_them():
    rng = np.random.default_rng(5)
    layout = MarkerLayout(parity=2)
    texture = raster.rs_marker_texture(layout, 7)
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    T = facing_marker_pose(1.2)
    # the layout's circles by corner: 0 TL, 1 TR, 2 BR, 3 BL (three each)
    for side, hidden_corners in (("left", [0, 3]), ("right", [1, 2]), ("top", [0, 1]), ("bottom", [2, 3])):
        occluder = occluders.side_occluder(texture, 0.15, T, 0.125, side, rng, level=90.0)
        rendering = renderer.render([raster.marker_quad(texture, 0.15, T), occluder], np.eye(4), 200.0)
        truth = raster.marker_truth(renderer, rendering, texture, 0.15, T, np.eye(4), 0)
        corners = np.ones(4, bool)
        corners[hidden_corners] = False
        np.testing.assert_array_equal(truth.corners_visible, corners, err_msg=side)
        np.testing.assert_array_equal(truth.circles_visible, np.repeat(corners, 3), err_msg=side)
        assert truth.inner_visible_fraction == pytest.approx(7 / 8, abs=0.03), side
        # along the side it runs on past both corners by at least one inner side (57 px here)
        along_px = np.count_nonzero((rendering.label == 1).any(axis=1 if side in ("left", "right") else 0))
        assert along_px > 3 * truth.inner_px, (side, along_px)


def test_corner_occluder_hides_one_corner():
    rng = np.random.default_rng(2)
    for corner in range(4):
        _, truth = face_on_truth(lambda t, T: occluders.corner_occluder(t, 0.15, T, 0.25, corner, rng))
        expected = np.ones(4, bool)
        expected[corner] = False
        np.testing.assert_array_equal(truth.corners_visible, expected)
        assert truth.inner_visible_fraction == pytest.approx(1 - 0.25**2, abs=0.03)


def test_blob_occluder_stays_inside_the_marker():
    rng = np.random.default_rng(3)
    for _ in range(5):
        _, truth = face_on_truth(lambda t, T: occluders.blob_occluder(0.15, T, rng, 0.18))
        assert truth.corners_visible.all()
        assert 0.8 < truth.inner_visible_fraction < 0.97


def test_person_occluder_hides_markers_behind_it():
    renderer = raster.Renderer(intrinsics_from_hfov(W, H, 70.0), [], W, H)
    texture = raster.aruco_marker_texture(ARUCO, 9)
    T = facing_marker_pose(3.0)
    rng = np.random.default_rng(4)
    # a person 1.5 m ahead, feet 1 m below the optical axis (camera y is down)
    plane = frames.make_transform(frames.R_camera_marker_face_on(), [0.0, 1.0, 1.5])
    quads = [raster.marker_quad(texture, 0.15, T), occluders.person_occluder(rng, plane)]
    rendering = renderer.render(quads, np.eye(4), 128.0)
    truth = raster.marker_truth(renderer, rendering, texture, 0.15, T, np.eye(4), 0)
    assert not truth.corners_visible.any()
    assert truth.inner_visible_fraction < 0.05


# ---------------------------------------------------------- degradations

def gradient_energy(image: np.ndarray, axis: int | None = None) -> float:
    img = image.astype(np.float64)
    gx, gy = np.diff(img, axis=1), np.diff(img, axis=0)
    if axis == 1:
        return float(np.mean(gx**2))
    if axis == 0:
        return float(np.mean(gy**2))
    return float(np.mean(gx**2) + np.mean(gy**2))


@pytest.fixture(scope="module")
def scene_image():
    rng = np.random.default_rng(5)
    return scenes.random_marker_scene(rng, (W, H), [raster.aruco_marker_texture(ARUCO, 0)],
                                      condition=scenes.SceneCondition("plain", degradations=degrade.Degradations())
                                      ).image


def test_gaussian_blur_lowers_gradient_energy(scene_image):
    e0 = gradient_energy(scene_image)
    e1 = gradient_energy(degrade.gaussian_blur(scene_image, 1.0))
    e2 = gradient_energy(degrade.gaussian_blur(scene_image, 2.5))
    assert e2 < e1 < 0.8 * e0


def test_motion_blur_smears_along_its_direction_only():
    # vertical stripes (x edges) and horizontal stripes (y edges) side by side
    image = np.zeros((200, 400), np.uint8)
    image[:, :200][:, (np.arange(200) // 10) % 2 == 0] = 255
    image[:, 200:][(np.arange(200) // 10) % 2 == 0, :] = 255
    blurred = degrade.motion_blur(image, 9.0, 0.0)  # horizontal motion
    left, right = (slice(20, 180), slice(20, 180)), (slice(20, 180), slice(220, 380))
    assert gradient_energy(blurred[left], axis=1) < 0.5 * gradient_energy(image[left], axis=1)
    assert gradient_energy(blurred[right], axis=0) == pytest.approx(gradient_energy(image[right], axis=0), rel=0.02)
    kernel = degrade.motion_blur_kernel(9.0, math.radians(90))
    assert kernel.sum() == pytest.approx(1.0)
    # a vertical kernel: mass spread over rows, one column wide (up to anti-aliasing)
    assert kernel.sum(axis=1).max() < 0.2 and kernel.sum(axis=0).max() > 0.8


def test_sensor_noise_has_the_requested_sigma():
    rng = np.random.default_rng(6)
    flat = np.full((400, 400), 100, np.uint8)
    read_only = degrade.sensor_noise(flat, rng, read_noise_dn=5.0, shot_noise_gain=0.0).astype(float)
    assert read_only.std() == pytest.approx(5.0, rel=0.03)
    assert read_only.mean() == pytest.approx(100.0, abs=0.1)
    # shot noise grows with the signal: variance = read^2 + gain * I
    bright = np.full((400, 400), 200, np.uint8)
    shot = degrade.sensor_noise(bright, rng, read_noise_dn=0.0, shot_noise_gain=0.5).astype(float)
    assert shot.std() == pytest.approx(math.sqrt(0.5 * 200), rel=0.03)


def test_exposure_and_low_light():
    rng = np.random.default_rng(7)
    image = np.tile(np.linspace(0, 250, 256).astype(np.uint8), (64, 1))
    half = degrade.exposure(image, 0.5)
    assert np.abs(half.astype(float) - image / 2).max() <= 0.5
    double = degrade.exposure(image, 2.0)
    assert double.max() == 255 and np.count_nonzero(double == 255) > 0.45 * image.size  # saturation
    dark = degrade.low_light(image, rng, light_fraction=0.15)
    assert dark.mean() == pytest.approx(0.15 * image.mean(), rel=0.1)
    # contrast of the marker-scale steps drops below the noise
    assert float(np.std(dark.astype(float) - degrade.exposure(image, 0.15))) > 1.5


def test_jpeg_error_grows_as_quality_drops(scene_image):
    def rms(q):
        return float(np.sqrt(np.mean((degrade.jpeg(scene_image, q).astype(float) - scene_image) ** 2)))
    errors = [rms(q) for q in (95, 50, 10)]
    assert 0 < errors[0] < errors[1] < errors[2]
    ok, data = cv2.imencode(".jpg", scene_image, [cv2.IMWRITE_JPEG_QUALITY, 50])
    np.testing.assert_array_equal(degrade.jpeg(scene_image, 50), cv2.imdecode(data, cv2.IMREAD_GRAYSCALE))


def test_degradations_apply_in_order_and_copy():
    rng = np.random.default_rng(8)
    image = np.full((32, 32), 120, np.uint8)
    out = degrade.Degradations().apply(image, rng)
    assert out is not image and np.array_equal(out, image)
    out = degrade.Degradations(exposure_gain=0.5, jpeg_quality=90).apply(image, rng)
    assert abs(float(out.mean()) - 60.0) < 1.0


@pytest.mark.parametrize("knob, value", [("read_noise_dn", -1.0), ("optics_blur_sigma_px", float("nan")),
                                         ("exposure_ms", -8.0), ("vignette_strength", 1.5),
                                         ("jpeg_quality", 101)])
def test_degradation_knobs_out_of_range_are_named(knob, value):
    with pytest.raises(degrade.DegradationError, match=f"degradations: {knob} must be"):
        degrade.Degradations(**{knob: value})


# ------------------------------------------------------- scenes, determinism

def test_scene_is_deterministic_under_a_seed():
    markers = [raster.aruco_marker_texture(ARUCO, i) for i in range(2)]
    a = scenes.random_marker_scene(np.random.default_rng(42), (W, H), markers, condition="strip_1_4")
    b = scenes.random_marker_scene(np.random.default_rng(42), (W, H), markers, condition="strip_1_4")
    c = scenes.random_marker_scene(np.random.default_rng(43), (W, H), markers, condition="strip_1_4")
    np.testing.assert_array_equal(a.image, b.image)
    for ta, tb in zip(a.truths, b.truths):
        np.testing.assert_array_equal(ta.corners_px, tb.corners_px)
        np.testing.assert_array_equal(ta.corners_visible, tb.corners_visible)
    assert not np.array_equal(a.image, c.image)


def test_every_condition_renders_with_sizes_in_range():
    rng = np.random.default_rng(9)
    markers = [raster.aruco_marker_texture(ARUCO, i) for i in range(3)]
    for name in scenes.CONDITIONS:
        scene = scenes.random_marker_scene(rng, (W, H), markers, (40, 150), name)
        assert scene.image.shape == (H, W) and scene.image.dtype == np.uint8
        assert len(scene.truths) >= 1
        for truth in scene.truths:
            # tilt shortens sides, never lengthens them past the face-on size
            assert 40 * math.cos(math.radians(50)) - 3 < truth.inner_px < 152
            assert raster.Renderer(scene.K, [], W, H).inside_image(truth.corners_px).all()
            if scenes.CONDITIONS[name].occlusion == "none":
                assert truth.corners_visible.all() and truth.inner_visible_fraction > 0.99
            elif scenes.CONDITIONS[name].occlusion in ("strip", "side", "corner"):
                assert not truth.corners_visible.all()


def test_unknown_condition_is_a_clear_error():
    with pytest.raises(raster.RenderError, match="unknown condition 'fog'"):
        scenes.random_marker_scene(np.random.default_rng(0), (W, H), [], condition="fog")


def test_quads_must_be_parallelograms():
    texture = raster.make_texture(np.zeros((8, 8), np.uint8))
    with pytest.raises(raster.RenderError, match="parallelogram"):
        raster.TexturedQuad(np.array([[0, 0, 1], [1, 0, 1], [1.5, 1, 1], [0, 1, 1.0]]), texture)


def test_mip_levels_halve_exactly():
    texture = raster.make_texture(np.zeros((256, 320), np.uint8))
    sizes = [level.shape for level in texture.levels]
    assert sizes[:4] == [(256, 320), (128, 160), (64, 80), (32, 40)]
    assert all(min(s) >= raster.MIN_MIP_SIZE_PX for s in sizes)


def test_rs_marker_scenes_for_the_detector_benchmark():
    from companion.markers import layout as marker
    from companion.markers.dictionary import load_dictionary

    layout = marker.MarkerLayout(parity=2)
    markers = [raster.rs_marker_texture(layout, i) for i in (0, 17, 42)]
    assert markers[0].circles_px.shape == (12, 2)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.minDistanceToBorder = 0
    inner = cv2.aruco.ArucoDetector(load_dictionary("6x6").aruco(), params)
    rng = np.random.default_rng(12)
    errors = []
    for size in ((W, H), (1280, 720)):
        for _ in range(4):
            scene = scenes.random_marker_scene(rng, size, markers, condition="clean")
            corners, ids, _ = inner.detectMarkers(scene.image)
            found = {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners)}
            for truth in scene.truths:
                assert truth.circles_visible.all() and markers[truth.key].marker_id == truth.marker_id
                if truth.marker_id in found:
                    errors.append(np.linalg.norm(found[truth.marker_id] - truth.corners_px, axis=1))
    errors = np.concatenate(errors)
    assert len(errors) >= 4 * 15
    assert np.median(errors) < 0.35
