"""The attitude's home (AttitudeHistory), attitude.csv, the clock of ATTITUDE, config, replay and simulate."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from companion import cli
from companion.capture.attitude_csv import (AttitudeCsvWriter, AttitudeFileError, read_attitude_csv,
                                            write_attitude_csv)
from companion.capture.replay import open_recording, ReplaySource
from companion.capture.source import SourceError
from companion.daemon.config import ConfigError, config_from_dict
from companion.geometry import frames
from companion.geometry.attitude import AttitudeHistory, history_of
from companion.mavlink import messages as mm
from companion.mavlink.attitude import AttitudeStream, BootClock
from companion.sim import simulate
from companion.types import AttitudeSample, Frame

REPO = Path(__file__).resolve().parents[1]
HOVER = REPO / "tests" / "data" / "sequences" / "warehouse_hover"
MS = 1_000_000


# ------------------------------------------------------------------ history

def test_history_interpolates_between_samples_and_holds_the_newest_briefly():
    h = AttitudeHistory(max_age_s=0.05)
    h.add(AttitudeSample(0, 0.0, 0.2))
    h.add(AttitudeSample(20 * MS, 0.1, 0.0))
    a = h.at(5 * MS)  # a quarter of the way: by hand
    assert (a.t_ns, a.roll_rad, a.pitch_rad) == (5 * MS, pytest.approx(0.025), pytest.approx(0.15))
    assert h.at(20 * MS + 49 * MS).roll_rad == 0.1     # after the newest: held while younger than max_age
    assert h.at(20 * MS + 51 * MS) is None             # stale
    assert h.at(-10 * MS).pitch_rad == 0.2            # just before the first sample: it, if young enough
    assert h.at(-60 * MS) is None


def test_history_does_not_interpolate_across_a_gap():
    h = AttitudeHistory(max_age_s=0.1)
    h.add(AttitudeSample(0, 0.0, 0.0))
    h.add(AttitudeSample(500 * MS, 0.5, 0.5))  # a 0.5 s gap in the stream
    assert h.at(50 * MS).roll_rad == 0.0        # the sample before, still young enough
    assert h.at(300 * MS) is None               # in the middle of the gap: stale


def test_history_roll_interpolates_across_plus_minus_pi():
    h = history_of([AttitudeSample(0, math.pi - 0.1, 0.0), AttitudeSample(10 * MS, -math.pi + 0.1, 0.0)])
    assert abs(math.remainder(h.at(5 * MS).roll_rad - math.pi, 2 * math.pi)) < 1e-12


def test_history_drops_out_of_order_samples_and_bisects_long_recordings():
    h = history_of([AttitudeSample(k * 20 * MS, k * 0.001, 0.0) for k in range(1000)])
    assert not h.add(AttitudeSample(5 * MS, 0.0, 0.0)) and h.out_of_order == 1
    assert h.at(12_345 * MS).roll_rad == pytest.approx(12_345 / 20 * 0.001)
    with pytest.raises(ValueError, match="max_age_s"):
        AttitudeHistory(max_age_s=0)


# -------------------------------------------------------------- attitude.csv

def test_attitude_csv_round_trip_and_streaming_writer(tmp_path):
    samples = [AttitudeSample(k * 20 * MS, math.radians(0.5 * k), math.radians(-0.25 * k)) for k in range(5)]
    write_attitude_csv(tmp_path / "a.csv", samples)
    assert (tmp_path / "a.csv").read_text().splitlines()[:2] == ["t_ns,roll_deg,pitch_deg", "0,0.000000,-0.000000"]
    back = read_attitude_csv(tmp_path / "a.csv")
    assert [s.t_ns for s in back] == [s.t_ns for s in samples]
    np.testing.assert_allclose([s.roll_rad for s in back], [s.roll_rad for s in samples], atol=1e-6)
    with AttitudeCsvWriter(tmp_path / "b.csv") as writer:
        for s in samples:
            writer.write(s)
    assert (tmp_path / "b.csv").read_text() == (tmp_path / "a.csv").read_text()


@pytest.mark.parametrize("text, words", [
    ("t_ns,roll,pitch\n0,1,2\n", "the header must be t_ns,roll_deg,pitch_deg"),
    ("t_ns,roll_deg,pitch_deg\n0,1\n", "line 2: want 3 values"),
    ("t_ns,roll_deg,pitch_deg\n0,a,2\n", "line 2: t_ns must be an integer"),
    ("t_ns,roll_deg,pitch_deg\n0,1,95\n", r"pitch within \+-90"),
    ("t_ns,roll_deg,pitch_deg\n10,1,2\n5,1,2\n", "t_ns must rise"),
    (b"\xf0\x9f\x00\xc5 not text", "cannot read .*not an attitude table"),
])
def test_bad_attitude_csv_is_one_line_naming_the_file(tmp_path, text, words):
    if isinstance(text, bytes):
        (tmp_path / "attitude.csv").write_bytes(text)
    else:
        (tmp_path / "attitude.csv").write_text(text)
    with pytest.raises(AttitudeFileError, match=words) as error:
        read_attitude_csv(tmp_path / "attitude.csv")
    assert str(error.value).startswith(str(tmp_path / "attitude.csv")) and "\n" not in str(error.value)


# ------------------------------------------------------------------- replay

def test_replay_attitude_is_the_recording_at_each_frames_recorded_time(tmp_path):
    """As fast as possible (frames stamped when read) and looping: each frame still gets the attitude of
    its recorded capture time, which the file gives (read here by hand)."""
    rows = [line.split(",") for line in (HOVER / "attitude.csv").read_text().splitlines()[1:]]
    source = ReplaySource(open_recording(HOVER), realtime=False, loop=True)
    lookup = source.attitude_lookup(max_age_s=0.1)
    recording = source.recording
    for index in (0, 7, 31 + 7):  # the 8th frame, then the same frame in the second loop
        frame = Frame(np.zeros((2, 2), np.uint8), t_ns=123_456_789_000 + index, index=index)
        t_ns = int(recording.t_ns[index % 31])
        before = max((r for r in rows if int(r[0]) <= t_ns), key=lambda r: int(r[0]))
        after = min((r for r in rows if int(r[0]) > t_ns), key=lambda r: int(r[0]))
        f = (t_ns - int(before[0])) / (int(after[0]) - int(before[0]))
        roll_deg = float(before[1]) + f * (float(after[1]) - float(before[1]))
        assert math.degrees(lookup(frame).roll_rad) == pytest.approx(roll_deg, abs=1e-6)


def test_replay_without_attitude_and_with_a_broken_one(tmp_path):
    folder = tmp_path / "seq"
    shutil.copytree(HOVER, folder)
    (folder / "attitude.csv").unlink()
    assert ReplaySource(open_recording(folder)).attitude_lookup() is None
    (folder / "attitude.csv").write_text("t_ns,roll_deg\n")
    with pytest.raises(SourceError, match=r"attitude.csv: the header must be"):
        open_recording(folder)
    code = cli.main(["localize", str(folder)])
    assert code == 2


# ---------------------------------------------------------------- simulate

def test_simulate_writes_the_truths_attitude_with_its_noise_and_bias(tmp_path):
    out = tmp_path / "seq"
    assert cli.main(["simulate", str(out), "--map", str(REPO / "maps" / "warehouse.yaml"), "--pattern", "waypoints",
                     "--waypoints", "4,5,1.5,0;6,5,1.5,0", "--speed", "2", "--max-accel", "3", "--fps", "5",
                     "--attitude-noise", "0", "--attitude-bias", "1.0", "--attitude-rate", "100",
                     "--no-progress"]) == 0
    samples = read_attitude_csv(out / "attitude.csv")
    assert np.median(np.diff([s.t_ns for s in samples])) == 10 * MS
    sequence = simulate.read_sequence(out)
    h = history_of(samples)
    tilts = []
    for t_ns, T_ned_body in zip(sequence.t_ns, sequence.T_ned_body):
        roll, pitch = frames.roll_pitch_321(T_ned_body[:3, :3])  # the ground truth written beside it
        a = h.at(int(t_ns))
        tilts.append(abs(pitch))
        # the bias on both angles; 100 Hz samples of a smooth flight interpolate to within 0.05 deg
        assert math.degrees(a.roll_rad - roll) == pytest.approx(1.0, abs=0.05)
        assert math.degrees(a.pitch_rad - pitch) == pytest.approx(1.0, abs=0.05)
    assert max(tilts) > math.radians(5)  # accelerating at 3 m/s^2: the body pitches, so the test sees motion
    assert sequence.info["attitude"] == {"rate_hz": 100.0, "noise_deg": 0.0, "bias_deg": 1.0}
    assert cli.main(["simulate", str(tmp_path / "none"), "--map", str(REPO / "maps" / "warehouse.yaml"),
                     "--duration", "0.2", "--no-attitude", "--no-progress"]) == 0
    assert not (tmp_path / "none" / "attitude.csv").exists()
    assert cli.main(["simulate", str(tmp_path / "bad"), "--map", str(REPO / "maps" / "warehouse.yaml"),
                     "--attitude-noise", "-1"]) == 2


# ------------------------------------------------------------ ATTITUDE clock

class Attitude:
    """An ATTITUDE as pymavlink gives it (the builder of the real message, then its fields)."""

    def __new__(cls, boot_ms, roll=0.01, pitch=-0.02):
        return mm.mavlink2.MAVLink_attitude_message(boot_ms, roll, pitch, 0.3, 0.0, 0.0, 0.0)


def test_boot_clock_takes_the_promptest_message_and_follows_a_reboot():
    # the autopilot booted at our 1000 s; messages arrive 0.3-5 ms after they were stamped
    boot_ns, rng = 1_000_000_000_000, np.random.default_rng(1)
    history = AttitudeHistory(0.1)
    stream = AttitudeStream(history, rate_hz=50)
    for k in range(200):
        stamp_ns = boot_ns + 5_000 * MS + k * 20 * MS + int(rng.uniform(0, MS))
        boot_ms = (stamp_ns - boot_ns) // MS
        stream.on_message(Attitude(boot_ms), stamp_ns + int(rng.uniform(0.3, 5.0) * MS))
    last = history.newest()
    assert abs(last.t_ns - stamp_ns) < 1.5 * MS
    # a reboot: time_boot_ms starts again near 0; the history restarts
    stream.on_message(Attitude(3_000), stamp_ns + 500 * MS)
    assert len(history.samples()) == 1 and abs(history.newest().t_ns - (stamp_ns + 500 * MS)) < MS
    clock = BootClock(window_s=1.0)
    assert clock.to_monotonic_ns(100, 10 * 10**9) == 10 * 10**9 + MS // 2 - 0  # one sample: its own delay


def test_attitude_quaternion_gives_the_same_roll_and_pitch():
    R = frames.rotation_from_euler_321(0.1, -0.2, 2.5)
    q = frames.quaternion_from_rotation(R)
    message = mm.mavlink2.MAVLink_attitude_quaternion_message(1000, *[float(v) for v in q], 0.0, 0.0, 0.0)
    history = AttitudeHistory()
    AttitudeStream(history).on_message(message, 10**9)
    assert (history.newest().roll_rad, history.newest().pitch_rad) == (pytest.approx(0.1), pytest.approx(-0.2))


def test_set_message_interval_asks_for_attitude_at_the_rate_then_again_only_while_slow():
    stream = AttitudeStream(AttitudeHistory(), rate_hz=50, request_retry_s=2.0)
    [command] = stream.requests_due(100.0, 1, 1)
    assert (command.command, command.param1, command.param2, command.target_system) == (511, 30.0, 20_000.0, 1)
    assert stream.requests_due(101.0, 1, 1) == []           # asked a second ago
    for k in range(100):                                     # 50 Hz arriving
        stream.on_message(Attitude(k * 20), int((101.0 + k * 0.02) * 1e9))
    assert stream.requests_due(103.1, 1, 1) == []            # streaming at the rate: no request
    assert len(stream.requests_due(106.0, 1, 1)) == 1        # silent for 3 s: asked again


# ------------------------------------------------------------------- config

def config_with(**sections):
    return {"source": {"kind": "v4l2"}, "camera": {"width": 640, "height": 480, "hfov_deg": 70.0},
            "map": str(REPO / "maps" / "warehouse.yaml"), **sections}


def test_attitude_config_defaults_and_errors():
    config = config_from_dict(config_with(), "site.yaml")
    assert (config.attitude.source, config.attitude.max_age_s, config.attitude.rate_hz) == ("auto", 0.1, 50.0)
    assert config_from_dict(config_with(attitude={"source": "none", "max_age_s": 0.2}), "site.yaml").attitude.source == "none"
    for section, message in (({"source": "imu"}, r"^site.yaml: attitude.source: must be one of auto, link, none, got 'imu'$"),
                             ({"max_age_s": 0}, r"^site.yaml: attitude.max_age_s: must be >= 0.005"),
                             ({"rate_hz": 1000}, r"^site.yaml: attitude.rate_hz: must be <= 500, got 1000$"),
                             ({"rate": 50}, r"^site.yaml: attitude.rate: unknown key 'rate'")):
        with pytest.raises(ConfigError, match=message):
            config_from_dict(config_with(attitude=section), "site.yaml")
    with pytest.raises(ConfigError, match=r"pose: pose parameter attitude_sd_deg must be a positive number"):
        config_from_dict(config_with(pose={"attitude_sd_deg": 0}), "site.yaml")
