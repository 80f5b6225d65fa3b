"""Where a survey's error comes from: the walk surveyed again with its detections' errors taken apart.

bench_survey's walk (rendered the same way, or reused from ``--work DIR``) is detected once, and every
sighting's points are compared with where the renderer's true camera pose (groundtruth.csv) and the true map
put them. The survey is then run on the detections as they are, and on the true points plus parts of the
detector's error, each against the true map (median / max marker position error, median / max angle error,
and the median left after the best rigid fit):

* ``detected``: the points as the survey sees them (bench_survey's row);
* ``true + noise of the stated sigma``: independent noise as large as the detector says each sighting's is
  (``Sighting.sigma_px``): what the map would be if the errors were only that (one draw of the noise moves a
  one-anchor map's median by a factor of two: the median of ``NOISE_DRAWS`` draws, their range beside it);
* ``detected, <part> taken out``: each sighting's four corners' error split into the affine map of the
  quadrilateral that fits it best (shift, scale, turn, aspect: x against y, shear) and the rest; one part
  removed (from every point of the sighting), the others kept;
* ``true + shift only``: every part but the shift removed.

Each map is also flown: bench_survey's aisle flight localized on it (``aisle_mm``, median position error), the
pose stage told each marker's ``sd`` as the survey wrote it (as bench_survey does), and told the map is exact
(``aisle_exact_mm``: every ``sd`` 0). Above the table, the aisle on the true map, and on the true map told the
detected survey's ``sd``: what the weighing alone costs. (``--quick``: one noise draw, one part taken out (the
aspect), the aisle for the ``detected`` row only: each kind of row once.)

A part whose removal shrinks the error most is what limits the map. The table after it gives each part's size
(RMS over the sightings, px at the corners) and how alike it is in two sightings of one marker some frames
apart (correlation of the sigma-normalised corner errors, shift removed): errors that repeat from frame to
frame do not average out over a walk.

    PYTHONPATH=. python benchmarks/bench_survey_budget.py [--quick] [--work DIR] [--size 640x480]
        [--anchors one|three]
"""
from __future__ import annotations

import argparse
import os
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml
from bench_survey import (ANCHORS, FLIGHTS, MAP_PATH, QUICK_ANCHORS, aligned_errors, anchors_map, hall_walk,
                          localization_median_m, marker_errors, quick_walk, render_walk)
from common import work_folder

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, load_map
from companion.localize import groundtruth, map_detector
from companion.markers.layout import MarkerLayout
from companion.survey import adjust
from companion.survey.observations import Footage, collect
from companion.survey.survey import SurveyOptions, survey_footage

PARTS = ("shift", "scale", "turn", "aspect", "shear")
GAPS = ((1, 2), (2, 5), (5, 20), (20, 10 ** 6))  # frame gaps between two sightings of one marker
NOISE_DRAWS = 3


def true_points(footage: Footage, walk: Path, truth, camera: CameraModel) -> list[list[np.ndarray]]:
    """Per frame, per sighting: (K, 2) where the true camera pose and the true map put its points (px)."""
    T_map_body = groundtruth(walk)
    projected = []
    for frame in footage.frames:
        T_camera_map = camera.T_camera_body @ frames.invert_transform(T_map_body[frame.index])
        projected.append([camera.project_from(T_camera_map @ truth.markers[s.marker_id].T_map_marker,
                                              s.points_marker_m) for s in frame.sightings])
    return projected


def affine_parts(true_px: np.ndarray, error_px: np.ndarray) -> dict[str, np.ndarray]:
    """Each part's (2,) shift or (2, 2) matrix of the affine map that fits a sighting's corner errors best:
    error ~ shift + M (corner - centre), M = scale I + turn [[0, -1], [1, 0]] + aspect diag(1, -1)
    + shear [[0, 1], [1, 0]] (aspect: the width read long against the height, in image axes)."""
    corners = true_px[:4] - true_px[:4].mean(axis=0)
    coefficients, *_ = np.linalg.lstsq(np.column_stack([corners, np.ones(4)]), error_px[:4], rcond=None)
    (a, b), (c, d) = coefficients[:2].T
    return {"shift": coefficients[2],
            "scale": (a + d) / 2 * np.eye(2),
            "turn": (c - b) / 2 * np.array([[0.0, -1.0], [1.0, 0.0]]),
            "aspect": (a - d) / 2 * np.diag([1.0, -1.0]),
            "shear": (b + c) / 2 * np.array([[0.0, 1.0], [1.0, 0.0]])}


def part_px(part: np.ndarray, true_px: np.ndarray) -> np.ndarray:
    """(K, 2) what one part moves each point of the sighting by."""
    if part.shape == (2,):
        return np.broadcast_to(part, true_px.shape)
    return (true_px - true_px[:4].mean(axis=0)) @ part.T


