"""The flight controller's attitude over a real MAVLink link: an independent libmav peer (its own process,
UDP on loopback) streams ATTITUDE on its own time base with a clock offset and send jitter."""
from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion import cli
from companion.capture.attitude_csv import ATTITUDE_FILE
from companion.daemon.config import config_from_dict
from companion.daemon.health import Health
from companion.daemon.pipeline import Pipeline
from companion.daemon.service import Daemon
from companion.detect.detector import Detector
from companion.fusion import PoseFilter
from companion.geometry import frames
from companion.geometry.attitude import AttitudeHistory
from companion.geometry.pose import PoseParams, PoseSolver
from companion.localize import groundtruth, map_detector, resources
from companion.capture.replay import open_recording
from companion.mavlink.attitude import AttitudeStream
from companion.mavlink.link import LinkParams, MavlinkLink
from companion.types import Frame
from mavlink_peer import PeerProcess, free_port

REPO = Path(__file__).resolve().parents[1]
RATE_HZ = 50.0


@pytest.fixture
def started(tmp_path):
    """start(peer args..., history=...) -> (peer, link): a libmav peer and our link with an attitude stream."""
    opened = []

    def start(*peer_args, history=None, statustext_interval_s=1.0):
        port = free_port()
        peer = PeerProcess(port, tmp_path / f"peer{len(opened)}.jsonl", "--attitude", *peer_args).wait_listening()
        history = history or AttitudeHistory(0.1)
        link = MavlinkLink(LinkParams(connection=f"udpout:127.0.0.1:{port}", heartbeat_interval_s=0.2,
                                      statustext_interval_s=statustext_interval_s),
                           attitude=AttitudeStream(history, RATE_HZ))
        link.start()
        opened.append((peer, link))
        return peer, link

    yield start
    for peer, link in opened:
        link.close()
        peer.stop()


def sent_attitude(peer) -> list[dict]:
    return peer.records("ATTITUDE", kind="sent")


def test_attitude_is_requested_and_put_on_our_clock(started):
    """time_boot_ms of a pretend autopilot booted 4321.5 s ago, each message sent 0-5 ms late: every sample
    filed after the first second lies within 2 ms of when the peer stamped it (the shared monotonic clock)."""
    peer, link = started("--attitude-jitter-ms", "5", "--boot-age", "4321.5")
    peer.wait_for("ATTITUDE", count=int(3 * RATE_HZ), kind="sent", timeout_s=20)
    time.sleep(0.2)
    request = [r for r in peer.records("COMMAND_LONG") if r["fields"]["command"] == 511]
    assert request and request[0]["fields"]["param1"] == 30 and request[0]["fields"]["param2"] == 20_000
    truth = sent_attitude(peer)
    stamps = np.array([r["stamp_ns"] for r in truth])
    samples = link.attitude.history.samples()
    assert len(samples) >= 0.9 * len(truth) - 10
    settled = [s for s in samples if s.t_ns > stamps[0] + 1_000_000_000]
    errors_ms = []
    for sample in settled:
        k = int(np.argmin(np.abs(stamps - sample.t_ns)))
        # the nearest stamp is the same message: its values (float32 on the wire)
        assert sample.roll_rad == pytest.approx(truth[k]["fields"]["roll"], abs=1e-6)
        assert sample.pitch_rad == pytest.approx(truth[k]["fields"]["pitch"], abs=1e-6)
        errors_ms.append((sample.t_ns - stamps[k]) / 1e6)
    errors_ms = np.array(errors_ms)
    assert len(errors_ms) > RATE_HZ
    assert np.abs(errors_ms).max() < 2.0, f"time alignment error up to {np.abs(errors_ms).max():.2f} ms"
    # and the clock offset the link found is the pretend boot's
    assert link.attitude.requests >= 1


