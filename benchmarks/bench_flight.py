"""A continuous flight past sparse wall markers: how soon, and how steadily, vision messages flow.

    python benchmarks/bench_flight.py [--quick]

Writes a sparse hall (``sparse_hall.yaml``: 0.18 m markers 7 m apart on one
wall, two more on the far wall only to give the hall its size), renders a
30 s flight along it with ``companion simulate`` (640x480, 70 degree field of
view, forward camera tilted 20 degrees down, 30 fps; the vehicle 4 m from
the wall, looking 30 degrees ahead of it, so each marker is seen alone, at
4-6 m, coming into view at the image's edge), with its ``attitude.csv``
(0.2 deg noise), and drives every frame, at its recorded capture time,
through the daemon's own pipeline (``companion.daemon.service.Daemon``:
detector, pose, Kalman filter, MAVLink link to a UDP sink on loopback):
once with the replay's attitude and once without (``attitude.source:
none``), same frames. The rendered hall is exactly its map: the pose stage
is told so (``pose.map_sd_m``, ``map_sd_deg``: 0).

A frame is **readable** when the detector decodes a mapped marker in it. Per
run: the readable frames; the time from the first readable frame to the
first vision message; the longest time a marker was readable without a
message (from the later of the last message and the start of the readable
stretch, to each readable frame); the share of readable frames that sent a
message; the position error of what was sent against the ground truth.
Times are capture times (the pipeline's own processing, a few ms, comes on
top; see ``bench_daemon.py``). Every target of issue 10 on this flight is
printed, met or not met, for both runs.
"""
from __future__ import annotations

import argparse
import csv
import logging
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from common import REPO  # noqa: F401  (puts the working tree's companion first)
from companion import cli
from companion.capture.replay import open_recording
from companion.daemon.config import config_from_dict
from companion.daemon.service import Daemon
from companion.sim.simulate import read_sequence
from companion.types import Frame

SPARSE_HALL = {
    "name": "Sparse hall (bench_flight)",
    "frame": {"origin": "south-west corner, floor", "x_bearing_deg": 0.0},
    "dictionary": "6x6", "parity": 2, "default_size_m": 0.18,
    "markers": [
        {"symbol": "A", "position_m": [3.0, 0.0, 1.2], "facing": "+y"},
        {"symbol": "B", "position_m": [10.0, 0.0, 1.6], "facing": "+y"},
        {"symbol": "C", "position_m": [17.0, 0.0, 1.2], "facing": "+y"},
        {"symbol": "D", "position_m": [24.0, 0.0, 1.6], "facing": "+y"},
        # the far wall, behind the camera all flight: they only make the hall 8 m wide
        {"symbol": "E", "position_m": [0.0, 8.0, 1.5], "facing": "-y"},
        {"symbol": "F", "position_m": [28.0, 8.0, 1.5], "facing": "-y"},
    ],
}
FLIGHT = "1,4,1.4,-60;27.5,4,1.4,-60"   # x, y, z, heading (deg ccw from +x): 30 degrees ahead of the wall
QUICK_FLIGHT = "1,4,1.4,-60;9,4,1.4,-60"
FPS = 30.0
TARGET_FIRST_S, TARGET_GAP_S, TARGET_SHARE = 0.2, 0.1, 0.99


