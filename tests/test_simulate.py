"""The camera simulator: ground truth against detected corners, trajectories, the sequence folder."""
from __future__ import annotations

import math
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion import cli
from companion.geometry import frames
from companion.sim import degrade
from companion.sim import raster
from companion.sim import simulate
from companion.sim import trajectory as tj
from companion.geometry.camera import CameraModel, load_camera
from companion.detect.detector import Detector, DetectorParams
from companion.markers.dictionary import load_dictionary
from companion.geometry.facility_map import load_map

REPO = Path(__file__).resolve().parents[1]
MAP = REPO / "maps" / "warehouse.yaml"
CAMERA = REPO / "config" / "camera-example.yaml"
# the hover flight is test data; the aisle flight ships with the package (the embedded default replays it)
SEQUENCES = {"warehouse_hover": REPO / "tests" / "data" / "sequences" / "warehouse_hover",
             "warehouse_aisle": REPO / "companion" / "data" / "sequences" / "warehouse_aisle"}


@pytest.fixture(scope="module")
def facility_map():
    return load_map(MAP)


@pytest.fixture(scope="module")
def world(facility_map):
    return simulate.build_world(facility_map, seed=0)


@pytest.fixture(scope="module")
def camera():
    return load_camera(CAMERA)  # with lens distortion


def inner_square_detector() -> cv2.aruco.ArucoDetector:
    """OpenCV ArUco on the RS marker's inner 6x6, via our dictionary as a custom ArUco dictionary."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.minDistanceToBorder = 0
    return cv2.aruco.ArucoDetector(load_dictionary("6x6").aruco(), params)


def reprojection_errors(sequence: simulate.RecordedSequence, facility_map, max_frames: int | None = None,
                        border_px: float = 24.0):
    """|detected - map corners projected with the ground-truth pose|, px: per corner, and per marker
    for the mean of its four corners (which cancels the detector's inward corner bias, about 0.3 px).

    Markers with a corner within ``border_px`` of the image edge are left out: there ArUco's corner
    refinement window is cut by the border and the lens distortion bends the edges it fits lines to.
    """
    camera = CameraModel.from_config(sequence.info["camera"], str(sequence.path / "sequence.yaml"))
    detector = inner_square_detector()
    errors, centres = [], []
    for index, image in sequence.images():
        if max_frames is not None and index >= max_frames:
            break
        corners, ids, _ = detector.detectMarkers(image)
        if ids is None:
            continue
        T_camera_map = frames.invert_transform(sequence.T_map_body[index] @ camera.T_body_camera)
        for marker_id, detected in zip(ids.ravel(), corners):
            expected = camera.project_from(T_camera_map, facility_map.markers[int(marker_id)].corners_map())
            if not camera.in_image(expected, border_px).all():
                continue
            errors.append(np.linalg.norm(detected.reshape(4, 2) - expected, axis=1))
            centres.append(np.linalg.norm(detected.reshape(4, 2).mean(axis=0) - expected.mean(axis=0)))
    return (np.concatenate(errors) if errors else np.zeros(0)), np.array(centres)


def short_flight() -> tj.Trajectory:
    """1.5 m along rack R1's north face, looking at it nearly face-on (markers 5, B, 6 at 1.7-2.1 m)."""
    return tj.smooth_path([(6.0, 5.4, 1.5, -80.0), (7.5, 5.2, 1.5, -95.0)], speed_m_s=1.0, max_accel_m_s2=1.5)


# --------------------------------------------------------- ground truth

def test_ground_truth_pose_reprojects_onto_detected_corners(tmp_path, world, camera, facility_map):
    simulator = simulate.Simulator(world, camera, short_flight(), simulate.DEFAULT_DEGRADATIONS, seed=1)
    out = simulate.write_sequence(tmp_path / "seq", simulator, fps=5.0, map_path=str(MAP))
    sequence = simulate.read_sequence(out)
    errors, centres = reprojection_errors(sequence, facility_map)
    assert len(errors) >= 4 * len(sequence.t_ns)  # at least one marker per frame
    assert np.median(errors) < 0.5, np.median(errors)
    assert errors.max() < 1.5, errors.max()
    assert np.median(centres) < 0.2, np.median(centres)


@pytest.mark.parametrize("dictionary", ["5x5", "8x8"])
def test_markers_are_drawn_in_the_maps_dictionary(tmp_path, camera, dictionary):
    site = tmp_path / f"site-{dictionary}.yaml"
    site.write_text(MAP.read_text().replace("dictionary: 6x6", f"dictionary: {dictionary}"))
    facility_map = load_map(site)
    simulator = simulate.Simulator(simulate.build_world(facility_map, seed=0), camera, short_flight(),
                                   degrade.Degradations(), seed=1)
    frame = simulator.render_frame(0, 0)
    in_view = {t.marker_id for t in frame.truths if t.corners_visible.all() and t.inner_px > 30}
    assert in_view

    def seen(dictionary_name):
        detector = Detector(DetectorParams(dictionary=dictionary_name, parity=facility_map.parity), camera=camera)
        return {d.id for d in detector.detect(frame.image)}

    assert seen(dictionary) == in_view
    assert not seen("6x6")  # a 6x6 detector reads none of them: they are not drawn as 6x6 markers


def test_markers_csv_matches_projection_and_flags_what_is_out_of_view(tmp_path, world, camera, facility_map):
    simulator = simulate.Simulator(world, camera, short_flight(), simulate.DEFAULT_DEGRADATIONS, seed=1)
    frame = simulator.render_frame(0, 0)
    T_camera_map = frames.invert_transform(frame.T_map_body @ camera.T_body_camera)
    assert frame.truths
    for truth in frame.truths:
        expected = camera.project_from(T_camera_map, facility_map.markers[truth.key].corners_map())
        np.testing.assert_allclose(truth.corners_px, expected, atol=1e-9)
        np.testing.assert_array_equal(truth.corners_visible & ~camera.in_image(expected),
                                      np.zeros(4, bool))


def test_circle_centres_land_on_the_rendered_circles(world, camera, facility_map):
    # hover square in front of marker B (7, 3.5, 1.4) at 1.3 m so the circles are large
    hover = tj.hover((7.0, 4.8, 1.9), -90.0, 0.1, drift_m=0.0)
    simulator = simulate.Simulator(world, camera, hover,
                                   simulate.DEFAULT_DEGRADATIONS.with_(read_noise_dn=0, shot_noise_gain=0))
    frame = simulator.render_frame(0, 0)
    truth = next(t for t in frame.truths if facility_map.markers[t.key].symbol == "B")
    assert truth.circles_visible.all()
    # a circle centre is a local darkness maximum: refine a dark-blob centroid around each
    image = frame.image.astype(np.float64)
    for (x, y) in truth.circles_px:
        xi, yi = int(round(x)), int(round(y))
        patch = 255.0 - image[yi - 4:yi + 5, xi - 4:xi + 5]
        patch -= patch.min()
        ys, xs = np.mgrid[-4:5, -4:5]
        cx, cy = (patch * xs).sum() / patch.sum() + xi, (patch * ys).sum() / patch.sum() + yi
        assert math.hypot(cx - x, cy - y) < 0.6


# --------------------------------------------------------- realism knobs

def test_simulation_is_deterministic_under_a_seed(world, camera):
    wandering = simulate.DEFAULT_DEGRADATIONS.with_(exposure_wander=0.3)

    def frame(seed):
        simulator = simulate.Simulator(world, camera, short_flight(), wandering, seed=seed, occluder_count=1)
        return simulator.render_frame(3, 300_000_000)
    a, b, c = frame(5), frame(5), frame(6)
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)