def variant(footage: Footage, projected, how: str, rng: np.random.Generator) -> Footage:
    """The footage with every sighting's points replaced as ``how`` says (see the module's list)."""
    out = []
    for frame, true_frame in zip(footage.frames, projected):
        sightings = []
        for s, true_px in zip(frame.sightings, true_frame):
            error = s.points_px - true_px
            if how == "detected":
                points = s.points_px
            elif how == "noise":
                points = true_px + rng.normal(0.0, s.sigma_px or 0.1, true_px.shape)
            else:
                parts = affine_parts(true_px, error)
                if how == "shift only":
                    points = true_px + part_px(parts["shift"], true_px)
                else:
                    points = s.points_px - part_px(parts[how], true_px)
            sightings.append(replace(s, points_px=np.asarray(points, dtype=float)))
        out.append(replace(frame, sightings=tuple(sightings)))
    return replace(footage, frames=tuple(out))


def errors(footage: Footage, camera: CameraModel, anchor_map, truth, anchors) -> tuple:
    """The footage surveyed against the true map: position median, max (m), angle median, max (deg), median
    position error after the best rigid fit (m), and the surveyed map."""
    result = survey_footage(footage, camera, anchor_map, SurveyOptions())
    position, angle, _ = marker_errors(result.facility_map, truth, anchors)
    rigid = aligned_errors(result.facility_map, truth, anchors)["rigid"]
    return (float(np.median(position)), float(position.max()), float(np.median(angle)), float(angle.max()),
            float(np.median(rigid)), result.facility_map)


def with_sd(facility_map: FacilityMap, sd_of) -> FacilityMap:
    """The map with each marker's ``sd`` (position m, angle deg) replaced by ``sd_of(marker)``."""
    markers = {}
    for marker_id, marker in facility_map.markers.items():
        sd_position_m, sd_angle_deg = sd_of(marker)
        markers[marker_id] = replace(marker, sd_position_m=sd_position_m, sd_angle_deg=sd_angle_deg)
    return replace(facility_map, markers=markers)


def aisle_mm(facility_map: FacilityMap) -> float:
    """Median position error (mm) of the aisle flight localized on the map, each marker weighed by its ``sd``
    (a marker without one: exact)."""
    return localization_median_m(FLIGHTS["aisle"], facility_map, 0.0, 0.0)[0] * 1000


def mode_vectors(corners_px: np.ndarray) -> np.ndarray:
    """(6, 8) unit vectors over four corners' (x, y) errors: shift x, shift y, then the PARTS' matrices
    applied to the corners, the aspect's the adjustment's own (``adjust.aspect_modes``)."""
    centred = corners_px - corners_px.mean(axis=0)
    x, y = centred[:, 0], centred[:, 1]
    vectors = [np.tile([1.0, 0.0], 4), np.tile([0.0, 1.0], 4), np.column_stack([x, y]).ravel(),
               np.column_stack([-y, x]).ravel(), adjust.aspect_modes(corners_px[None])[0],
               np.column_stack([y, x]).ravel()]
    return np.array([v / np.linalg.norm(v) for v in vectors])


