"""Map check: does each marker still hang where the map says?

For every mapped marker seen in a walk-through, its pose is estimated from
the others alone: a bundle adjustment over the frames that show it together
with other mapped markers, the cameras and this one marker free, the others
held at their map poses: exactly where their entry states no ``sd`` (or
0), within it where it does (a surveyed map), so that their error reaches
the estimate. The estimate's covariance (cameras marginalised out) plus
the marker's own stated ``sd`` gives the uncertainty of the comparison; the
marker has ``moved`` when its position or orientation differs from the map
by more than ``sigmas`` standard deviations along the difference, and by
more than a floor that stands for the error of a map that states none
(``min_position_m``, ``min_angle_deg``).
A moved marker is no reference for the others: the check runs again without
the worst of them for the markers that shared a frame with it, and so on
until no new marker is moved.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap
from companion.markers.layout import MarkerLayout
from companion.progress import progress_bar
from companion.survey import graph
from companion.survey.adjust import BundleAdjustment, Priors
from companion.survey.observations import SurveyError, SurveyFrame, collect, keyframes

VERDICTS = ("ok", "moved", "unseen")
# a reference held to an sd of 0 in one of its two parts (the map states only the other): held this closely
MIN_SD_M = 1e-5
MIN_SD_RAD = math.radians(1e-3)


@dataclass(frozen=True)
class CheckParams:
    """When a marker counts as moved.

    sigmas: the difference must exceed this many standard deviations (along the difference);
    min_position_m, min_angle_deg: and these floors (the map's own error);
    max_frames: frames used per marker at most (evenly spread over those that show it).
    """

    sigmas: float = 3.0
    min_position_m: float = 0.02
    min_angle_deg: float = 1.5
    max_frames: int = 60
    sigma_px: float = 0.5


@dataclass(frozen=True)
class MarkerCheck:
    """One mapped marker against its map entry.

    frames: frames it was decoded in; errors: None when unseen. T_map_marker: the estimate (None when unseen).
    position_limit_m, angle_limit_deg: the thresholds it was held to.
    """

    symbol: str
    marker_id: int
    frames: int
    position_error_m: float | None
    angle_error_deg: float | None
    verdict: str
    T_map_marker: np.ndarray | None = None
    position_limit_m: float | None = None
    angle_limit_deg: float | None = None

    def as_json(self) -> dict:
        def rounded(value, digits):
            return None if value is None else round(value, digits)
        return {"symbol": self.symbol, "frames": self.frames, "position_error_m": rounded(self.position_error_m, 5),
                "angle_error_deg": rounded(self.angle_error_deg, 4), "verdict": self.verdict}


def check_markers(survey_frames: list[SurveyFrame], facility_map: FacilityMap, camera: CameraModel,
                  frames_seen: dict[int, int], params: CheckParams = CheckParams(),
                  on_checked: Callable[[], None] | None = None) -> list[MarkerCheck]:
    """A MarkerCheck for every marker of the map (in map order), from frames of mapped markers only.

    on_checked: called after each marker's estimate (a progress bar's step).
    """
    mapped = {m: marker.T_map_marker for m, marker in facility_map.markers.items()}
    shown = [_only_mapped(f, mapped) for f in survey_frames]
    shown = [f for f in shown if len(f.sightings) >= 2]
    def check(m: int, excluded: set[int]) -> MarkerCheck:
        result = _check_one(m, shown, mapped, excluded, camera, frames_seen, facility_map, params)
        if on_checked is not None:
            on_checked()
        return result

    results = {m: check(m, set()) for m in mapped}
    excluded: set[int] = set()
    while True:
        # the worst moved marker first: when two markers disagree only with each other, both look moved
        candidates = [r for m, r in results.items() if r.verdict == "moved" and m not in excluded]
        if not candidates:
            break
        worst = max(candidates, key=_excess).marker_id
        excluded.add(worst)
        # only the markers that shared a frame with it change
        affected = {m for f in shown if worst in f.marker_ids for m in f.marker_ids} - {worst}
        for m in affected:
            again = check(m, excluded - {m})
            # left with no reference but the one it disagreed with: which of the two moved, the images cannot
            # tell; it stays moved (dropped as unseen, the one that did move went unreported half the time)
            if not (again.verdict == "unseen" and results[m].verdict == "moved"):
                results[m] = again
    return [results[m] for m in facility_map.markers]


def _excess(check: MarkerCheck) -> float:
    """How far beyond its limits a marker's disagreement is (the larger ratio)."""
    return max(check.position_error_m / check.position_limit_m, check.angle_error_deg / check.angle_limit_deg)


def _only_mapped(frame: SurveyFrame, mapped) -> SurveyFrame:
    return SurveyFrame(frame.walk, frame.index, frame.t_ns, tuple(s for s in frame.sightings if s.marker_id in mapped))