def test_stopped_attitude_falls_back_once_and_comes_back(started):
    """The peer streams, pauses 1.5 s, streams again: the health judge (fed by the pipeline, telling the
    link as the daemon does) says 'stale' within a second, once, and 'back' when it returns; frames in the
    gap get no attitude."""
    history = AttitudeHistory(0.4)   # well inside the 1.5 s pause, and above a loaded machine's stalls
    peer, link = started("--attitude-pause", "1.5,1.5", history=history, statustext_interval_s=0.1)
    facility_map = REPO / "maps" / "warehouse.yaml"
    from companion.geometry.facility_map import load_map
    from companion.sim.simulate import DEFAULT_CAMERA
    from companion.geometry.camera import CameraModel

    fm, camera = load_map(facility_map), CameraModel.from_config(DEFAULT_CAMERA, "default camera")
    pipeline = Pipeline(Detector(camera=camera), PoseSolver(fm, camera), PoseFilter(), link,
                        frames.invert_transform(fm.T_ned_map), attitude=history.lookup)
    health = Health(lambda text, severity, topic: link.statustext(f"companion: {text}", severity, topic),
                    attitude_expected=True)
    pipeline.observers.append(health.observe)
    peer.wait_for("ATTITUDE", count=5, kind="sent")
    blank = np.full((camera.height, camera.width), 128, np.uint8)
    records = []
    end = time.monotonic() + 4.5
    index = 0
    while time.monotonic() < end:
        records.append(pipeline.process(Frame(blank, time.monotonic_ns() - 20_000_000, index)))
        index += 1
        time.sleep(1 / 30)
    texts = peer.wait_for("STATUSTEXT", count=3)
    time.sleep(0.3)
    said = [(r["t_ns"], r["fields"]["text"]) for r in peer.records("STATUSTEXT")]
    assert [t for _, t in said] == ["companion: flight controller attitude in use",
                                    "companion: attitude stale: poses without it",
                                    "companion: attitude back: poses use it"], said
    sent = [r["stamp_ns"] for r in sent_attitude(peer)]
    gap_start = max(t for t, nxt in zip(sent, sent[1:]) if nxt - t > 1e9)
    stale_said = said[1][0]
    assert 0 < stale_said - gap_start < 1.0e9
    in_gap = [r for r in records if gap_start + 0.45e9 < r.t_ns < gap_start + 1.4e9]   # past max_age_s
    assert in_gap and all(r.attitude is None for r in in_gap)
    assert sum(r.attitude is not None for r in records) > len(records) / 3
    assert len(texts) >= 3


def test_a_daemon_records_the_peers_attitude_and_tells_a_pause_once(tmp_path, caplog):
    """The daemon (attitude.source: link, a looping replay for frames) against a peer that streams ATTITUDE,
    pauses 1.2 s and streams again, recording with ``record``: the pause is told once (log and STATUSTEXT) and
    its end once; attitude.csv holds the samples the peer sent, each at the peer's stamp on the frames' time
    base (0 = the first frame) within 2 ms, and replay reads it back."""
    port = free_port()
    peer = PeerProcess(port, tmp_path / "peer.jsonl", "--attitude", "--attitude-jitter-ms", "3",
                       "--attitude-pause", "1.5,1.2", duration_s=60).wait_listening()
    hover = REPO / "tests" / "data" / "sequences" / "warehouse_hover"
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(hover), "realtime": True, "loop": True},
        "map": str(REPO / "maps" / "warehouse.yaml"),
        "mavlink": {"connection": f"udpout:127.0.0.1:{port}", "duplicate_listen_s": 0.0,
                    "statustext_interval_s": 0.1},
        "attitude": {"source": "link", "max_age_s": 0.4},   # the pause only, not a loaded machine's stalls
        "record": str(tmp_path / "flight"),
    }, tmp_path / "daemon.yaml")
    daemon = Daemon(config)
    caplog.set_level(logging.INFO, logger="companion")
    runner = threading.Thread(target=daemon.run)
    try:
        runner.start()
        peer.wait_for("ATTITUDE", count=int(1.5 * RATE_HZ), kind="sent", timeout_s=20)
        time.sleep(3.5)   # the pause, and a second of samples after it
    finally:
        stopped_ns = time.monotonic_ns()
        daemon.stop_event.set()
        runner.join(timeout=20)
        time.sleep(0.3)
        peer.stop()
    said = [r["fields"]["text"] for r in peer.records("STATUSTEXT") if "attitude" in r["fields"]["text"]]
    if said and said[0] == "companion: no attitude yet: poses without it":   # frames before the first sample
        said = said[1:]
    assert said == ["companion: flight controller attitude in use", "companion: attitude stale: poses without it",
                    "companion: attitude back: poses use it"], said
    logged = [r.getMessage() for r in caplog.records if "attitude stale" in r.getMessage()]
    assert logged == ["attitude stale: poses without it"], logged

    recorded = open_recording(tmp_path / "flight").attitude
    assert recorded is not None and (tmp_path / "flight" / ATTITUDE_FILE).is_file()
    first_frame_ns = daemon.pipeline.stats.records[0].t_ns
    sent = sent_attitude(peer)
    stamps = np.array([r["stamp_ns"] for r in sent])
    sent_deg = np.degrees([[r["fields"]["roll"], r["fields"]["pitch"]] for r in sent])
    errors_ms = []
    for sample in recorded:
        # the message it came from: the one with its values (the peer's slow sine never repeats in a run)
        k = int(np.argmin(np.abs(sent_deg - np.degrees([sample.roll_rad, sample.pitch_rad])).sum(axis=1)))
        assert math.degrees(sample.roll_rad) == pytest.approx(sent_deg[k, 0], abs=1e-3)
        assert math.degrees(sample.pitch_rad) == pytest.approx(sent_deg[k, 1], abs=1e-3)
        errors_ms.append((sample.t_ns + first_frame_ns - stamps[k]) / 1e6)
    settled = np.array(errors_ms[int(RATE_HZ):])   # after the offset filter's first second
    assert np.abs(settled).max() < 2.0, f"recorded times off by up to {np.abs(settled).max():.2f} ms"
    # the samples sent while it recorded (but the first and last few ms) are there; the pause too
    while_recording = stamps[(stamps > first_frame_ns + 5_000_000) & (stamps < stopped_ns - 50_000_000)]
    # a sample whose time on our clock does not rise (the offset filter re-anchored under load) is dropped
    assert len(recorded) >= 0.97 * len(while_recording) - 2, (len(recorded), len(while_recording))
    gaps_s = np.diff([s.t_ns for s in recorded]) * 1e-9
    assert 1.0 < gaps_s.max() < 1.4


