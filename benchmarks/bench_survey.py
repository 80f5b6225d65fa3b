"""Survey accuracy, speed and map check on walk-throughs rendered through ``maps/warehouse.yaml``.

A person walks the hall with a phone (70 degree field of view, at eye height 1.5 m, tilted 15 degrees down) the
way docs/survey.md asks (``hall_walk``): the anchor filmed from 45 degrees to each side with its neighbours, a
loop around each rack, each face filmed diagonally ahead with pans across the aisle at each stop, the rack's last
marker held in view with the end wall's at each aisle end, the high signs looked up at, back to the anchor; slow
walking and turning with the hand's shake (``handheld``). The simulator renders it with a phone video's
degradations (``WALK_DEGRADATIONS``: motion blur, optics blur, vignetting, sensor noise, auto-exposure wander,
JPEG) and people and boxes crossing the view, at 640x480 and 1280x720 (``--work DIR`` keeps the walks in
DIR/hall-WxH and reuses them). The survey sees the true map only through its anchors (one marker; and three
spread over the hall), the marker sizes and which markers hang on walls, and is then held to the true map:

* marker position and orientation errors (median, max), markers seen in >= 3 frames mapped; and the position
  errors left after the best rigid and similarity fit of the surveyed map to the truth (the map's turn, shift
  and scale about its anchors taken out: what is left is its bending);
* localization (``companion.localize``, joint PnP) on the committed flights with the surveyed
  map (each marker weighed by the ``sd`` the survey wrote for it), the true map and a "tape" map (the true
  map with +-2 cm and +-2 deg errors per marker);
* survey time of the walk (detection + adjustment) with the machine's load;
* map check: a marker moved 5 cm or turned 3 deg flagged, no false alarm on the untouched map.

    PYTHONPATH=. python benchmarks/bench_survey.py [--quick] [--configs 640x480/one,...] [--work DIR]

``--configs``: only these walk/anchors runs (e.g. ``640x480/one``; default all four); the map check runs when
the 640x480 walk is among them.

``--quick`` (CI's smoke run): a short walk at the anchor's end of aisle 1 at 640x480 (three anchors: it
sees three groups of markers hardly ever in view together), the hover flight, two check trials.
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
from common import REPO, work_folder

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, MapMarker, load_map
from companion.geometry.pose import PoseParams, PoseSolver
from companion.localize import groundtruth, localize, map_detector, resources
from companion.markers.layout import MarkerLayout
from companion.sim import simulate, trajectory
from companion.survey.check import CheckParams, check_markers
from companion.survey.observations import collect, keyframes
from companion.survey.survey import SurveyOptions, survey_footage

MAP_PATH = REPO / "maps" / "warehouse.yaml"
FLIGHTS = {"aisle": REPO / "companion" / "data" / "sequences" / "warehouse_aisle",
           "hover": REPO / "tests" / "data" / "sequences" / "warehouse_hover"}
EYE_HEIGHT_M = 1.5        # a phone held at eye level ...
WALK_M_S = 0.5            # ... walked slowly between stops (docs/survey.md) ...
TURN_DEG_S = 30.0         # ... and turned slowly (peak rates 1.875 times these)
# a phone's video in a warehouse: the simulator's camera (motion blur, optics blur, vignetting, sensor noise)
# with an indoor exposure, auto-exposure wander and video compression; people and boxes crossing the view
WALK_DEGRADATIONS = replace(simulate.DEFAULT_DEGRADATIONS, exposure_ms=12.0, exposure_wander=0.2, jpeg_quality=90)
WALK_OCCLUDERS = 12
ANCHORS = {"one": ("A",), "three": ("A", "X", "STOP")}
# the quick walk sees three groups of markers hardly ever in view together (the dock end with R2's E and F, its G
# and H, its I and J; one frame shows G, 12 px, with E and F): an anchor in each
QUICK_ANCHORS = {"three": ("A", "G", "I")}
TARGETS = ("position median <= 5 mm, max <= 2 cm; orientation median <= 0.3 deg, max <= 1 deg; every marker seen "
           "in >= 3 frames mapped; localization median within 1.5x of the true map's and below the tape map's; "
           "1,000 frames in <= 2 min; map check >= 95 % of moves found, 0 false alarms on an untouched map")


def camera_model(width: int, height: int) -> CameraModel:
    return CameraModel.from_config({"width": width, "height": height, "hfov_deg": 70.0,
                                    "distortion": [-0.05, 0.02, 0.0, 0.0, 0.0],
                                    "mount": {"facing": "forward", "tilt_down_deg": 15.0}}, "bench camera")


# ------------------------------------------------------------------ the walk

def look(x: float, y: float, from_deg: float, to_deg: float, pitch_deg: float = 0.0) -> list[tuple]:
    """Stand at (x, y) and turn slowly from one heading to another (map frame, ccw from +x)."""
    return [(x, y, from_deg, pitch_deg), (x, y, to_deg, pitch_deg)]


def aim(x: float, y: float, heading_deg: float, pitch_deg: float = 0.0, hold_s: float = 2.0) -> list[tuple]:
    """Turn slowly onto a heading, hold the phone there (still but for the hand's shake), turn on:
    how one films two markers far apart that the survey needs in one view."""
    still = [(x, y, heading_deg, pitch_deg)] * (1 + int(hold_s / 0.5))
    return [(x, y, heading_deg - 30.0, pitch_deg)] + still + [(x, y, heading_deg + 30.0, pitch_deg)]


def anchor_views(x: float, y: float, facing_deg: float, distance_m: float = 1.2) -> list[tuple]:
    """Film a marker at (x, y) that faces ``facing_deg`` from ``distance_m``, 45 degrees to each side of it,
    holding still at each: the way docs/survey.md asks to film a lone anchor (the map's heading is only as
    good as the views of it with its neighbours, and an oblique view gives a marker's turn far better than a
    straight one, which here would show the anchor alone)."""
    poses = []
    for side_deg in (-45.0, 45.0):
        bearing = math.radians(facing_deg + side_deg)
        px, py = x + distance_m * math.cos(bearing), y + distance_m * math.sin(bearing)
        poses += [(px, py, facing_deg + side_deg + 180.0, 0.0)] * 5
    return poses


def along(y: float, xs, walking_deg: float, pan_to_deg: float) -> list[tuple]:
    """Walk along an aisle (at y) with the phone diagonally ahead at a rack face (walking_deg); at each stop
    (xs) pan across to the other face (pan_to_deg) and back."""
    poses = []
    for x in xs:
        poses += [(x, y, walking_deg, 0.0), (x, y, pan_to_deg, 0.0), (x, y, walking_deg, 0.0)]
    return poses


def hall_walk() -> list[tuple]:
    """(x, y, heading_deg, pitch_deg) stops of a walk through ``maps/warehouse.yaml``, the way docs/survey.md asks:
    the anchor A from 45 degrees to each side, a loop around each rack, each face filmed from 1.4 m with the next
    markers in view, stops that pan across the aisle, the high signs looked up at, and at every aisle end the
    rack's last marker aimed at together with the end wall's (perpendicular faces 4 m apart: at 640x480 only a few
    headings show both large enough)."""
    poses = []
    # loop 1, around rack R1, from the dock end of aisle 1 where the anchor A hangs
    poses += look(2.5, 5.0, 150.0, 210.0)                   # dock wall: ENTRY, T
    poses += anchor_views(4.0, 3.5, 90.0)                   # the anchor A from 1.2 m, 45 deg to each side
    poses += aim(3.5, 5.0, 180.0, pitch_deg=25.0)           # the sign 4 above them
    poses += aim(2.75, 2.9, 104.0)                          # E with T
    poses += aim(4.5, 3.9, 203.0)                           # A with ENTRY
    poses += along(4.9, (3.0, 6.0, 9.0, 12.0), -45.0, 60.0)  # aisle 1 east, R1's north face ahead on the right
    poses += aim(13.5, 4.15, 335.0)                         # R1's last marker 8 with EXIT
    poses += aim(14.5, 5.0, 0.0, pitch_deg=25.0)            # the sign 3 above EXIT and W
    poses += look(15.75, 2.9, -30.0, 40.0)                  # office wall: STOP, V, EXIT
    poses += aim(13.5, 2.15, 26.0)                          # AT with STOP
    poses += along(1.1, (12.0, 9.0, 6.0), 135.0, 45.0)      # aisle 0 west, R1's south face ahead on the right
    poses += aim(4.5, 0.4, 137.0)                           # P with S
    poses += look(2.5, 2.9, 150.0, 210.0)                   # dock wall: S, ENTRY
    poses += look(2.5, 5.0, 210.0, 45.0)                    # loop 1 closed at the anchor
    # loop 2, around rack R2
    poses += along(5.1, (3.0, 6.0, 9.0, 12.0), 45.0, -60.0)  # aisle 1 east, R2's south face ahead on the left
    poses += aim(13.5, 5.4, 34.0)                           # R2's last marker L with W
    poses += [(16.0, 7.0, 90.0, 0.0)]
    poses += look(16.0, 8.5, 60.0, 200.0)                   # office end of aisle 2
    poses += aim(11.5, 8.4, 11.0)                           # X with HASH
    poses += along(9.0, (11.0, 8.5, 6.0), 150.0, 30.0)      # aisle 2 west, the north wall ahead on the right
    poses += aim(4.0, 8.4, 14.0)                            # UP with LEFT
    poses += aim(4.5, 7.9, 203.0)                           # R2's first marker RIGHT with DOCK
    poses += look(2.5, 9.0, 150.0, 210.0)                   # dock wall: DOCK, U
    for x in (5.25, 7.75, 10.25, 12.75):                    # aisle 2 east by the wall: R2's north face, two at a time
        poses += aim(x, 10.1, 270.0)
    poses += aim(9.75, 8.15, 12.0)                          # HOME with MINUS
    poses += [(8.0, 8.6, 180.0, 0.0), (2.5, 8.6, 180.0, 0.0)]   # back to the dock end ...
    poses += aim(2.5, 6.9, 175.0)                           # dock wall: T with DOCK
    poses += look(2.5, 5.0, 220.0, 360.0)                   # ... and to the anchor
    return poses


def quick_walk() -> list[tuple]:
    """CI's short walk: the dock end of aisle 1 (the anchor A with the dock wall) and R1's north face."""
    return (look(2.5, 5.0, 150.0, 210.0) + aim(4.5, 3.9, 203.0)
            + along(4.9, (3.0, 6.0, 9.0), -45.0, 60.0))


def handheld(poses, rate_hz: float = 20.0, seed: int = 3) -> trajectory.SampledTrajectory:
    """A phone carried through ``poses`` (x, y, heading_deg, pitch_deg) at eye height, stopping at each: each leg
    eases in and out (minimum jerk) no faster than WALK_M_S and TURN_DEG_S; the hand shakes slowly
    (+-0.7 deg, +-2 cm)."""
    stops = np.asarray(poses, dtype=float)
    rng = np.random.default_rng(seed)
    periods_s, phases = rng.uniform(2.0, 5.0, 4), rng.uniform(0.0, 2 * np.pi, 4)
    times_s, states, start_s = [], [], 0.0
    for a, b in zip(stops[:-1], stops[1:]):
        distance_m = float(np.hypot(*(b[:2] - a[:2])))
        turn_deg = float(np.max(np.abs(b[2:] - a[2:])))
        # minimum jerk over T: peak speed 1.875 d / T, peak acceleration 5.77 d / T^2
        duration_s = max(1.875 * distance_m / WALK_M_S, math.sqrt(5.77 * distance_m / 0.5),
                         1.875 * turn_deg / TURN_DEG_S, 0.5)
        for s in np.arange(0.0, 1.0, 1.0 / max(int(duration_s * rate_hz), 1)):
            times_s.append(start_s + s * duration_s)
            # minimum-jerk progress: 10 s^3 - 15 s^4 + 6 s^5
            states.append(a + s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s) * (b - a))
        start_s += duration_s
    times_s.append(start_s)
    states.append(stops[-1])
    poses_T = []
    for t_s, (x, y, heading_deg, pitch_deg) in zip(times_s, states):
        shake = np.sin(2 * np.pi * t_s / periods_s + phases)
        R = trajectory.R_map_body_from_attitude(heading_deg + 0.7 * shake[0], math.radians(pitch_deg + 0.7 * shake[1]),
                                                math.radians(0.7 * shake[2]))
        poses_T.append(frames.make_transform(R, [x, y, EYE_HEIGHT_M + 0.02 * shake[3]]))
    return trajectory.SampledTrajectory(np.array(times_s), np.array(poses_T),
                                        {"pattern": "hand-held walk (bench_survey)", "stops": stops.tolist()})


def render_walk(out: Path, poses, size: tuple[int, int], fps: float) -> Path:
    sim = simulate.Simulator(simulate.build_world(load_map(MAP_PATH)), camera_model(*size), handheld(poses),
                             WALK_DEGRADATIONS, seed=11, occluder_count=WALK_OCCLUDERS)
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


def aligned_errors(surveyed: FacilityMap, truth: FacilityMap, anchors) -> dict:
    """Where the position error of the surveyed (non-anchor) markers lies: their errors (m) after the best
    rigid fit of the surveyed map to the truth ("rigid": the map's turn and shift about its anchors taken out)
    and after the best similarity ("similar": its scale too), with that fit's scale and turn (deg).
    What is left after the fits is the map's own bending."""
    ids = [i for i, m in surveyed.markers.items() if m.symbol not in anchors]
    P = np.array([surveyed.markers[i].T_map_marker[:3, 3] for i in ids])
    Q = np.array([truth.markers[i].T_map_marker[:3, 3] for i in ids])
    p, q = P - P.mean(axis=0), Q - Q.mean(axis=0)
    # Umeyama: R = U D V' from the SVD of the cross-covariance q' p / n; scale = trace(S D) / var(p)
    U, S, Vt = np.linalg.svd(q.T @ p / len(P))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D) / (p * p).sum(axis=1).mean())
    return {"rigid": np.linalg.norm(p @ R.T - q, axis=1), "similar": np.linalg.norm(scale * p @ R.T - q, axis=1),
            "scale": scale, "turn_deg": math.degrees(frames.rotation_angle_rad(R, np.eye(3)))}


