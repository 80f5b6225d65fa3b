"""End to end: `companion run` as a subprocess replaying a recorded sequence into an
independent MAVLink peer (libmav, its own process) on loopback."""
from __future__ import annotations

import csv
import dataclasses
import datetime
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.geometry.facility_map import load_map, write_map
from companion.capture.replay import open_recording
from aisle import tape_map
from mavlink_peer import PeerProcess, free_port

REPO = Path(__file__).resolve().parent.parent
# the hover flight is test data; the aisle flight ships with the package (the embedded default replays it)
SEQUENCES = {"warehouse_hover": REPO / "tests" / "data" / "sequences" / "warehouse_hover",
             "warehouse_aisle": REPO / "companion" / "data" / "sequences" / "warehouse_aisle"}
HOVER = SEQUENCES["warehouse_hover"]     # 1 s hovering in an aisle, PNG frames
AISLE = SEQUENCES["warehouse_aisle"]     # a flight along an aisle at 1.4 m/s, video
MAP = REPO / "maps" / "warehouse.yaml"
OFFSET_RE = re.compile(r"recorded t_ns 0 is monotonic (\d+) ns")


# ------------------------------------------------------------------ helpers

def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


class Truth:
    """groundtruth.csv by recorded capture time."""

    def __init__(self, sequence: Path):
        rows = read_rows(sequence / "groundtruth.csv")
        self.t_ns = np.array([int(r["t_ns"]) for r in rows])
        self.frame = np.array([int(r["frame"]) for r in rows])
        self.ned = np.array([[float(r["north_m"]), float(r["east_m"]), float(r["down_m"])] for r in rows])
        self.yaw = np.array([float(r["yaw_rad"]) for r in rows])

    def at(self, recorded_t_ns: float) -> int:
        """Row of the frame captured at this recorded time (within half a microsecond-truncation)."""
        row = int(np.argmin(np.abs(self.t_ns - recorded_t_ns)))
        assert abs(self.t_ns[row] - recorded_t_ns) < 1_000_000, "a message time that is no frame's capture time"
        return row


def write_config(tmp_path: Path, sequence: Path, port: int, **overrides) -> Path:
    data = {
        "source": {"kind": "replay", "path": str(sequence), "realtime": True},
        "map": str(MAP),
        "mavlink": {"connection": f"udpout:127.0.0.1:{port}", "origin_wait_s": 5.0, "origin_retry_s": 0.3,
                    "statustext_interval_s": 0.2, "heartbeat_interval_s": 0.5, "duplicate_listen_s": 0.6},
        "status": {"interval_s": 0.2},
    }
    for section, values in overrides.items():
        data.setdefault(section, {}).update(values)
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def start_daemon(config: Path | None, env: dict | None = None, preexec_fn=None) -> subprocess.Popen:
    command = [sys.executable, "-m", "companion", "run"] + (["--config", str(config)] if config else [])
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, **(env or {})}, preexec_fn=preexec_fn)


def finish(process: subprocess.Popen, timeout_s: float = 30.0) -> tuple[int, str, str]:
    stdout, stderr = process.communicate(timeout=timeout_s)
    return process.returncode, stdout, stderr


def clock_offset_ns(stderr: str) -> int:
    match = OFFSET_RE.search(stderr)
    assert match, stderr
    return int(match.group(1))


@pytest.fixture
def peers(tmp_path):
    started = []

    def start(port, *extra):
        peer = PeerProcess(port, tmp_path / f"peer{len(started)}.jsonl", *extra, duration_s=60)
        started.append(peer)
        return peer.wait_listening()

    yield start
    for peer in started:
        peer.stop()


def vision_frames(peer: PeerProcess, offset_ns: int, truth: Truth) -> list[tuple[dict, int]]:
    """(VISION_POSITION_ESTIMATE fields, ground-truth row) for every message the peer got."""
    return [(r["fields"], truth.at(r["fields"]["usec"] * 1000 - offset_ns + 500))
            for r in peer.records("VISION_POSITION_ESTIMATE")]


# -------------------------------------------------------------------- tests

def test_replay_reaches_an_independent_peer_with_the_true_pose(tmp_path, peers):
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--timesync-period", "0.3")
    process = start_daemon(write_config(tmp_path, HOVER, port))
    code, stdout, stderr = finish(process)
    assert code == 0, stderr
    truth = Truth(HOVER)
    offset = clock_offset_ns(stderr)
    received = peer.records()
    vision = vision_frames(peer, offset, truth)
    # Order: the origin, confirmed, before any vision.
    first_vision_ns = min(r["t_ns"] for r in received if r["name"] == "VISION_POSITION_ESTIMATE")
    origin = peer.records("SET_GPS_GLOBAL_ORIGIN")
    assert origin and origin[0]["t_ns"] < first_vision_ns
    geodetic = load_map(MAP).frame.geodetic_origin
    assert origin[0]["fields"]["latitude"] == round(geodetic.latitude_deg * 1e7)
    assert origin[0]["fields"]["longitude"] == round(geodetic.longitude_deg * 1e7)
    assert origin[0]["fields"]["altitude"] == round(geodetic.altitude_m * 1000)
    # Identity.
    assert {(r["sysid"], r["compid"]) for r in received} == {(1, 197)}
    assert all(h["fields"]["type"] == 18 and h["fields"]["autopilot"] == 8 for h in peer.records("HEARTBEAT"))
    # Rate: one message per frame at the camera rate, never closer than 20 ms.
    usec = np.array(sorted(f["usec"] for f, _ in vision))
    frame_period_us = np.median(np.diff(truth.t_ns)) / 1000
    assert np.all(np.diff(usec) >= 20_000)
    assert abs(np.median(np.diff(usec)) - frame_period_us) < 1_000
    # Once streaming, every frame is sent (the bounded coast bridges a frame without pose).
    first_frame = min(truth.frame[row] for _, row in vision)
    assert len(vision) >= 0.95 * np.count_nonzero(truth.frame >= first_frame)
    assert first_frame < 0.5 * truth.frame.max()
    # Values against ground truth, covariance present, no reset.
    errors = np.array([np.linalg.norm([f["x"] - truth.ned[row][0], f["y"] - truth.ned[row][1],
                                       f["z"] - truth.ned[row][2]]) for f, row in vision])
    yaw_errors = np.array([abs(math.remainder(f["yaw"] - truth.yaw[row], 2 * math.pi)) for f, row in vision])
    assert np.median(errors) < 0.05 and errors.max() < 0.25, errors
    assert np.degrees(np.median(yaw_errors)) < 2.0
    for fields, _ in vision:
        covariance = fields["covariance"]
        assert all(math.isfinite(c) for c in covariance)
        assert covariance[0] > 0 and covariance[6] > 0 and covariance[11] > 0 and covariance[20] > 0
        assert fields["reset_counter"] == 0
    # TIMESYNC answered with our clock, ts1 mirrored.
    requests = {r["fields"]["ts1"] for r in peer.records("TIMESYNC", kind="sent")}
    replies = peer.records("TIMESYNC")
    assert replies and all(r["fields"]["ts1"] in requests and r["fields"]["tc1"] > 0 for r in replies)
    # Live status and per-stage timings.
    assert re.search(r"\d+\.\d fps \| markers \d+ \| N [+-]\d", stdout)
    assert "stage capture->send" in stderr and "stage detect" in stderr


def recorded_images(sequence: Path) -> dict[int, np.ndarray]:
    """Every frame of a sequence (PNG files or a video), by frame number."""
    rec = open_recording(sequence)
    if rec.files is not None:
        return {int(n): cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for n, f in zip(rec.frames, rec.files)}
    capture = cv2.VideoCapture(str(rec.video))
    images = {}
    for n in rec.frames:
        ok, image = capture.read()
        assert ok, f"{rec.video}: frame {n} unreadable"
        images[int(n)] = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    capture.release()
    return images