def render_far_marker_hover(folder: Path) -> Path:
    """A rendered hover (simulate's default camera) 5 m from the dock wall in aisle 2, facing it: far markers."""
    out = folder / "hover"
    code = cli.main(["simulate", str(out), "--map", str(REPO / "maps" / "warehouse.yaml"), "--pattern", "hover",
                     "--center", "5.0,9.1,1.5", "--heading", "180", "--duration", "1.5", "--fps", "10",
                     "--no-progress"])
    assert code == 0
    return out


def test_poses_with_the_peers_attitude_match_the_ground_truth(started, tmp_path):
    """The peer streams a rendered hover's attitude.csv as the frames' capture times pass; single-marker
    poses solved with it, frame by frame without a prior, against the renderer's ground truth."""
    sequence = render_far_marker_hover(tmp_path)
    facility_map, camera = resources(sequence, None, None)
    truth = groundtruth(sequence)
    recording = open_recording(sequence)
    start_ns = time.monotonic_ns() + 1_500_000_000  # recorded t 0 on our clock
    history = AttitudeHistory(0.1)
    peer, link = started("--attitude-csv", str(sequence / "attitude.csv"), "--attitude-start-ns", str(start_ns),
                         history=history)
    detector = map_detector(facility_map, camera)
    params = PoseParams(prior_max_age_s=0.0, max_markers=1, attitude_sd_deg=0.3, map_sd_m=0.0, map_sd_deg=0.0)  # a rendered, exact map
    with_attitude, without = PoseSolver(facility_map, camera, params), PoseSolver(facility_map, camera, params)
    images = {number: image for number, image in zip(recording.frames, _images(sequence))}
    rows = []
    for number, recorded_t_ns in zip(recording.frames.tolist(), recording.t_ns.tolist()):
        t_ns = start_ns + recorded_t_ns
        while time.monotonic_ns() < t_ns + 60_000_000:  # the sample after the frame has arrived
            time.sleep(0.005)
        detections = detector.detect(images[number])
        attitude = history.at(t_ns)
        rows.append((number, attitude, with_attitude.solve_detailed(detections, t_ns, attitude=attitude),
                     without.solve_detailed(detections, t_ns)))
    errors_m, attitude_errors_deg = [], []
    for number, attitude, solution, plain in rows:
        T_true = truth[number]
        roll, pitch = frames.roll_pitch_321(facility_map.T_ned_map[:3, :3] @ T_true[:3, :3])
        assert attitude is not None
        attitude_errors_deg += [math.degrees(attitude.roll_rad - roll), math.degrees(attitude.pitch_rad - pitch)]
        assert solution.used_attitude and solution.measurement is not None, solution.status
        errors_m.append(float(np.linalg.norm(solution.measurement.T_map_body[:3, 3] - T_true[:3, 3])))
    # the attitude at each frame: the truth within the simulated 0.2 deg noise
    assert np.abs(attitude_errors_deg).max() < 1.0
    assert np.median(errors_m) < 0.05 and max(errors_m) < 0.3
    # the attitude is information the image lacks: where both are posed, the roll/pitch prior narrows the
    # pose (a far marker alone constrains its tilt weakly)
    pairs = [(s.measurement, p.measurement) for *_, s, p in rows if p.measurement is not None]
    assert pairs, [p.status for *_, p in rows]
    assert all(np.trace(a.covariance_ned[3:5, 3:5]) < np.trace(b.covariance_ned[3:5, 3:5]) for a, b in pairs)


def _images(sequence: Path):
    from companion.sim.simulate import read_sequence

    return [image for _, image in read_sequence(sequence).images()]
