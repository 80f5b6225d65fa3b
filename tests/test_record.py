"""Flight recording: `companion run --record DIR` writes a sequence folder that replay reads back.

The round trip runs the real daemon as a user would (a subprocess, UDP to a
loopback port with nothing listening), copies the recording elsewhere and
replays the copy: the frames must be the pixels the daemon processed and the
poses the same.
"""
from __future__ import annotations

import csv
import datetime
import math
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.capture.replay import open_recording, replay_source
from companion.daemon.config import ConfigError, config_from_dict
from companion.daemon.record import (ESTIMATE_COLUMNS, VERDICTS, Recorder, RecordError, RecordParams,
                                     expand_folder)
from companion.daemon.service import Daemon
from companion.geometry.camera import CameraModel
from mavlink_peer import free_port

REPO = Path(__file__).resolve().parent.parent
HOVER = REPO / "tests" / "data" / "sequences" / "warehouse_hover"   # 31 frames at 15 fps, mp4v video
MAP = REPO / "maps" / "warehouse.yaml"


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def decoded_frames(sequence: Path) -> dict[int, np.ndarray]:
    """Frame number -> (H, W) gray image, as the replay decodes them."""
    source = replay_source(sequence, realtime=False)
    source.start()
    images = {}
    try:
        while True:
            frame = source.get(timeout_s=2.0)
            if frame is None:
                break
            images[frame.index] = frame.image
    finally:
        source.close()
    return images


def run_companion(config: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion", "run", "--config", str(config), *options],
                          capture_output=True, text=True, timeout=60)


def write_config(folder: Path, source: dict, **sections) -> Path:
    data = {"source": source,
            # nothing listens: stream at once (no origin handshake, no listening for another companion)
            "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}", "origin_wait_s": 0.0, "duplicate_listen_s": 0.0}, **sections}
    path = folder / f"config{len(list(folder.glob('config*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def measured_poses(recording: Path) -> dict[int, np.ndarray]:
    """Frame -> the raw pose stage's NED position and attitude (6,), from estimates.csv."""
    columns = [c for c in ESTIMATE_COLUMNS if c.startswith("meas_")]
    return {int(r["frame"]): np.array([float(r[c]) for c in columns])
            for r in read_rows(recording / "estimates.csv") if r["meas_north_m"]}


# ----------------------------------------------------------------- round trip

