"""The live view over real loopback HTTP: the daemon replays the hover flight (looping, real time) and
the tests are its clients. The page itself is tested in a real browser in test_browser.py."""
from __future__ import annotations

import csv
import dataclasses
import json
import socket
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.daemon.config import ConfigError, config_from_dict
from companion.daemon.overlay import REJECTED, UNMAPPED, USED, annotate
from companion.daemon.pipeline import FrameRecord
from companion.daemon.service import Daemon
from companion.daemon.status import DaemonStatus
from companion.daemon.web import LiveView, WebError
from companion.geometry.facility_map import load_map
from companion.geometry.pose import PoseSolution
from companion.types import Detection, PoseMeasurement
from mavlink_peer import free_port

REPO = Path(__file__).resolve().parent.parent
HOVER = REPO / "tests" / "data" / "sequences" / "warehouse_hover"
MAP = REPO / "maps" / "warehouse.yaml"


def make_daemon(tmp_path: Path, http="127.0.0.1:0") -> Daemon:
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(HOVER), "realtime": True, "loop": True},
        "map": str(MAP),
        "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}", "origin_wait_s": 0.0, "duplicate_listen_s": 0.0},
        "status": {"http": http},
    }, tmp_path / "daemon.yaml")
    return Daemon(config)


@pytest.fixture
def daemon(tmp_path):
    daemon = make_daemon(tmp_path)
    runner = threading.Thread(target=daemon.run, name="test-daemon")
    runner.start()
    yield daemon
    daemon.stop_event.set()
    runner.join(timeout=15)
    assert not runner.is_alive()


def get(daemon: Daemon, path: str, timeout_s: float = 5.0):
    with urllib.request.urlopen(daemon.live_view.url.rstrip("/") + path, timeout=timeout_s) as response:
        return response.status, dict(response.headers), response.read()


def wait_for(condition, timeout_s: float = 10.0) -> None:
    done = threading.Event()
    for _ in range(int(timeout_s / 0.05)):
        if condition():
            return
        done.wait(0.05)
    raise AssertionError("condition not met in time")


def test_no_client_no_work(daemon):
    wait_for(lambda: daemon.pipeline.stats.frames >= 20)
    assert daemon.live_view.counters.encoded == 0 and daemon.live_view.counters.dropped == 0
    assert not daemon.live_view.wanted()


def test_frame_jpg_is_the_annotated_newest_frame_and_after_waits_for_a_newer_one(daemon):
    status, headers, body = get(daemon, "/frame.jpg")
    assert status == 200 and headers["Content-Type"] == "image/jpeg"
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (480, 640, 3)
    # annotated: the banner is drawn in colour on the gray frame
    assert np.abs(image[5, :, 2].astype(int) - image[5, :, 1]).mean() > 30
    serial, index = int(headers["X-Frame-Serial"]), int(headers["X-Frame-Index"])
    _, newer, _ = get(daemon, f"/frame.jpg?after={serial}")
    assert int(newer["X-Frame-Serial"]) > serial and int(newer["X-Frame-Index"]) != index


def run_daemon(tmp_path: Path, http: str):
    """A started daemon and its thread; stopped by stop_daemon."""
    tmp_path.mkdir(exist_ok=True)
    daemon = make_daemon(tmp_path, http=http)
    runner = threading.Thread(target=daemon.run, name="test-daemon")
    runner.start()
    return daemon, runner


def stop_daemon(daemon: Daemon, runner: threading.Thread) -> None:
    daemon.stop_event.set()
    runner.join(timeout=15)
    assert not runner.is_alive()


def test_a_client_of_the_previous_run_gets_the_restarted_daemons_frames_at_once(tmp_path):
    """A page that saw serial N from a daemon that ran an hour (about 54000 frames) asks a restarted
    daemon on the same port for ``?after=N``: it gets the new run's newest frame at once. (Before, the
    new run counted from 1 and answered 503 until its count passed N: the page froze about an hour.)"""
    port = free_port("tcp")
    first, runner = run_daemon(tmp_path / "first", f"127.0.0.1:{port}")
    try:
        _, headers, _ = get(first, "/frame.jpg")
        view = first.live_view
        with view._new_frame:   # an hour at 15 frames a second
            view._latest = dataclasses.replace(view._latest, serial=view._latest.serial + 54000)
        _, headers, _ = get(first, f"/frame.jpg?after={headers['X-Frame-Serial']}")
        seen = int(headers["X-Frame-Serial"])
        assert seen > 54000
    finally:
        stop_daemon(first, runner)
    second, runner = run_daemon(tmp_path / "second", f"127.0.0.1:{port}")
    try:
        status, headers, body = get(second, f"/frame.jpg?after={seen}")   # not a 503
        assert status == 200 and 1 <= int(headers["X-Frame-Serial"]) < seen
        assert cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR).shape == (480, 640, 3)
        # and the page's next request waits for the next frame of this run
        _, newer, _ = get(second, f"/frame.jpg?after={headers['X-Frame-Serial']}")
        assert int(newer["X-Frame-Serial"]) > int(headers["X-Frame-Serial"])
    finally:
        stop_daemon(second, runner)