class UdpSink:
    """A loopback UDP socket that reads and discards what the daemon sends."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                self.sock.recv(2048)
            except socket.timeout:
                pass

    def close(self):
        self._stop.set()
        self._thread.join()
        self.sock.close()


def render(folder: Path, waypoints: str) -> Path:
    map_path = folder / "sparse_hall.yaml"
    map_path.write_text(yaml.safe_dump(SPARSE_HALL, sort_keys=False))
    out = folder / "flight"
    code = cli.main(["simulate", str(out), "--map", str(map_path), "--pattern", "path", "--waypoints", waypoints,
                     "--speed", "0.95", "--fps", str(FPS), "--no-progress"])
    if code != 0:
        raise SystemExit("simulate failed")
    return out


@dataclass
class Row:
    """One frame through the pipeline: capture time (s), readable, sent, error of what was sent (m)."""

    t_s: float
    readable: bool
    sent: bool
    error_m: float | None


def fly(sequence: Path, port: int, workdir: Path, attitude: bool) -> list[Row]:
    data = {
        "source": {"kind": "replay", "path": str(sequence), "realtime": False},
        # no flight controller on the sink: stream at once (no wait for the origin, nor for another companion:
        # frames come faster than real time, a wall-clock hold would swallow seconds of the flight);
        # one message per frame at 30 fps
        "mavlink": {"connection": f"udpout:127.0.0.1:{port}", "max_rate_hz": 50, "origin_wait_s": 0.0,
                    "duplicate_listen_s": 0.0},
        "attitude": {"source": "auto" if attitude else "none"},
        "pose": {"map_sd_m": 0.0, "map_sd_deg": 0.0},  # the rendered hall is exactly its map
    }
    config = config_from_dict(data, workdir / "bench_flight.yaml")
    daemon = Daemon(config, status_stream=None, record_frames=100_000)
    daemon.link.start()
    deadline = time.monotonic() + 5.0
    while daemon.link.state.value != "streaming" and time.monotonic() < deadline:
        time.sleep(0.01)
    recording = open_recording(sequence)
    truth = groundtruth_ned(sequence)
    offset_ns = time.monotonic_ns()
    rows = []
    mapped = set(config.facility_map.markers)
    try:
        for (number, image), t_ns in zip(read_sequence(sequence).images(), recording.t_ns):
            record = daemon.pipeline.process(Frame(image, offset_ns + int(t_ns), number))
            error_m = None
            if record.sent:
                error_m = float(np.linalg.norm(record.estimate.position_ned_m - truth[number]))
            rows.append(Row(int(t_ns) * 1e-9, any(d.id in mapped for d in record.detections), record.sent, error_m))
    finally:
        daemon.link.close()
    return rows


def groundtruth_ned(sequence: Path) -> dict[int, np.ndarray]:
    with open(sequence / "groundtruth.csv", newline="") as handle:
        return {int(r["frame"]): np.array([float(r["north_m"]), float(r["east_m"]), float(r["down_m"])])
                for r in csv.DictReader(handle)}


@dataclass
class Summary:
    readable: int
    first_message_s: float
    longest_gap_s: float
    share_sent: float
    median_error_m: float
    max_error_m: float


def summarise(rows: list[Row]) -> Summary:
    readable = [r for r in rows if r.readable]
    first_readable = readable[0].t_s if readable else float("nan")
    first_sent = next((r.t_s for r in rows if r.sent and r.t_s >= first_readable), float("inf"))
    longest, last_sent, stretch_start, previous_readable = 0.0, None, None, False
    for r in rows:
        if r.readable and not previous_readable:
            stretch_start = r.t_s
        if r.readable:
            # readable since stretch_start; the gap runs from the later of that and the last message
            since = max(stretch_start, last_sent) if last_sent is not None else stretch_start
            longest = max(longest, r.t_s - since)
        if r.sent:
            last_sent = r.t_s
        previous_readable = r.readable
    errors = [r.error_m for r in rows if r.error_m is not None]
    return Summary(len(readable), first_sent - first_readable, longest,
                   sum(r.sent for r in readable) / max(len(readable), 1),
                   float(np.median(errors)) if errors else float("nan"), max(errors, default=float("nan")))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: an 8 m (~9 s) flight")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    sink = UdpSink()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        sequence = render(workdir, QUICK_FLIGHT if args.quick else FLIGHT)
        frames = len(open_recording(sequence).t_ns)
        results = {name: summarise(fly(sequence, sink.port, workdir, attitude))
                   for name, attitude in (("with attitude", True), ("without attitude", False))}
    sink.close()
    print(f"\nbench_flight: {frames} frames at {FPS:g} fps past sparse wall markers (0.18 m, 7 m apart, 4-6 m away)")
    print(f"{'run':<17} {'readable':>8} {'first msg s':>11} {'longest gap ms':>14} {'readable sent':>13} "
          f"{'err med m':>9} {'err max m':>9}")
    for name, s in results.items():
        print(f"{name:<17} {s.readable:>8} {s.first_message_s:>11.3f} {s.longest_gap_s * 1e3:>14.0f} "
              f"{s.share_sent:>13.1%} {s.median_error_m:>9.3f} {s.max_error_m:>9.3f}")
    print()
    for name, s in results.items():
        for text, value, ok in (
                (f"first vision message <= {TARGET_FIRST_S:g} s after the first readable marker",
                 f"{s.first_message_s:.3f} s", s.first_message_s <= TARGET_FIRST_S),
                (f"no gap > {TARGET_GAP_S * 1e3:.0f} ms while a marker is readable",
                 f"longest {s.longest_gap_s * 1e3:.0f} ms", s.longest_gap_s <= TARGET_GAP_S + 1e-9),
                (f">= {TARGET_SHARE:.0%} of marker-readable frames with a message", f"{s.share_sent:.1%}",
                 s.share_sent >= TARGET_SHARE)):
            print(f"target [{name}] {text}: {value}: {'met' if ok else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