def test_a_recorded_replay_replays_from_a_copy_with_the_same_frames_and_poses(tmp_path):
    first = tmp_path / "first"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": False}, map=str(MAP))
    run = run_companion(config, "--record", str(first))
    assert run.returncode == 0, run.stderr
    assert f"recording to {first}" in run.stderr

    # what the daemon processed, pixel for pixel (FFV1 is lossless), with the source's frame numbers
    original = decoded_frames(HOVER)
    recorded = decoded_frames(first)
    assert sorted(recorded) == sorted(original) == list(range(31))
    for index, image in original.items():
        assert np.array_equal(recorded[index], image), f"frame {index} differs"

    info = yaml.safe_load((first / "sequence.yaml").read_text())
    assert info["map"] == "map.yaml" and (first / "map.yaml").read_text() == MAP.read_text()
    camera = CameraModel.from_config(info["camera"], "recorded")
    hover_camera = CameraModel.from_config(yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"], "hover")
    np.testing.assert_allclose(camera.K, hover_camera.K)
    np.testing.assert_allclose(camera.T_body_camera, hover_camera.T_body_camera, atol=1e-9)
    assert (info["frames"], info["dropped_frames"], info["stopped"]) == (31, 0, "the daemon stopped")
    # the replayed sequence's ground truth comes along, same frame numbers
    assert (first / "groundtruth.csv").read_text() == (HOVER / "groundtruth.csv").read_text()

    rows = read_rows(first / "estimates.csv")
    assert [int(r["frame"]) for r in rows] == list(range(31))
    assert {r["verdict"] for r in rows} <= set(VERDICTS)
    # a fresh fix in nearly every frame; as fast as possible, the link's rate limit holds most back ("link")
    assert sum(r["verdict"] in ("ok", "link") for r in rows) >= 25, [r["verdict"] for r in rows]
    sent = [r for r in rows if r["sent"] == "1"]
    covariance = np.array([[float(r["cov_north_north"]), float(r["cov_east_east"]), float(r["cov_down_down"])]
                           for r in sent])
    assert len(sent) >= 3 and np.all(covariance > 0)
    detections = read_rows(first / "detections.csv")
    assert {d["frame"] for d in detections} >= {r["frame"] for r in rows if r["verdict"] == "ok"}

    # the recorded poses are right: against the hover flight's ground truth
    truth = {int(r["frame"]): np.array([float(r["north_m"]), float(r["east_m"]), float(r["down_m"])])
             for r in read_rows(HOVER / "groundtruth.csv")}
    first_poses = measured_poses(first)
    errors = [np.linalg.norm(pose[:3] - truth[frame]) for frame, pose in first_poses.items()]
    assert len(errors) >= 25 and np.median(errors) < 0.05

    # copied anywhere, the recording replays with no camera or map in the config
    moved = shutil.copytree(first, tmp_path / "elsewhere" / "flight")
    shutil.rmtree(first)
    second = tmp_path / "second"
    config = write_config(tmp_path, {"kind": "replay", "path": str(moved), "realtime": False})
    run = run_companion(config, "--record", str(second))
    assert run.returncode == 0, run.stderr
    second_poses = measured_poses(second)
    assert sorted(second_poses) == sorted(first_poses)
    # half a millimetre apart at most (the poses' errors are millimetres): the pose stage weighs each marker
    # at its starting pose, which follows the filter's prior, and the filter's steps follow the pace of a
    # replay as fast as possible (measured: up to 0.11 mm on a loaded machine)
    for frame, pose in first_poses.items():
        np.testing.assert_allclose(second_poses[frame], pose, atol=5e-4, err_msg=f"frame {frame}")


def test_mjpg_recording_is_high_quality_and_replays(tmp_path):
    folder = tmp_path / "flight"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": False}, map=str(MAP),
                          record={"path": str(folder), "codec": "mjpg", "jpeg_quality": 95})
    run = run_companion(config)
    assert run.returncode == 0, run.stderr
    original, recorded = decoded_frames(HOVER), decoded_frames(folder)
    assert sorted(recorded) == sorted(original)
    for index, image in original.items():
        difference = np.abs(recorded[index].astype(int) - image)
        assert difference.mean() < 1.5 and np.percentile(difference, 99) <= 6, index
    assert yaml.safe_load((folder / "sequence.yaml").read_text())["video_codec"] == "mjpg"


# ------------------------------------------------------------ limits, slow disk

def test_the_duration_limit_stops_the_recording_not_the_daemon(tmp_path):
    folder = tmp_path / "flight"
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(HOVER), "realtime": True},
        "map": str(MAP),
        "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}", "origin_wait_s": 0.0, "duplicate_listen_s": 0.0},
        "record": {"path": str(folder), "max_duration_s": 0.5},
    }, tmp_path / "daemon.yaml")
    daemon = Daemon(config)
    assert daemon.run() == 0
    info = yaml.safe_load((folder / "sequence.yaml").read_text())
    assert info["stopped"] == "duration limit reached (0.5 s)"
    recording = open_recording(folder)
    # frames at 15 fps (66.7 ms apart) from t = 0 up to the first one at or past 0.5 s
    assert recording.t_ns[-1] <= 0.5e9 + 66_666_667 and recording.t_ns[-1] >= 0.5e9 - 66_666_667
    assert daemon.pipeline.stats.frames > len(recording.t_ns) == info["frames"]
    assert len(decoded_frames(folder)) == info["frames"]