def test_status_json_holds_every_status_field_and_the_true_estimate(daemon):
    wait_for(lambda: daemon.status().track_state == "tracking")
    _, headers, body = get(daemon, "/status.json")
    document = json.loads(body)
    assert headers["Content-Type"] == "application/json"
    assert set(document["status"]) == {f.name for f in dataclasses.fields(DaemonStatus)}
    assert document["status"]["track_state"] == "tracking" and document["line"].count("|") >= 5
    estimate = document["estimate"]
    covariance = np.array(estimate["covariance_ned"])
    assert covariance.shape == (6, 6) and np.allclose(covariance, covariance.T) and np.all(np.diag(covariance) > 0)
    # the hover flight's ground truth (map frame and NED) from the renderer
    with open(HOVER / "groundtruth.csv", newline="") as handle:
        truth = list(csv.DictReader(handle))[-1]
    np.testing.assert_allclose(estimate["position_map_m"], [float(truth[k]) for k in ("x_m", "y_m", "z_m")],
                               atol=0.05)
    np.testing.assert_allclose(estimate["position_ned_m"],
                               [float(truth[k]) for k in ("north_m", "east_m", "down_m")], atol=0.05)
    assert document["track_map_m"] and document["frame"]["verdict"] in ("ok", "link")
    assert any(m["text"] == "companion: tracking markers" for m in document["statustexts"])


def test_map_json_places_the_markers_of_the_map(daemon):
    _, _, body = get(daemon, "/map.json")
    document = json.loads(body)
    markers = {m["symbol"]: m for m in document["markers"]}
    assert len(markers) == 49
    # maps/warehouse.yaml: HOME on the north wall (y = 10.5) facing -y
    assert markers["HOME"]["centre_m"][1] == pytest.approx(10.5) and markers["HOME"]["normal"] == \
        pytest.approx([0.0, -1.0], abs=1e-9)


def test_mjpeg_stream_sends_successive_frames_and_counts_its_client(daemon):
    host, port = daemon.live_view.server.server_address[:2]
    with socket.create_connection((host, port), timeout=5) as sock:
        sock.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")
        reader = sock.makefile("rb")   # closed below: the socket stays open while it is
        assert b"200" in reader.readline()
        headers = {}
        while (line := reader.readline().strip()):
            name, _, value = line.decode().partition(":")
            headers[name.lower()] = value.strip()
        assert headers["content-type"] == "multipart/x-mixed-replace; boundary=companionframe"
        indices = []
        for _ in range(3):
            assert reader.readline().strip() == b"--companionframe"
            part = {}
            while (line := reader.readline().strip()):
                name, _, value = line.decode().partition(":")
                part[name.lower()] = value.strip()
            jpeg = reader.read(int(part["content-length"]))
            assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (480, 640)
            reader.readline()
            indices.append(int(part["x-frame-index"]))
        assert daemon.live_view.wanted() and daemon.live_view._streams == 1
        assert indices[0] < indices[1] < indices[2]   # a looping replay numbers on
        reader.close()
    wait_for(lambda: daemon.live_view._streams == 0)


def test_a_client_that_stops_taking_the_stream_or_sends_nothing_is_dropped(daemon, caplog):
    """A frozen viewer (its MJPEG stream no longer read) and a client that connects and sends no request:
    each is dropped after the client timeout (1 s here), without a traceback; the frames then stop being
    encoded. (Before, the stream's thread waited on the full socket forever and every frame was encoded
    for it; the silent client's thread waited for its request forever.)"""
    daemon.live_view.client_timeout_s = 1.0
    host, port = daemon.live_view.server.server_address[:2]
    frozen = socket.socket()
    frozen.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    frozen.connect((host, port))
    silent = socket.create_connection((host, port))
    try:
        frozen.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")
        wait_for(lambda: daemon.live_view._streams == 1)
        wait_for(lambda: daemon.live_view._streams == 0, timeout_s=30.0)
        wait_for(lambda: not daemon.live_view.wanted())
        silent.settimeout(10.0)
        assert silent.recv(1) == b""   # closed by the server
    finally:
        frozen.close()
        silent.close()
    assert "Traceback" not in caplog.text and "Exception" not in caplog.text


def test_stream_clients_that_leave_while_no_frame_comes_are_dropped():
    """Three MJPEG clients connect while no frame comes (the camera lost) and close their connections
    (``curl -m 2``): all three are dropped while still no frame comes, and nobody wants frames any more.
    (Before, a stream noticed its client gone only when it wrote a frame: ``streams: 3`` stayed, and the
    frames were encoded for nobody once the camera came back.)"""
    view = LiveView(("127.0.0.1", 0), load_map(MAP), lambda: None, lambda: [])
    view.start()
    host, port = view.server.server_address[:2]
    clients = []
    try:
        for _ in range(3):
            client = socket.create_connection((host, port), timeout=5)
            client.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: x\r\n\r\n")
            clients.append(client)
        for client in clients:
            assert b"200" in client.recv(1024)
        wait_for(lambda: view._streams == 3)
        assert view.wanted()
        for client in clients:
            client.close()
        wait_for(lambda: view._streams == 0, timeout_s=5.0)   # well before the client timeout (10 s)
        wait_for(lambda: not view.wanted())
        assert view.counters.encoded == 0
    finally:
        for client in clients:
            client.close()
        view.close()


