"""The closed loop in a simulator, against a stand-in for ArduCopter SITL (no SITL binary here or in CI).

The harness (tests/closed_loop_harness.py) runs the stand-in
(tests/sim_vehicle_peer.py, its own process), the daemon with the
``simulated_camera`` source over the test hall's map
(tests/data/maps/closed_loop_hall.yaml) and the example mission
(examples/sitl_square_mission.py, its own process); what is judged comes
from the stand-in's own record.
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

import sim_vehicle_peer as peer
from closed_loop_harness import (ENV, FPS, HALL_MAP, START_M, X_BEARING_DEG, ClosedLoop, R_ned_map_by_hand,
                                 hall_config, judge_flight)

ESTIMATE_LIMIT_M = 0.05
# "no vision gap > 100 ms" at the configured 30 fps, counted in frames: a shared, loaded machine slows the
# frame rate (a benchmark measures that: benchmarks/bench_closed_loop.py), never which frames give a pose
GAP_LIMIT_FRAMES = 2
# a 150 ms stall of the simulator: no state to render for that long, so no frame; with it the longest gap
# between vision messages was 0.25-0.56 s (load 2-4, bench_closed_loop); a camera that stalls on a history
# stamped on the old send clock: 1.0-1.1 s each time
STALL_GAP_LIMIT_S = 0.9
# and the estimates around the stalls: 95 % within 1 cm (0.3-0.4 cm here), every one within the 5 cm bound.
# (On the old send clock the 95th percentile was 2.2 cm; with the first sample after a stall filed at its
# grid stamp, one estimate in a flight could be 9-15 cm off: docs/sitl.md.)
STALL_P95_LIMIT_M = 0.01
assert FPS == 30


@pytest.fixture
def closed_loop(tmp_path):
    loops = []

    def start(side_m: float, **source) -> ClosedLoop:
        loops.append(ClosedLoop(tmp_path, side_m, **source))
        return loops[-1]

    yield start
    for loop in loops:
        loop.stop()


def test_sitl_home_puts_the_vehicle_at_the_start_position(tmp_path):
    """companion sitl-home's --home, converted back by the peer's own rule, is start_m in the map (by hand)."""
    path = hall_config(tmp_path, 5762)
    result = subprocess.run([sys.executable, "-m", "companion", "sitl-home", "--config", str(path)],
                            capture_output=True, text=True, env=ENV)
    assert result.returncode == 0, result.stderr
    latitude, longitude, altitude, heading = (float(v) for v in result.stdout.strip().split(","))
    map_file = yaml.safe_load(HALL_MAP.read_text())["frame"]["geodetic_origin"]
    north, east = peer.distance_ne(map_file["latitude_deg"], map_file["longitude_deg"], latitude, longitude)
    expected_ned = R_ned_map_by_hand(X_BEARING_DEG) @ np.array(START_M)
    np.testing.assert_allclose([north, east, map_file["altitude_m"] - altitude], expected_ned, atol=2e-3)
    # facing map -x: the compass bearing of map -x is 35 + 180
    assert heading == pytest.approx(215.0)


def test_sitl_home_says_what_is_wrong(tmp_path):
    replay = tmp_path / "replay.yaml"
    replay.write_text(f"source: {{kind: replay, path: {HALL_MAP.parents[1] / 'sequences/warehouse_hover'}}}\n")
    run = [sys.executable, "-m", "companion", "sitl-home", "--config"]
    result = subprocess.run([*run, str(replay)], capture_output=True, text=True, env=ENV)
    assert result.returncode == 2 and "source.kind must be simulated_camera" in result.stderr
    assert "Traceback" not in result.stderr
    result = subprocess.run([*run, str(tmp_path / "missing.yaml")], capture_output=True, text=True, env=ENV)
    assert result.returncode == 2 and "missing.yaml" in result.stderr and "Traceback" not in result.stderr


def fly_and_judge(loop: ClosedLoop, side_m: float) -> None:
    mission = loop.fly()
    assert mission.returncode == 0, mission.stdout + mission.stderr
    assert "truth vs autopilot estimate" in mission.stdout
    result = judge_flight(loop, side_m)
    errors_cm = result["errors_m"] * 100
    print(f"closed loop, {side_m:g} m square: {result['messages']} vision messages during the square, "
          f"{result['fps']:.1f} fps, estimate - truth median {np.median(errors_cm):.2f} cm, "
          f"max {errors_cm.max():.2f} cm, longest gap {result['max_gap_s'] * 1000:.0f} ms, "
          f"{result['longest_unsent_frames']} frames")
    assert errors_cm.max() < ESTIMATE_LIMIT_M * 100
    assert result["longest_unsent_frames"] <= GAP_LIMIT_FRAMES
    status = loop.daemon.status()
    assert status.render_ms is not None and status.render_ms > 0
    assert "render" in status.line()


def test_closed_loop_flies_a_2_m_square_on_markers_alone(closed_loop):
    fly_and_judge(closed_loop(side_m=2.0), 2.0)


@pytest.mark.slow
def test_closed_loop_flies_a_4_m_square_on_markers_alone(closed_loop):
    """The issue's flight: 4 m square, the far side 5.5 m from the markers."""
    fly_and_judge(closed_loop(side_m=4.0), 4.0)


@pytest.mark.slow
def test_closed_loop_keeps_its_estimate_when_the_simulator_stalls(closed_loop):
    """The stand-in's process stopped for 150 ms every 1.5 s of the 2 m square (a SITL falling behind on a
    loaded machine: it skips the sends it missed and restarts its clock): the rendered frames keep to the
    truth (every estimate within 5 cm, 95 % within 1 cm) and the camera keeps delivering. (Stamped on the
    old grid, every sample for 2 s after a stall was 150 ms early: the camera found no sample near its
    render time and stalled for a second.)"""
    loop = closed_loop(side_m=2.0)
    loop.stall_simulator(every_s=1.5, stall_s=0.15)
    mission = loop.fly()
    assert mission.returncode == 0, mission.stdout + mission.stderr
    result = judge_flight(loop, 2.0)
    errors_cm = result["errors_m"] * 100
    restarts = loop.daemon.source.state_stream.clock.restarts
    print(f"closed loop, simulator stalls: {result['messages']} vision messages, estimate - truth median "
          f"{np.median(errors_cm):.2f} cm, p95 {np.percentile(errors_cm, 95):.2f} cm, max {errors_cm.max():.2f} cm, longest gap {result['max_gap_s'] * 1000:.0f} "
          f"ms, {restarts} send clock restarts")
    assert np.percentile(errors_cm, 95) < STALL_P95_LIMIT_M * 100
    assert errors_cm.max() < ESTIMATE_LIMIT_M * 100
    assert restarts >= 4
    assert result["max_gap_s"] < STALL_GAP_LIMIT_S