def localization_median_m(flight: Path, facility_map: FacilityMap, map_sd_m: float,
                          map_sd_deg: float) -> tuple[float, int, int]:
    """(median position error m, frames with a pose, frames) of the flight localized on the map, the pose
    stage told how far its markers may be from where the map says: 0 for the true map (exact), 2 cm and
    2 degrees for the tape map (``PoseParams.map_sd_m``, ``map_sd_deg``); a surveyed map states each marker's
    own ``sd``, which the pose stage uses (its daemon defaults then apply to no marker)."""
    _, camera = resources(flight, str(MAP_PATH), None)
    solver = PoseSolver(facility_map, camera, PoseParams(map_sd_m=map_sd_m, map_sd_deg=map_sd_deg))
    results = list(localize(flight, solver, groundtruth(flight), detector=map_detector(facility_map, camera)))
    errors = [r.error_m for r in results if r.error_m is not None]
    return (float(np.median(errors)) if errors else math.inf), len(errors), len(results)


def surveyed_sd(result) -> tuple[float, float]:
    """(m, deg) the median over the surveyed (non-anchor) markers of the standard deviations the survey states
    for them (their ``sd`` in the map; ``SurveyedMarker.sd_position_m``, ``sd_angle_deg``), for the table."""
    surveyed = [s for s in result.markers if not s.anchor]
    return (float(np.median([s.sd_position_m for s in surveyed])), float(np.median([s.sd_angle_deg for s in surveyed])))


