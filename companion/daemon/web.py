"""The live view: a small HTTP server in the daemon (``status.http: 127.0.0.1:8080``).

    /             one page: the annotated camera image, the status, a top view of the map with
                  the estimate and its recent track, the latest STATUSTEXTs; it updates by itself
    /frame.jpg    the latest annotated frame (``?after=N`` waits up to 2 s for a frame newer than N;
                  an N beyond this run's newest serial, from the daemon's previous run, gets the newest)
    /stream.mjpg  the annotated frames as an MJPEG stream (VLC, ffplay, a browser)
    /status.json  the DaemonStatus (everything the status line knows) plus the estimate with its
                  covariance, its map position, the recent track and STATUSTEXTs
    /map.json     the map's markers in the top view

Each answers HEAD too (its GET's status and headers, no body).

Threads: the standard library's ``ThreadingHTTPServer`` (one thread per
request, plus ``serve_forever``) and an ``encoder`` thread. The pipeline-side
observer does nothing unless a client wants frames (an open MJPEG stream, or
a ``/frame.jpg`` request within the last ``INTEREST_S``); then it hands at
most ``MAX_FPS`` frames a second to the encoder through a one-slot queue
(dropped and counted when the encoder is busy), so the pipeline never waits.
A client that sends no request, or stops taking what it asked for, is
dropped after ``CLIENT_TIMEOUT_S``; a stream whose client closed the
connection is dropped within ``STREAM_CHECK_S`` even while no frame comes.

No authentication and no encryption: anyone who reaches the address sees the
camera and the vehicle's position. The default address is loopback
(127.0.0.1); a wider one (0.0.0.0) is logged as a warning.
"""
from __future__ import annotations

import dataclasses
import enum
import importlib.resources
import json
import logging
import math
import queue
import select
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Callable
from urllib.parse import parse_qs, urlsplit

import cv2
import numpy as np

from companion.daemon.overlay import annotate
from companion.daemon.pipeline import FrameRecord
from companion.daemon.record import verdict
from companion.geometry.facility_map import FacilityMap
from companion.plan import MapPlane, map_bounds_m, markers_plan
from companion.types import Estimate, Frame

log = logging.getLogger("companion")

MAX_FPS = 15.0             # frames a second annotated for viewers at most
INTEREST_S = 2.0           # a /frame.jpg request keeps frames coming this long
FRAME_WAIT_S = 2.0         # longest wait of /frame.jpg?after=N
JPEG_QUALITY = 80
TRACK_S = 30.0             # the map panel's track: the estimates of the last TRACK_S
LOOPBACK_HOSTS = {"127.0.0.1", "localhost", "::1"}
PAGE = "live_view.html"
BOUNDARY = "companionframe"
# a client that sends no request, or stops taking the stream it asked for (a frozen viewer), is dropped
# after this long: its thread ends and, when it was the last stream, the frames stop being encoded
CLIENT_TIMEOUT_S = 10.0
# while no frame comes (camera lost) an MJPEG stream looks this often whether its client closed the connection
STREAM_CHECK_S = 1.0


class WebError(ValueError):
    """The live view cannot start (address in use, bad host): ``problem`` names the address; the message puts
    the key that gives it first (``status.http: ...``; ``companion run`` names ``--http`` instead when that
    gave it)."""

    def __init__(self, problem: str):
        super().__init__(f"status.http: {problem}")
        self.problem = problem


@dataclasses.dataclass
class ViewCounters:
    encoded: int = 0     # frames annotated and encoded
    dropped: int = 0     # frames wanted while the encoder was busy
    requests: int = 0


@dataclasses.dataclass(frozen=True)
class EncodedFrame:
    index: int           # the pipeline frame's number
    serial: int          # 1, 2, 3, ... in encoding order
    jpeg: bytes