def test_motion_blur_follows_the_vehicle_motion(world, camera):
    # sideways at 3 m/s in front of rack R1: 8 ms exposure smears by many pixels
    fast = tj.smooth_path([(5.0, 5.5, 1.9, -90.0), (11.0, 5.5, 1.9, -90.0)], speed_m_s=3.0, max_accel_m_s2=6.0)
    moving = simulate.DEFAULT_DEGRADATIONS.with_(motion_blur=True, read_noise_dn=0, shot_noise_gain=0,
                                                 optics_blur_sigma_px=0)
    still = moving.with_(motion_blur=False)
    t_ns = int(fast.duration_s / 2 * 1e9)
    sim_blur = simulate.Simulator(world, camera, fast, moving)
    blurred = sim_blur.render_frame(0, t_ns)
    sharp = simulate.Simulator(world, camera, fast, still).render_frame(0, t_ns)
    dx, dy = sim_blur.image_motion_px(t_ns * 1e-9, blurred.truths)
    assert abs(dx) > 5.0 and abs(dx) > 3 * abs(dy)  # sideways flight: horizontal image motion
    x_energy = lambda im: float(np.mean(np.diff(im.astype(float), axis=1) ** 2))
    assert x_energy(blurred.image) < 0.7 * x_energy(sharp.image)
    hover = tj.hover((7.0, 5.5, 1.9), -90.0, 1.0, drift_m=0.0)
    assert np.hypot(*simulate.Simulator(world, camera, hover, moving).image_motion_px(0.5, [])) < 0.5