def verdict(ok: bool) -> str:
    return "met" if ok else "NOT MET"


# ------------------------------------------------------------------ parts

def survey_runs(walks: dict[str, Path], truth: FacilityMap, anchor_sets, configs=None) -> dict:
    """Survey every walk with every anchor set; print the accuracy table. Returns the surveyed maps by (walk, anchors).

    Each walk's markers are detected once (detect_s) and surveyed from those detections with each anchor set
    (adjust_s), as ``survey`` does in one call; the survey time of a run is detect_s + adjust_s.
    """
    print(f"\n{'walk':<10} {'anchors':<8} {'frames':>6} {'adjusted':>8} {'mapped':>6} {'seen>=3':>7} "
          f"{'pos_med_mm':>10} {'pos_max_mm':>10} {'ang_med_deg':>11} {'ang_max_deg':>11} {'detect_s':>8} "
          f"{'adjust_s':>8} {'load':>5} {'in_3sd':>6}  worst  weak")
    maps, checks, aligned = {}, [], []
    for walk_name, walk in walks.items():
        camera = CameraModel.from_config(yaml.safe_load((walk / "sequence.yaml").read_text())["camera"], str(walk))
        first = anchors_map(truth, next(iter(anchor_sets.values())))
        layout = MarkerLayout(parity=first.parity, dictionary=first.dictionary)
        detector = map_detector(first, camera)
        start = time.perf_counter()
        footage = collect([walk], camera, detector, lambda m: truth.markers[m].size_m if m in truth.markers else None,
                          layout, progress=False)
        detect_s = time.perf_counter() - start
        for anchor_name, symbols in anchor_sets.items():
            if configs and (walk_name, anchor_name) not in configs:
                continue
            start = time.perf_counter()
            result = survey_footage(footage, camera, anchors_map(truth, symbols), SurveyOptions())
            adjust_s = time.perf_counter() - start
            load = os.getloadavg()[0]
            position, angle, names = marker_errors(result.facility_map, truth, symbols)
            seen = {s.marker.symbol for s in result.markers} | set(result.dropped)
            seen_enough = {s.marker.symbol for s in result.markers if s.frames >= 3}
            mapped = {m.symbol for m in result.facility_map.markers.values()}
            worst = names[int(np.argmax(position))] if len(position) else "-"
            weak = ",".join(s.marker.symbol for s in result.markers if s.weakly_linked) or "-"
            sd_m = {s.marker.symbol: s.sd_position_m for s in result.markers}
            covered = sum(e <= 3.0 * sd_m[name] for e, name in zip(position, names))
            print(f"{walk_name:<10} {anchor_name:<8} {result.frames_read:>6} {result.frames_adjusted:>8} "
                  f"{len(mapped):>6} {len(seen_enough):>7} {np.median(position) * 1000:>10.1f} "
                  f"{position.max() * 1000:>10.1f} {np.median(angle):>11.3f} {angle.max():>11.3f} {detect_s:>8.1f} "
                  f"{adjust_s:>8.1f} {load:>5.2f} {f'{covered}/{len(position)}':>6}  {worst:<6} {weak}")
            fit = aligned_errors(result.facility_map, truth, symbols)
            aligned.append(f"  {walk_name}/{anchor_name}: best rigid fit to the truth "
                           f"{np.median(fit['rigid']) * 1000:.1f} / {fit['rigid'].max() * 1000:.1f} mm "
                           f"(turn {fit['turn_deg']:.3f} deg), with scale "
                           f"{np.median(fit['similar']) * 1000:.1f} / {fit['similar'].max() * 1000:.1f} mm "
                           f"(scale {fit['scale']:.5f})")
            maps[(walk_name, anchor_name)] = (result.facility_map, *surveyed_sd(result))
            checks.append((walk_name, anchor_name, position, angle, seen_enough <= mapped, len(seen),
                           result.frames_read, detect_s + adjust_s, load))
    print("\nposition error median / max without the map's gauge (what is left: its bending):")
    print("\n".join(aligned))
    return {"maps": maps, "checks": checks}