class LiveView:
    """The HTTP server, the encoder thread and the pipeline observer (``__call__``).

    status: the daemon's ``status()`` (a DaemonStatus); records: the pipeline's recent
    FrameRecords (oldest first); statustexts: the latest STATUSTEXTs as
    (wall time s, severity, text).
    """

    def __init__(self, address: tuple[str, int], facility_map: FacilityMap, status: Callable[[], object],
                 records: Callable[[], list[FrameRecord]],
                 statustexts: Callable[[], list[tuple[float, int, str]]] = lambda: []):
        self.facility_map = facility_map
        self.plane = MapPlane(facility_map)
        self._status = status
        self._records = records
        self._statustexts = statustexts
        self.counters = ViewCounters()
        self.client_timeout_s = CLIENT_TIMEOUT_S
        self._frames: queue.Queue = queue.Queue(maxsize=1)
        self._latest: EncodedFrame | None = None
        self._new_frame = threading.Condition()
        self._streams = 0
        self._last_pull_s = -math.inf
        self._last_handed_ns = -(10 ** 18)
        self._stop = threading.Event()
        self._page = (importlib.resources.files("companion") / "data" / PAGE).read_bytes()
        self._map_json = json.dumps(map_document(facility_map)).encode()
        host, port = address
        try:
            self.server = _Server((host, port), _handler_for(self))
        except OSError as error:
            raise WebError(f"cannot listen on {host}:{port}: {error.strerror or error}") from None
        self._threads = [threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.2},
                                          name="http", daemon=True),
                         threading.Thread(target=self._encode_loop, name="encoder", daemon=True)]

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{f'[{host}]' if ':' in host else host}:{port}/"

    def start(self) -> None:
        for thread in self._threads:
            thread.start()
        host = self.server.server_address[0]
        if host in LOOPBACK_HOSTS:
            log.info("live view on %s (this machine only)", self.url)
        else:
            log.warning("live view on %s: reachable from the network, with no password and no encryption "
                        "(anyone who can reach it sees the camera and the position)", self.url)

    def close(self) -> None:
        self._stop.set()
        with self._new_frame:
            self._new_frame.notify_all()
        if self._threads[0].is_alive():
            self.server.shutdown()
        self.server.server_close()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(timeout=5.0)

    # ------------------------------------------------------ pipeline thread

    def wanted(self) -> bool:
        """A client wants frames: an MJPEG stream is open or /frame.jpg was asked for lately."""
        return self._streams > 0 or time.monotonic() - self._last_pull_s < INTEREST_S

    def __call__(self, frame: Frame, record: FrameRecord) -> None:
        if not self.wanted() or frame.t_ns - self._last_handed_ns < 1e9 / MAX_FPS:
            return
        try:
            self._frames.put_nowait((frame.image, record))
            self._last_handed_ns = frame.t_ns
        except queue.Full:
            self.counters.dropped += 1

    # ---------------------------------------------------------------- encoder

    def _encode_loop(self) -> None:
        while not self._stop.is_set():
            try:
                image, record = self._frames.get(timeout=0.2)
            except queue.Empty:
                continue
            ok, jpeg = cv2.imencode(".jpg", annotate(image, record), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                continue
            with self._new_frame:
                serial = self._latest.serial + 1 if self._latest else 1
                self._latest = EncodedFrame(record.index, serial, jpeg.tobytes())
                self.counters.encoded += 1
                self._new_frame.notify_all()

    def next_frame(self, after_serial: int, timeout_s: float) -> EncodedFrame | None:
        """The newest encoded frame once its serial exceeds ``after_serial``; None on timeout or stop.

        A serial beyond this run's newest (a client of the daemon's previous run: the serials start
        at 1 again with every start) is none of this run's: the newest frame is at once newer for it.
        """
        deadline = time.monotonic() + timeout_s
        with self._new_frame:
            while not self._stop.is_set():
                latest = self._latest
                if latest is not None and latest.serial != after_serial:
                    return latest
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._new_frame.wait(remaining)
        return None

    # ------------------------------------------------------------ documents

    def status_document(self) -> dict:
        """What /status.json serves."""
        status = self._status()
        document = {"status": plain(dataclasses.asdict(status)), "line": status.line()}
        records = self._records()
        last = records[-1] if records else None
        document["frame"] = None if last is None else {
            "index": last.index, "verdict": verdict(last),
            "pose_status": last.solution.status if last.solution is not None else "no marker",
            "markers": [d.symbol for d in last.detections]}
        document["estimate"] = self.estimate_document(status.estimate)
        document["track_map_m"] = self.track_m(records)
        document["statustexts"] = [{"time_s": t, "severity": severity, "text": text}
                                   for t, severity, text in self._statustexts()]
        document["view"] = {**dataclasses.asdict(self.counters), "streams": self._streams,
                            "frame_serial": self._latest.serial if self._latest else 0}
        return document

    def estimate_document(self, estimate: Estimate | None) -> dict | None:
        if estimate is None:
            return None
        x, y, z = self.plane.positions_m(estimate.position_ned_m)[0]
        return {
            "t_ns": estimate.t_ns,
            "position_ned_m": plain(estimate.position_ned_m),
            "velocity_ned_m_s": plain(estimate.velocity_ned_m_s),
            "roll_deg": math.degrees(estimate.roll_rad), "pitch_deg": math.degrees(estimate.pitch_rad),
            "yaw_deg": math.degrees(estimate.yaw_rad),
            "covariance_ned": plain(estimate.covariance_ned),
            "position_sd_m": plain(np.sqrt(np.clip(np.diag(estimate.covariance_ned)[:3], 0, None))),
            "tracking": estimate.tracking, "reset_counter": estimate.reset_counter,
            "position_map_m": [float(x), float(y), float(z)],
            "heading_map_deg": math.degrees(self.plane.heading_rad(estimate.roll_rad, estimate.pitch_rad,
                                                                   estimate.yaw_rad)),
        }

    def track_m(self, records: list[FrameRecord]) -> list[list[float]]:
        """(x, y) map positions of the estimates of the last ``TRACK_S``, at most 300 points."""
        if not records:
            return []
        newest_ns = records[-1].t_ns
        positions = [r.estimate.position_ned_m for r in records
                     if r.estimate is not None and newest_ns - r.t_ns <= TRACK_S * 1e9]
        if not positions:
            return []
        step = max(1, len(positions) // 300)
        xy = self.plane.positions_m(np.array(positions[::step]))[:, :2]
        return [[round(float(x), 3), round(float(y), 3)] for x, y in xy]

    # ------------------------------------------------------ request helpers

    def pulled(self) -> None:
        self._last_pull_s = time.monotonic()

    def stream_opened(self, opened: bool) -> None:
        with self._new_frame:
            self._streams += 1 if opened else -1

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    @property
    def page(self) -> bytes:
        return self._page

    @property
    def map_json(self) -> bytes:
        return self._map_json


def map_document(facility_map: FacilityMap) -> dict:
    """What /map.json serves: the map's name, extent and markers in the top view (metres)."""
    x_min, x_max, y_min, y_max = map_bounds_m(facility_map)
    return {"name": facility_map.name, "bounds_m": [x_min, x_max, y_min, y_max],
            "markers": [dataclasses.asdict(m) for m in markers_plan(facility_map)]}


def plain(value):
    """A JSON-ready copy: dataclasses, numpy arrays and scalars, enums, paths, non-finite floats (null)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return plain(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, enum.Enum):
        return plain(value.value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (str, int, bool)) or value is None:
        return value
    if isinstance(value, Path):
        return str(value)
    return str(value)


# ------------------------------------------------------------------ HTTP

class _Server(ThreadingHTTPServer):
    daemon_threads = True          # a stuck client never holds up shutdown
    allow_reuse_address = True

    def __init__(self, address, handler):
        if ":" in address[0]:      # an IPv6 address such as ::1
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)


def _handler_for(view: LiveView):
    class Handler(_Handler):
        pass
    Handler.view = view
    return Handler


class _Handler(BaseHTTPRequestHandler):
    view: LiveView
    server_version = "companion"
    protocol_version = "HTTP/1.1"

    def setup(self) -> None:
        self.timeout = self.view.client_timeout_s   # set on the connection: reads and writes wait this long
        super().setup()

    def log_message(self, format, *args) -> None:   # noqa: A002 (BaseHTTPRequestHandler's name)
        log.debug("http %s: " + format, self.client_address[0], *args)

    head = False   # a HEAD request: the GET's status and headers, no body

    def do_GET(self) -> None:   # noqa: N802 (BaseHTTPRequestHandler's name)
        self.head = False
        self._serve()

    def do_HEAD(self) -> None:   # noqa: N802 (BaseHTTPRequestHandler's name)
        self.head = True
        self._serve()

    def _serve(self) -> None:
        self.view.counters.requests += 1
        url = urlsplit(self.path)
        route = {"/": self._page, "/index.html": self._page, "/status.json": self._status,
                 "/map.json": self._map, "/frame.jpg": self._frame, "/stream.mjpg": self._stream}.get(url.path)
        if route is None:
            self._send(HTTPStatus.NOT_FOUND, b"not found: try / /frame.jpg /stream.mjpg /status.json /map.json\n",
                       "text/plain")
            return
        try:
            route(parse_qs(url.query))
        except (BrokenPipeError, ConnectionResetError):
            pass   # the client went away

    def _send(self, status: HTTPStatus, body: bytes, content_type: str, headers: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.end_headers()
        if not self.head:
            self.wfile.write(body)

    def _page(self, _query) -> None:
        self._send(HTTPStatus.OK, self.view.page, "text/html; charset=utf-8")

    def _map(self, _query) -> None:
        self._send(HTTPStatus.OK, self.view.map_json, "application/json")

    def _status(self, _query) -> None:
        body = json.dumps(self.view.status_document()).encode()
        self._send(HTTPStatus.OK, body, "application/json")

    def _frame(self, query) -> None:
        self.view.pulled()
        after = query.get("after", ["0"])[0]
        after_serial = int(after) if after.isdigit() else 0
        frame = self.view.next_frame(after_serial, FRAME_WAIT_S)
        if frame is None:
            self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"no new frame yet\n", "text/plain", {"Retry-After": "1"})
            return
        self._send(HTTPStatus.OK, frame.jpeg, "image/jpeg",
                   {"X-Frame-Index": str(frame.index), "X-Frame-Serial": str(frame.serial)})

    def _stream(self, _query) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        if self.head:
            return
        self.view.stream_opened(True)
        try:
            serial = 0
            while not self.view.stopping:
                frame = self.view.next_frame(serial, STREAM_CHECK_S)
                if frame is None:
                    if self._client_gone():   # no frame to write (camera lost): look at the socket
                        return
                    continue
                serial = frame.serial
                self.wfile.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(frame.jpeg)}\r\n"
                                 f"X-Frame-Index: {frame.index}\r\n\r\n".encode() + frame.jpeg + b"\r\n")
                self.wfile.flush()
        finally:
            self.view.stream_opened(False)

    def _client_gone(self) -> bool:
        """The client closed its end (or reset it): a stream's socket sends nothing more after the request."""
        try:
            readable, _, _ = select.select([self.connection], [], [], 0)
            return bool(readable) and self.connection.recv(1, socket.MSG_PEEK) == b""
        except (OSError, ValueError):
            return True
