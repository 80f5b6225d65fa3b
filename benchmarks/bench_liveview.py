"""The live view's cost: pipeline time per frame with one client against no client, in the same run.

    python benchmarks/bench_liveview.py [--quick] [--cycles N]

Renders the aisle flight at 640x480 (as ``bench_daemon.py`` does) and runs
the real daemon on it, looping, with ``status.http`` on. One client reading
``/stream.mjpg`` (a browser page costs the same: the view annotates and
encodes at most ``MAX_FPS`` frames a second for any number of clients)
connects for ``WINDOW_S`` seconds, disconnects for as long, and so on: the
frames of the two kinds of window are compared. Alternating within one run
lets the load of other processes on a shared machine fall on both alike.
Two modes:

* **real time** (30 fps, as a camera): the pipeline's time per frame
  (``Pipeline.process``: the four stages and every observer), median and p90;
* **as fast as possible**: frames per second in each window, median.

The encoder thread's own work (annotate + JPEG) per second is printed too:
it runs beside the pipeline, so what matters is how much it slows the
pipeline. Target: with one client, at most 10 % more pipeline time than
without (ratio <= 1.10). Baseline: the no-client windows of the same run.
"""
from __future__ import annotations

import argparse
import logging
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from common import REPO  # noqa: E402  (puts the working tree's companion first)
from bench_daemon import AISLE_WAYPOINTS, UdpSink, render_sequence  # noqa: E402

import companion.daemon.web as web  # noqa: E402
from companion.daemon.config import config_from_dict  # noqa: E402
from companion.daemon.service import Daemon  # noqa: E402

TARGET_RATIO = 1.10
WINDOW_S = 2.0
SETTLE_S = 0.3      # left out at the start of each window (the stream opening or closing)


class StreamClient:
    """One client reading /stream.mjpg to the end, counting the bytes and frames."""

    def __init__(self, host: str, port: int):
        self.frames = 0
        self._sock = socket.create_connection((host, port), timeout=5)
        self._sock.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: bench\r\n\r\n")
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while chunk := self._sock.recv(1 << 16):
                self.frames += chunk.count(b"--companionframe")
        except OSError:
            pass

    def close(self) -> None:
        self._sock.close()
        self._thread.join(timeout=5)


def run(sequence: Path, realtime: bool, cycles: int, sink_port: int, workdir: Path) -> dict:
    """Frames processed in windows with and without the client: {"client": [...], "none": [...]} of
    (start monotonic s, wall ns of Pipeline.process), plus the windows and the encoder's counts."""
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(sequence), "realtime": realtime, "loop": True},
        "map": str(REPO / "maps" / "warehouse.yaml"),
        # No flight controller on the sink: stream at once (no origin handshake, no 1.5 s wall-clock hold
        # listening for another companion: it would leave the first 1.5 s of frames unsent, unlike the rest).
        "mavlink": {"connection": f"udpout:127.0.0.1:{sink_port}", "max_rate_hz": 50, "origin_wait_s": 0.0,
                    "duplicate_listen_s": 0.0},
        "status": {"http": "127.0.0.1:0"},
    }, workdir / "bench.yaml")
    daemon = Daemon(config, status_stream=None, record_frames=100_000)
    frames = []   # (start s, process ns)
    process = daemon.pipeline.process

    def timed_process(frame):
        start = time.perf_counter_ns()
        record = process(frame)
        frames.append((start / 1e9, time.perf_counter_ns() - start))
        return record

    daemon.pipeline.process = timed_process
    encode_ns = []
    annotate = web.annotate

    def timed_annotate(image, record):
        start = time.perf_counter_ns()
        result = annotate(image, record)
        encode_ns.append(time.perf_counter_ns() - start)
        return result

    web.annotate = timed_annotate
    runner = threading.Thread(target=daemon.run)
    runner.start()
    host, port = daemon.live_view.server.server_address[:2]
    windows = []   # (kind, from s, to s)
    try:
        time.sleep(1.0)   # the first frames warm caches up
        for _ in range(cycles):
            started = time.perf_counter()
            viewer = StreamClient(host, port)
            time.sleep(WINDOW_S)
            viewer.close()
            windows.append(("client", started + SETTLE_S, time.perf_counter()))
            started = time.perf_counter()
            time.sleep(WINDOW_S)
            windows.append(("none", started + SETTLE_S, time.perf_counter()))
    finally:
        daemon.stop_event.set()
        runner.join()
        web.annotate = annotate
    by_kind = {"client": [], "none": []}
    for kind, begin, end in windows:
        by_kind[kind].append([ns for t, ns in frames if begin <= t < end])
    client_s = sum(end - begin for kind, begin, end in windows if kind == "client")
    return {"windows": by_kind, "window_s": WINDOW_S - SETTLE_S, "encoded": daemon.live_view.counters.encoded,
            "encoded_per_client_s": daemon.live_view.counters.encoded / client_s,
            "annotate_ms": float(np.median(encode_ns)) / 1e6 if encode_ns else float("nan")}