def test_exposure_wander_changes_brightness_slowly():
    gains = [degrade.exposure_wander_gain(t, 0.3, seed=2) for t in np.arange(0, 10, 0.1)]
    assert max(gains) / min(gains) > 1.2
    assert max(abs(a / b - 1) for a, b in zip(gains[1:], gains[:-1])) < 0.05
    assert degrade.exposure_wander_gain(3.0, 0.0, seed=2) == 1.0


def test_a_frame_resolves_the_exposure_wander_into_its_gain():
    flat = np.full((16, 16), 100, np.uint8)
    wandering = degrade.Degradations(exposure_wander=0.3)
    # a wander has no value until a frame time is given: applying it directly is an error, not a no-op
    with pytest.raises(degrade.DegradationError, match="exposure_wander"):
        wandering.apply(flat, np.random.default_rng(0))
    for t_s in (0.0, 1.7, 4.2):
        gain = degrade.exposure_wander_gain(t_s, 0.3, seed=2)
        frame = wandering.at(t_s, seed=2)
        assert frame.exposure_wander == 0.0
        assert float(frame.apply(flat, np.random.default_rng(0)).mean()) == pytest.approx(100 * gain, abs=0.5)
    assert degrade.Degradations(exposure_gain=0.5).at(1.0, seed=2).exposure_gain == 0.5


def test_passing_occluder_hides_markers_for_a_while(world, camera, facility_map):
    hover = tj.hover((7.0, 5.6, 1.9), -90.0, 6.0, drift_m=0.01)
    simulator = simulate.Simulator(world, camera, hover, seed=3, occluder_count=1)
    (occluder,) = simulator.occluders
    marker_b = facility_map.marker_by_symbol("B").id
    times = np.arange(0.0, 6.0, 0.1)
    hidden = []
    for t in times:
        frame = simulator.render_frame(0, int(t * 1e9))
        b = [x for x in frame.truths if x.key == marker_b]
        hidden.append(not b or not b[0].corners_visible.all())
    hidden = np.array(hidden)
    crossing = (times >= occluder.t_start_s) & (times <= occluder.t_end_s)
    assert hidden[crossing].any()
    assert not hidden[~crossing].any()


# -------------------------------------------------------------- trajectories

def test_body_tilts_toward_its_acceleration():
    traj = tj.waypoints([(0.0, 0.0, 1.0, 0.0), (4.0, 0.0, 1.0, 0.0)], speed_m_s=2.0, max_accel_m_s2=2.0)
    R_ned_map = frames.R_ned_map(0.0)
    early = R_ned_map @ traj.pose_at(0.2 * traj.duration_s)[:3, :3]
    late = R_ned_map @ traj.pose_at(0.8 * traj.duration_s)[:3, :3]
    _, pitch_early, yaw = frames.euler_321_from_rotation(early)
    _, pitch_late, _ = frames.euler_321_from_rotation(late)
    assert pitch_early < -math.radians(2)  # nose down to speed up
    assert pitch_late > math.radians(2)  # nose up to slow down
    assert abs(yaw) < 1e-9  # heading 0 = map +x = north in a map whose x is north
    # the body's forward axis points along the flight, map +x
    assert traj.pose_at(0.0)[:3, 0] == pytest.approx([1.0, 0.0, 0.0], abs=1e-2)
    # the body's down axis points down the map's z
    assert traj.pose_at(0.0)[:3, 2] == pytest.approx([0.0, 0.0, -1.0], abs=1e-2)


def accelerations(traj: tj.PathTrajectory, dt: float = 0.01) -> np.ndarray:
    t = np.arange(dt, traj.duration_s - dt, dt)
    p = np.array([traj.position_m(x) for x in t])
    return np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / dt**2


def test_smooth_path_passes_the_waypoints_within_limits():
    points = [(0.0, 0.0, 1.0, 0.0), (3.0, 1.0, 1.5, 30.0), (6.0, 0.0, 1.2, -20.0)]
    traj = tj.smooth_path(points, speed_m_s=1.5, max_accel_m_s2=1.0)
    samples = np.array([traj.position_m(t) for t in np.linspace(0, traj.duration_s, 4000)])
    for p in points:
        assert np.min(np.linalg.norm(samples - p[:3], axis=1)) < 0.01
    np.testing.assert_allclose(traj.position_m(0.0), points[0][:3], atol=1e-6)
    np.testing.assert_allclose(traj.position_m(traj.duration_s), points[-1][:3], atol=1e-6)
    assert traj.heading_deg(traj.duration_s) == pytest.approx(-20.0, abs=1e-6)
    speeds = np.linalg.norm(np.diff(samples, axis=0), axis=1) / (traj.duration_s / 3999)
    assert speeds.max() < 1.5 * 1.05
    # the along-path profile respects max_accel; curvature adds v^2 / r on top
    assert np.median(accelerations(traj)) < 1.0