def spliced_sequence(tmp_path: Path, sequence: Path, keep: list[int], blank=(), gap_after: int | None = None,
                     gap_ns: int = 0, gap_after_index: int | None = None) -> Path:
    """A PNG copy of a sequence with only the frames ``keep`` (original numbers, in
    order, repeats allowed), those in ``blank`` turned black (markers out of sight),
    re-timed at the recorded frame period with ``gap_ns`` of silence after frame
    ``gap_after`` (or after ``keep[gap_after_index]``: the camera delivering
    nothing). groundtruth.csv follows the new times."""
    out = tmp_path / "spliced"
    (out / "frames").mkdir(parents=True)
    images = recorded_images(sequence)
    truth = {int(r["frame"]): r for r in read_rows(sequence / "groundtruth.csv")}
    period_ns = int(np.median(np.diff([int(r["t_ns"]) for r in truth.values()])))
    kept, kept_truth, t_ns = [], [], 0
    for index, frame in enumerate(keep):
        name = f"frames/{frame:06d}.png"
        image = images[frame]
        cv2.imwrite(str(out / name), np.zeros_like(image) if frame in blank else image)
        kept.append({"frame": frame, "t_ns": t_ns, "file": name})
        kept_truth.append(dict(truth[frame], t_ns=t_ns))
        t_ns += period_ns + (gap_ns if frame == gap_after or index == gap_after_index else 0)
    for name, table in (("timestamps.csv", kept), ("groundtruth.csv", kept_truth)):
        with open(out / name, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
    info = yaml.safe_load((sequence / "sequence.yaml").read_text())
    info["map"] = str(MAP)
    info.pop("video", None)
    (out / "sequence.yaml").write_text(yaml.safe_dump(info))
    return out


def test_markers_lost_then_seen_elsewhere_resets_instead_of_dragging(tmp_path, peers):
    """Markers out of sight (black frames), then the camera delivering nothing for 0.4 s,
    then the markers again far away: the stream stops, resumes, and reset_counter steps."""
    keep = list(range(0, 38)) + list(range(70, 100))
    sequence = spliced_sequence(tmp_path, AISLE, keep, blank=range(30, 38), gap_after=37, gap_ns=400_000_000)
    truth = Truth(sequence)
    assert np.linalg.norm(truth.ned[keep.index(70)] - truth.ned[keep.index(29)]) > 0.5, "no jump in this data"
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    process = start_daemon(write_config(tmp_path, sequence, port, fusion={"max_coast_s": 0.2}))
    code, _, stderr = finish(process)
    assert code == 0, stderr
    vision = vision_frames(peer, clock_offset_ns(stderr), truth)
    frames = np.array([truth.frame[row] for _, row in vision])
    before = [(f, row) for f, row in vision if truth.frame[row] < 30]
    after = [(f, row) for f, row in vision if truth.frame[row] >= 70]
    # Nothing is sent once coasting ran out (0.2 s = 6 frames after the last seen frame 29).
    assert not np.any((frames > 29 + 6) & (frames < 70)), frames
    assert before and after
    assert all(f["reset_counter"] == 0 for f, _ in before)
    assert all(f["reset_counter"] == 1 for f, _ in after)
    # The first estimate after the jump is where the vehicle is, not dragged from where it was.
    first, row = after[0]
    assert np.linalg.norm([first["x"], first["y"], first["z"]] - truth.ned[row]) < 0.1
    texts = [r["fields"]["text"] for r in peer.wait_for("STATUSTEXT", count=3)]
    assert "companion: markers lost" in texts and "companion: re-acquired (reset 1)" in texts


def test_a_jump_across_a_gap_in_the_frames_reaches_the_fc_with_a_reset(tmp_path, peers):
    """The camera delivers nothing for 2 s while the vehicle flies on 2.8 m: the first poses after the gap
    are a re-acquisition with reset_counter + 1, not a tracked step (the filter's prediction had grown wide
    enough over the gap to take the jump as tracking: reset 0, and the EKF was pulled 2.8 m in one sample)."""
    keep = list(range(0, 60)) + list(range(120, 160))
    sequence = spliced_sequence(tmp_path, AISLE, keep, gap_after=59, gap_ns=2_000_000_000)
    truth = Truth(sequence)
    assert np.linalg.norm(truth.ned[keep.index(120)] - truth.ned[keep.index(59)]) > 2.0, "no jump in this data"
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    code, _, stderr = finish(start_daemon(write_config(tmp_path, sequence, port)))
    assert code == 0, stderr
    vision = vision_frames(peer, clock_offset_ns(stderr), truth)
    before = [f for f, row in vision if truth.frame[row] < 60]
    after = [f for f, row in vision if truth.frame[row] >= 120]
    assert before and after
    assert {f["reset_counter"] for f in before} == {0} and {f["reset_counter"] for f in after} == {1}
    texts = [r["fields"]["text"] for r in peer.wait_for("STATUSTEXT", count=2)]
    assert "companion: re-acquired (reset 1)" in texts, texts


def test_corrupt_frames_are_skipped_counted_and_the_stream_goes_on(tmp_path, peers):
    sequence = spliced_sequence(tmp_path, HOVER, keep=[int(r["frame"]) for r in read_rows(HOVER / "timestamps.csv")])
    rows = read_rows(sequence / "timestamps.csv")
    broken = [rows[i] for i in (10, 11, 20)]
    (sequence / broken[0]["file"]).write_bytes(b"\x89PNG but no image")
    (sequence / broken[1]["file"]).write_bytes((sequence / broken[1]["file"]).read_bytes()[:200])
    (sequence / broken[2]["file"]).unlink()
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    code, _, stderr = finish(start_daemon(write_config(tmp_path, sequence, port)))
    assert code == 0, stderr
    assert re.search(r"corrupt 3\b", stderr)
    truth = Truth(sequence)
    frames = {int(truth.frame[row]) for _, row in vision_frames(peer, clock_offset_ns(stderr), truth)}
    assert not frames & {int(r["frame"]) for r in broken}
    # The stream went on past the broken frames to the end of the sequence.
    assert max(frames) == int(rows[-1]["frame"]) and len(frames & set(range(21, len(rows)))) >= 5


def test_frames_that_change_size_mid_run_are_skipped_counted_and_said_once(tmp_path, peers):
    """The intrinsics describe the first frames' size: frames of another size (a camera that changed its mode,
    a mixed image folder) were posed with them, 'no pose: reprojection' and nothing said about the size."""
    sequence = spliced_sequence(tmp_path, HOVER, keep=[int(r["frame"]) for r in read_rows(HOVER / "timestamps.csv")])
    rows = read_rows(sequence / "timestamps.csv")
    for row in rows[10:20]:
        image = cv2.imread(str(sequence / row["file"]), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(sequence / row["file"]), cv2.resize(image, (320, 240)))
    port = free_port()
    peers(port, "--origin-reply", "on_set")
    code, _, stderr = finish(start_daemon(write_config(tmp_path, sequence, port)))
    assert code == 0, stderr
    assert stderr.count("camera frames 320x240, not 640x480: skipped") == 1, stderr
    assert re.search(r"frames 21, .* resized 10\b", stderr), stderr
    assert "reprojection" not in stderr


def test_sigterm_mid_run_with_the_peer_going_away_and_coming_back(tmp_path, peers):
    """One looping run: systemd notify, the FC vanishing and returning (origin again
    before vision), then SIGTERM: a clean exit with nothing sent afterwards."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify_path = str(tmp_path / "notify.sock")
    notify.bind(notify_path)
    notify.settimeout(0.2)
    messages: list[str] = []
    reading = threading.Event()
    reading.set()

    def read_notify():  # systemd reads at once; the socket's queue is short
        while reading.is_set():
            try:
                messages.append(notify.recv(4096).decode())
            except socket.timeout:
                pass

    reader = threading.Thread(target=read_notify, daemon=True)
    reader.start()
    port = free_port()
    first = peers(port, "--origin-reply", "on_set")
    config = write_config(tmp_path, HOVER, port, source={"loop": True},
                          mavlink={"fc_timeout_s": 1.5, "origin_wait_s": 3.0})
    process = start_daemon(config, env={"NOTIFY_SOCKET": notify_path, "WATCHDOG_USEC": "400000"})
    first.wait_for("VISION_POSITION_ESTIMATE", count=5, timeout_s=15)
    first.stop()
    time.sleep(2.0)  # longer than fc_timeout_s
    second = peers(port, "--origin-reply", "on_set")
    vision = second.wait_for("VISION_POSITION_ESTIMATE", count=5, timeout_s=15)
    origin = second.records("SET_GPS_GLOBAL_ORIGIN")
    assert origin and origin[0]["t_ns"] < vision[0]["t_ns"]
    process.send_signal(signal.SIGTERM)
    stopped_ns = time.monotonic_ns()
    code, _, stderr = finish(process, timeout_s=10)
    assert code == 0, stderr
    assert "SIGTERM: stopping" in stderr and "stage total" in stderr
    exited_ns = time.monotonic_ns()
    late = [r for r in second.records("VISION_POSITION_ESTIMATE") if r["t_ns"] > exited_ns]
    assert not late
    assert process.poll() == 0 and stopped_ns < exited_ns
    time.sleep(0.3)
    reading.clear()
    reader.join()
    notify.close()
    assert messages[0].startswith("READY=1")
    assert "WATCHDOG=1" in messages and messages[-1] == "STOPPING=1"
    assert any(m.startswith("STATUS=") and "fps" in m for m in messages)


def test_embedded_default_runs_with_no_arguments(peers):
    """`companion run`: the bundled sequence and maps/warehouse.yaml to udpout:127.0.0.1:14550."""
    peer = peers(14550, "--origin-reply", "on_set")
    process = start_daemon(None)
    vision = peer.wait_for("VISION_POSITION_ESTIMATE", count=10, timeout_s=20)
    process.send_signal(signal.SIGINT)
    code, stdout, stderr = finish(process, timeout_s=10)
    assert code == 0, stderr
    assert "warehouse_aisle" in stderr and "warehouse.yaml" in stderr and "udpout:127.0.0.1:14550" in stderr
    assert all(math.isfinite(v["fields"]["x"]) and v["fields"]["covariance"][0] > 0 for v in vision)
    assert "SIGINT: stopping" in stderr and " fps | " in stdout


def test_config_error_exits_2_naming_the_file_and_key(tmp_path):
    config = write_config(tmp_path, HOVER, 14550, mavlink={"max_rate_hz": 80})
    code, _, stderr = finish(start_daemon(config), timeout_s=30)
    assert code == 2
    assert f"{config}: mavlink.max_rate_hz: must be in (0, 50], got 80" in stderr and "Traceback" not in stderr


def test_detector_layout_comes_from_the_map_and_a_mismatch_is_named():
    import dataclasses

    from companion.daemon.config import ConfigError, load_config
    from companion.daemon.service import detector_params_for

    config = load_config()
    params = detector_params_for(config)
    assert (params.parity, params.dictionary) == (config.facility_map.parity, config.facility_map.dictionary)
    wrong = dataclasses.replace(config, detector={"parity": 6 - config.facility_map.parity})
    with pytest.raises(ConfigError, match=r"detector\.parity: .* differs from the map's"):
        detector_params_for(wrong)


def test_the_daemons_detector_aligns_corners_through_the_camera():
    from companion.daemon.config import load_config
    from companion.daemon.service import make_detector

    config = load_config()
    assert np.any(config.camera.dist != 0)  # the bundled sequence's lens distorts
    detector = make_detector(config)
    assert detector.refiner.camera is config.camera
    assert detector.layout.parity == config.facility_map.parity


def test_detector_section_takes_stage_parameters_and_names_a_wrong_key():
    import dataclasses

    from companion.daemon.config import ConfigError, load_config
    from companion.daemon.service import detector_params_for

    config = load_config()
    section = {"circles": {"run": "always", "min_area_px": 7}, "decoder": {"min_gap_cells": 8},
               "square": {"aruco_threshold_windows_px": [5, 25, 10]}, "sampling": {"ambiguity_fraction": 0.2}}
    params = detector_params_for(dataclasses.replace(config, detector=section))
    assert (params.circles.run, params.circles.min_area_px, params.decoder.min_gap_cells) == ("always", 7, 8)
    assert params.square.aruco_threshold_windows_px == (5, 25, 10) and params.sampling.ambiguity_fraction == 0.2
    assert params.edges.square_samples == 11  # untouched stages keep their defaults
    for section, key, words in [({"circle": {}}, "detector.circle", "unknown key"),
                                ({"circles": {"min_aera_px": 3}}, "detector.circles.min_aera_px", "unknown key"),
                                ({"circles": {"run": "sometimes"}}, "detector.circles.run", "when_square_empty"),
                                ({"decoder": {"min_gap_cells": 0}}, "detector.decoder.min_gap_cells", ">= 1"),
                                ({"refine": {"tolerance_px": "small"}}, "detector.refine.tolerance_px", "number"),
                                ({"edges": 3}, "detector.edges", "mapping")]:
        with pytest.raises(ConfigError) as error:
            detector_params_for(dataclasses.replace(config, detector=section))
        assert str(error.value).startswith(f"{config.path}: {key}: "), error.value
        assert words in str(error.value)


def test_a_wrong_detector_key_stops_the_daemon_naming_file_and_key(tmp_path):
    config = write_config(tmp_path, HOVER, 14550, detector={"circles": {"min_aera_px": 3}})
    code, _, stderr = finish(start_daemon(config), timeout_s=30)
    assert code == 2
    assert f"{config}: detector.circles.min_aera_px: unknown key" in stderr and "Traceback" not in stderr


# ------------------------------------------- issue 11: health, start order, parameters, two daemons

class NotifyListener:
    """systemd's side of the notify socket: collects every datagram (STATUS= lines among them)."""

    def __init__(self, path: Path):
        self.path = str(path)
        self.messages: list[str] = []
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._socket.bind(self.path)
        self._socket.settimeout(0.1)
        self._reading = threading.Event()
        self._reading.set()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        while self._reading.is_set():
            try:
                self.messages.append(self._socket.recv(4096).decode())
            except socket.timeout:
                pass

    def statuses(self) -> list[str]:
        return [m[len("STATUS="):] for m in self.messages if m.startswith("STATUS=")]

    def close(self):
        self._reading.clear()
        self._thread.join()
        self._socket.close()


def wait_for_status(notify: NotifyListener, pattern: str, after: int = 0, timeout_s: float = 15.0
                    ) -> tuple[int, re.Match]:
    """(index, match) of the first STATUS= line from ``after`` on that matches ``pattern``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for index, line in enumerate(notify.statuses()[after:], after):
            match = re.search(pattern, line)
            if match:
                return index, match
        time.sleep(0.05)
    raise AssertionError(f"no STATUS= matching {pattern!r} within {timeout_s} s: {notify.statuses()[-3:]}")


def test_a_flight_controller_that_goes_silent_is_on_the_status_line_for_as_long_as_it_lasts(tmp_path, peers):
    """The UDP flight controller is killed mid-run: vision streams on (the start order gives up waiting for
    it), and systemd's STATUS (the status line) says 'link streaming, no FC heard N s' from fc_timeout_s on,
    on every line, counting up, until a flight controller is heard again. Before, it read 'link streaming'
    throughout, and only one log line and one STATUSTEXT said otherwise."""
    port = free_port()
    first = peers(port, "--origin-reply", "on_set")
    notify = NotifyListener(tmp_path / "notify.sock")
    config = write_config(tmp_path, HOVER, port, source={"loop": True},
                          mavlink={"fc_timeout_s": 1.5, "origin_wait_s": 1.0})
    process = start_daemon(config, env={"NOTIFY_SOCKET": notify.path})
    try:
        first.wait_for("VISION_POSITION_ESTIMATE", count=5, timeout_s=20)
        heard, _ = wait_for_status(notify, r"\| link streaming \| sent")
        first.process.kill()   # kill -9: a UDP peer says no goodbye, the link stays open
        first.process.wait()
        killed = len(notify.statuses())
        unheard, match = wait_for_status(notify, r"\| link streaming, no FC heard (\d+) s \| sent (\d+)", killed)
        lasted, later = wait_for_status(notify, r"\| link streaming, no FC heard ([4-9]|\d\d+) s \| sent (\d+)",
                                        unheard)
        assert int(later.group(1)) > int(match.group(1)) and int(later.group(2)) > int(match.group(2))  # vision on
        # it says so on every line meanwhile (the link held vision for origin_wait_s, then streamed on)
        assert all("no FC heard" in line for line in notify.statuses()[unheard:lasted + 1])
        second = peers(port, "--origin-reply", "on_set")
        back, _ = wait_for_status(notify, r"\| link streaming \| sent", lasted)
        second.wait_for("VISION_POSITION_ESTIMATE", count=3)
    finally:
        process.send_signal(signal.SIGTERM)
        code, _, stderr = finish(process, timeout_s=15)
        notify.close()
    assert code == 0, stderr
    assert "no flight controller seen after 1.0 s" in stderr


def test_a_camera_that_stalls_is_reported_and_the_heartbeat_goes_critical(tmp_path, peers):
    """The replay delivers nothing for 3 s in the middle (a stalled camera): the status line
    says so with 0 fps, one STATUSTEXT per change, HEARTBEAT CRITICAL during the stall and
    ACTIVE again once frames return."""
    rows = read_rows(HOVER / "timestamps.csv")
    sequence = spliced_sequence(tmp_path, HOVER, keep=[int(r["frame"]) for r in rows], gap_after=12,
                                gap_ns=3_000_000_000)
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    notify = NotifyListener(tmp_path / "notify.sock")
    try:
        code, _, stderr = finish(start_daemon(write_config(tmp_path, sequence, port),
                                              env={"NOTIFY_SOCKET": notify.path}), timeout_s=40)
    finally:
        notify.close()
    assert code == 0, stderr
    truth = Truth(sequence)
    offset = clock_offset_ns(stderr)
    vision = peer.records("VISION_POSITION_ESTIMATE")
    frame_of = {id(r): truth.frame[truth.at(r["fields"]["usec"] * 1000 - offset + 500)] for r in vision}
    last_before_ns = max(r["t_ns"] for r in vision if frame_of[id(r)] <= 12)
    first_after_ns = min(r["t_ns"] for r in vision if frame_of[id(r)] > 12)
    heartbeats = [(r["t_ns"], r["fields"]["system_status"]) for r in peer.records("HEARTBEAT")]
    during = [status for t, status in heartbeats if last_before_ns < t < first_after_ns]
    after = [status for t, status in heartbeats if t > first_after_ns + 0.3e9]
    assert 5 in during, heartbeats       # MAV_STATE_CRITICAL while no frame comes
    assert after and set(after) == {4}   # MAV_STATE_ACTIVE once they are back
    # the first CRITICAL heartbeat and the STATUSTEXT come during the stall, long before the frames return
    first_critical_ns = min(t for t, status in heartbeats if status == 5)
    assert last_before_ns < first_critical_ns < first_after_ns - 1.5e9
    texts = [(r["t_ns"], r["fields"]["text"]) for r in peer.records("STATUSTEXT")]
    stalled = [t for t, text in texts if "camera stalled" in text]
    again = [t for t, text in texts if "frames again" in text]
    assert len(stalled) == 1 and len(again) == 1, texts
    assert last_before_ns < stalled[0] < first_after_ns - 1.5e9 and again[0] > first_after_ns - 1e9
    statuses = notify.statuses()
    assert any(s.startswith("  0.0 fps") and "camera stalled" in s for s in statuses), statuses
    assert any(" fps | markers " in s and "| tracking |" in s for s in statuses)
    assert stderr.count("camera stalled") == 1


def test_a_recording_keeps_the_daemons_log_at_the_frame_each_line_was_logged(tmp_path, peers):
    """The stalled camera of the test above, recorded: events.csv holds the daemon's log (INFO and up) while
    it recorded, with every health message the flight controller received as STATUSTEXT (there cut to 50
    characters), each at the newest frame when it was logged: the stall at the last frame before the gap,
    ERROR; and the report lists them."""
    rows = read_rows(HOVER / "timestamps.csv")
    sequence = spliced_sequence(tmp_path, HOVER, keep=[int(r["frame"]) for r in rows], gap_after=12,
                                gap_ns=3_000_000_000)
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    flight = tmp_path / "flight"
    code, _, stderr = finish(start_daemon(write_config(tmp_path, sequence, port, record={"path": str(flight)})),
                             timeout_s=40)
    assert code == 0, stderr
    # all but the last words at the stop, which come after the recording closed
    received = [r["fields"]["text"].removeprefix("companion: ") for r in peer.records("STATUSTEXT")
                if r["fields"]["text"] != "companion: stopped, no more vision"]
    events = read_rows(flight / "events.csv")
    said = [e["text"] for e in events]
    assert said[0].startswith(f"recording to {flight}")
    assert len(received) >= 3 and all(r in said for r in received), (received, said)
    stalled = [e for e in events if "camera stalled" in e["text"]]
    again = [e for e in events if "frames again" in e["text"]]
    assert len(stalled) == 1 and len(again) == 1, said
    assert stalled[0]["level"] == "ERROR" and stalled[0]["frame"] == "12"
    assert int(again[0]["frame"]) > 12
    # the track ended for the gap, and the loss says so (it said 'filter gating')
    assert [e["text"] for e in events if "markers lost" in e["text"]] == ["markers lost: no frame for 3.1 s"]
    # on timestamps.csv's time base, at their own times: the stall within the 3 s without frames (it was put at
    # frame 12's time), the return at or after the frame it was said at
    recorded_ns = {int(r["frame"]): int(r["t_ns"]) for r in read_rows(flight / "timestamps.csv")}
    assert recorded_ns[12] + 0.4e9 < int(stalled[0]["t_ns"]) < recorded_ns[13]
    assert int(again[0]["t_ns"]) >= recorded_ns[int(again[0]["frame"])]

    run = subprocess.run([sys.executable, "-m", "companion", "report", str(flight)], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    page = (flight / "report.html").read_text()
    assert "<h2>Log while recording</h2>" in page
    assert re.search(rf"<td>{int(stalled[0]['t_ns']) * 1e-9:.2f}</td><td>12</td><td>ERROR</td>"
                     rf"<td>{re.escape(stalled[0]['text'])}</td>", page)
    warnings = sum(e["level"] in ("CRITICAL", "WARNING", "ERROR") for e in events)
    assert f"<td>log lines</td><td>{len(events)} ({warnings} warning" in page


def log_time_ns(stderr: str, text: str) -> int:
    """The monotonic time (this machine's, the peer's clock) of the last log line containing ``text``."""
    line = [line for line in stderr.splitlines() if text in line][-1]
    wall_s = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
    return int(wall_s * 1e9) - (time.time_ns() - time.monotonic_ns())


def test_a_stall_is_told_within_a_second_though_a_silent_fc_left_its_parameters_queued(tmp_path, peers):
    """A flight controller that answers no parameter read (ten problems), STATUSTEXTs at the default one
    per second, and the camera stalling 3 s once the parameters are judged: the stall's STATUSTEXT reaches
    the peer within a second of the daemon logging it, and the parameters take two STATUSTEXTs, not ten
    (the log keeps all ten). Before: the ten queued first, the stall came after the frames were back."""
    hover = list(range(31)) + list(range(29, 0, -1))          # 4 s of hovering at 15 fps, there and back
    keep = hover * 3                                          # stall after 4 s (parameters judged at ~2.5 s)
    sequence = spliced_sequence(tmp_path, HOVER, keep, gap_after_index=60, gap_ns=3_000_000_000)
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")            # --params not given: no PARAM_VALUE ever
    config = write_config(tmp_path, sequence, port, mavlink={"statustext_interval_s": 1.0})
    code, _, stderr = finish(start_daemon(config), timeout_s=60)
    assert code == 0, stderr
    texts = [(r["t_ns"], r["fields"]["text"]) for r in peer.records("STATUSTEXT")]
    stalled = [t for t, text in texts if "camera stalled" in text]
    assert len(stalled) == 1, texts
    # the last one logged: a slow start (no frame within 1 s) is a stall too, whose text the first frame replaced
    delay_s = (stalled[0] - log_time_ns(stderr, "camera stalled")) * 1e-9
    print(f"camera stalled: STATUSTEXT at the peer {delay_s:.3f} s after the daemon logged it")
    assert -0.01 < delay_s < 1.5, texts   # one statustext_interval_s at most, and the log's ms rounding
    parameter_texts = [text for _, text in texts if ("vision" in text or "params" in text) and "stopped" not in text]
    assert parameter_texts == ["companion: VISO_TYPE=? blocks vision", "companion: FC did not report 9 params"]
    assert stderr.count("flight controller parameter ") == 10, stderr


def test_parameters_read_again_at_a_reconnection_are_not_told_again(tmp_path, peers):
    """A TCP flight controller that answers no parameter read, restarted mid-flight: the link reads the
    parameters at each connection; the same values are judged once (ten log lines, two STATUSTEXTs), not
    again at every reconnection (seen in a recording's events.csv: the ten lines twice)."""
    port = free_port("tcp")
    first = peers(port, "--tcp")
    config = write_config(tmp_path, HOVER, port, source={"loop": True},
                          mavlink={"connection": f"tcp:127.0.0.1:{port}", "reconnect_initial_s": 0.1,
                                   "reconnect_max_s": 0.4})
    daemon = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config),
                               "--log-level", "debug"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first.wait_for("VISION_POSITION_ESTIMATE", count=45, timeout_s=30)   # 30 sent: the latency, then judged
        first.stop()
        second = peers(port, "--tcp")
        second.wait_for("PARAM_REQUEST_READ", count=30, timeout_s=30)       # three rounds of ten: read again
        second.wait_for("VISION_POSITION_ESTIMATE", count=len(second.records("VISION_POSITION_ESTIMATE")) + 15)
    finally:
        daemon.send_signal(signal.SIGTERM)
        code, _, stderr = finish(daemon)
    assert code == 0, stderr
    assert stderr.count("flight controller parameter VISO_TYPE = - blocks vision fusion") == 1, stderr
    assert stderr.count("flight controller parameters read again, unchanged: not judged again") == 1, stderr
    texts = [r["fields"]["text"] for peer in (first, second) for r in peer.records("STATUSTEXT")]
    assert texts.count("companion: VISO_TYPE=? blocks vision") == 1, texts


def test_frames_of_another_aspect_ratio_than_the_calibration_stop_the_daemon(tmp_path):
    """A 1280x720 calibration and 640x480 frames: no silent 'no pose', a clear error."""
    config = write_config(tmp_path, HOVER, free_port(),
                          camera={"width": 1280, "height": 720, "hfov_deg": 70.0,
                                  "mount": {"lever_arm_m": [0.1, 0.0, 0.05], "facing": "forward",
                                            "tilt_down_deg": 20.0}})
    code, _, stderr = finish(start_daemon(config))
    assert code == 2, stderr   # a config that cannot work: systemd does not restart it (RestartPreventExitStatus)
    assert "calibrated for 1280x720 frames but gets 640x480" in stderr
    assert "Traceback" not in stderr


def test_a_replay_without_one_readable_frame_is_an_error_not_a_flight(tmp_path):
    frames = tmp_path / "corrupt"
    frames.mkdir()
    for k in range(15):   # 1.5 s at 10 fps: the replay is lost (nothing readable for 1 s) before its end
        (frames / f"{k:06d}.png").write_bytes(np.random.default_rng(k).integers(0, 256, 5000, np.uint8).tobytes())
    config = write_config(tmp_path, HOVER, free_port(),
                          camera=yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"])
    process = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config), "--replay",
                                str(frames), "--fps", "10"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    code, _, stderr = finish(process)
    assert code == 2, stderr
    assert f"replay of {frames} (real time): not one readable frame (15 unreadable); stopping" in stderr
    assert "nothing readable for 1.0 s of recording (" in stderr and "); reading on to its end" in stderr
    assert "Traceback" not in stderr


def test_frames_of_a_scaled_size_scale_the_intrinsics_and_the_pose_is_right(tmp_path, peers):
    """The sequence's camera calibrated at twice the resolution (same field of view): the daemon
    says it scales the intrinsics and the vehicle's pose is still the true one."""
    camera = yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"]
    assert (camera["width"], camera["height"]) == (640, 480)
    # a 2x sensor mode: the same rays land on pixel 2 (x + 0.5) - 0.5
    doubled = dict(camera, width=1280, height=960, fx_px=2 * camera["fx_px"], fy_px=2 * camera["fy_px"],
                   cx_px=2 * (camera["cx_px"] + 0.5) - 0.5, cy_px=2 * (camera["cy_px"] + 0.5) - 0.5)
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    code, _, stderr = finish(start_daemon(write_config(tmp_path, HOVER, port, camera=doubled)))
    assert code == 0, stderr
    assert "camera calibrated for 1280x960, frames are 640x480: intrinsics scaled by 0.5" in stderr
    truth = Truth(HOVER)
    vision = vision_frames(peer, clock_offset_ns(stderr), truth)
    errors = [np.linalg.norm([f["x"], f["y"], f["z"]] - truth.ned[row]) for f, row in vision]
    assert len(vision) >= 5 and np.median(errors) < 0.05, errors


def test_markers_but_no_pose_say_why_in_the_status_line_and_the_log(tmp_path, peers):
    """Every pose is rejected (a reprojection bound no fit meets, on a map stated exact: no error of the map
    explains any): after 2 s the status line and the log say 'no pose' with the pose stage's reason counted,
    instead of a silent 'sent 0'."""
    port = free_port()
    peers(port, "--origin-reply", "on_set")
    notify = NotifyListener(tmp_path / "notify.sock")
    config = write_config(tmp_path, HOVER, port, source={"loop": True},
                          pose={"max_rms_px": 1e-6, "map_sd_m": 0.0, "map_sd_deg": 0.0})
    process = start_daemon(config, env={"NOTIFY_SOCKET": notify.path})
    deadline = time.monotonic() + 20
    while not any("no pose" in s and "reprojection" in s for s in notify.statuses()) and time.monotonic() < deadline:
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    code, _, stderr = finish(process)
    notify.close()
    assert code == 0, stderr
    line = next(s for s in notify.statuses() if "| no pose" in s and "reprojection" in s)
    assert re.search(r"markers [1-9]\d* \| no pose \| latency - \| no pose \d+\.\d s: reprojection \d+", line), line
    assert re.search(r"no pose for 2\.\d s: reprojection \d+", stderr)


def test_loop_replays_a_recording_until_stopped_and_needs_a_replay(tmp_path):
    """The live view's README example: the embedded default's 8 s flight once is over before a browser opens."""
    # a port of its own: the embedded default's 14550 is another test's flight controller
    config = write_config(tmp_path, HOVER, free_port())
    command = [sys.executable, "-m", "companion", "run", "--config", str(config), "--replay", str(HOVER), "--loop"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        process.wait(timeout=4.0)   # the hover is 1 s long
    except subprocess.TimeoutExpired:
        pass
    assert process.poll() is None, "the replay ended"
    process.send_signal(signal.SIGTERM)
    code, _, stderr = finish(process)
    assert code == 0 and "(real time, looping)" in stderr, stderr
    camera = tmp_path / "camera.yaml"
    camera.write_text(yaml.safe_dump({"source": {"kind": "v4l2", "device": "/dev/video97"}, "map": str(MAP),
                                      "camera": yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"]}))
    refused = subprocess.run([sys.executable, "-m", "companion", "run", "--config", str(camera), "--loop"],
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "--loop replays a recording over and over: the source of" in refused.stderr
    assert "is a V4L2 camera, not a replay (give --replay PATH)" in refused.stderr


def test_a_config_camera_that_did_not_take_the_replayed_frames_is_named_at_the_start(tmp_path):
    """--replay of a recording under a config with another camera: every pose is off or rejected ('markers
    lost' with markers in view). The start says which camera is used and what differs from the recording's."""
    recorded = yaml.safe_load((HOVER / "sequence.yaml").read_text())["camera"]
    other = {**recorded, "fx_px": recorded["fx_px"] * 0.8, "fy_px": recorded["fy_px"] * 0.8,
             "mount": {**recorded["mount"], "pitch_deg": recorded["mount"]["pitch_deg"] + 10.0}}
    runs = {}
    for name, camera in (("same", recorded), ("other", other)):
        config = write_config(tmp_path, HOVER, free_port())
        config.write_text(yaml.safe_dump({**yaml.safe_load(config.read_text()), "camera": camera}))
        runs[name] = finish(start_daemon(config))
    assert runs["same"][0] == 0 and "is not the one" not in runs["same"][2], runs["same"][2]
    code, _, stderr = runs["other"]
    warnings = [line for line in stderr.splitlines() if "is not the one" in line]
    assert code == 0 and len(warnings) == 1, stderr
    assert "WARNING" in warnings[0] and f"{HOVER / 'sequence.yaml'}" in warnings[0]
    fx = recorded["fx_px"]
    assert f"fx {0.8 * fx:.1f} -> {fx:.1f} px" in warnings[0] and "mount turned by 10.0 deg" in warnings[0]


def test_a_config_map_that_is_not_the_recordings_is_named_at_the_start(tmp_path):
    """--replay of a recording under a config with another map: the frames are posed on the config's map. The
    start says so, naming the markers that differ from the map the recording names (its own copy, map.yaml)."""
    recording = tmp_path / "recording"
    shutil.copytree(HOVER, recording)
    site = yaml.safe_load(MAP.read_text())
    moved = site["markers"][0]
    moved["position_m"][0] += 0.5
    (recording / "map.yaml").write_text(yaml.safe_dump(site))
    info = yaml.safe_load((recording / "sequence.yaml").read_text())
    (recording / "sequence.yaml").write_text(yaml.safe_dump({**info, "map": "map.yaml"}))
    code, _, stderr = finish(start_daemon(write_config(tmp_path, recording, free_port())))
    warnings = [line for line in stderr.splitlines() if "is not the one" in line]
    assert code == 0 and len(warnings) == 1, stderr
    assert f"the config's map ({MAP}) is not the one {recording / 'sequence.yaml'} names" in warnings[0]
    assert f"moved or resized: {moved['symbol']}" in warnings[0]


def test_a_parameter_that_blocks_vision_is_logged_and_told(tmp_path, peers):
    port = free_port()
    served = {"AHRS_EKF_TYPE": 3, "VISO_TYPE": 0, "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 6, "EK3_SRC1_YAW": 6,
              "EK3_SRC1_VELXY": 0, "VISO_DELAY_MS": 10, "VISO_POS_X": 0, "VISO_POS_Y": 0, "VISO_POS_Z": 0}
    peer = peers(port, "--origin-reply", "on_set", "--params", json.dumps(served))
    process = start_daemon(write_config(tmp_path, HOVER, port, source={"loop": True}))
    texts = peer.wait_for("STATUSTEXT", timeout_s=25)
    deadline = time.monotonic() + 15
    while not any("VISO_TYPE" in r["fields"]["text"] for r in peer.records("STATUSTEXT")) \
            and time.monotonic() < deadline:
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    code, _, stderr = finish(process)
    assert code == 0, stderr
    texts = [r["fields"]["text"] for r in peer.records("STATUSTEXT")]
    assert "companion: VISO_TYPE=0 blocks vision" in texts, texts
    assert "flight controller parameter VISO_TYPE = 0 blocks vision fusion: visual odometry is off" in stderr
    assert not [t for t in texts if "EK3_" in t or "VISO_POS" in t]  # the rest fits


def test_check_fc_prints_the_table_and_exits_1_on_a_blocking_parameter(peers):
    port = free_port()
    served = {"AHRS_EKF_TYPE": 3, "VISO_TYPE": 1, "EK3_SRC1_POSXY": 3, "EK3_SRC1_POSZ": 1, "EK3_SRC1_YAW": 6,
              "EK3_SRC1_VELXY": 0, "VISO_DELAY_MS": 10, "VISO_POS_X": 0.1, "VISO_POS_Y": 0, "VISO_POS_Z": 0}
    peers(port, "--params", json.dumps(served))
    result = subprocess.run([sys.executable, "-m", "companion", "check-fc", f"udpout:127.0.0.1:{port}",
                             "--config", str(write_config(Path(tempfile.mkdtemp()), HOVER, port))],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result.stderr
    lines = {line.split()[0]: line for line in result.stdout.splitlines() if line.strip()}
    assert re.match(r"EK3_SRC1_POSXY\s+3\s+6 \(ExternalNav\)\s+BLOCKS\s+horizontal position from GPS", lines["EK3_SRC1_POSXY"])
    assert re.match(r"EK3_SRC1_POSZ\s+1\s+.*degrades\s+height from baro", lines["EK3_SRC1_POSZ"])
    # the hover sequence's camera sits 0.1 m forward of the body origin: VISO_POS_X = 0.1 applies it twice
    assert "degrades" in lines["VISO_POS_X"] and "applied twice" in lines["VISO_POS_X"]
    assert re.match(r"VISO_TYPE\s+1\s+1 \(MAVLink\)\s+ok", lines["VISO_TYPE"])
    assert "1 parameter(s) block vision fusion, 2 degrade it" in result.stdout


def test_check_fc_tells_a_slow_answer_from_none_and_names_another_system_id(peers):
    """A flight controller that serves one parameter of ten: its heartbeat answered, the re-asked parameters
    outlast a short --timeout-s; 'no flight controller answered' was untrue. And a --system-id that is not the
    FC's was passed over in silence."""
    port = free_port()
    peers(port, "--params", json.dumps({"VISO_TYPE": 1}))
    short = subprocess.run([sys.executable, "-m", "companion", "check-fc", f"udpout:127.0.0.1:{port}", "--timeout-s",
                            "1.5"], capture_output=True, text=True, timeout=60)
    assert short.returncode == 2 and short.stderr.startswith(
        f"companion check-fc: flight controller system 1 answered on udpout:127.0.0.1:{port}, but not every "
        "parameter within 1.5 s"), short.stderr
    other = subprocess.run([sys.executable, "-m", "companion", "check-fc", f"udpout:127.0.0.1:{port}",
                            "--system-id", "2"], capture_output=True, text=True, timeout=60)
    assert "system id: the flight controller is system 1, the daemon's is 2" in other.stdout, other.stdout


@pytest.mark.parametrize("connection, why", [
    ("udpout:127.0.0.1:{port}", None),  # datagrams to nobody: nothing to say but the silence
    ("tcp:127.0.0.1:{port}", "(cannot open: [Errno 111] Connection refused)"),
    ("/dev/ttyACM97,115200", "(cannot open: [Errno 2] could not open port /dev/ttyACM97"),
])
def test_check_fc_with_nothing_listening_is_a_clear_error_that_says_why(connection, why):
    connection = connection.format(port=free_port())
    result = subprocess.run([sys.executable, "-m", "companion", "check-fc", connection, "--timeout-s", "1.5"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    message = result.stderr.strip()
    assert message.startswith(f"companion check-fc: no flight controller answered on {connection} within 1.5 s")
    assert (why in message) if why else ("cannot open" not in message)
    assert len(message.splitlines()) == 1 and "Traceback" not in result.stderr


@pytest.mark.parametrize("option, value, message", [
    ("--timeout-s", "inf", "--timeout-s must be more than 0 and at most 3600 s, not inf"),
    ("--timeout-s", "0", "--timeout-s must be more than 0 and at most 3600 s, not 0"),
    ("--latency-ms", "nan", "--latency-ms must be more than 0 and at most 250 ms (where VISO_DELAY_MS and "
                            "EKF2_EV_DELAY end), not nan"),
    ("--latency-ms", "-5", "--latency-ms must be more than 0 and at most 250 ms (where VISO_DELAY_MS and "
                           "EKF2_EV_DELAY end), not -5"),
    ("--latency-ms", "400", "--latency-ms must be more than 0 and at most 250 ms (where VISO_DELAY_MS and "
                            "EKF2_EV_DELAY end), not 400"),
    ("--system-id", "0", "--system-id must be 1 to 254 (255 is a ground station), not 0"),
])
def test_check_fc_refuses_a_number_out_of_range_before_it_connects(peers, option, value, message):
    """With a flight controller answering: --timeout-s inf was an OverflowError traceback, --latency-ms nan a
    ValueError one once the FC answered, --latency-ms -5 was judged against 'VISO_DELAY_MS -5'."""
    port = free_port()
    served = {"AHRS_EKF_TYPE": 3, "VISO_TYPE": 1, "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 6, "EK3_SRC1_YAW": 6,
              "EK3_SRC1_VELXY": 0, "VISO_DELAY_MS": 10, "VISO_POS_X": 0, "VISO_POS_Y": 0, "VISO_POS_Z": 0}
    peers(port, "--params", json.dumps(served))
    result = subprocess.run([sys.executable, "-m", "companion", "check-fc", f"udpout:127.0.0.1:{port}", option, value],
                            capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stdout, result.stderr) == (2, "", f"companion check-fc: {message}\n")


def test_a_second_daemon_on_the_same_vehicle_refuses_to_run(tmp_path):
    """Two daemons with the same ids through one router to the FC: the second exits with a
    clear error and never sends vision; the first goes on."""
    from mavlink_peer import UdpRouter
    fc_port, router_port = free_port(), free_port()
    fc = PeerProcess(fc_port, tmp_path / "fc.jsonl", "--origin-reply", "on_set", duration_s=60).wait_listening()
    router = UdpRouter(router_port, fc_port)
    first = start_daemon(write_config(tmp_path, HOVER, router_port, source={"loop": True}))
    try:
        fc.wait_for("VISION_POSITION_ESTIMATE", count=10, timeout_s=20)
        second_dir = tmp_path / "second"
        second_dir.mkdir()
        code, _, stderr = finish(start_daemon(write_config(second_dir, HOVER, router_port, source={"loop": True})),
                                 timeout_s=30)
        vision_after_ns = time.monotonic_ns()
        fc.wait_for("VISION_POSITION_ESTIMATE", count=len(fc.records("VISION_POSITION_ESTIMATE")) + 10)
        assert first.poll() is None
        first.send_signal(signal.SIGTERM)
        first_code, _, first_stderr = finish(first)
    finally:
        if first.poll() is None:
            first.kill()
        router.stop()
        fc.stop()
    assert code == 1, stderr
    assert "refusing to run: another companion sends as system 1 component 197" in stderr
    assert "Traceback" not in stderr
    assert first_code == 0, first_stderr
    vision_id = 102
    assert router.sent_by[0].count(vision_id) > 20 and vision_id not in router.sent_by[1]
    assert any(r["t_ns"] > vision_after_ns for r in fc.records("VISION_POSITION_ESTIMATE"))


def test_a_looping_replay_whose_files_vanish_does_not_flood_the_log(tmp_path, peers):
    """loop: true and the frames deleted mid-run: a few log lines and one 'camera lost', not one
    line per frame (the landed code wrote 480,000 lines in 16 s)."""
    sequence = spliced_sequence(tmp_path, HOVER, keep=[int(r["frame"]) for r in read_rows(HOVER / "timestamps.csv")])
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    process = start_daemon(write_config(tmp_path, sequence, port, source={"loop": True}))
    peer.wait_for("VISION_POSITION_ESTIMATE", count=5, timeout_s=20)
    (sequence / "frames").rename(tmp_path / "gone")
    texts = []
    deadline = time.monotonic() + 15
    while not any("camera lost" in t for t in texts) and time.monotonic() < deadline:
        time.sleep(0.1)
        texts = [r["fields"]["text"] for r in peer.records("STATUSTEXT")]
    time.sleep(3.0)
    process.send_signal(signal.SIGTERM)
    code, _, stderr = finish(process)
    assert code == 0, stderr
    lines = stderr.splitlines()
    assert len(lines) < 40, f"{len(lines)} log lines:\n" + "\n".join(lines[:60])
    assert sum("camera lost" in line for line in lines) == 1
    assert [t for t in texts if "camera lost" in t] == [next(t for t in texts if "camera lost" in t)]
    assert any(r["fields"]["system_status"] == 5 for r in peer.records("HEARTBEAT"))
    corrupt = int(re.search(r"corrupt (\d+)", stderr).group(1))
    assert 0 < corrupt < 500, corrupt  # paced at the recording's 15 fps and backed off, not a tight loop


def test_log_level_chooses_what_is_logged(tmp_path):
    """Two unreadable frames in a row: the first is a warning at any level, the second (within the
    throttle's 5 s) only at debug; info lines only from info down."""
    sequence = spliced_sequence(tmp_path, HOVER, keep=[int(r["frame"]) for r in read_rows(HOVER / "timestamps.csv")])
    rows = read_rows(sequence / "timestamps.csv")
    for row in rows[10:12]:
        (sequence / row["file"]).unlink()
    config = write_config(tmp_path, sequence, free_port())

    def run(level: str) -> str:
        result = subprocess.run([sys.executable, "-m", "companion", "run", "--config", str(config), "--log-level", level],
                                capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        return result.stderr

    quiet, chatty = run("warning"), run("debug")
    assert " INFO " not in quiet and "stage total" not in quiet
    assert quiet.count("is unreadable") == 1 and rows[10]["file"] in quiet
    assert chatty.count("is unreadable") == 2 and f"DEBUG companion.capture.replay: replay: {sequence / rows[11]['file']}" in chatty
    assert "stage total" in chatty


def test_a_missing_camera_is_reported_once_by_the_daemon_not_by_opencv_at_every_reopen(tmp_path):
    """A V4L2 device that is not there: the log says why (the missing node) and 'camera lost', the daemon
    keeps retrying and stops on SIGTERM; OpenCV's own warning, repeated at every reopen without the cause,
    is left out unless the log level is debug."""
    config = tmp_path / "camera.yaml"
    config.write_text(yaml.safe_dump({
        "source": {"kind": "v4l2", "device": "/dev/video97", "stall_timeout_s": 0.5},
        "map": str(MAP), "camera": {"calibration_file": str(REPO / "config" / "calibration.yaml")},
        "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}"}}))

    def run(*level: str) -> str:
        process = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config), *level],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(4.0)  # the first open and the reopens after 1 and 2 s
        process.send_signal(signal.SIGTERM)
        code, _, stderr = finish(process)
        assert code == 0, stderr
        return stderr

    info, debug = run(), run("--log-level", "debug")
    assert "/dev/video97 does not exist" in info and info.count("ERROR companion: camera lost") == 1
    assert int(re.search(r"camera reopens (\d+)", info).group(1)) >= 1, info  # retried, not given up
    assert "[ WARN" not in info, info
    assert "[ WARN" in debug and "VIDEOIO(V4L2)" in debug  # OpenCV does warn here: the test above means something


def wait_while_running(process: subprocess.Popen, condition, why=lambda: "", timeout_s: float = 30.0) -> None:
    """Until ``condition()`` holds, the daemon still running (``why()`` says what went wrong otherwise)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert process.poll() is None and time.monotonic() < deadline, why()
        time.sleep(0.1)


def assert_still_streaming(process: subprocess.Popen, peer: PeerProcess) -> None:
    """The daemon runs on and its 30 fps vision keeps reaching the peer (over 20 messages in 1.5 s)."""
    sent_then = len(peer.records("VISION_POSITION_ESTIMATE"))
    time.sleep(1.5)
    assert process.poll() is None
    assert len(peer.records("VISION_POSITION_ESTIMATE")) > sent_then + 20


def test_a_status_line_reader_that_goes_away_does_not_stop_the_vehicles_positioning(tmp_path, peers):
    """`companion run | head -1`, or a terminal closed under it: the status line cannot be written any more.
    The daemon says so once in the log and goes on sending vision (before, the broken pipe stopped it), and
    SIGTERM still stops it cleanly with status 0."""
    port = free_port()
    peer = peers(port)
    config = write_config(tmp_path, AISLE, port, source={"loop": True})
    with open(tmp_path / "stderr.log", "w") as stderr_file:
        process = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config)],
                                   stdout=subprocess.PIPE, stderr=stderr_file, text=True)
    try:
        assert " fps | " in process.stdout.readline()
        process.stdout.close()  # the reader goes away: the next status line (5 s on) meets a broken pipe
        log = tmp_path / "stderr.log"
        wait_while_running(process, lambda: "status line: cannot write" in log.read_text(), log.read_text)
        assert_still_streaming(process, peer)
    finally:
        process.send_signal(signal.SIGTERM)
        code = process.wait(timeout=30)
    stderr = (tmp_path / "stderr.log").read_text()
    assert code == 0, stderr
    assert stderr.count("status line: cannot write it any more ([Errno 32] Broken pipe)") == 1, stderr
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr


def full_pipe() -> tuple[int, int]:
    """(read end, write end) of a pipe filled to its last byte: the next write to it waits for a reader."""
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    for size in (65536, 4096, 256, 1):
        try:
            while True:
                os.write(write_end, b"x" * size)
        except BlockingIOError:
            pass
    os.set_blocking(write_end, True)
    return read_end, write_end


def test_a_status_line_reader_that_stops_reading_does_not_hold_up_the_daemon(tmp_path, peers):
    """`companion run | less`, not scrolled: the pipe fills (after about half an hour of lines) and the next
    status line would wait for the reader, and with it the supervisor: its health reports, the systemd
    watchdog and SIGTERM (before, the daemon did not stop). Lines are left out, said once in the log; vision
    goes on; the status line comes back when the reader reads; SIGTERM stops the daemon with 0."""
    port = free_port()
    peer = peers(port)
    config = write_config(tmp_path, AISLE, port, source={"loop": True})
    read_end, write_end = full_pipe()
    log = tmp_path / "stderr.log"
    try:
        with open(log, "w") as stderr_file:
            process = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config)],
                                       stdout=write_end, stderr=stderr_file)
        os.close(write_end)
        try:
            wait_while_running(process, lambda: "status line: its reader is not reading" in log.read_text(),
                               log.read_text)
            assert_still_streaming(process, peer)
            os.set_blocking(read_end, False)
            drained = b""
            deadline = time.monotonic() + 15  # the next status line, 5 s on, once the pipe has room
            while b" fps | " not in drained and time.monotonic() < deadline:
                try:
                    drained += os.read(read_end, 65536)
                except BlockingIOError:
                    time.sleep(0.1)
            assert b" fps | " in drained, log.read_text()
        finally:
            process.send_signal(signal.SIGTERM)
            code = process.wait(timeout=30)
    finally:
        os.close(read_end)
    stderr = log.read_text()
    assert code == 0, stderr
    assert stderr.count("status line: its reader is not reading") == 1, stderr
    assert "status line: its reader reads again" in stderr, stderr
    assert "Traceback" not in stderr, stderr


def test_on_a_narrow_terminal_the_status_line_is_cut_to_its_width(tmp_path):
    """An 80-column terminal (a default ssh session): each rewrite of the status line fits in 79 columns,
    so that the carriage return rewrites all of it (a wrapped line left its first rows behind at every
    update); the last line, which nothing rewrites, is whole."""
    import fcntl
    import pty
    import struct
    import termios

    config = write_config(tmp_path, HOVER, free_port())
    pid, fd = pty.fork()
    if pid == 0:  # the child: an 80 x 24 terminal, then the daemon on it
        fcntl.ioctl(0, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
        os.execv(sys.executable, [sys.executable, "-m", "companion", "run", "--config", str(config)])
    output = b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        output += chunk
    _, status = os.waitpid(pid, 0)
    os.close(fd)
    text = output.decode(errors="replace")
    assert os.waitstatus_to_exitcode(status) == 0, text
    # each rewrite runs to the end of its row, or to a log line written after it (stderr, the same terminal)
    rewrites = [re.split(r"\r\n|\d{4}-\d\d-\d\d \d\d:", part)[0] for part in text.split("\r\x1b[K")[1:]]
    assert len(rewrites) >= 3 and all(" fps | " in line for line in rewrites), text
    assert all(len(line) <= 79 for line in rewrites[:-1]), [len(line) for line in rewrites]
    assert len(rewrites[-1]) > 79 and "| sent " in rewrites[-1]  # the last line, whole


def test_a_hangup_leaves_the_daemon_running_and_sigterm_still_stops_it(tmp_path, peers):
    """SIGHUP (the ssh session that started `companion run` dropped): said once in the log, vision goes on
    (by default the signal ended the process at once: no clean stop, no finished recording)."""
    port = free_port()
    peer = peers(port)
    config = write_config(tmp_path, AISLE, port, source={"loop": True})
    process = start_daemon(config)
    try:
        wait_while_running(process, lambda: len(peer.records("VISION_POSITION_ESTIMATE")) >= 10)
        process.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        assert_still_streaming(process, peer)
    finally:
        process.send_signal(signal.SIGTERM)
        code, _, stderr = finish(process)
    assert code == 0, stderr
    assert stderr.count("SIGHUP (the terminal went away?): the daemon goes on") == 1, stderr
    assert "SIGTERM: stopping" in stderr


def test_stop_signals_that_keep_coming_while_the_daemon_stops_leave_a_clean_exit(tmp_path):
    """An impatient stop: SIGTERM after SIGTERM until the process is gone. Those after the summary came when the
    daemon's handlers were gone and ended a cleanly stopped daemon with 143 (4 runs of 4 by hand)."""
    process = start_daemon(write_config(tmp_path, HOVER, free_port(), source={"loop": True}))
    deadline = time.monotonic() + 30
    while "running: source" not in process.stderr.readline():
        assert process.poll() is None and time.monotonic() < deadline, "the daemon never ran"
    stderr_reader = threading.Thread(target=process.stderr.read, daemon=True)   # its pipe must not fill
    stderr_reader.start()
    deadline = time.monotonic() + 30
    while process.poll() is None and time.monotonic() < deadline:
        process.send_signal(signal.SIGTERM)
        time.sleep(0.01)
    assert process.wait(timeout=30) == 0


def wait_until_importing(process: subprocess.Popen, timeout_s: float = 20.0) -> None:
    """Until the daemon's modules are importing: numpy is mapped into the process (`companion` and its
    dispatcher load none; `companion run` loads it, OpenCV, SciPy and pymavlink before it has handlers)."""
    maps = Path(f"/proc/{process.pid}/maps")
    deadline = time.monotonic() + timeout_s
    while "/numpy/" not in maps.read_text():
        assert process.poll() is None and time.monotonic() < deadline, "the daemon never imported numpy"
        time.sleep(0.002)


@pytest.mark.parametrize("stop, ignored", [(signal.SIGTERM, None), (signal.SIGINT, signal.SIGINT)])
def test_a_stop_while_the_daemon_starts_ends_it_cleanly_with_a_log_line(tmp_path, stop, ignored):
    """systemd stops the service while `companion run` imports its modules (a second or more on a small
    computer): exit 0 and a log line, as a stop later on. Before, the default SIGTERM ended it: 143, not a word.
    So does SIGINT when the daemon came with it ignored (`companion run &` in a script): it was lost, and the
    daemon ran on (10 minutes in a fault tour), though it stops on SIGINT once running."""
    ignore = None if ignored is None else (lambda: signal.signal(ignored, signal.SIG_IGN))
    process = start_daemon(write_config(tmp_path, HOVER, free_port(), source={"loop": True}), preexec_fn=ignore)
    try:
        wait_until_importing(process)
        process.send_signal(stop)
    finally:
        code, _, stderr = finish(process)
    assert code == 0, stderr
    assert f"{stop.name} while starting: stopping" in stderr and "Traceback" not in stderr, stderr
    assert "running:" not in stderr  # stopped before it began


def test_a_stopped_daemon_says_so_to_the_flight_controller_last(tmp_path, peers):
    """SIGTERM (systemd's stop): after the last vision the flight controller hears a STATUSTEXT saying vision ends,
    so that a ground station tells a stop from a crash (both fall silent); it said nothing."""
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    process = start_daemon(write_config(tmp_path, HOVER, port, source={"loop": True}))
    try:
        wait_while_running(process, lambda: len(peer.records("VISION_POSITION_ESTIMATE")) >= 10)
    finally:
        process.send_signal(signal.SIGTERM)
        code, _, stderr = finish(process)
    assert code == 0, stderr
    deadline = time.monotonic() + 5   # the datagram may still be on its way when the daemon has exited
    while not any(r["fields"]["text"] == "companion: stopped, no more vision" for r in peer.records("STATUSTEXT")):
        assert time.monotonic() < deadline, [r["fields"]["text"] for r in peer.records("STATUSTEXT")]
        time.sleep(0.05)
    names = [r["name"] if r["name"] != "STATUSTEXT" else r["fields"]["text"] for r in peer.records()]
    # after the last vision (a heartbeat may still follow it)
    assert names.index("companion: stopped, no more vision") > max(
        i for i, name in enumerate(names) if name == "VISION_POSITION_ESTIMATE")


def test_a_hangup_while_the_daemon_starts_is_said_and_it_runs_on(tmp_path, peers):
    """SIGHUP while `companion run` imports its modules (the ssh session that started it dropped at once):
    said in the log and the daemon runs on, as later. Before, the default SIGHUP ended it: 129, not a word."""
    port = free_port()
    peer = peers(port)
    process = start_daemon(write_config(tmp_path, HOVER, port, source={"loop": True}))
    try:
        wait_until_importing(process)
        process.send_signal(signal.SIGHUP)
        wait_while_running(process, lambda: len(peer.records("VISION_POSITION_ESTIMATE")) >= 10)
    finally:
        process.send_signal(signal.SIGTERM)
        code, _, stderr = finish(process)
    assert code == 0, stderr
    assert stderr.count("SIGHUP (the terminal went away?): the daemon goes on") == 1, stderr
    assert "SIGTERM: stopping" in stderr


def test_a_replay_as_fast_as_possible_is_filtered_as_in_real_time(tmp_path):
    """realtime: false: the frames keep their recorded times, so the filter sees the flight's own motion
    and gates none of its poses (stamped when read, time compressed several times, it rejected most of
    them: 217 of 246 on this flight); the status line's rate is still the frames done per second."""
    config = write_config(tmp_path, AISLE, free_port(), source={"realtime": False})
    process = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(config)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    code, stdout, stderr = finish(process, timeout_s=60)
    assert code == 0, stderr
    frames = len(open_recording(AISLE).t_ns)
    assert f"frames {frames}," in stderr
    last = [line for line in stdout.splitlines() if " fps | " in line][-1]
    assert "| tracking |" in last and "rejected 0 resets 0" in last, last
    assert float(last.split()[0]) > 0, last


def test_a_marker_moved_since_the_map_was_made_is_said_with_how_far_and_weighed_by_it(tmp_path, peers):
    """A rendered 2 s hover before the north wall (O, N and DOWN in view), replayed on a map where N hangs
    10 cm off where it is: the daemon says once, in its log with how far off and to the flight controller
    by STATUSTEXT, that N disagrees with the map, hands the offset to the pose stage (which from then on
    leaves N out beside the others) and streams on, tracking, to the end of the replay."""
    camera = tmp_path / "camera.yaml"
    camera.write_text(yaml.safe_dump({"width": 640, "height": 480, "hfov_deg": 70.0,
                                      "mount": {"facing": "forward", "tilt_down_deg": 0.0}}))
    wall = tmp_path / "wall"
    subprocess.run([sys.executable, "-m", "companion", "simulate", str(wall), "--map", str(MAP), "--camera",
                    str(camera), "--pattern", "hover", "--center", "9.5,8.0,1.3", "--heading", "90", "--duration",
                    "2", "--fps", "15", "--no-progress"], check=True, capture_output=True)
    truth = load_map(MAP)
    marker = truth.marker_by_symbol("N")
    T_moved = marker.T_map_marker.copy()
    T_moved[:3, 3] += 0.10 * T_moved[:3, 0]  # along the wall
    moved = tmp_path / "moved.yaml"
    write_map(dataclasses.replace(truth, markers={**truth.markers, marker.id: dataclasses.replace(
        marker, T_map_marker=T_moved)}), moved)
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    config = write_config(tmp_path, wall, port)
    config.write_text(yaml.safe_dump({**yaml.safe_load(config.read_text()), "map": str(moved)}))
    code, stdout, stderr = finish(start_daemon(config), timeout_s=60)
    assert code == 0, stderr
    said = [line for line in stderr.splitlines() if "disagrees with the map" in line]
    assert len(said) == 1 and "marker N disagrees with the map by " in said[0], stderr
    offset_cm = float(said[0].split(" by ")[1].split(" cm")[0])
    assert 9.0 < offset_cm < 11.0, said
    assert "markers lost" not in stderr
    told_ns = [r["t_ns"] for r in peer.records("STATUSTEXT")
               if r["fields"]["text"] == "companion: marker N disagrees with the map"]
    assert len(told_ns) == 1
    # the frames after it were posed without N: vision went on
    assert sum(r["t_ns"] > told_ns[0] for r in peer.records("VISION_POSITION_ESTIMATE")) >= 5


def test_a_map_less_accurate_than_the_config_says_is_told_and_weighed_as_it_is(tmp_path, peers):
    """The shipped aisle flight replayed (as fast as possible) on a tape-measured map (every entry off by 2 cm
    and 2 degrees sd) with the config's default accuracy (5 mm, 0.2 deg): most frames of two markers went
    without a pose. The daemon says once, in its log and by STATUSTEXT, that markers disagree with each other
    by more than the map states, and weighs every marker as that uncertain from then on: vision goes on."""
    taped = tmp_path / "taped.yaml"
    write_map(tape_map(load_map(MAP), 0), taped)
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set")
    config = write_config(tmp_path, AISLE, port, source={"realtime": False})
    config.write_text(yaml.safe_dump({**yaml.safe_load(config.read_text()), "map": str(taped)}))
    code, _, stderr = finish(start_daemon(config), timeout_s=60)
    assert code == 0, stderr
    said = [line for line in stderr.splitlines() if "markers disagree with each other by" in line]
    assert len(said) == 1 and "the map is less accurate than the config states (pose.map_sd_m" in said[0], stderr
    assert "disagrees with the map" not in stderr  # no one marker is blamed
    told = [r for r in peer.records("STATUSTEXT") if r["fields"]["text"].startswith("companion: markers disagree by")]
    assert len(told) == 1
    assert sum(r["t_ns"] > told[0]["t_ns"] for r in peer.records("VISION_POSITION_ESTIMATE")) >= 50