def error_sizes(footage: Footage, projected) -> tuple[dict[str, float], dict[str, float], list[tuple[int, float]]]:
    """Over the square-path sightings: each part's RMS at the corners (px); each part's variance in units of
    its sighting's stated noise (the corners' error along the part's unit mode over sigma, squared: 1 where
    the stated noise is right and alike for every mode); and per frame gap (GAPS) the number of same-marker
    sighting pairs and the correlation of their sigma-normalised corner errors (shift removed)."""
    moved = {part: [] for part in PARTS}
    along = {part: [] for part in PARTS}
    shapes: dict[int, list[tuple[int, np.ndarray]]] = {}
    for frame, true_frame in zip(footage.frames, projected):
        for s, true_px in zip(frame.sightings, true_frame):
            if s.path != "square" or not s.sigma_px:
                continue
            error = s.points_px - true_px
            parts = affine_parts(true_px, error)
            for part in PARTS:
                moved[part].append(part_px(parts[part], true_px[:4]))
            in_sd = error[:4].ravel() / s.sigma_px
            # the two shift modes together count for "shift" (variance per mode)
            projections = mode_vectors(s.points_px[:4]) @ in_sd
            along["shift"].extend(projections[:2])
            for part, value in zip(PARTS[1:], projections[2:]):
                along[part].append(value)
            shape = (error[:4] - parts["shift"]).ravel() / s.sigma_px
            shapes.setdefault(s.marker_id, []).append((frame.index, shape))
    sizes = {part: float(np.sqrt(np.mean(np.square(moved[part])))) for part in PARTS}
    variances = {part: float(np.mean(np.square(along[part]))) for part in PARTS}
    correlations = []
    for low, high in GAPS:
        first, second = [], []
        for sightings in shapes.values():
            for i, (index, shape) in enumerate(sightings):
                for later_index, later in sightings[i + 1:]:
                    if later_index - index >= high:
                        break
                    if later_index - index >= low:
                        first.append(shape)
                        second.append(later)
        a, b = np.array(first), np.array(second)
        correlation = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b))) if len(a) else np.nan
        correlations.append((len(a), correlation))
    return sizes, variances, correlations


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="CI smoke run: bench_survey's short walk, a minute")
    parser.add_argument("--work", type=work_folder,
                        help="folder of bench_survey's rendered walks, reused (default: a temporary one)")
    parser.add_argument("--size", default="640x480", choices=("640x480", "1280x720"), help="which walk")
    parser.add_argument("--anchors", default="one", choices=sorted(ANCHORS), help="bench_survey's anchor set")
    args = parser.parse_args()
    truth = load_map(MAP_PATH)
    print(f"bench_survey_budget: {'quick' if args.quick else 'full'} run on {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.work or temporary)
        size = (640, 480) if args.quick else tuple(int(v) for v in args.size.split("x"))
        walk = work / ("quick-640x480" if args.quick else f"hall-{args.size}")
        if not (walk / "sequence.yaml").exists():
            render_walk(walk, quick_walk() if args.quick else hall_walk(), size, 4.0)
        anchors = QUICK_ANCHORS["three"] if args.quick else ANCHORS[args.anchors]
        camera = CameraModel.from_config(yaml.safe_load((walk / "sequence.yaml").read_text())["camera"], str(walk))
        anchor_map = anchors_map(truth, anchors)
        footage = collect([walk], camera, map_detector(anchor_map, camera), lambda m: truth.markers[m].size_m,
                          MarkerLayout(parity=truth.parity, dictionary=truth.dictionary), progress=False)
        projected = true_points(footage, walk, truth, camera)
        print(f"\nwalk {walk.name}, anchors {','.join(anchors)}: {footage.frame_count} frames, "
              f"{sum(len(f.sightings) for f in footage.frames)} sightings")
        true_aisle = aisle_mm(truth)
        print(f"\n{'points surveyed':<34} {'pos_med_mm':>10} {'pos_max_mm':>10} {'ang_med_deg':>11} "
              f"{'ang_max_deg':>11} {'rigid_med_mm':>12} {'vs_detected':>11} {'aisle_mm':>8} {'aisle_exact_mm':>14}")
        rows = [("detected", "detected"), ("noise", "true + noise of the stated sigma")]
        rows += [(part, f"detected, {part} taken out") for part in (("aspect",) if args.quick else PARTS)]
        rows += [("shift only", "true + shift only")]
        reference = detected_map = None
        for how, label in rows:
            draws = [errors(variant(footage, projected, how, np.random.default_rng(seed)), camera, anchor_map,
                            truth, anchors) for seed in range(NOISE_DRAWS if how == "noise" and not args.quick else 1)]
            medians = [d[0] for d in draws]
            median, worst, angle_median, angle_max, rigid, surveyed = sorted(draws, key=lambda d: d[0])[len(draws) // 2]
            reference = reference or median
            if detected_map is None:
                detected_map = surveyed
            flown = how == "detected" or not args.quick
            aisle = f"{aisle_mm(surveyed):>8.2f} {aisle_mm(with_sd(surveyed, lambda m: (0.0, 0.0))):>14.2f}" \
                if flown else f"{'-':>8} {'-':>14}"
            spread = f"  (draws {min(medians) * 1000:.2f}-{max(medians) * 1000:.2f})" if len(draws) > 1 else ""
            print(f"{label:<34} {median * 1000:>10.2f} {worst * 1000:>10.2f} {angle_median:>11.3f} "
                  f"{angle_max:>11.3f} {rigid * 1000:>12.2f} {median / reference:>11.2f} {aisle}{spread}", flush=True)
        told = aisle_mm(with_sd(truth, lambda m: (detected_map.markers[m.id].sd_position_m,
                                                   detected_map.markers[m.id].sd_angle_deg)
                                if m.id in detected_map.markers else (None, None)))
        print(f"\naisle flight on the true map: {true_aisle:.2f} mm told it is exact; {told:.2f} mm told the "
              f"detected survey's sd of each marker it maps (the weighing alone)")
        sizes, variances, correlations = error_sizes(footage, projected)
        print("\nthe detector's corner error, square-path sightings, by part (RMS at the corners, px): "
              + ", ".join(f"{part} {sizes[part]:.4f}" for part in PARTS))
        print("its variance along each part's mode in units of the stated noise (ASPECT_VARIANCE_FACTOR "
              f"{adjust.ASPECT_VARIANCE_FACTOR:g} is the aspect's): "
              + ", ".join(f"{part} {variances[part]:.2f}" for part in PARTS))
        print("alike in two sightings of one marker (correlation of the sigma-normalised corner errors, shift "
              "removed), by frames apart: "
              + ", ".join(f"{low}{'+' if high > 10 ** 5 else f'-{high - 1}'}: {c:.2f} ({n} pairs)"
                          for (low, high), (n, c) in zip(GAPS, correlations)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
