"""The camera mount watch: the markers' level against the flight controller's (companion.daemon.mount_watch)."""
from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys

import yaml

import numpy as np
import pytest

from companion.daemon.mount_watch import level_difference_deg, tilt_turn_deg
from companion.geometry import frames
from companion.types import AttitudeSample
from mavlink_peer import PeerProcess, free_port
from test_daemon import AISLE, MAP, finish, start_daemon, write_config

SAID = re.compile(r"the markers and the flight controller disagree on level by ([0-9.]+) deg \(median of the last "
                  r"(\d+) frames; markers - FC: roll ([-+0-9.]+), pitch ([-+0-9.]+) deg\)")


def test_level_difference_is_the_angle_between_the_two_downs_whatever_the_yaw():
    R_ned_body = frames.rotation_from_euler_321(math.radians(2.0), math.radians(-3.0), math.radians(140.0))
    angle, roll, pitch = level_difference_deg(R_ned_body, AttitudeSample(0, 0.0, 0.0))
    assert roll == pytest.approx(2.0) and pitch == pytest.approx(-3.0)
    down = R_ned_body.T @ np.array([0.0, 0.0, 1.0])
    assert angle == pytest.approx(math.degrees(math.acos(down[2])))
    assert level_difference_deg(R_ned_body, AttitudeSample(0, math.radians(2.0), math.radians(-3.0)))[0] < 1e-6


def test_the_turn_between_two_sets_of_tilts_is_found_when_the_vehicle_tilts_enough():
    rng = np.random.default_rng(3)
    directions = rng.uniform(0, 2 * math.pi, 60)

    def downs(tilt_deg, turn_deg=0.0):
        t = math.radians(tilt_deg)
        across = np.column_stack([np.cos(directions + math.radians(turn_deg)),
                                  np.sin(directions + math.radians(turn_deg))]) * math.sin(t)
        return np.column_stack([across, np.full(60, math.cos(t))])

    assert tilt_turn_deg(downs(5.0, 30.0), downs(5.0)) == pytest.approx(30.0)
    assert tilt_turn_deg(downs(5.0, -90.0), downs(5.0)) == pytest.approx(-90.0)
    assert tilt_turn_deg(downs(1.0, 30.0), downs(1.0)) is None  # about level: a turn does not show
    tilted = np.tile([math.sin(math.radians(4.0)), 0.0, math.cos(math.radians(4.0))], (60, 1))
    level = np.tile([0.0, 0.0, 1.0], (60, 1)) + rng.normal(0.0, 0.003, (60, 3))
    assert tilt_turn_deg(level, tilted) is None  # a level error alone: no turn to tell
    # tilts that no turn explains: the FC's of half a second before (a tilting flight), or a fixed error
    # turning with the vehicle's heading (a marker turned in the map, seen alone): no turn claimed (it
    # fitted +50 deg and said CRITICAL 'camera yaw off')
    t = np.linspace(0.0, 6.0, 60)
    def swinging(delay_s):
        roll, pitch = np.radians(6.0) * np.sin(2.0 * (t - delay_s)), np.radians(4.0) * np.sin(1.3 * (t - delay_s))
        return np.array([frames.down_in_body_at(r, p) for r, p in zip(roll, pitch)])
    assert tilt_turn_deg(swinging(0.0), swinging(0.0)) == pytest.approx(0.0, abs=1e-6)
    assert tilt_turn_deg(swinging(0.5), swinging(0.0)) is None
    heading = np.linspace(0.0, 4.0 * math.pi, 60)
    map_error = math.radians(5.0) * np.column_stack([np.cos(heading), np.sin(heading), np.zeros(60)])
    assert tilt_turn_deg(swinging(0.0) + map_error, swinging(0.0)) is None


