"""Survey accuracy, speed and map check on walk-throughs rendered through ``maps/warehouse.yaml``.

A person walks the hall with a camera (70 degree field of view, 1.5 m up,
tilted 15 degrees down), stopping every few metres in the aisles and
cross-aisles to turn once around (``walk_stops``); the simulator renders it
with realistic degradations (``simulate.DEFAULT_DEGRADATIONS``: motion blur,
optics blur, vignetting, sensor noise) at 640x480 and 1280x720. The survey
sees the true map only through its anchors (one marker; and three spread
over the hall), the marker sizes and which markers hang on walls, and is then
held to the true map:

* marker position and orientation errors (median, max), markers seen in >= 3 frames mapped;
* localization (``companion.localize``, joint PnP) on the committed flights with the surveyed
  map, the true map and a "tape" map (the true map with +-2 cm and +-2 deg errors per marker);
* survey time of the walk (detection + adjustment) with the machine's load;
* map check: a marker moved 5 cm or turned 3 deg flagged, no false alarm on the untouched map.

    PYTHONPATH=. python benchmarks/bench_survey.py [--quick]

``--quick`` (CI's smoke run, about a minute): a short walk in aisle 1 at 640x480 (three anchors: its three stops
see three groups of markers never in view together), the hover flight, two check trials.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from common import REPO
from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, MapMarker, load_map
from companion.geometry.pose import PoseParams, PoseSolver
from companion.localize import groundtruth, localize, map_detector, resources
from companion.sim import simulate, trajectory
from companion.survey.check import CheckParams, check_markers
from companion.survey.observations import keyframes
from companion.survey.survey import SurveyOptions, survey

MAP_PATH = REPO / "maps" / "warehouse.yaml"
FLIGHTS = {"aisle": REPO / "companion" / "data" / "sequences" / "warehouse_aisle",
           "hover": REPO / "tests" / "data" / "sequences" / "warehouse_hover"}
# stops (x, y) of the walk: aisle 0, the office cross-aisle, aisle 1, the dock cross-aisle, aisle 2
FULL_STOPS = ([(x, 1.25) for x in (2.0, 4.5, 7.0, 9.5, 12.0, 14.5)] + [(16.5, 1.5), (16.5, 3.5)]
              + [(x, 5.0) for x in (15.0, 12.5, 10.0, 7.5, 5.0, 2.5)] + [(1.5, 6.5)]
              + [(x, 9.0) for x in (2.5, 5.0, 7.5, 10.0, 12.5, 15.0)])
QUICK_STOPS = [(2.5, 5.0), (5.0, 5.0), (7.5, 5.0)]
ANCHORS = {"one": ("A",), "three": ("A", "X", "STOP")}
# the quick walk's three stops see three groups never in view together: an anchor in each
QUICK_ANCHORS = {"three": ("A", "I", "T")}
TARGETS = ("position median <= 5 mm, max <= 2 cm; orientation median <= 0.3 deg, max <= 1 deg; every marker seen "
           "in >= 3 frames mapped; localization median within 1.5x of the true map's and below the tape map's; "
           "1,000 frames in <= 2 min; map check >= 95 % of moves found, 0 false alarms")


def camera_model(width: int, height: int) -> CameraModel:
    return CameraModel.from_config({"width": width, "height": height, "hfov_deg": 70.0,
                                    "distortion": [-0.05, 0.02, 0.0, 0.0, 0.0],
                                    "mount": {"facing": "forward", "tilt_down_deg": 15.0}}, "bench camera")


def walk_stops(stops, height_m: float = 1.5) -> trajectory.Trajectory:
    """Walk from stop to stop, turning once around (four quarter turns) at each."""
    points, heading = [], 0.0
    for x, y in stops:
        points += [(x, y, height_m, heading + 90.0 * k) for k in range(5)]
        heading += 360.0
    return trajectory.waypoints(points, speed_m_s=0.7, max_accel_m_s2=0.8)


def render_walk(out: Path, stops, size: tuple[int, int], fps: float) -> Path:
    sim = simulate.Simulator(simulate.build_world(load_map(MAP_PATH)), camera_model(*size), walk_stops(stops), seed=11)
    return simulate.write_sequence(out, sim, fps, str(MAP_PATH), progress=True)


def anchors_map(truth: FacilityMap, symbols) -> FacilityMap:
    """The true map's frame, the anchors' true poses, sizes of the others, and which markers hang upright on walls."""
    walls = frozenset(m.symbol for m in truth.markers.values() if abs(m.T_map_marker[2, 1] - 1.0) < 1e-9)
    sizes = {m.symbol: m.size_m for m in truth.markers.values()}
    hints = replace(truth.survey, on_vertical_wall=walls, sizes_m=sizes)
    anchors = {m.id: m for m in truth.markers.values() if m.symbol in symbols}
    return replace(truth, markers=anchors, survey=hints)


def tape_map(truth: FacilityMap, seed: int = 3) -> FacilityMap:
    """The true map as a tape measure and a compass give it: +-2 cm per axis, turned up to 2 deg about a random axis."""
    rng = np.random.default_rng(seed)
    markers = {}
    for m in truth.markers.values():
        axis = rng.normal(size=3)
        turn = frames.rotation_from_rotvec(axis / np.linalg.norm(axis) * math.radians(rng.uniform(-2.0, 2.0)))
        T = frames.make_transform(turn @ m.T_map_marker[:3, :3], m.T_map_marker[:3, 3] + rng.uniform(-0.02, 0.02, 3))
        markers[m.id] = MapMarker(m.symbol, m.id, m.size_m, T, m.note)
    return replace(truth, markers=markers)


def marker_errors(surveyed: FacilityMap, truth: FacilityMap, anchors) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Position (m) and angle (deg) errors of the surveyed (non-anchor) markers, and their symbols."""
    position, angle, symbols = [], [], []
    for marker_id, marker in surveyed.markers.items():
        if marker.symbol in anchors:
            continue
        T_true = truth.markers[marker_id].T_map_marker
        position.append(float(np.linalg.norm(marker.T_map_marker[:3, 3] - T_true[:3, 3])))
        angle.append(math.degrees(frames.rotation_angle_rad(marker.T_map_marker[:3, :3], T_true[:3, :3])))
        symbols.append(marker.symbol)
    return np.array(position), np.array(angle), symbols