def test_waypoint_legs_respect_the_acceleration_limit():
    traj = tj.waypoints([(0, 0, 1, 0), (5, 0, 1, 0), (5, 3, 1, 90)], speed_m_s=2.0, max_accel_m_s2=0.8)
    assert accelerations(traj).max() < 0.8 * 1.05


def test_lawnmower_passes_and_hover_stays_put():
    traj = tj.lawnmower((0, 0, 1.5), (6, 0, 1.5), sweep_m=2.0, passes=3, heading_deg=90.0)
    samples = np.array([traj.position_m(t) for t in np.linspace(0, traj.duration_s, 600)])
    assert samples[:, 1].min() == pytest.approx(0.0, abs=1e-9) and samples[:, 1].max() == pytest.approx(2.0)
    np.testing.assert_allclose(traj.position_m(traj.duration_s), (6.0, 2.0, 1.5), atol=1e-9)
    hover = tj.hover((1, 2, 3), 45.0, 10.0, drift_m=0.05)
    wander = np.array([hover.position_m(t) for t in np.linspace(0, 10, 200)]) - (1, 2, 3)
    assert np.abs(wander).max() <= 0.05 + 1e-9 and np.abs(wander).max() > 0.01


def test_figure_eight_crosses_its_centre():
    traj = tj.figure_eight((2.0, 3.0, 1.5), (1.5, 0.8), period_s=8.0, heading_deg=30.0, duration_s=17.0)
    samples = np.array([traj.position_m(t) for t in np.linspace(0, 17, 3000)])
    assert np.min(np.linalg.norm(samples[1000:] - (2.0, 3.0, 1.5), axis=1)) < 0.02
    extent = samples - (2.0, 3.0, 1.5)
    along = extent @ np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0])
    assert along.max() == pytest.approx(1.5, abs=0.01)


def test_trajectory_csv_round_trip_and_errors(tmp_path):
    traj = short_flight()
    path = tmp_path / "traj.csv"
    tj.write_trajectory_csv(path, traj, fps=20.0)
    back = tj.read_trajectory_csv(path)
    for t in (0.0, 0.05, 0.75, back.duration_s):
        np.testing.assert_allclose(back.pose_at(t), traj.pose_at(t), atol=2e-4)
    # between samples: slerp and linear position stay close to the smooth path
    np.testing.assert_allclose(back.pose_at(0.525)[:3, 3], traj.pose_at(0.525)[:3, 3], atol=2e-3)
    bad = tmp_path / "bad.csv"
    bad.write_text("t_ns,x_m,y_m,z_m,qw,qx,qy\n0,0,0,0,1,0,0\n")
    with pytest.raises(tj.TrajectoryError, match=r"bad\.csv: missing column\(s\) qz"):
        tj.read_trajectory_csv(bad)
    bad.write_text("t_ns,x_m,y_m,z_m,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n0,1,0,0,1,0,0,0\n")
    with pytest.raises(tj.TrajectoryError, match="must increase"):
        tj.read_trajectory_csv(bad)


# ------------------------------------------------------ sequence folders