def aisle_with_attitude_offset(folder, pitch_offset_deg: float):
    """The bundled aisle flight, its attitude.csv's pitch raised by ``pitch_offset_deg``: what a camera mount
    tilted that much off its config (or a FC levelled that much off) looks like."""
    shutil.copytree(AISLE, folder)
    lines = (folder / "attitude.csv").read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    (folder / "attitude.csv").write_text("\n".join([lines[0]] + [f"{t},{roll},{float(pitch) + pitch_offset_deg:.4f}"
                                                                  for t, roll, pitch in rows]) + "\n")
    return folder


@pytest.mark.parametrize("pitch_offset_deg", [0.0, 4.0])
def test_a_camera_mount_off_its_config_is_said_once_with_the_difference(tmp_path, pitch_offset_deg):
    """Replayed with the FC's pitch 4 degrees off the markers', the daemon says once, in the log and by
    STATUSTEXT, that the markers and the FC disagree on level, with the pitch difference; untouched, it says
    nothing (before, the pose stage quietly left the attitude out of every frame)."""
    port = free_port()
    peer = PeerProcess(port, tmp_path / "peer.jsonl", "--origin-reply", "on_set", duration_s=60).wait_listening()
    try:
        sequence = aisle_with_attitude_offset(tmp_path / "aisle", pitch_offset_deg)
        code, _, stderr = finish(start_daemon(write_config(tmp_path, sequence, port, source={"realtime": False})),
                                 timeout_s=60)
    finally:
        peer.stop()
    assert code == 0, stderr
    said = SAID.findall(stderr)
    texts = [r["fields"]["text"] for r in peer.records("STATUSTEXT") if "camera mount?" in r["fields"]["text"]]
    if pitch_offset_deg == 0:
        assert not said and not texts, stderr
        return
    assert len(said) == 1 and len(texts) == 1, stderr
    angle, frames_counted, roll, pitch = (float(v) for v in said[0])
    assert frames_counted == 60 and abs(roll) < 0.3 and pitch == pytest.approx(-pitch_offset_deg, abs=0.3)
    assert angle == pytest.approx(pitch_offset_deg, abs=0.3)
    assert texts[0] == f"companion: camera mount? level {angle:.1f} deg off FC"


def test_a_camera_turned_against_its_config_is_told_as_its_yaw_error_critical(tmp_path):
    """A figure eight (tilts of 5-11 degrees) rendered with the camera facing forward, flown with a config
    that says it is turned 30 degrees right: the markers see the FC's tilts turned by +30 degrees; the daemon
    says once, CRITICAL, that the camera's yaw is +30 degrees off (every heading sent is; before, nothing)."""
    sequence = tmp_path / "eight"
    subprocess.run([sys.executable, "-m", "companion", "simulate", str(sequence), "--map", str(MAP), "--pattern",
                    "figure8", "--fps", "15", "--duration", "4.5", "--period", "4", "--size", "0.6,0.3",
                    "--no-progress"], check=True, capture_output=True)
    camera = yaml.safe_load((sequence / "sequence.yaml").read_text())["camera"]
    camera["mount"]["yaw_deg"] = 30.0
    port = free_port()
    peer = PeerProcess(port, tmp_path / "peer.jsonl", "--origin-reply", "on_set", duration_s=60).wait_listening()
    try:
        config = write_config(tmp_path, sequence, port, source={"realtime": False}, camera=camera)
        code, _, stderr = finish(start_daemon(config), timeout_s=60)
    finally:
        peer.stop()
    assert code == 0, stderr
    turned = re.findall(r"ERROR companion: the markers and the flight controller disagree on level .* the tilt the "
                        r"markers see is the FC's turned by ([-+0-9]+) deg", stderr)
    assert len(turned) == 1 and abs(int(turned[0]) - 30) <= 2, stderr
    texts = [r["fields"] for r in peer.records("STATUSTEXT") if r["fields"]["text"].startswith("companion: camera")]
    assert [(t["text"], t["severity"]) for t in texts] == [(f"companion: camera/FC board yaw off by {turned[0]} deg", 2)]