def localization_median_m(flight: Path, facility_map: FacilityMap, map_sd_m: float,
                          map_sd_deg: float) -> tuple[float, int, int]:
    """(median position error m, frames with a pose, frames) of the flight localized on the map, the pose
    stage told how far its markers may be from where the map says (``PoseParams.map_sd_m``, ``map_sd_deg``:
    0 for the true and the surveyed maps, as the pose stage weighed them before it had that term; 2 cm and
    2 degrees for the tape map, whose markers' disagreements its gates would otherwise refuse)."""
    _, camera = resources(flight, str(MAP_PATH), None)
    solver = PoseSolver(facility_map, camera, PoseParams(map_sd_m=map_sd_m, map_sd_deg=map_sd_deg))
    results = list(localize(flight, solver, groundtruth(flight), detector=map_detector(facility_map, camera)))
    errors = [r.error_m for r in results if r.error_m is not None]
    return (float(np.median(errors)) if errors else math.inf), len(errors), len(results)


def verdict(ok: bool) -> str:
    return "met" if ok else "NOT MET"


# ------------------------------------------------------------------ parts

def survey_runs(walks: dict[str, Path], truth: FacilityMap, anchor_sets) -> dict:
    """Survey every walk with every anchor set; print the accuracy table. Returns the surveyed maps by (walk, anchors)."""
    print(f"\n{'walk':<10} {'anchors':<8} {'frames':>6} {'adjusted':>8} {'mapped':>6} {'seen>=3':>7} "
          f"{'pos_med_mm':>10} {'pos_max_mm':>10} {'ang_med_deg':>11} {'ang_max_deg':>11} {'time_s':>6} {'load':>5}  "
          "worst")
    maps, checks = {}, []
    for walk_name, walk in walks.items():
        camera = CameraModel.from_config(yaml.safe_load((walk / "sequence.yaml").read_text())["camera"], str(walk))
        for anchor_name, symbols in anchor_sets.items():
            start = time.perf_counter()
            result = survey([walk], camera, anchors_map(truth, symbols), SurveyOptions())
            elapsed_s = time.perf_counter() - start
            load = os.getloadavg()[0]
            position, angle, names = marker_errors(result.facility_map, truth, symbols)
            seen = {s.marker.symbol for s in result.markers} | set(result.dropped)
            seen_enough = {s.marker.symbol for s in result.markers if s.frames >= 3}
            mapped = {m.symbol for m in result.facility_map.markers.values()}
            worst = names[int(np.argmax(position))] if len(position) else "-"
            print(f"{walk_name:<10} {anchor_name:<8} {result.frames_read:>6} {result.frames_adjusted:>8} "
                  f"{len(mapped):>6} {len(seen_enough):>7} {np.median(position) * 1000:>10.1f} "
                  f"{position.max() * 1000:>10.1f} {np.median(angle):>11.3f} {angle.max():>11.3f} {elapsed_s:>6.1f} "
                  f"{load:>5.2f}  {worst}")
            maps[(walk_name, anchor_name)] = result.facility_map
            checks.append((walk_name, anchor_name, position, angle, seen_enough <= mapped, len(seen),
                           result.frames_read, elapsed_s, load))
    return {"maps": maps, "checks": checks}