def test_a_slow_disk_drops_recorded_frames_counted_never_rows(tmp_path):
    """Frames offered far faster than FFV1 encodes them: the images beyond the budget are dropped and
    counted, every frame's estimate row is still written, and timestamps match the video."""
    daemon_config = config_from_dict({"source": {"kind": "replay", "path": str(HOVER)}, "map": str(MAP)},
                                     tmp_path / "c.yaml")
    recorder = Recorder(RecordParams(path=tmp_path / "flight", queue_frames=2), daemon_config.camera, MAP)
    recorder.start()
    from companion.daemon.pipeline import FrameRecord
    from companion.types import Frame
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(4)]
    offered = 200
    for index in range(offered):
        record = FrameRecord(index, 1_000_000 + index * 10_000_000, 0, (0, 0, 0, 0), False, None, (), None, None)
        recorder(Frame(images[index % 4], record.t_ns, index), record)
    recorder.close()
    counters = recorder.counters
    assert counters.dropped_frames > 0
    assert counters.frames + counters.dropped_frames == offered
    assert counters.rows == offered and counters.dropped_rows == 0
    rows = read_rows(tmp_path / "flight" / "estimates.csv")
    assert len(rows) == offered and {r["verdict"] for r in rows} == {"no marker"}
    recording = open_recording(tmp_path / "flight")
    assert len(recording.t_ns) == counters.frames
    assert yaml.safe_load((tmp_path / "flight" / "sequence.yaml").read_text())["dropped_frames"] == \
        counters.dropped_frames
    decoded = decoded_frames(tmp_path / "flight")
    for number, image in decoded.items():
        assert np.array_equal(image, images[number % 4])


def test_recording_and_pipeline_threads_end_when_the_daemon_stops(tmp_path):
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(HOVER), "realtime": True, "loop": True},
        "map": str(MAP),
        "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}", "origin_wait_s": 0.0, "duplicate_listen_s": 0.0},
        "record": str(tmp_path / "flight"),
    }, tmp_path / "daemon.yaml")
    daemon = Daemon(config)
    runner = threading.Thread(target=daemon.run)
    runner.start()
    threading.Event().wait(1.0)
    daemon.stop_event.set()
    runner.join(timeout=15)
    assert not runner.is_alive()
    assert not any(t.name == "record" and t.is_alive() for t in threading.enumerate())
    assert yaml.safe_load((tmp_path / "flight" / "sequence.yaml").read_text())["stopped"] == "the daemon stopped"


# ---------------------------------------------------------------- bad input

def test_an_existing_recording_is_never_overwritten(tmp_path):
    folder = tmp_path / "flight"
    folder.mkdir()
    (folder / "timestamps.csv").write_text("frame,t_ns,file\n")
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER)}, map=str(MAP))
    run = run_companion(config, "--record", str(folder))
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "already exists and is not an empty folder" in run.stderr
    assert "Traceback" not in run.stderr
    assert (folder / "timestamps.csv").read_text() == "frame,t_ns,file\n"


def test_time_in_the_path_makes_a_folder_per_run():
    moment = datetime.datetime(2026, 12, 1, 12, 33, 52)
    assert expand_folder(Path("/var/lib/companion/flight-{time}"), moment) == \
        Path("/var/lib/companion/flight-2026-12-01T12-33-52")


@pytest.mark.parametrize("section, message", [
    ({"path": "x", "codec": "h264"}, "record: codec must be one of ffv1, mjpg, got 'h264'"),
    ({"path": "x", "max_size_mb": 0}, "record: max_size_mb must be positive, got 0"),
    ({"path": "x", "jpeg_quality": 101}, "record: jpeg_quality must be an integer in 1..100, got 101"),
    ({"codec": "ffv1"}, "record.path: missing"),
    ({"path": "x", "speed": 2}, "record.speed: unknown key 'speed'"),
    (["x"], "record: must be a mapping"),
])
def test_record_section_errors_name_the_key(tmp_path, section, message):
    with pytest.raises(ConfigError, match=message.replace(".", r"\.").replace("(", r"\(")):
        config_from_dict({"source": {"kind": "replay", "path": str(HOVER)}, "map": str(MAP), "record": section},
                         tmp_path / "daemon.yaml")


def test_a_missing_record_path_names_the_file_once(tmp_path):
    with pytest.raises(ConfigError) as raised:
        config_from_dict({"source": {"kind": "replay", "path": str(HOVER)}, "map": str(MAP),
                          "record": {"codec": "ffv1"}}, tmp_path / "daemon.yaml")
    assert str(raised.value) == f"{tmp_path / 'daemon.yaml'}: record.path: missing"