def jpeg_ms(sequence: Path) -> float:
    """Median JPEG encoding time of an annotated 640x480 frame (the rest of the encoder's work)."""
    import cv2
    from companion.capture.replay import open_recording
    recording = open_recording(sequence)
    image = cv2.imread(str(recording.files[0]), cv2.IMREAD_GRAYSCALE) if recording.files else None
    if image is None:
        return float("nan")
    colour = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    times = []
    for _ in range(50):
        start = time.perf_counter_ns()
        cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 80])
        times.append(time.perf_counter_ns() - start)
    return float(np.median(times)) / 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: the first leg of the flight, 3 cycles per mode")
    parser.add_argument("--cycles", type=int, default=15, help="client on/off cycles per mode (default 15)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    cycles = 3 if args.quick else args.cycles
    sink = UdpSink()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        sequence = render_sequence(workdir, 640, 480, AISLE_WAYPOINTS[:2] if args.quick else AISLE_WAYPOINTS)
        encode_jpeg_ms = jpeg_ms(sequence)
        results = {realtime: run(sequence, realtime, cycles, sink.port, workdir) for realtime in (True, False)}
    sink.close()

    print(f"\nLive view cost at 640x480: one client on /stream.mjpg vs none, alternating {WINDOW_S:g} s windows "
          f"in one run ({cycles} of each per mode)")
    print(f"{'mode':<22} {'client':<7} {'frames':>6} {'pipeline ms':>11} {'p90 ms':>7} {'fps':>6} {'ratio':>6} "
          f"{'target':>7}")
    for realtime, result in results.items():
        mode = "real time (30 fps)" if realtime else "as fast as possible"
        windows = result["windows"]
        medians = {kind: [float(np.median(w)) / 1e6 for w in windows[kind]] for kind in ("none", "client")}
        rates = {kind: [len(w) / result["window_s"] for w in windows[kind]] for kind in ("none", "client")}
        # each client window against the no-client window right after it, then the median over the pairs
        if realtime:
            ratio = float(np.median([c / n for c, n in zip(medians["client"], medians["none"])]))
        else:
            ratio = float(np.median([n / c for c, n in zip(rates["client"], rates["none"])]))
        for kind in ("none", "client"):
            times_ms = np.concatenate([np.array(w, dtype=float) for w in windows[kind]]) / 1e6
            shown = 1.0 if kind == "none" else ratio
            verdict = "" if kind == "none" else ("met" if ratio <= TARGET_RATIO else "NOT met")
            print(f"{mode:<22} {'one' if kind == 'client' else 'none':<7} {len(times_ms):6d} "
                  f"{float(np.median(times_ms)):11.2f} {float(np.percentile(times_ms, 90)):7.2f} "
                  f"{float(np.median(rates[kind])):6.1f} {shown:6.3f} {verdict:>7}")
    realtime = results[True]
    encoder_ms = realtime["annotate_ms"] + encode_jpeg_ms
    none = np.concatenate([np.array(w, dtype=float) for w in realtime["windows"]["none"]]) / 1e6
    pipeline_per_s = float(np.median(none)) * 30.0
    encoder_per_s = realtime["encoded_per_client_s"] * encoder_ms
    print(f"\nencoder thread, per frame shown: annotate {realtime['annotate_ms']:.2f} ms + JPEG {encode_jpeg_ms:.2f} ms; "
          f"real time: {realtime['encoded_per_client_s']:.1f} frames shown a second, {encoder_per_s:.1f} ms of work a "
          f"second beside the pipeline's {pipeline_per_s:.0f} ms ({100 * encoder_per_s / pipeline_per_s:.1f} %)")
    print("ratio: pipeline time per frame (real time) or time per frame from the rate (as fast as possible), "
          "in a client window / in the no-client window after it, median over the pairs; "
          f"target <= {TARGET_RATIO:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
