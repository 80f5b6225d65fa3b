"""The live view's cost: pipeline time per frame with one client against the same run with none.

    python benchmarks/bench_liveview.py [--quick]

Renders the aisle flight at 640x480 (as ``bench_daemon.py`` does), then runs
the real daemon with ``status.http`` on, alternating runs with no client and
with one client reading ``/stream.mjpg`` (a browser page costs the same: the
view annotates and encodes at most ``MAX_FPS`` frames a second for any number
of clients). Two modes:

* **real time** (30 fps, as a camera): the pipeline's time per frame
  (``Pipeline.process``: the four stages and every observer), median and p90;
* **as fast as possible**: frames per second over the run.

The encoder thread's own time per frame (annotate + JPEG) is printed too:
it runs beside the pipeline, so what matters is how much it slows the
pipeline. Target: with one client, at most 10 % more pipeline time than
without (ratio <= 1.10). Baseline: the no-client runs, measured in the same
run on the same frames.
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

from companion.daemon import overlay  # noqa: E402
from companion.daemon.config import config_from_dict  # noqa: E402
from companion.daemon.service import Daemon  # noqa: E402

TARGET_RATIO = 1.10


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


def run(sequence: Path, realtime: bool, client: bool, sink_port: int, workdir: Path) -> dict:
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(sequence), "realtime": realtime},
        "map": str(REPO / "maps" / "warehouse.yaml"),
        "mavlink": {"connection": f"udpout:127.0.0.1:{sink_port}", "max_rate_hz": 50, "origin_wait_s": 0.0},
        "status": {"http": "127.0.0.1:0"},
    }, workdir / "bench.yaml")
    daemon = Daemon(config, status_stream=None, record_frames=100_000)
    process_ns, encode_ns = [], []
    process = daemon.pipeline.process

    def timed_process(frame):
        start = time.perf_counter_ns()
        record = process(frame)
        process_ns.append(time.perf_counter_ns() - start)
        return record

    daemon.pipeline.process = timed_process
    annotate = overlay.annotate

    def timed_annotate(image, record):   # the encoder thread's share, JPEG encoding timed with it below
        start = time.perf_counter_ns()
        result = annotate(image, record)
        encode_ns.append(time.perf_counter_ns() - start)
        return result

    import companion.daemon.web as web
    web.annotate = timed_annotate
    viewer = None
    if client:
        host, port = daemon.live_view.server.server_address[:2]
        # the server is bound in the constructor: a client can connect before the daemon runs
        viewer = StreamClient(host, port)
    started = time.perf_counter()
    try:
        daemon.run()
    finally:
        web.annotate = annotate
        if viewer is not None:
            viewer.close()
    wall_s = time.perf_counter() - started
    process_ms = np.array(process_ns[5:]) / 1e6   # the first frames warm caches up
    return {"frames": len(process_ns), "median_ms": float(np.median(process_ms)),
            "p90_ms": float(np.percentile(process_ms, 90)), "fps": len(process_ns) / wall_s,
            "encoded": daemon.live_view.counters.encoded, "streamed": viewer.frames if viewer else 0,
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
    parser.add_argument("--quick", action="store_true", help="smoke test: the first leg of the flight, one pair of runs")
    parser.add_argument("--pairs", type=int, default=3, help="alternating (no client, client) pairs per mode (default 3)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    pairs = 1 if args.quick else args.pairs
    waypoints = AISLE_WAYPOINTS[:2] if args.quick else AISLE_WAYPOINTS
    sink = UdpSink()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        sequence = render_sequence(workdir, 640, 480, waypoints)
        encode_jpeg_ms = jpeg_ms(sequence)
        for realtime in (True, False):
            for _ in range(pairs):
                for client in (False, True):   # alternating: a burst of load hits both alike
                    results.setdefault((realtime, client), []).append(run(sequence, realtime, client, sink.port, workdir))
    sink.close()

    print("\nLive view cost at 640x480, one client on /stream.mjpg vs none (same frames, alternating runs; "
          "medians over the runs)")
    print(f"{'mode':<22} {'client':<7} {'frames':>6} {'pipeline ms':>11} {'p90 ms':>7} {'fps':>6} "
          f"{'encoded':>7} {'ratio':>6} {'target':>7}")
    for realtime in (True, False):
        mode = "real time (30 fps)" if realtime else "as fast as possible"
        base = results[(realtime, False)]
        for client in (False, True):
            runs = results[(realtime, client)]
            median_ms = float(np.median([r["median_ms"] for r in runs]))
            base_ms = float(np.median([r["median_ms"] for r in base]))
            fps = float(np.median([r["fps"] for r in runs]))
            base_fps = float(np.median([r["fps"] for r in base]))
            # real time: pipeline time per frame; as fast as possible: time per frame from the rate
            ratio = median_ms / base_ms if realtime else base_fps / fps
            verdict = "" if not client else ("met" if ratio <= TARGET_RATIO else "NOT met")
            print(f"{mode:<22} {'one' if client else 'none':<7} {int(np.median([r['frames'] for r in runs])):6d} "
                  f"{median_ms:11.2f} {float(np.median([r['p90_ms'] for r in runs])):7.2f} {fps:6.1f} "
                  f"{int(np.median([r['encoded'] for r in runs])):7d} {ratio:6.3f} {verdict:>7}")
    annotate_ms = float(np.nanmedian([r["annotate_ms"] for key, runs in results.items() if key[1] for r in runs]))
    print(f"\nencoder thread, per frame shown (beside the pipeline, at most 15 a second): "
          f"annotate {annotate_ms:.2f} ms + JPEG {encode_jpeg_ms:.2f} ms")
    realtime_client = results[(True, True)]
    shown_per_s = float(np.median([r["encoded"] / (r["frames"] / r["fps"]) for r in realtime_client]))
    pipeline_per_s = float(np.median([r["median_ms"] * r["fps"] for r in results[(True, False)]]))
    encoder_per_s = shown_per_s * (annotate_ms + encode_jpeg_ms)
    print(f"real time: the encoder works {encoder_per_s:.1f} ms a second ({shown_per_s:.1f} frames shown) against "
          f"the pipeline's {pipeline_per_s:.0f} ms a second: {100 * encoder_per_s / pipeline_per_s:.1f} % of "
          "pipeline time, on another thread")
    print("ratio: pipeline time per frame (real time) or time per frame from the rate (as fast as possible), "
          f"with the client / without; target <= {TARGET_RATIO:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