def run_in_child(argv: list[str], as_nobody: bool) -> tuple[int, str]:
    """``companion ARGV`` in a forked child of this process, as the user nobody when ``as_nobody`` and
    this is root (without exec: this interpreter needs nothing more from the disk than the config and
    the recording); returns its exit status and its stderr."""
    import importlib
    import tempfile

    from companion.cli import main
    importlib.import_module("companion.cli.run")   # before the fork: the child may not read the code
    with tempfile.TemporaryFile("w+") as stderr:
        pid = os.fork()
        if pid == 0:
            code = 99
            try:
                sys.stderr = stderr
                if as_nobody and os.geteuid() == 0:
                    os.setgroups([])
                    os.setgid(65534)
                    os.setuid(65534)
                code = main(argv)
            except BaseException as error:   # noqa: BLE001  the test reads it
                print(f"child failed: {error!r}", file=stderr)
            finally:
                stderr.flush()
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        stderr.seek(0)
        return os.waitstatus_to_exitcode(status), stderr.read()


@pytest.mark.parametrize("blocked", ["unsearchable", "read-only", "too long"])
@pytest.mark.parametrize("given", ["config", "--record"])
def test_a_record_path_that_cannot_be_written_is_one_line_naming_the_key(given, blocked):
    """A record path in a folder the daemon's user cannot enter or write in (or a name the file system
    refuses): one line naming record.path (or --record) and the folder, exit 2, no traceback."""
    import tempfile
    top = Path(tempfile.mkdtemp(dir="/tmp"))   # pytest's tmp_path is root's alone
    try:
        os.chmod(top, 0o755)
        sequence = shutil.copytree(HOVER, top / "hover")
        flight_map = shutil.copyfile(MAP, top / "warehouse.yaml")
        parent = top / "parent"
        parent.mkdir()
        folder = parent / ("x" * 300 if blocked == "too long" else "flight")
        os.chmod(parent, {"unsearchable": 0o000, "read-only": 0o555, "too long": 0o755}[blocked])
        if os.geteuid() != 0 and blocked != "too long" and os.access(parent, os.W_OK):
            pytest.skip("this user writes anywhere")
        config = write_config(top, {"kind": "replay", "path": str(sequence)}, map=str(flight_map),
                              **({"record": str(folder)} if given == "config" else {}))
        os.chmod(config, 0o644)
        code, stderr = run_in_child(["run", "--config", str(config),
                                     *(["--record", str(folder)] if given == "--record" else [])],
                                    as_nobody=blocked != "too long")
    finally:
        os.chmod(top / "parent", 0o755)
        shutil.rmtree(top)
    why = "File name too long" if blocked == "too long" else "Permission denied"
    where = f"{config}: record.path" if given == "config" else "--record"
    assert code == 2, stderr
    assert stderr.count("\n") == 1 and stderr.rstrip().endswith(f"ERROR companion: {where}: cannot write {folder}: {why}"), \
        stderr


def test_recorder_refuses_a_file_in_the_way(tmp_path):
    (tmp_path / "flight").write_text("not a folder")
    with pytest.raises(RecordError, match="flight already exists"):
        Recorder(RecordParams(path=tmp_path / "flight"), None, MAP)