def _check_one(marker_id: int, shown, mapped, excluded: set[int], camera: CameraModel, frames_seen,
               facility_map: FacilityMap, params: CheckParams) -> MarkerCheck:
    symbol = facility_map.markers[marker_id].symbol
    references = {m: T for m, T in mapped.items() if m != marker_id and m not in excluded}
    unseen = MarkerCheck(symbol, marker_id, frames_seen.get(marker_id, 0), None, None, "unseen")
    usable = []
    for frame in shown:
        if marker_id in frame.marker_ids:
            kept = tuple(s for s in frame.sightings if s.marker_id == marker_id or s.marker_id in references)
            if len(kept) >= 2:
                usable.append(SurveyFrame(frame.walk, frame.index, frame.t_ns, kept))
    if not usable:
        return unseen
    usable = _spread(usable, params.max_frames)
    ippe = graph.IppeCache(camera)
    start = graph.consensus_pose(marker_id, usable, references, camera, ippe)
    known = {**references, marker_id: start}
    cameras = np.array([graph.camera_pose_candidates(f, known, camera, ippe)[0] for f in usable])
    used_ids = {m for f in usable for m in f.marker_ids}
    # references whose map entry states an uncertainty move within it: their error reaches the estimate
    map_sd = {m: _map_sd(facility_map, m) for m in used_ids}
    soft = {m: sd for m, sd in map_sd.items() if m != marker_id and max(sd) > 0}
    priors = Priors(soft_anchors={m: known[m] for m in soft},
                    anchor_sd={m: (max(sd_m, MIN_SD_M), max(sd_rad, MIN_SD_RAD)) for m, (sd_m, sd_rad) in soft.items()})
    problem = BundleAdjustment(usable, camera, {m: known[m] for m in used_ids}, cameras, [marker_id, *soft],
                               priors=priors, noise_px=params.sigma_px)
    adjustment = problem.solve(max_iterations=30)
    T_estimate = adjustment.markers[marker_id]
    T_map = mapped[marker_id]
    # the comparison's uncertainty: the estimate's and the map entry's own (independent)
    sd_m, sd_rad = map_sd[marker_id]
    covariance = adjustment.covariance[marker_id] + np.diag([sd_m ** 2] * 3 + [sd_rad ** 2] * 3)
    position_error = T_estimate[:3, 3] - T_map[:3, 3]
    angle_error = frames.rotvec_from_rotation(T_estimate[:3, :3] @ T_map[:3, :3].T)
    position_limit = max(params.sigmas * _sd_along(covariance[:3, :3], position_error), params.min_position_m)
    angle_limit = max(params.sigmas * math.degrees(_sd_along(covariance[3:, 3:], angle_error)), params.min_angle_deg)
    position_m = float(np.linalg.norm(position_error))
    angle_deg = math.degrees(float(np.linalg.norm(angle_error)))
    verdict = "moved" if position_m > position_limit or angle_deg > angle_limit else "ok"
    return MarkerCheck(symbol, marker_id, frames_seen.get(marker_id, 0), position_m, angle_deg, verdict, T_estimate,
                       position_limit, angle_limit)


def _map_sd(facility_map: FacilityMap, marker_id: int) -> tuple[float, float]:
    """(position m, angle rad) the map entry states for its pose (``sd``); 0 where it says nothing."""
    marker = facility_map.markers[marker_id]
    return marker.sd_position_m or 0.0, math.radians(marker.sd_angle_deg or 0.0)


def _sd_along(covariance: np.ndarray, direction: np.ndarray) -> float:
    """Standard deviation along ``direction`` (sqrt(u^T C u), u the unit direction); the largest if it is zero."""
    norm = float(np.linalg.norm(direction))
    if norm == 0.0:
        return math.sqrt(max(float(np.linalg.eigvalsh(covariance)[-1]), 0.0))
    u = direction / norm
    return math.sqrt(max(float(u @ covariance @ u), 0.0))


def _spread(items: list, count: int) -> list:
    """At most ``count`` items, evenly spread over the list."""
    if len(items) <= count:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def check_map(sequences: list[Path], facility_map: FacilityMap, camera: CameraModel, params: CheckParams = CheckParams(),
              fps: float | None = None, min_motion_px: float = 3.0, progress: bool = False) -> list[MarkerCheck]:
    """Replay walk-throughs against a map: a MarkerCheck per map marker (markers not in the map are ignored)."""
    from companion.localize import map_detector

    layout = MarkerLayout(parity=facility_map.parity, dictionary=facility_map.dictionary)
    detector = map_detector(facility_map, camera)

    def size_m(marker_id: int) -> float | None:
        marker = facility_map.markers.get(marker_id)
        return None if marker is None else marker.size_m

    footage = collect(sequences, camera, detector, size_m, layout, fps, progress)
    if not footage.frames:
        raise SurveyError(f"no marker of {facility_map.path} in the footage ({footage.frame_count} frames read)")
    with progress_bar(len(facility_map.markers), "marker", progress, "checking") as bar:
        return check_markers(keyframes(footage.frames, min_motion_px), facility_map, camera, footage.frames_seen(),
                             params, on_checked=lambda: bar.update(1))