def localization_runs(flights: dict[str, Path], truth: FacilityMap, surveyed: dict) -> list:
    print(f"\n{'flight':<7} {'map':<18} {'frames_posed':>12} {'median_err_mm':>13} {'vs_true':>7}")
    rows = []
    for flight_name, flight in flights.items():
        reference, posed, total = localization_median_m(flight, truth, 0.0, 0.0)
        print(f"{flight_name:<7} {'true':<18} {posed:>5}/{total:<6} {reference * 1000:>13.2f} {1.0:>7.2f}")
        tape, posed, total = localization_median_m(flight, tape_map(truth), 0.02, 2.0)
        print(f"{flight_name:<7} {'tape (2 cm, 2 deg)':<18} {posed:>5}/{total:<6} {tape * 1000:>13.2f} "
              f"{tape / reference:>7.2f}")
        for (walk_name, anchor_name), facility_map in surveyed.items():
            median, posed, total = localization_median_m(flight, facility_map, 0.0, 0.0)
            label = f"surveyed {walk_name}/{anchor_name}"
            print(f"{flight_name:<7} {label:<18} {posed:>5}/{total:<6} {median * 1000:>13.2f} {median / reference:>7.2f}")
            rows.append((flight_name, label, median, reference, tape))
    return rows


def check_runs(walk: Path, truth: FacilityMap, trials: int, seed: int = 5) -> tuple[int, int, int, int]:
    """(moves flagged, moves, false alarms, markers judged) over ``trials`` moved-marker maps and the untouched map."""
    camera = CameraModel.from_config(yaml.safe_load((walk / "sequence.yaml").read_text())["camera"], str(walk))
    from companion.markers.layout import MarkerLayout
    from companion.survey.observations import collect

    layout = MarkerLayout(parity=truth.parity, dictionary=truth.dictionary)
    footage = collect([walk], camera, map_detector(truth, camera), lambda m: truth.markers[m].size_m
                      if m in truth.markers else None, layout, progress=False)
    kept, seen = keyframes(footage.frames, 3.0), footage.frames_seen()
    untouched = check_markers(kept, truth, camera, seen, CheckParams())
    judged = [c for c in untouched if c.verdict != "unseen"]
    false_alarms = sum(c.verdict == "moved" for c in judged)
    rng = np.random.default_rng(seed)
    candidates = [truth.markers[c.marker_id] for c in judged]
    flagged = 0
    print(f"\n{'trial':>5} {'marker':<7} {'change':<12} {'found_cm':>8} {'found_deg':>9} {'verdict':<7} {'others':>6}")
    for trial in range(trials):
        marker = candidates[rng.integers(len(candidates))]
        if trial % 2 == 0:  # moved 5 cm along the wall or up
            direction = marker.T_map_marker[:3, rng.integers(2)] * rng.choice([-1.0, 1.0])
            T = marker.T_map_marker.copy()
            T[:3, 3] += 0.05 * direction
            change = "moved 5 cm"
        else:  # turned 3 deg about its normal or the vertical
            axis = marker.T_map_marker[:3, 2] if rng.uniform() < 0.5 else np.array([0.0, 0.0, 1.0])
            T = frames.make_transform(frames.rotation_from_rotvec(axis * math.radians(3.0) * rng.choice([-1, 1]))
                                      @ marker.T_map_marker[:3, :3], marker.T_map_marker[:3, 3])
            change = "turned 3 deg"
        moved_map = replace(truth, markers={**truth.markers, marker.id: replace(marker, T_map_marker=T)})
        results = {c.marker_id: c for c in check_markers(kept, moved_map, camera, seen, CheckParams())}
        hit = results[marker.id].verdict == "moved"
        others = sum(c.verdict == "moved" for m, c in results.items() if m != marker.id)
        flagged += hit
        false_alarms += others
        r = results[marker.id]
        found = "       -         -" if r.position_error_m is None else \
            f"{r.position_error_m * 100:>8.2f} {r.angle_error_deg:>9.2f}"
        print(f"{trial:>5} {marker.symbol:<7} {change:<12} {found} {r.verdict:<7} {others:>6}")
    return flagged, trials, false_alarms, len(judged)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="CI smoke run: a short walk, about a minute")
    parser.add_argument("--work", help="folder for the rendered walks (default: a temporary one)")
    args = parser.parse_args()
    truth = load_map(MAP_PATH)
    print(f"bench_survey: {'quick' if args.quick else 'full'} run on {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.work or temporary)
        if args.quick:
            walks = {"640x480": render_walk(work / "quick", QUICK_STOPS, (640, 480), 4.0)}
            anchor_sets, flights, trials = QUICK_ANCHORS, {"hover": FLIGHTS["hover"]}, 2
        else:
            walks = {}
            for size in ((640, 480), (1280, 720)):
                name = f"{size[0]}x{size[1]}"
                out = work / name
                walks[name] = out if (out / "timestamps.csv").exists() else render_walk(out, FULL_STOPS, size, 4.0)
            anchor_sets, flights, trials = ANCHORS, FLIGHTS, 20
        runs = survey_runs(walks, truth, anchor_sets)
        local = localization_runs(flights, truth, runs["maps"])
        flagged, moves, false_alarms, judged = check_runs(walks["640x480"], truth, trials)
    print(f"\nmap check: {flagged}/{moves} moves flagged, {false_alarms} false alarms "
          f"({judged} markers judged per trial)")
    print(f"\ntargets ({TARGETS}):")
    for walk_name, anchor_name, position, angle, all_mapped, seen, frames_read, elapsed_s, load in runs["checks"]:
        print(f"  {walk_name}/{anchor_name}: position median {np.median(position) * 1000:.1f} mm "
              f"{verdict(np.median(position) <= 0.005)}, max {position.max() * 1000:.1f} mm "
              f"{verdict(position.max() <= 0.02)}; orientation median {np.median(angle):.3f} deg "
              f"{verdict(np.median(angle) <= 0.3)}, max {angle.max():.3f} deg {verdict(angle.max() <= 1.0)}; "
              f"seen >= 3 frames mapped {verdict(all_mapped)}; {frames_read} frames in {elapsed_s:.1f} s "
              f"(load {load:.2f}): {frames_read / elapsed_s * 120:.0f} frames per 2 min "
              f"{verdict(frames_read / elapsed_s * 120 >= 1000)}")
    for flight, label, median, reference, tape in local:
        print(f"  {flight} on {label}: {median / reference:.2f}x the true map's median "
              f"{verdict(median <= 1.5 * reference)}, tape map {tape / reference:.2f}x "
              f"{verdict(median < tape)}")
    print(f"  map check: {100 * flagged / max(moves, 1):.0f} % flagged {verdict(flagged >= 0.95 * moves)}, "
          f"{false_alarms} false alarms {verdict(false_alarms == 0)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