def test_attitude_samples_are_recorded_on_the_frames_clock(tmp_path):
    """attitude.csv (t_ns,roll_deg,pitch_deg) with t_ns on the time base of timestamps.csv (0 = first frame);
    samples from before the first frame have no place on it and are left out, and so is one that is not
    after the last (replay needs rising times)."""
    from companion.daemon.pipeline import FrameRecord
    from companion.types import AttitudeSample, Frame
    recorder = Recorder(RecordParams(path=tmp_path / "flight"), CameraModel.from_config(
        yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"], "hover"), MAP)
    recorder.start()
    start_ns = 5_000_000_000
    recorder.attitude(AttitudeSample(start_ns - 10_000_000, math.radians(9.0), math.radians(9.0)))
    for index in range(3):
        t_ns = start_ns + index * 33_000_000
        record = FrameRecord(index, t_ns, t_ns, (0, 0, 0, 0), False, None, (), None, None)
        recorder(Frame(np.zeros((480, 640), np.uint8), t_ns, index), record)
        recorder.attitude(AttitudeSample(t_ns + 5_000_000, math.radians(1.5 + index), math.radians(-2.25)))
        recorder.attitude(AttitudeSample(t_ns + 4_000_000, math.radians(7.0), math.radians(7.0)))
    recorder.close()
    rows = read_rows(tmp_path / "flight" / "attitude.csv")
    assert [(int(r["t_ns"]), float(r["roll_deg"]), float(r["pitch_deg"])) for r in rows] == \
        [(5_000_000, 1.5, -2.25), (38_000_000, 2.5, -2.25), (71_000_000, 3.5, -2.25)]
    assert [int(t) for t in open_recording(tmp_path / "flight").t_ns] == [0, 33_000_000, 66_000_000]


def test_the_daemons_log_is_recorded_at_the_newest_frame(tmp_path, caplog):
    """events.csv (frame,t_ns,level,text): the daemon's log (the companion logger and its children, INFO and
    up) from start to close: a line logged before the first frame has neither; one after frame k carries k
    and on the recording's time base k's time plus the time since k came; commas and quotes kept; DEBUG,
    other loggers and what is logged after close are not."""
    import logging
    from companion.daemon.pipeline import FrameRecord
    from companion.types import Frame
    recorder = Recorder(RecordParams(path=tmp_path / "flight"), CameraModel.from_config(
        yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"], "hover"), MAP)
    caplog.set_level(logging.DEBUG, logger="companion")   # DEBUG lines are made, and still not recorded
    recorder.start()
    logging.getLogger("companion.mavlink.link").warning("link: no flight controller heard for %.1f s", 3.0)
    long_text = 'marker "X", seen 40 times, disagrees with the map by 12 cm (companion map check)'
    start_ns = 7_000_000_000
    for index in range(3):
        t_ns = start_ns + index * 50_000_000
        recorder(Frame(np.zeros((480, 640), np.uint8), t_ns, index + 10),
                 FrameRecord(index + 10, t_ns, t_ns, (0, 0, 0, 0), False, None, (), None, None))
        if index == 1:
            logging.getLogger("companion").error(long_text.replace(" (", "\n("))   # one row, one line
            logging.getLogger("companion").debug("not recorded")
            logging.getLogger("elsewhere").warning("not ours")
    recorder.close()
    logging.getLogger("companion").warning("after the recording")
    rows = [tuple(r.values()) for r in read_rows(tmp_path / "flight" / "events.csv")]
    assert rows[0][:3] == ("", "", "INFO") and rows[0][3].startswith(f"recording to {tmp_path / 'flight'}")
    assert rows[1] == ("", "", "WARNING", "link: no flight controller heard for 3.0 s")
    # frame 11 (50 ms after the first), its time and the little time since it came
    assert rows[2][0] == "11" and rows[2][2:] == ("ERROR", long_text) and 50_000_000 <= int(rows[2][1]) < 1_050_000_000
    assert rows[3][0] == "12" and rows[3][2:] == ("INFO", "recording stopped: the daemon stopped") and len(rows) == 4


def test_a_disk_without_room_refuses_the_recording_at_the_start_and_vision_goes_on(tmp_path):
    """Less than min_free_mb free when the daemon starts (the disk's real free space, with the floor set
    above it): the recording is not started, one line says why, no folder is made; every frame is still
    processed and sent."""
    folder = tmp_path / "flight"
    floor_mb = shutil.disk_usage(tmp_path).free / 1e6 + 1000.0
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": False}, map=str(MAP),
                          record={"path": str(folder), "min_free_mb": floor_mb})
    run = run_companion(config)
    assert run.returncode == 0, run.stderr
    said = [line for line in run.stderr.splitlines() if "recording" in line or str(folder) in line]
    assert len(said) == 1 and re.search(
        r"WARNING companion: recording not started: [0-9.]+ MB free on the disk of " + re.escape(
            f"{folder}, less than record.min_free_mb ({floor_mb:g} MB); the daemon goes on without it") + "$",
        said[0]), said
    assert not folder.exists()
    assert re.search(r"frames 31, sent [1-9]", run.stderr), run.stderr


def test_a_recording_that_holds_no_frame_is_removed(tmp_path, caplog):
    """Nothing to replay: what the recorder wrote goes, and the folder if it made it (one it was given
    empty stays, empty)."""
    camera = CameraModel.from_config(yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"], "hover")
    given = tmp_path / "given"
    given.mkdir()
    for folder in (tmp_path / "new" / "flight", given):
        recorder = Recorder(RecordParams(path=folder), camera, MAP)
        recorder.start()
        assert (folder / "sequence.yaml").is_file()
        recorder.close()
    assert not (tmp_path / "new" / "flight").exists() and (tmp_path / "new").is_dir()
    assert given.is_dir() and list(given.iterdir()) == []
    said = [r.getMessage() for r in caplog.records if "no frame recorded" in r.getMessage()]
    assert said == [f"recording: no frame recorded (the daemon stopped); {tmp_path / 'new' / 'flight'} removed",
                    f"recording: no frame recorded (the daemon stopped); {given} left empty"]


def test_a_table_the_disk_took_part_of_is_cut_after_its_last_whole_row(tmp_path):
    """A full disk stops a flush anywhere, in a row or in the header: what is left is whole rows."""
    from companion.daemon.record import count_rows, cut_after_last_line
    table = tmp_path / "estimates.csv"
    table.write_bytes(b"frame,t_ns,file\r\n0,0,\r\n1,33,\r\n2,6")
    cut_after_last_line(table)
    assert table.read_bytes() == b"frame,t_ns,file\r\n0,0,\r\n1,33,\r\n" and count_rows(table) == 2
    table.write_bytes(b"frame,t_n")
    cut_after_last_line(table)
    assert table.read_bytes() == b"" and count_rows(table) == 0
    long = b"x" * 100_000 + b"\n" + b"y" * 100_000   # the end is read back in blocks
    table.write_bytes(long)
    cut_after_last_line(table)
    assert table.stat().st_size == 100_001


# ------------------------------------------------------ faults while recording

def wait_for(condition, what: str, timeout_s: float = 60.0) -> None:
    """Wait until ``condition()`` holds (polled; the deadline is only a guard against a hang)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        time.sleep(0.05)


def test_a_recording_folder_removed_mid_run_is_said_once_and_vision_goes_on(tmp_path):
    """`rm -rf` of the folder being recorded: the recording stops, one line says why (no traceback from the
    record thread), and the daemon keeps positioning until it is stopped."""
    folder = tmp_path / "flight"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": True, "loop": True},
                          map=str(MAP))
    log_path, status_path = tmp_path / "stderr.txt", tmp_path / "stdout.txt"

    def last_sent() -> int:
        return ([0] + [int(n) for n in re.findall(r"sent (\d+)", status_path.read_text())])[-1]

    with open(log_path, "w") as log_file, open(status_path, "w") as status_file:
        daemon = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config),
                                   "--record", str(folder)], stdout=status_file, stderr=log_file)
        try:
            # some frames on disk (the tables are flushed every second), then the folder goes
            wait_for(lambda: (folder / "timestamps.csv").is_file()
                     and len((folder / "timestamps.csv").read_text().splitlines()) > 3, "recorded frames")
            shutil.rmtree(folder)
            wait_for(lambda: "removed" in log_path.read_text() or "Traceback" in log_path.read_text(),
                     "the daemon to notice", timeout_s=30.0)
            # vision goes on: the status line's count of fixes sent still rises
            sent_then = last_sent()
            wait_for(lambda: last_sent() > sent_then, "more fixes sent", timeout_s=30.0)
        finally:
            daemon.send_signal(signal.SIGINT)
            daemon.wait(timeout=30)
    log = log_path.read_text()
    assert daemon.returncode == 0, log
    assert "Traceback" not in log and "Exception in thread" not in log, log
    said = [line for line in log.splitlines() if str(folder) in line]
    assert len(said) == 2 and "recording to" in said[0] and "removed" in said[1], log
    assert not folder.exists()


def run_with_file_limit(args: list[str], limit_bytes: int, foresee: bool = True) -> subprocess.CompletedProcess:
    """``companion ARGS`` in a child whose files may not pass ``limit_bytes`` (RLIMIT_FSIZE: a write past it
    fails with EFBIG, as a full disk's with ENOSPC). foresee=False: the recorder is not told of the limit
    (``record.file_size_limit``), as of a limit it cannot know (a file system's own, a quota)."""
    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of the process being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    code = ("import sys; import companion.daemon.record as record; "
            + ("" if foresee else "record.file_size_limit = lambda: None; ")
            + "from companion.cli import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          preexec_fn=limit, timeout=120, cwd=REPO)


def replayed(folder: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    """The daemon replaying ``folder`` as fast as possible."""
    return run_companion(write_config(tmp_path, {"kind": "replay", "path": str(folder), "realtime": False}))


@pytest.mark.parametrize("codec", ["ffv1", "mjpg"])
def test_a_file_size_limit_stops_the_recording_before_the_video_is_cut(tmp_path, codec):
    """Files may not pass 1.5 MB (the hover flight's video is 2 MB): OpenCV's writer would say nothing of
    the writes refused. The recording stops before, says why in the log and in sequence.yaml, and the
    video holds every frame timestamps.csv lists; the daemon processes every frame."""
    folder = tmp_path / "flight"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": False}, map=str(MAP),
                          record={"path": str(folder), "codec": codec})
    run = run_with_file_limit(["run", "--config", str(config)], 1_500_000)
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    info = yaml.safe_load((folder / "sequence.yaml").read_text())
    assert info["stopped"].startswith("file size limit reached (video.avi at "), info["stopped"]
    assert f"recording stopped: {info['stopped']}; {info['frames']} frames in {folder}" in run.stderr
    assert re.search(r"frames 31, sent [1-9]", run.stderr), run.stderr
    listed = [int(r["frame"]) for r in read_rows(folder / "timestamps.csv")]
    assert 0 < info["frames"] == len(listed) < 31
    assert sorted(decoded_frames(folder)) == listed
    again = replayed(folder, tmp_path)
    assert again.returncode == 0 and f"frames {len(listed)}, " in again.stderr and "corrupt 0" in again.stderr, \
        again.stderr


def test_a_video_the_disk_refused_is_said_and_its_frames_counted_honestly(tmp_path):
    """A limit the recorder does not know of (its check of RLIMIT_FSIZE left out): the video is cut at
    1.2 MB, mid-frame, and OpenCV's writer says nothing. At the stop the video file tells: timestamps.csv
    lists only the frames it holds whole, the count says so, the log and sequence.yaml say why; the
    folder replays and `companion report` reads it."""
    folder = tmp_path / "flight"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": False}, map=str(MAP))
    run = run_with_file_limit(["run", "--config", str(config), "--record", str(folder)], 1_200_000, foresee=False)
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    info = yaml.safe_load((folder / "sequence.yaml").read_text())
    held = len(decoded_frames(folder))
    assert 0 < held < 31
    assert info["frames"] == held and len(read_rows(folder / "timestamps.csv")) == held
    assert info["stopped"] == f"video write failed: video.avi holds {held} of the 31 frames written " \
                              "(the disk refused the rest)"
    said = [line for line in run.stderr.splitlines() if " ERROR " in line]
    assert len(said) == 1 and f"{folder / 'video.avi'} holds {held} of the 31 frames written" in said[0], said
    assert f"recorded {held} frames (0 dropped) to {folder}: video write failed" in run.stderr
    again = replayed(folder, tmp_path)
    assert again.returncode == 0 and f"frames {held}, " in again.stderr and "corrupt 0" in again.stderr, \
        again.stderr
    report = subprocess.run([sys.executable, "-m", "companion", "report", str(folder)], capture_output=True,
                            text=True, timeout=120)
    assert report.returncode == 0, report.stderr


def test_a_file_size_limit_too_small_for_a_video_refuses_the_recording_at_the_start(tmp_path):
    folder = tmp_path / "flight"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": False}, map=str(MAP))
    run = run_with_file_limit(["run", "--config", str(config), "--record", str(folder)], 200_000)
    assert run.returncode == 0, run.stderr
    said = [line for line in run.stderr.splitlines() if "recording" in line or str(folder) in line]
    assert len(said) == 1 and said[0].endswith(
        "recording not started: a file may have at most 0.20 MB here (RLIMIT_FSIZE, ulimit -f), too little for "
        "a video; the daemon goes on without it"), said
    assert not folder.exists()
    assert re.search(r"frames 31, sent [1-9]", run.stderr), run.stderr


def test_avi_frames_counts_the_frames_a_cut_video_holds_whole(tmp_path):
    """Both writers' AVI files, whole and cut mid-frame: the frames held whole (a decoder may make something
    of the cut one, in pieces)."""
    from companion.daemon.record import avi_frames
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(5)]
    for codec in ("ffv1", "mjpg"):
        recorder = Recorder(RecordParams(path=tmp_path / codec, codec=codec), CameraModel.from_config(
            yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"], "hover"), MAP)
        recorder.start()
        from companion.daemon.pipeline import FrameRecord
        from companion.types import Frame
        for index, image in enumerate(images):
            record = FrameRecord(index, 1_000 + index * 33_000_000, 0, (0, 0, 0, 0), False, None, (), None, None)
            recorder(Frame(image, record.t_ns, index), record)
        recorder.close()
        video = tmp_path / codec / "video.avi"
        assert avi_frames(video) == 5 == len(decoded_frames(tmp_path / codec))
        cut = tmp_path / f"cut-{codec}.avi"
        cut.write_bytes(video.read_bytes()[:video.stat().st_size * 3 // 5])   # in the third frame's data
        count, capture = 0, cv2.VideoCapture(str(cut))
        while capture.grab():
            count += 1
        assert avi_frames(cut) == 2 and count in (2, 3), codec


@pytest.fixture
def small_disk(tmp_path):
    """A file system of its own, 8 MB (a tmpfs: root may mount one; skipped where it cannot)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_a_disk_filled_under_the_recording_leaves_a_whole_folder_that_says_why(tmp_path, small_disk):
    """Another program fills the disk while the daemon records on it (the brief's 400 KB disk, from the
    other side): the recording stops, the log says so without a traceback, and the folder holds whole
    rows, a timestamps.csv that lists only what the video holds, a sequence.yaml that says why and counts
    them (the room it kept for that is given back at the stop), and it replays."""
    folder = small_disk / "flight"
    config = write_config(tmp_path, {"kind": "replay", "path": str(HOVER), "realtime": True, "loop": True},
                          map=str(MAP), record={"path": str(folder), "min_free_mb": 0.5})
    log_path = tmp_path / "stderr.txt"
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config)],
                                  stdout=subprocess.DEVNULL, stderr=log_file)
        try:
            wait_for(lambda: (folder / "timestamps.csv").is_file()
                     and len((folder / "timestamps.csv").read_text().splitlines()) > 3, "recorded frames")
            with open(small_disk / "filler", "wb", buffering=0) as filler:   # every block left
                try:
                    while filler.write(bytes(4096)):
                        pass
                except OSError:
                    pass
            wait_for(lambda: " recorded " in log_path.read_text(), "the recording to stop", timeout_s=30.0)
        finally:
            daemon.send_signal(signal.SIGINT)
            daemon.wait(timeout=30)
    log = log_path.read_text()
    assert daemon.returncode == 0 and "Traceback" not in log, log
    info = yaml.safe_load((folder / "sequence.yaml").read_text())
    rows = read_rows(folder / "timestamps.csv")
    assert info["frames"] == len(rows) > 0, info
    assert info["stopped"].startswith(("disk nearly full", "write failed: No space left", "video write failed")), info
    assert f"recorded {len(rows)} frames (0 dropped) to {folder}: {info['stopped']}" in log, log
    for table in ("timestamps.csv", "estimates.csv", "detections.csv", "events.csv"):
        assert (folder / table).read_bytes().endswith(b"\r\n"), table
    # the last line of the recording's log says why it stopped (written in the room kept for the end)
    last = read_rows(folder / "events.csv")[-1]
    assert (last["level"], last["text"]) == ("WARNING", f"recording stopped: {info['stopped']}"), last
    assert not (folder / ".reserve").exists()
    (small_disk / "filler").unlink()
    again = replayed(folder, tmp_path)
    assert again.returncode == 0 and f"frames {len(rows)}, " in again.stderr and "corrupt 0" in again.stderr, \
        again.stderr