def test_unknown_path_is_404_and_names_every_path(daemon):
    with pytest.raises(urllib.error.HTTPError) as error:
        get(daemon, "/admin")
    assert error.value.code == 404
    assert error.value.read().decode().split("try")[1].split() == \
        ["/", "/frame.jpg", "/stream.mjpg", "/status.json", "/map.json"]


@pytest.mark.parametrize("path, content_type", [
    ("/", "text/html; charset=utf-8"), ("/status.json", "application/json"), ("/map.json", "application/json"),
    ("/frame.jpg", "image/jpeg"), ("/stream.mjpg", "multipart/x-mixed-replace; boundary=companionframe"),
])
def test_head_answers_the_get_endpoints_without_a_body(daemon, path, content_type):
    """``curl -I``: the GET's status and headers, no body (before: 501)."""
    host, port = daemon.live_view.server.server_address[:2]
    with socket.create_connection((host, port), timeout=10) as sock:
        sock.sendall(f"HEAD {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        reader = sock.makefile("rb")
        assert reader.readline().split()[1] == b"200"
        headers = {}
        while (line := reader.readline().strip()):
            name, _, value = line.decode().partition(":")
            headers[name.lower()] = value.strip()
        assert headers["content-type"] == content_type
        # then nothing: the next request on the connection (or its close, after a stream) comes next
        sock.sendall(b"GET /nothing HTTP/1.1\r\nHost: x\r\n\r\n")
        rest = reader.readline()
        assert rest == b"" if path == "/stream.mjpg" else rest.split()[1] == b"404"
        reader.close()
    wait_for(lambda: daemon.live_view._streams == 0)


def test_a_busy_port_is_a_one_line_error(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(WebError, match=f"status.http: cannot listen on 127.0.0.1:{port}"):
            make_daemon(tmp_path, http=f"127.0.0.1:{port}")
        run = subprocess.run([sys.executable, "-m", "companion", "run", "--http", f"127.0.0.1:{port}"],
                             capture_output=True, text=True, timeout=30)
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert f"--http: cannot listen on 127.0.0.1:{port}: " in run.stderr   # the option that gave it, not the key


@pytest.mark.parametrize("value, message", [
    ("8080", "must be HOST:PORT"), ("localhost:http", "the port must be 0..65535"),
    ("127.0.0.1:70000", "the port must be 0..65535"), ([8080], "must be HOST:PORT"),
])
def test_http_key_errors_name_the_key(tmp_path, value, message):
    with pytest.raises(ConfigError, match=f"status.http: {message}"):
        config_from_dict({"source": {"kind": "replay", "path": str(HOVER)}, "map": str(MAP),
                          "status": {"http": value}}, tmp_path / "daemon.yaml")


def test_a_wide_address_is_announced_as_reachable_from_the_network(tmp_path, caplog):
    daemon = make_daemon(tmp_path, http="0.0.0.0:0")
    try:
        with caplog.at_level("WARNING", logger="companion"):
            daemon.live_view.start()
        assert "reachable from the network, with no password and no encryption" in caplog.text
    finally:
        daemon.live_view.close()
        daemon.link.close()


# --------------------------------------------------------------- the overlay

def test_overlay_outlines_markers_by_their_part_in_the_pose():
    gray = np.full((480, 640), 128, np.uint8)
    square = np.array([[100.0, 100.0], [200.0, 100.0], [200.0, 200.0], [100.0, 200.0]])
    detections = (Detection("A", 0, square, "square", 0, 1.0),
                  Detection("B", 1, square + [250.0, 0.0], "circles", 2, 1.0),
                  Detection("STAR", 49, square + [0.0, 220.0], "square", 0, 1.0))
    solution = PoseSolution(None, "ambiguous", marker_ids=(0,), rejected_ids=(1,), unmapped_ids=(49,))
    record = FrameRecord(7, 0, 0, (0, 0, 0, 0), False, None, detections, solution, None)
    image = annotate(gray, record)
    # the pose was withheld: no mapped marker is "used"; the unmapped one is grey
    assert tuple(image[100, 150]) == REJECTED and tuple(image[100, 400]) == REJECTED
    assert tuple(image[320, 150]) == UNMAPPED
    pose = PoseMeasurement(0, np.eye(4), np.eye(4), np.eye(6), (0,), 0.1)
    accepted = PoseSolution(pose, "ok", marker_ids=(0,), rejected_ids=(1,), unmapped_ids=(49,))
    image = annotate(gray, dataclasses.replace(record, solution=accepted))
    assert tuple(image[100, 150]) == USED and tuple(image[100, 400]) == REJECTED
    assert tuple(image[150, 150]) == (128, 128, 128)   # inside the outline: the frame itself
