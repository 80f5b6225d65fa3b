"""The detector's small_window pass in the daemon: noisy frames, one core, with and without it.

    python benchmarks/bench_noisy_frames.py [--quick] [--read-noise 12,20,28]

For each read noise level (standard deviation, gray levels) it renders the
quick aisle of ``bench_daemon.py`` (the first leg of the committed aisle
flight, 640x480, ``companion simulate --read-noise``), stores the frames
raw, and replays them as fast as possible through the real daemon on one
core three times, the detector configured three ways:

* ``never``: the pass never runs on these frames (``square.noisy_frame_sd_gray``
  out of reach; the aisle is neither dim nor blurred): the baseline;
* ``default``: with the daemon's expected places, only where fewer than
  ``square.small_window_enough_markers`` markers were found and an expected
  one is missing;
* ``every frame``: wherever an expected marker is missing
  (``small_window_enough_markers`` out of reach).

Printed per level and way: frames per second (and its ratio to ``never``'s),
the detect stage's median, markers decoded over the run, frames posed, and
the median position error of the per-frame poses against the ground truth.
docs/detector.md ("Noisy and dim frames") has the measurement.
"""
from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

import bench_daemon as daemon_bench  # noqa: E402  (its import of common puts the working tree first)

WAYS = {"never": {"square": {"noisy_frame_sd_gray": 1.0e9}},
        "default": {},
        "every frame": {"square": {"small_window_enough_markers": 1_000_000}}}


def replay(sequence: Path, truth: dict, port: int, workdir: Path, detector: dict) -> dict:
    """One fast replay of the raw frames: fps, detect median ms, markers, frames posed, median error m."""
    daemon, wall_s, _ = daemon_bench.run_daemon(sequence, realtime=False, port=port, workdir=workdir,
                                                detector=detector)
    records = daemon.pipeline.stats.records
    raw, _ = daemon_bench.errors(daemon, truth)
    return {"fps": daemon.pipeline.stats.frames / wall_s,
            "detect_ms": daemon_bench.stage_medians(daemon)["detect"][0],
            "markers": sum(len(r.detections) for r in records),
            "posed": sum(r.measurement is not None for r in records),
            "frames": len(records),
            "error_m": float(np.median(raw)) if len(raw) else float("nan")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: one noise level (12)")
    parser.add_argument("--read-noise", default="12,20,28", help="read noise levels, sd in gray levels")
    args = parser.parse_args()
    levels = [12.0] if args.quick else [float(v) for v in args.read_noise.split(",")]
    print(f"one core: pinned to CPU {daemon_bench.pin_to_one_core()}")
    logging.basicConfig(level=logging.ERROR)
    sink = daemon_bench.UdpSink()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        for level in levels:
            folder = workdir / f"noise_{level:g}"
            folder.mkdir()
            rendered = daemon_bench.render_sequence(folder, 640, 480, daemon_bench.AISLE_WAYPOINTS[:2],
                                                    ("--read-noise", str(level)))
            sequence = daemon_bench.raw_copy(rendered)
            truth = daemon_bench.groundtruth_ned(sequence)
            for way, detector in WAYS.items():
                rows.append((level, way, replay(sequence, truth, sink.port, workdir, detector)))
    sink.close()

    print("\nThe quick aisle at 640x480 with read noise, fast replay of raw frames on one core")
    print(f"{'noise sd':>8} {'small_window':<12} {'fps':>7} {'x never':>7} {'detect ms':>9} {'markers':>7} "
          f"{'posed':>9} {'error mm':>8}")
    never = {level: result["fps"] for level, way, result in rows if way == "never"}
    for level, way, r in rows:
        print(f"{level:8g} {way:<12} {r['fps']:7.1f} {r['fps'] / never[level]:7.2f} {r['detect_ms']:9.2f} "
              f"{r['markers']:7d} {r['posed']:4d}/{r['frames']:<4d} {1e3 * r['error_m']:8.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