def test_sequence_folder_round_trip(tmp_path, world, camera, facility_map):
    traj = short_flight()
    simulator = simulate.Simulator(world, camera, traj, simulate.DEFAULT_DEGRADATIONS, seed=4)
    out = simulate.write_sequence(tmp_path / "seq", simulator, fps=10.0, map_path=str(MAP))
    sequence = simulate.read_sequence(out)
    n = int(math.floor(traj.duration_s * 10.0)) + 1
    assert len(sequence.t_ns) == n and sequence.t_ns[0] == 0
    np.testing.assert_array_equal(np.diff(sequence.t_ns), np.round(np.diff(np.arange(n) * 1e8)).astype(np.int64))
    assert all((out / f).is_file() for f in sequence.files)
    for i in (0, n // 2, n - 1):
        T = traj.pose_at(sequence.t_ns[i] * 1e-9)
        np.testing.assert_allclose(sequence.T_map_body[i], T, atol=1e-6)
        np.testing.assert_allclose(sequence.T_ned_body[i], facility_map.T_ned_map @ T, atol=1e-6)
    # the stored camera section rebuilds the same camera
    stored = CameraModel.from_config(sequence.info["camera"], "sequence.yaml")
    np.testing.assert_allclose(stored.K, camera.K)
    np.testing.assert_allclose(stored.dist, camera.dist)
    np.testing.assert_allclose(stored.T_body_camera, camera.T_body_camera, atol=1e-12)
    # the map travels with the sequence: a copy beside it, the original named for reference
    assert sequence.map_path() == out / "map.yaml" and sequence.map_path().read_bytes() == MAP.read_bytes()
    assert sequence.info["map_source"] == str(MAP.resolve())
    # and says it is exact: the world was rendered from it
    assert sequence.info["map_sd_m"] == 0.0 and sequence.info["map_sd_deg"] == 0.0
    assert sequence.info["trajectory"]["pattern"] == "path" and sequence.info["seed"] == 4
    # groundtruth.csv reads back as a trajectory
    replay = tj.read_trajectory_csv(out / "groundtruth.csv")
    np.testing.assert_allclose(replay.pose_at(sequence.t_ns[3] * 1e-9), sequence.T_map_body[3], atol=1e-6)
    # the frames on disk are the frames rendered
    again = simulate.Simulator(world, camera, traj, simulate.DEFAULT_DEGRADATIONS, seed=4)
    _, first = next(sequence.images())
    np.testing.assert_array_equal(first, again.render_frame(0, 0).image)
    # and the rebuilt trajectory (from sequence.yaml) is the same flight
    rebuilt = tj.trajectory_from_description(sequence.info["trajectory"])
    np.testing.assert_allclose(rebuilt.pose_at(0.3), traj.pose_at(0.3), atol=1e-9)


def test_video_output_round_trip(tmp_path, world, camera):
    traj = tj.hover((7.0, 5.5, 1.9), -90.0, 0.4, drift_m=0.02)
    simulator = simulate.Simulator(world, camera, traj, simulate.DEFAULT_DEGRADATIONS, seed=1)
    lossless = simulate.read_sequence(simulate.write_sequence(tmp_path / "ffv1", simulator, 10.0, str(MAP),
                                                              video=True, codec="ffv1"))
    small = simulate.read_sequence(simulate.write_sequence(tmp_path / "mp4v", simulator, 10.0, str(MAP),
                                                           video=True, codec="mp4v"))
    assert lossless.files == [""] * 5 and (tmp_path / "ffv1" / "video.avi").is_file()
    for (i, a), (_, b) in zip(lossless.images(), small.images()):
        np.testing.assert_array_equal(a, simulator.render_frame(i, int(lossless.t_ns[i])).image)
        assert np.sqrt(np.mean((a.astype(float) - b) ** 2)) < 5.0
    assert sum(1 for _ in small.images()) == 5


def test_cli_writes_a_sequence_and_reports_bad_options(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = cli.main(["simulate", str(out), "--map", str(MAP), "--pattern", "hover", "--center", "7,5.5,1.9",
                   "--heading", "-90", "--duration", "0.2", "--fps", "10", "--seed", "3", "--no-progress"])
    assert rc == 0
    sequence = simulate.read_sequence(out)
    assert len(sequence.t_ns) == 3 and sequence.info["options"]["pattern"] == "hover"
    assert sequence.info["camera"]["width"] == 640 and sequence.info["fps"] == 10.0
    # with no realism options: the documented defaults (docs/simulator.md), every knob recorded
    assert sequence.info["degradations"] == {
        "motion_blur": True, "exposure_ms": 8.0, "motion_length_px": 0.0, "motion_angle_rad": 0.0,
        "optics_blur_sigma_px": 0.6, "exposure_gain": 1.0, "exposure_wander": 0.0, "vignette_strength": 0.15,
        "read_noise_dn": 1.5, "shot_noise_gain": 0.03, "jpeg_quality": 0}
    assert sequence.info["occluders"] == 0
    hfov = math.degrees(2 * math.atan(320 / sequence.info["camera"]["fx_px"]))
    assert hfov == pytest.approx(70.0)
    rc = cli.main(["simulate", str(tmp_path / "x"), "--map", str(MAP), "--pattern", "lawnmower"])
    assert rc == 2
    assert "--start" in capsys.readouterr().err
    rc = cli.main(["simulate", str(tmp_path / "y"), "--map", str(tmp_path / "missing.yaml")])
    assert rc == 2
    assert "missing.yaml" in capsys.readouterr().err
    rc = cli.main(["simulate", str(tmp_path / "z"), "--map", str(MAP), "--jpeg", "150"])
    assert rc == 2
    assert "jpeg_quality must be 0 (off) or 1..100, got 150" in capsys.readouterr().err
    rc = cli.main(["simulate", str(tmp_path / "z"), "--map", str(MAP), "--occluders", "-1"])
    assert rc == 2
    assert "--occluders must be 0..100, not -1" in capsys.readouterr().err


WAYPOINTS = "3.2,5.6,1.5,-55;6.0,5.2,1.7,-65"
STANDING_STILL = "3.2,5.6,1.5,-55;3.2,5.6,1.5,-55"
BAD_NUMBERS = [
    # (options, the start of the one line after "companion simulate: "); {csv}: a trajectory with a nan in it
    (["--heading", "nan"], "--heading must be -360..360 degrees, not nan"),
    (["--center", "nan,4.6,1.6"], "--center must be x,y,z within +-100000 m, not nan,4.6,1.6"),
    (["--trajectory", "{csv}"], "{csv}:3: x_m is 'nan', not a finite number"),
    (["--pattern", "waypoints", "--waypoints", WAYPOINTS, "--max-accel", "nan"],
     "--max-accel must be 0.01..50 m/s^2, not nan"),
    (["--pattern", "path", "--waypoints", WAYPOINTS, "--speed", "nan"], "--speed must be 0.01..50 m/s, not nan"),
    (["--pattern", "path", "--waypoints", WAYPOINTS, "--speed", "-1"], "--speed must be 0.01..50 m/s, not -1.0"),
    (["--pattern", "path", "--waypoints", "3.2,5.6,1.5,-55;inf,5.2,1.7,-65"],
     "--waypoints must be x,y,z within +-100000 m and a heading within +-360 degrees, each, not inf,5.2,1.7,-65 "
     "(waypoint 2)"),
    (["--pattern", "path", "--waypoints", STANDING_STILL],
     "--waypoints: waypoints 1 and 2 are both at 3.2,5.6,1.5: a path flies through its waypoints without stopping"),
    (["--pattern", "waypoints", "--waypoints", STANDING_STILL],
     "--waypoints: every waypoint is 3.2,5.6,1.5,-55: there is nothing to fly"),
    (["--pattern", "lawnmower", "--start", "3,4,1.5", "--end", "8,4,1.5", "--passes", "0"],
     "--passes must be 1..1000, not 0"),
    (["--duration", "inf"], "--duration must be a positive number of seconds, not inf"),
    (["--fps", "inf"], "--fps must be positive, got inf"),
    (["--drift", "nan"], "--drift must be 0..100000 m, not nan"),
    (["--seed", "-1"], "--seed must be 0 or more, not -1"),
    (["--occluders", "101"], "--occluders must be 0..100, not 101"),
    (["--blur", "inf"], "--blur: optics_blur_sigma_px must be 0..50, got inf"),
    (["--exposure-ms", "nan"], "--exposure-ms: exposure_ms must be 0..1000, got nan"),
    (["--read-noise", "inf"], "--read-noise: read_noise_dn must be 0..255, got inf"),
    (["--exposure-wander", "inf"], "--exposure-wander: exposure_wander must be 0..5, got inf"),
    (["--attitude-rate", "inf"], "--attitude-rate: attitude rate must be positive and at most 1000 Hz, got inf"),
    (["--attitude-noise", "nan"], "--attitude-noise: attitude noise must be 0..45 degrees, got nan"),
]


@pytest.mark.parametrize("options, message", BAD_NUMBERS, ids=[" ".join(o[:2]) + (" " + o[-2] if len(o) > 2 else "")
                                                               for o, _ in BAD_NUMBERS])
def test_a_number_that_is_not_finite_or_out_of_range_is_named(tmp_path, capsys, options, message):
    """Every number of the options and of a trajectory CSV is finite and in its range, and a flight moves: one
    line naming the option (or file, line and column), exit 2, nothing written, no warning. Before: NaN headings,
    centres, CSV values and accelerations made a sequence of NaN poses with exit 0, '--speed nan' said only
    'cannot convert float NaN to integer', two equal waypoints leaked a RuntimeWarning and wrote a NaN frame."""
    csv_path = tmp_path / "flight.csv"
    csv_path.write_text("t_ns,x_m,y_m,z_m,qw,qx,qy,qz\n0,3.4,4.6,1.6,1,0,0,0\n100000000,nan,4.6,1.6,1,0,0,0\n")
    out = tmp_path / "seq"
    options = [o.replace("{csv}", str(csv_path)) for o in options]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code = cli.main(["simulate", str(out), "--map", str(MAP), "--duration", "0.2", "--fps", "5", "--no-progress",
                         *options])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith(f"companion simulate: {message.replace('{csv}', str(csv_path))}") and err.count("\n") == 1, err
    assert not out.exists()


def test_a_render_too_large_for_memory_is_refused_up_front(tmp_path, capsys):
    """--supersample 1..8, a frame of at most 12 million pixels and a supersampled canvas of at most 40 million
    (about 1.2 GB to draw), each refused in one line before anything is written. Before: --supersample 100 grew
    to 24 GB and was killed, a 100000x100000 camera file raised MemoryError."""
    def camera_file(name, section):
        path = tmp_path / name
        path.write_text(yaml.safe_dump({"camera": section}))
        return path

    huge = camera_file("huge.yaml", {"width": 100000, "height": 100000, "hfov_deg": 70})
    full_hd = camera_file("full-hd.yaml", {"width": 1920, "height": 1080, "hfov_deg": 70})
    # a strong barrel lens: its pinhole canvas is 992x804 for the 640x480 frame
    fisheye = camera_file("fisheye.yaml", {"width": 640, "height": 480, "fx_px": 300, "fy_px": 300, "cx_px": 319.5,
                                           "cy_px": 239.5, "distortion": [-0.4, 0.1, 0, 0, 0]})
    out = tmp_path / "seq"
    base = ["simulate", str(out), "--map", str(MAP), "--duration", "0.2", "--fps", "10", "--no-progress"]
    for extra, message in (
            (["--supersample", "100"], "--supersample must be 1..8, not 100"),
            (["--camera", str(huge)], f"--camera {huge} at --supersample 1: a 100000x100000 frame is 10000 million "
                                      "pixels: more than the 12 million the renderer allows"),
            (["--camera", str(full_hd), "--supersample", "5"],
             f"--camera {full_hd} at --supersample 5: a 1920x1080 frame at supersample 5 is drawn on 9600x5400 "
             "pixels, 52 million: more than the 40 million (about 1.2 GB of memory) the renderer allows"),
            (["--camera", str(fisheye), "--supersample", "8"],
             f"--camera {fisheye} at --supersample 8: a 640x480 frame at supersample 8 is drawn on 7936x6432 pixels "
             "(the lens distortion's canvas is 992x804), 51 million: more than the 40 million")):
        assert cli.main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert err.startswith(f"companion simulate: {message}") and err.count("\n") == 1, err
        assert not out.exists()
    # what fits: 1920x1080 at supersample 4 is 33 million, the default camera at 8 is 20 million
    raster.check_render_size(1920, 1080, 4)
    raster.check_render_size(640, 480, 8)


def folder_contents(folder: Path) -> dict[str, bytes]:
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


@pytest.mark.parametrize("failure, status, message", [
    (KeyboardInterrupt(), 130, "interrupted"),
    (OSError(28, "No space left on device"), 1, "{out}: No space left on device")], ids=["ctrl-c", "disk full"])
def test_a_render_that_stops_half_way_leaves_the_earlier_sequence_as_it_was(tmp_path, monkeypatch, capsys, failure,
                                                                            status, message):
    """A new sequence is written beside the earlier one and replaces it only once complete: Ctrl-C or a failure
    on the third frame leaves the earlier sequence whole and no partial folder. Before, the earlier sequence was
    deleted first, and an interrupted run left an empty folder."""
    out = tmp_path / "seq"
    base = ["simulate", str(out), "--map", str(MAP), "--fps", "10", "--no-progress"]
    assert cli.main([*base, "--duration", "0.4"]) == 0
    earlier = folder_contents(out)
    assert len(earlier) == 5 + 6  # 5 frames, sequence.yaml, map.yaml and 4 CSVs
    render_frame = simulate.Simulator.render_frame

    def stop_at_the_third_frame(simulator, index, t_ns):
        if index == 2:
            raise failure
        return render_frame(simulator, index, t_ns)

    monkeypatch.setattr(simulate.Simulator, "render_frame", stop_at_the_third_frame)
    capsys.readouterr()
    assert cli.main([*base, "--duration", "0.9"]) == status
    assert capsys.readouterr().err == f"companion simulate: {message.replace('{out}', str(out))}\n"
    assert folder_contents(out) == earlier
    assert [path.name for path in tmp_path.iterdir()] == ["seq"]
    monkeypatch.undo()
    assert cli.main([*base, "--duration", "0.9"]) == 0
    assert len(simulate.read_sequence(out).t_ns) == 10 and [path.name for path in tmp_path.iterdir()] == ["seq"]


TERMINATED_AT_THE_THIRD_FRAME = """
import os, signal, sys
from companion import cli
from companion.sim import simulate
render_frame = simulate.Simulator.render_frame
def terminated_at_the_third_frame(simulator, index, t_ns):
    if index == 2:
        os.kill(os.getpid(), signal.SIGTERM)
    return render_frame(simulator, index, t_ns)
simulate.Simulator.render_frame = terminated_at_the_third_frame
sys.exit(cli.main(sys.argv[1:]))
"""


def test_a_render_stopped_by_sigterm_is_removed_as_an_interrupted_one(tmp_path):
    """SIGTERM (`timeout`, a cancelled job) on the third frame: exit 130 as for Ctrl-C, the earlier sequence as it
    was, no partial folder. Before, the process died at once and left its partial folder beside the sequence."""
    out = tmp_path / "seq"
    base = ["simulate", str(out), "--map", str(MAP), "--fps", "10", "--no-progress"]
    assert cli.main([*base, "--duration", "0.4"]) == 0
    earlier = folder_contents(out)
    result = subprocess.run([sys.executable, "-c", TERMINATED_AT_THE_THIRD_FRAME, *base, "--duration", "0.9"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 130 and result.stderr == "companion simulate: interrupted\n", result
    assert folder_contents(out) == earlier
    assert [path.name for path in tmp_path.iterdir()] == ["seq"]


def test_a_sequence_folder_holding_anything_else_is_refused_not_replaced(tmp_path, capsys):
    """The whole folder is replaced by a new sequence: a file of the user's in it is refused (named), not
    deleted with it; the folder is left as it was. Before, a folder with sequence.yaml was accepted whatever
    else it held."""
    out = tmp_path / "seq"
    base = ["simulate", str(out), "--map", str(MAP), "--fps", "10", "--duration", "0.2", "--no-progress"]
    assert cli.main(base) == 0
    (out / "notes.txt").write_text("camera was cleaned before this run")
    (out / "frames" / "marked.png").write_bytes((out / "frames" / "000001.png").read_bytes())
    before = folder_contents(out)
    capsys.readouterr()
    assert cli.main(base) == 2
    assert capsys.readouterr().err == (f"companion simulate: {out}: holds frames/marked.png, notes.txt besides the "
                                       "sequence companion simulate wrote, which a new one replaces: move them away, "
                                       "or give a new or empty folder\n")
    assert folder_contents(out) == before


def test_progress_bar_shows_for_long_renders_or_when_asked(tmp_path, world, camera, capsys):
    def shown(total, progress):
        with simulate.frames_progress_bar(total, progress) as bar:
            return not bar.disable
    limit = simulate.PROGRESS_MIN_FRAMES
    assert shown(limit + 1, None) and not shown(limit, None) and not shown(limit + 1, False)
    capsys.readouterr()
    traj = tj.hover((7.0, 5.5, 1.9), -90.0, 0.2, drift_m=0.0)  # 3 frames at 10 fps
    simulator = simulate.Simulator(world, camera, traj)
    simulate.write_sequence(tmp_path / "quiet", simulator, 10.0, str(MAP))
    assert capsys.readouterr().err == ""
    simulate.write_sequence(tmp_path / "asked", simulator, 10.0, str(MAP), progress=True)
    captured = capsys.readouterr()
    assert "3/3" in captured.err and captured.out == ""


# ------------------------------------------------------ committed sequences

@pytest.mark.parametrize("name", ["warehouse_hover", "warehouse_aisle"])
def test_committed_sequences_ground_truth(name, facility_map):
    sequence = simulate.read_sequence(SEQUENCES[name])
    # sequences made before maps travelled with them name the repository's map, still found
    assert sequence.map_path().resolve() == MAP.resolve()
    count = sum(1 for _ in sequence.images())
    assert count == len(sequence.t_ns) == sequence.info["frames"]
    errors, centres = reprojection_errors(sequence, facility_map, max_frames=60)
    assert len(errors) >= 4 * 20
    # markers of 25-50 px, oblique, blurred (and in the aisle flight a lossy video): ArUco's
    # inward corner bias grows to about 0.6 px; the marker centres stay within a quarter pixel
    assert np.median(errors) < 0.8, np.median(errors)
    assert np.percentile(errors, 95) < 2.0
    assert np.median(centres) < 0.3, np.median(centres)