def localization_runs(flights: dict[str, Path], truth: FacilityMap, surveyed: dict) -> list:
    # map_sd: what the pose stage is told; for a surveyed map the median of its markers' own sd (non-anchors)
    print(f"\n{'flight':<7} {'map':<18} {'map_sd_mm':>9} {'map_sd_deg':>10} {'frames_posed':>12} {'median_err_mm':>13} "
          f"{'vs_true':>7}")
    rows = []
    for flight_name, flight in flights.items():
        reference, posed, total = localization_median_m(flight, truth, 0.0, 0.0)
        print(f"{flight_name:<7} {'true':<18} {0.0:>9.1f} {0.0:>10.2f} {posed:>5}/{total:<6} {reference * 1000:>13.2f} "
              f"{1.0:>7.2f}")
        tape, posed, total = localization_median_m(flight, tape_map(truth), 0.02, 2.0)
        print(f"{flight_name:<7} {'tape (2 cm, 2 deg)':<18} {20.0:>9.1f} {2.0:>10.2f} {posed:>5}/{total:<6} "
              f"{tape * 1000:>13.2f} {tape / reference:>7.2f}")
        for (walk_name, anchor_name), (facility_map, sd_m, sd_deg) in surveyed.items():
            # each marker's own sd from the map; the defaults below would apply to a marker without one (none)
            median, posed, total = localization_median_m(flight, facility_map, PoseParams().map_sd_m,
                                                         PoseParams().map_sd_deg)
            label = f"surveyed {walk_name}/{anchor_name}"
            print(f"{flight_name:<7} {label:<18} {sd_m * 1000:>9.1f} {sd_deg:>10.2f} {posed:>5}/{total:<6} "
                  f"{median * 1000:>13.2f} {median / reference:>7.2f}")
            rows.append((flight_name, label, median, reference, tape))
    return rows


