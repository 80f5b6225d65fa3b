"""The closed loop in a simulator: SIM_STATE in -> render -> detect -> pose -> fuse -> send, end to end.

    python benchmarks/bench_closed_loop.py [--quick]

Each flight runs the SITL stand-in (tests/sim_vehicle_peer.py, its own
process), the daemon with the ``simulated_camera`` source (this process) and
the example square mission (its own process), as tests/test_closed_loop.py
does (no SITL binary on this machine). Flights: the test hall's 4 m square,
and config/sitl-camera.yaml's 2 m square in the example warehouse
(``--quick``: the test hall's 2 m square only).

Per flight, while the vehicle flies the square: frames processed per second
(target >= 20 at 640x480), the render time per frame and the pipeline's
detect -> send time per frame (medians and 95th percentiles from one run:
the pipeline is the baseline, the render's cost is stated as its ratio),
capture -> send latency, our estimate against the stand-in's truth at each
capture time, and the longest gap between vision messages (wall clock, and
in frames). The machine is shared: the load average is printed with them.
Two more flights of the test hall's 2 m square stop the stand-in's process
for 60 or 150 ms every 1.5 s, a simulator falling behind on a loaded
machine (SendClock must follow its restarted send clock).
Then the render alone (no flight): the simulated camera's render and
degradations of config/sitl-camera.yaml's warehouse at poses around its 2 m
square, median CPU time (time.process_time: the machine is loaded) and wall
time per frame.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import common

sys.path.insert(0, str(common.REPO / "tests"))
from closed_loop_harness import ClosedLoop, judge_flight  # noqa: E402
from test_render_reference import vehicle_state  # noqa: E402

from companion.capture.simulated import SimulatedCamera  # noqa: E402
from companion.daemon.config import load_config  # noqa: E402

TARGET_FPS = 20.0
STALL_EVERY_S = 1.5    # the stalled-simulator flights: the stand-in stopped this often


def fly(name: str, side_m: float, config_path: Path | None, stall_ms: float = 0.0) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        loop = ClosedLoop(Path(folder), side_m, config_path=config_path)
        try:
            if stall_ms:
                loop.stall_simulator(STALL_EVERY_S, stall_ms / 1000)
            mission = loop.fly()
            if mission.returncode != 0:
                raise SystemExit(f"{name}: the mission failed: {mission.stderr.strip() or mission.stdout[-400:]}")
            result = judge_flight(loop, side_m)
            records = [r for r in loop.daemon.pipeline.stats.records if result["window_ns"][0] <= r.t_ns
                       <= result["window_ns"][1]]
            render_ms = np.array(loop.daemon.source.render_times_ms())
        finally:
            loop.stop()
    pipeline_ms = np.array([sum(r.stage_ns) / 1e6 for r in records])
    latency_ms = np.array([r.latency_ns / 1e6 for r in records if r.latency_ns is not None])
    return {"name": name, **result, "render_ms": render_ms, "pipeline_ms": pipeline_ms, "latency_ms": latency_ms}


def table(rows: list[dict]) -> None:
    print(f"load average {' '.join(f'{v:.1f}' for v in os.getloadavg())} on {os.cpu_count()} cores")
    print(f"{'flight':<28} {'fps':>5} {'render ms':>15} {'pipeline ms':>15} {'render/pipe':>11} "
          f"{'latency ms':>10} {'est-truth cm':>15} {'gap ms':>7} {'gap fr':>6} {'>=20 fps':>8}")
    for r in rows:
        render, pipe, errors = r["render_ms"], r["pipeline_ms"], r["errors_m"] * 100
        print(f"{r['name']:<28} {r['fps']:5.1f} "
              f"{np.median(render):6.1f} p95 {np.percentile(render, 95):5.1f} "
              f"{np.median(pipe):6.1f} p95 {np.percentile(pipe, 95):5.1f} "
              f"{np.median(render) / np.median(pipe):11.2f} {np.median(r['latency_ms']):10.1f} "
              f"{np.median(errors):5.2f} max {errors.max():5.2f} {r['max_gap_s'] * 1000:7.0f} "
              f"{r['longest_unsent_frames']:6d} {'met' if r['fps'] >= TARGET_FPS else 'not met':>8}")


def render_only(config_path: Path, n_frames: int = 60) -> None:
    """The simulated camera's render + degradations alone, at n_frames poses around the config's 2 m square."""
    config = load_config(config_path)
    camera = SimulatedCamera(config.facility_map, config.camera, config.source.params)
    # (x, y) offsets from the start along the square's perimeter, 8 m in all
    perimeter = [np.array(corner, float) for corner in ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))]
    offsets = [perimeter[int(4 * k / n_frames)] + (4 * k / n_frames % 1)
               * (perimeter[int(4 * k / n_frames) + 1] - perimeter[int(4 * k / n_frames)]) for k in range(n_frames)]
    cpu_ms, wall_ms = [], []
    for index, offset in enumerate(offsets):
        state = vehicle_state(config, offset, index)
        cpu0, wall0 = time.process_time(), time.perf_counter()
        camera._render(state, index)
        cpu_ms.append((time.process_time() - cpu0) * 1e3)
        wall_ms.append((time.perf_counter() - wall0) * 1e3)
    print(f"render only ({config_path.name}, {camera.camera.width}x{camera.camera.height}, {n_frames} poses): "
          f"CPU {np.median(cpu_ms):.1f} ms p95 {np.percentile(cpu_ms, 95):.1f}, "
          f"wall {np.median(wall_ms):.1f} ms p95 {np.percentile(wall_ms, 95):.1f} per frame")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: the test hall's 2 m square only")
    args = parser.parse_args()
    flights = ([("test hall, 2 m square", 2.0, None)] if args.quick else
               [("test hall, 4 m square", 4.0, None),
                ("warehouse (sitl-camera), 2 m", 2.0, common.REPO / "config" / "sitl-camera.yaml"),
                ("hall 2 m, sim stalls 60 ms", 2.0, None, 60.0),
                ("hall 2 m, sim stalls 150 ms", 2.0, None, 150.0)])
    table([fly(*flight) for flight in flights])
    render_only(common.REPO / "config" / "sitl-camera.yaml")


if __name__ == "__main__":
    main()
