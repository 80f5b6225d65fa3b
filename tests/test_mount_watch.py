"""The camera mount watch: the markers' level against the flight controller's (companion.daemon.mount_watch)."""
from __future__ import annotations

import math
import re
import shutil

import numpy as np
import pytest

from companion.daemon.mount_watch import level_difference_deg
from companion.geometry import frames
from companion.types import AttitudeSample
from mavlink_peer import PeerProcess, free_port
from test_daemon import AISLE, finish, start_daemon, write_config

SAID = re.compile(r"the markers and the flight controller disagree on level by ([0-9.]+) deg \(median of the last "
                  r"(\d+) frames; markers - FC: roll ([-+0-9.]+), pitch ([-+0-9.]+) deg\)")


def test_level_difference_is_the_angle_between_the_two_downs_whatever_the_yaw():
    R_ned_body = frames.rotation_from_euler_321(math.radians(2.0), math.radians(-3.0), math.radians(140.0))
    angle, roll, pitch = level_difference_deg(R_ned_body, AttitudeSample(0, 0.0, 0.0))
    assert roll == pytest.approx(2.0) and pitch == pytest.approx(-3.0)
    down = R_ned_body.T @ np.array([0.0, 0.0, 1.0])
    assert angle == pytest.approx(math.degrees(math.acos(down[2])))
    assert level_difference_deg(R_ned_body, AttitudeSample(0, math.radians(2.0), math.radians(-3.0)))[0] < 1e-6


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