def check_runs(walk: Path, truth: FacilityMap, trials: int, seed: int = 5) -> tuple[int, int, int, int, int]:
    """(moves flagged, moves, false alarms on the untouched map, other markers flagged beside a moved one, markers
    judged) over ``trials`` moved-marker maps and the untouched map. A marker seen only with the moved one is
    flagged beside it by design (the images cannot tell which of the two moved): counted apart from false alarms."""
    camera = CameraModel.from_config(yaml.safe_load((walk / "sequence.yaml").read_text())["camera"], str(walk))
    layout = MarkerLayout(parity=truth.parity, dictionary=truth.dictionary)
    footage = collect([walk], camera, map_detector(truth, camera), lambda m: truth.markers[m].size_m
                      if m in truth.markers else None, layout, progress=False)
    kept, seen = keyframes(footage.frames, 3.0), footage.frames_seen()
    untouched = check_markers(kept, truth, camera, seen, CheckParams())
    judged = [c for c in untouched if c.verdict != "unseen"]
    false_alarms = sum(c.verdict == "moved" for c in judged)
    beside_moved = 0
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
        beside_moved += others
        r = results[marker.id]
        found = "       -         -" if r.position_error_m is None else \
            f"{r.position_error_m * 100:>8.2f} {r.angle_error_deg:>9.2f}"
        print(f"{trial:>5} {marker.symbol:<7} {change:<12} {found} {r.verdict:<7} {others:>6}")
    return flagged, trials, false_alarms, beside_moved, len(judged)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="CI smoke run: a short walk, about a minute")
    parser.add_argument("--work", type=work_folder, help="folder for the rendered walks (default: a temporary one)")
    parser.add_argument("--configs", help="comma-separated walk/anchors runs of the full benchmark, e.g. "
                        "640x480/one (default: all)")
    args = parser.parse_args()
    configs = None if not args.configs else {tuple(c.strip().split("/", 1)) for c in args.configs.split(",")}
    known = {(f"{w}x{h}", a) for w, h in ((640, 480), (1280, 720)) for a in ANCHORS}
    if configs and not configs <= known:
        parser.error(f"--configs: unknown {', '.join('/'.join(c) for c in sorted(configs - known))} "
                     f"(known: {', '.join('/'.join(c) for c in sorted(known))})")
    truth = load_map(MAP_PATH)
    print(f"bench_survey: {'quick' if args.quick else 'full'} run on {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.work or temporary)
        if args.quick:
            out = work / "quick-640x480"
            walks = {"640x480": out if (out / "sequence.yaml").exists() else render_walk(out, quick_walk(), (640, 480), 4.0)}
            anchor_sets, flights, trials = QUICK_ANCHORS, {"hover": FLIGHTS["hover"]}, 2
        else:
            walks = {}
            for size in ((640, 480), (1280, 720)):
                name = f"{size[0]}x{size[1]}"
                if configs and not any(walk == name for walk, _ in configs):
                    continue
                out = work / f"hall-{name}"
                walks[name] = out if (out / "sequence.yaml").exists() else render_walk(out, hall_walk(), size, 4.0)
            anchor_sets, flights, trials = ANCHORS, FLIGHTS, 20
        runs = survey_runs(walks, truth, anchor_sets, configs)
        local = localization_runs(flights, truth, runs["maps"])
        check = check_runs(walks["640x480"], truth, trials) if "640x480" in walks else None
    if check:
        flagged, moves, false_alarms, beside_moved, judged = check
        print(f"\nmap check: {flagged}/{moves} moves flagged, {false_alarms} false alarms on the untouched map, "
              f"{beside_moved} other markers flagged beside a moved one ({judged} markers judged per trial)")
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
    if check:
        print(f"  map check: {100 * flagged / max(moves, 1):.0f} % flagged {verdict(flagged >= 0.95 * moves)}, "
              f"{false_alarms} false alarms on the untouched map {verdict(false_alarms == 0)} (beside a moved "
              f"marker {beside_moved} others flagged: a marker seen only with it cannot be told from it)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
