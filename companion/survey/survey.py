"""``survey(...)``: a facility map from walk-through footage and a few anchors.

    detections (companion.survey.observations) -> keyframes -> marker groups and first poses
    (companion.survey.graph) -> bundle adjustment (companion.survey.adjust), bad sightings out,
    adjusted again -> a FacilityMap with each marker's uncertainty

A marker placed through frames of one standpoint only (a small, far marker:
its two IPPE poses fit every one of those frames) has a rival placement
(``graph.Rival``); each plausible rival grows a map of its own, adjusted like
the first, and the better fit is kept. When the other fits nearly as well
(its chi-square within ``RIVAL_CHI2``, the link's frames weighed as one view),
the markers it places elsewhere are weakly linked: their reported sd covers
both places, and the map's note, the report and the CLI say they need another look.

Anchors are markers whose poses were measured (the anchors file, or every
marker of an existing map with ``extend``); they keep their poses and fix the
map frame. With several anchors they are first held softly (to within their
stated ``anchor_sd_m`` / ``anchor_sd_deg``) to test that they agree with each
other; then they are held exactly. Markers seen in fewer than ``min_frames``
frames are not mapped. Bad input raises ``SurveyError``, never a partial map.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, MapMarker
from companion.markers.layout import MarkerLayout
from companion.survey import graph
from companion.survey.adjust import Adjustment, BundleAdjustment, Priors
from companion.survey.check import CheckParams, MarkerCheck, check_markers
from companion.survey.observations import POINT_KINDS, Footage, SurveyError, SurveyFrame, collect, keyframes

GATE_PROBABILITY = 0.999   # a sighting whose errors fail this chi-square test at the fitted noise is left out
MIN_POINTS_FOR_NOISE = 40  # a kind of point needs this many to measure its noise
MIN_NOISE_PX = 0.005       # no kind of point is trusted beyond this (rendering and rounding)
RIVAL_CHI2 = 25.0          # a rival placement whose adjustment fits worse by less than this is not ruled out
MAX_RIVALS = 6             # rival placements adjusted (each costs an adjustment)
# a surveyed marker placed no better than this is no better than a tape: named for another look
LOOSE_SD_M = 0.05
# The images fit one map to about the noise the detector states for its square-path corners when the anchors
# file and the camera are right: 0.66-0.96 times it on bench_survey's walks and on the walks of docs/survey.md
# ("When the images do not fit"). A marker of another size than stated, or one taken to hang on a vertical wall
# that tilts, bends the map to fit it (tens of centimetres at 10 m, each marker's sd still saying millimetres) and
# leaves 3.9-45 times it. So does a camera calibration that is off (k1 off by 0.02: 6.7 times, the map 8 cm off),
# which the anchors file cannot fix: hence a warning naming every cause, with the map written.
MAX_CORNER_MISFIT = 3.0
WORST_NAMED = 4            # the markers that fit worst, named when the images do not fit one map


@dataclass(frozen=True)
class SurveyOptions:
    """How to survey.

    size_m: inner-square side of markers with no other stated size.
    fps: frame rate of a video or image folder without timestamps.
    min_motion_px: a frame is kept when its markers moved this much (median corner) since the last kept one.
    min_frames: markers seen in fewer frames are not mapped.
    sigma_px: expected detector noise of a point (x and y), the unit of the residuals.
    max_iterations: of each bundle adjustment.
    """

    size_m: float | None = None
    fps: float | None = None
    min_motion_px: float = 3.0
    min_frames: int = 3
    sigma_px: float = 0.5
    max_iterations: int = 60
    progress: bool = False


@dataclass(frozen=True)
class SurveyedMarker:
    """One marker of the result.

    anchor: held at its given pose (no uncertainty then); frames: frames it was decoded in;
    sd_position_m, sd_angle_deg: one standard deviation along the worst axis (0 for an anchor: its map entry
        carries its stated sd), the noise's and the detector's systematic error's (``adjust.SYSTEMATIC_POINT_PX``);
        written into the map as the marker's ``sd`` for the pose stage;
    covariance: (6, 6) [position m, small rotation rad] on map axes (None for an anchor);
    rms_px: RMS point reprojection error over its sightings.
    weakly_linked: the images also fit another place for it nearly as well (a rival placement, see
        ``graph.Rival``): the sd covers both places, and it needs another look.
    """

    marker: MapMarker
    anchor: bool
    frames: int
    sd_position_m: float
    sd_angle_deg: float
    rms_px: float
    covariance: np.ndarray | None
    weakly_linked: bool = False


@dataclass(frozen=True)
class AnchorAgreement:
    """How far the images move an anchor from its stated pose when all anchors are held only softly.

    tied: the images tie it to another anchor (some frames link their markers); if not, nothing checks it
    against the others and it moves by nothing.
    """

    symbol: str
    position_m: float
    angle_deg: float
    chi2: float
    tied: bool


@dataclass(frozen=True)
class SurveyResult:
    """The map and how it was made.

    markers: every marker of ``facility_map`` with its statistics; dropped: symbol -> frames for markers
    seen too rarely; anchors: agreement of several anchors (empty for one); moved: markers of an existing
    map that disagreed with it (``extend``); camera_path_m: (N, 3) camera positions of the adjusted frames.
    sigma_px: RMS point error of the adjustment; noise_px: the noise of each kind of point it measured (the
    weights of the points), by ``POINT_KINDS`` name. corner_misfit: ``corner_misfit`` of the adjustment;
    worst_fitting: the ``WORST_NAMED`` markers with the largest RMS point error, (symbol, px, on a vertical wall).
    """

    facility_map: FacilityMap
    markers: list[SurveyedMarker]
    dropped: dict[str, int]
    anchors: list[AnchorAgreement]
    moved: list[MarkerCheck]
    camera_path_m: np.ndarray
    frames_read: int
    frames_skipped: int
    frames_adjusted: int
    sigma_px: float
    noise_px: dict[str, float]
    corner_misfit: float = math.nan
    worst_fitting: tuple[tuple[str, float, bool], ...] = ()

    @property
    def misfit(self) -> bool:
        """The images do not fit one map (``MAX_CORNER_MISFIT``): the anchors file or the camera is not as stated."""
        return self.corner_misfit > MAX_CORNER_MISFIT

    @property
    def loose(self) -> list[SurveyedMarker]:
        """Surveyed markers placed no better than ``LOOSE_SD_M`` without a rival place to blame (the images
        barely tie them to the rest: seen from too few places, or only far away); they need another look."""
        return [s for s in self.markers if not s.anchor and not s.weakly_linked and placed_loosely(s.sd_position_m)]


def placed_loosely(sd_position_m: float) -> bool:
    """An sd over ``LOOSE_SD_M`` (or not a number): the marker needs another look."""
    return not sd_position_m <= LOOSE_SD_M


def survey(sequences: list[Path], camera: CameraModel, anchors: FacilityMap, options: SurveyOptions = SurveyOptions(),
           extend: bool = False, detector=None) -> SurveyResult:
    """Map every marker seen in the footage; ``anchors`` is the anchors file, or the existing map with ``extend``."""
    layout = MarkerLayout(parity=anchors.parity, dictionary=anchors.dictionary)
    if detector is None:
        from companion.localize import map_detector

        detector = map_detector(anchors, camera)
    sizes = _Sizes(anchors, options.size_m, layout)
    footage = collect(sequences, camera, detector, sizes, layout, options.fps, options.progress)
    return survey_footage(footage, camera, anchors, options, extend, sizes)


def survey_footage(footage: Footage, camera: CameraModel, anchors: FacilityMap, options: SurveyOptions,
                   extend: bool = False, sizes=None) -> SurveyResult:
    """The survey from already detected footage (see ``survey``)."""
    sizes = sizes or _Sizes(anchors, options.size_m, MarkerLayout(parity=anchors.parity, dictionary=anchors.dictionary))
    symbols = sizes.symbols
    counts = footage.frames_seen()
    if not counts:
        raise SurveyError(f"no markers in the footage ({footage.frame_count} frames read): check the dictionary "
                          f"({anchors.dictionary}) and parity ({anchors.parity}) of {anchors.path}, the focus and the light")
    if not set(counts) & set(anchors.markers):
        raise SurveyError(f"no anchor of {anchors.path} ({_names(anchors.markers, symbols)}) is seen in the footage; "
                          f"markers seen: {_names(counts, symbols)}")
    dropped = {m: n for m, n in counts.items() if n < options.min_frames and m not in anchors.markers}
    mapped_ids = set(counts) - set(dropped)
    kept = [_without(f, set(dropped)) for f in keyframes(footage.frames, options.min_motion_px)]
    shared = [f for f in kept if len(f.sightings) >= 2]
    groups = _check_groups(shared, mapped_ids, anchors, symbols, footage)

    moved: list[MarkerCheck] = []
    fixed = {m: marker.T_map_marker for m, marker in anchors.markers.items() if m in mapped_ids}
    if extend:
        moved = [c for c in check_markers(shared, anchors, camera, counts, CheckParams(sigma_px=options.sigma_px))
                 if c.verdict == "moved"]
        for check in moved:
            del fixed[check.marker_id]
    initial, rivals = graph.grow(shared, fixed, camera)
    free_ids = sorted(m for m in initial if m not in fixed)
    priors = _priors(free_ids, anchors, symbols)
    # a placement the images cannot decide by itself (graph.Rival): each rival grows its own map, adjusted too
    tried = _plausible_rivals(rivals, priors)
    starts = [initial] + [graph.grow(shared, fixed, camera, placed={m: rival.T_map_marker})[0] for m, rival in tried]
    for start in starts:
        for check in moved:  # start from where the check found it
            start[check.marker_id] = check.T_map_marker
    firsts = [_first_adjustment(shared, camera, start, free_ids, priors, options) for start in starts]
    best = min(range(len(firsts)), key=lambda k: firsts[k][0].cost)
    adjustment, posed_frames = _adjust_again(*firsts[best], camera, free_ids, priors, options)
    # the rival of start k > 0 is tried[k - 1]; start 0 against the winning rival differs by that rival's link
    link_frames = [rival.support for _, rival in tried]
    weak = _weak_links(adjustment, firsts[best][0],
                       [(a, link_frames[(k or best) - 1], _placed_apart(starts[best], starts[k]))
                        for k, (a, _) in enumerate(firsts) if k != best])
    agreement: list[AnchorAgreement] = []
    if len(fixed) >= 2 and not extend:
        agreement = _anchor_agreement(shared, camera, fixed, groups, counts, anchors, symbols, options,
                                      _noise(adjustment, options))
    markers = _result_markers(adjustment, posed_frames, fixed, anchors, counts, sizes, priors.on_wall, weak, extend)
    facility_map = replace(anchors, path="", markers={s.marker.id: s.marker for s in markers})
    if extend:  # the existing map's markers not seen this time stay as they were
        facility_map = replace(facility_map, markers={**anchors.markers, **facility_map.markers})
        markers += [SurveyedMarker(m, True, 0, 0.0, 0.0, math.nan, None) for i, m in anchors.markers.items()
                    if i not in initial]
    camera_path = np.array([frames.invert_transform(T)[:3, 3] for T in adjustment.cameras])
    return SurveyResult(facility_map, sorted(markers, key=lambda s: s.marker.id),
                        {symbols[m]: n for m, n in sorted(dropped.items())}, agreement, moved, camera_path,
                        footage.frame_count, footage.skipped, len(posed_frames), adjustment.sigma_px,
                        _noise(adjustment, options), corner_misfit(adjustment, posed_frames),
                        _worst_fitting(markers, priors.on_wall))


# ------------------------------------------------------------------ sizes

class _Sizes:
    """The inner-square side of every marker id: the map's entry, the survey section's sizes_m,
    --size-m, the map's default_size_m, in that order; symbols by id."""

    def __init__(self, anchors: FacilityMap, size_m: float | None, layout: MarkerLayout):
        self.anchors, self.size_m = anchors, size_m
        self.symbols = list(layout.dictionary.symbols)

    def __call__(self, marker_id: int) -> float:
        if marker_id in self.anchors.markers:
            return self.anchors.markers[marker_id].size_m
        symbol = self.symbols[marker_id]
        size = self.anchors.survey.sizes_m.get(symbol, self.size_m or self.anchors.default_size_m)
        if size is None:
            raise SurveyError(f"marker {symbol} is seen but its size is unknown: give --size-m, default_size_m or "
                              f"survey.sizes_m in {self.anchors.path}")
        return size


# ------------------------------------------------------------------ steps

def _names(ids, symbols) -> str:
    return ", ".join(symbols[m] for m in sorted(ids))


def _without(frame: SurveyFrame, ids: set[int]) -> SurveyFrame:
    return SurveyFrame(frame.walk, frame.index, frame.t_ns, tuple(s for s in frame.sightings if s.marker_id not in ids))


def _check_groups(shared, mapped_ids: set[int], anchors: FacilityMap, symbols, footage: Footage) -> list[set[int]]:
    """The groups of markers seen together; each must hold an anchor, else SurveyError names the groups and the
    markers that need a shared view (those seen closest in time across the gap)."""
    groups = graph.marker_groups(shared, mapped_ids)
    anchored = [g for g in groups if g & set(anchors.markers)]
    loose = [g for g in groups if not g & set(anchors.markers)]
    if not loose:
        return groups
    text = "; ".join("{" + _names(g, symbols) + "}" for g in groups)
    hints = [_bridge(footage, set().union(*anchored), g, symbols) for g in loose]
    raise SurveyError(f"the markers fall into {len(groups)} groups never seen together: {text}. No anchor is in "
                      f"{', '.join('{' + _names(g, symbols) + '}' for g in loose)}: walk so that these markers share a "
                      f"view with the anchored ones, e.g. {'; '.join(hints)}")


def _bridge(footage: Footage, anchored: set[int], group: set[int], symbols) -> str:
    """The anchored marker and the group's marker seen closest in time in one walk, as advice."""
    best = None
    last_seen: dict[int, tuple[int, int]] = {}  # walk -> (t_ns, marker) of the latest anchored sighting
    last_group: dict[int, tuple[int, int]] = {}
    for frame in footage.frames:
        for m in frame.marker_ids:
            mine, other = (last_seen, last_group) if m in anchored else (last_group, last_seen) if m in group else (None, None)
            if mine is None:
                continue
            mine[frame.walk] = (frame.t_ns, m)
            if frame.walk in other:
                gap = frame.t_ns - other[frame.walk][0]
                pair = (m, other[frame.walk][1])
                if best is None or gap < best[0]:
                    best = (gap, pair)
    if best is None:
        return f"{symbols[min(group)]} together with an anchored marker"
    a, b = best[1]
    return f"{symbols[a]} and {symbols[b]} (seen {best[0] / 1e9:.1f} s apart)"


def _posed(shared, known: dict[int, np.ndarray], camera: CameraModel) -> tuple[list[SurveyFrame], np.ndarray]:
    """The frames whose camera pose two or more known markers agree on, with only those markers, and the poses."""
    ippe = graph.IppeCache(camera)
    posed, cameras = [], []
    for frame in shared:
        found = graph.frame_pose(frame, known, camera, ippe)
        if found is None:
            continue
        T_camera_map, agreeing = found
        posed.append(SurveyFrame(frame.walk, frame.index, frame.t_ns,
                                 tuple(s for s in frame.sightings if s.marker_id in agreeing)))
        cameras.append(T_camera_map)
    if not posed:
        raise SurveyError("no frame shows two markers whose poses agree: walk so that two or more markers are in view")
    return posed, np.array(cameras)


def _priors(free_ids, anchors: FacilityMap, symbols) -> Priors:
    on_wall = frozenset(m for m in free_ids if anchors.survey.on_wall(symbols[m]))
    return Priors(on_wall=on_wall, wall_sd_rad=math.radians(anchors.survey.wall_sd_deg))


def _anchor_agreement(shared, camera, fixed: dict[int, np.ndarray], groups, counts, anchors: FacilityMap, symbols,
                      options: SurveyOptions, noise_px: dict[str, float]) -> list[AnchorAgreement]:
    """How far the images move each anchor when all are held softly (to within their stated uncertainty);
    SurveyError when they disagree beyond it (a chi-square test over all of them).

    The map is first grown from one anchor per group (the most seen), so that the images, not the other
    anchors, place each anchor to begin with: a badly measured anchor then pulls against the images. Such a
    map can start far off where an anchor is reached through a long chain or one small sighting (first poses
    are single-frame poses), and the adjustment then stops in a wrong minimum: a disagreement found from it
    is checked again from the map grown from every anchor as stated, and reported only if found there too.
    """
    references = {}
    for group in groups:
        in_group = [m for m in fixed if m in group]
        if in_group:
            best = max(in_group, key=lambda m: counts.get(m, 0))
            references[best] = fixed[best]
    hints = anchors.survey
    limit = float(chi2.ppf(GATE_PROBABILITY, 6 * (len(fixed) - len(references))))
    # an anchor is tied to the others where a group of markers seen together holds another anchor too
    tied = {m for group in groups if len(group & set(fixed)) >= 2 for m in group & set(fixed)}
    agreement = _anchors_moved(shared, camera, fixed, references, tied, anchors, symbols, options, noise_px)
    if sum(a.chi2 for a in _judged(agreement)) > limit and len(references) < len(fixed):
        agreement = _anchors_moved(shared, camera, fixed, fixed, tied, anchors, symbols, options, noise_px)
    tested = _judged(agreement)
    if sum(a.chi2 for a in tested) > limit:
        worst = max(tested, key=lambda a: a.chi2)
        detail = ", ".join(f"{a.symbol} {a.position_m * 1000:.0f} mm {a.angle_deg:.1f} deg" for a in tested)
        raise SurveyError(f"the anchors of {anchors.path} disagree beyond their stated uncertainty "
                          f"({hints.anchor_sd_m * 1000:g} mm, {hints.anchor_sd_deg:g} deg): the images move them by "
                          f"{detail}; measure {worst.symbol} again (or state a larger survey.anchor_sd_m/anchor_sd_deg)")
    return agreement


def _judged(agreement: list[AnchorAgreement]) -> list[AnchorAgreement]:
    """The anchors the test judges: those the images tie to another (an anchor alone in its group of markers is
    checked by nothing; where its group is barely tied together the adjustment may still move it)."""
    return [a for a in agreement if a.tied]


def _anchors_moved(shared, camera, fixed: dict[int, np.ndarray], references: dict[int, np.ndarray], tied: set[int],
                   anchors: FacilityMap, symbols, options: SurveyOptions, noise_px) -> list[AnchorAgreement]:
    """How far the images move each anchor, every anchor held softly, adjusted from the map grown from
    ``references`` (``tied``: the anchors the images tie to another)."""
    start = graph.initial_poses(shared, references, camera)
    posed_frames, cameras = _posed(shared, start, camera)
    hints = anchors.survey
    free_ids = sorted(start)
    soft = replace(_priors(free_ids, anchors, symbols), soft_anchors=dict(fixed), anchor_sd_m=hints.anchor_sd_m,
                   anchor_sd_rad=math.radians(hints.anchor_sd_deg))
    problem = BundleAdjustment(posed_frames, camera, start, cameras, free_ids, soft, noise_px)
    adjustment = problem.solve(options.max_iterations, options.progress, "checking the anchors")
    agreement = []
    for m, T_stated in sorted(fixed.items()):
        T = adjustment.markers[m]
        position_m = float(np.linalg.norm(T[:3, 3] - T_stated[:3, 3]))
        angle_rad = frames.rotation_angle_rad(T[:3, :3], T_stated[:3, :3])
        chi2_value = (position_m / hints.anchor_sd_m) ** 2 + (angle_rad / math.radians(hints.anchor_sd_deg)) ** 2
        agreement.append(AnchorAgreement(symbols[m], position_m, math.degrees(angle_rad), chi2_value, m in tied))
    return agreement


def _plausible_rivals(rivals: dict[int, graph.Rival], priors: Priors) -> list[tuple[int, graph.Rival]]:
    """The rival placements worth an adjustment of their own (the best supported first, at most MAX_RIVALS): a
    marker that hangs on a wall cannot be tilted off the vertical."""
    limit = math.sin(math.radians(graph.AGREE_ANGLE_DEG))
    plausible = [(m, r) for m, r in rivals.items()
                 if m not in priors.on_wall or np.linalg.norm(r.T_map_marker[:2, 1]) < limit]
    return sorted(plausible, key=lambda item: (-item[1].rival_support, item[0]))[:MAX_RIVALS]


def _first_adjustment(shared, camera, start: dict[int, np.ndarray], free_ids, priors, options: SurveyOptions):
    """(the adjustment from these first poses with the expected noise, the frames it used)."""
    posed_frames, cameras = _posed(shared, start, camera)
    problem = BundleAdjustment(posed_frames, camera, start, cameras, free_ids, priors, options.sigma_px)
    return problem.solve(options.max_iterations, options.progress, "adjusting"), posed_frames


def _placed_apart(start: dict[int, np.ndarray], other: dict[int, np.ndarray]) -> set[int]:
    """The markers that two sets of first poses place apart (the rival's marker and those placed through it)."""
    return {m for m, T in start.items() if m in other and not graph.same_pose(T, other[m])}


def _weak_links(adjustment: Adjustment, first: Adjustment,
                rivals: list[tuple[Adjustment, int, set[int]]]) -> dict[int, tuple[float, float]]:
    """Free marker id -> (m, deg) how far a rival adjustment put it from where the chosen one did (both from
    their first poses with the expected noise), for the markers that a rival which fits nearly as well puts
    elsewhere (beyond 3 sd of the final ``adjustment``): the images cannot tell where these markers are, and
    their reported uncertainty must cover both places.

    ``rivals``: (the rival's first adjustment, the frames that link the placement, the markers it placed
    elsewhere to begin with: only these can be weakly linked through it). Nearly as well: chi-square
    within RIVAL_CHI2 of the chosen first adjustment's (both with the expected noise, in units of the residuals'
    variance) per linking frame. The linking frames were taken from one standpoint (else they would not support
    both placements): they share their systematic errors (the detector's bias at that scale and angle, the
    lens model), so together they weigh as one view, not as many independent ones.
    """
    weak: dict[int, tuple[float, float]] = {}
    for rival, link_frames, apart in rivals:
        # chi-square difference: 2 (cost_rival - cost_chosen) / s^2, over the link's frames taken as one view
        if 2.0 * (rival.cost - first.cost) / first.variance / max(link_frames, 1) >= RIVAL_CHI2:
            continue
        for m, covariance in adjustment.covariance.items():
            T, T_rival = first.markers.get(m), rival.markers.get(m)
            if T is None or T_rival is None or m not in apart:
                continue
            position_m = float(np.linalg.norm(T[:3, 3] - T_rival[:3, 3]))
            angle_rad = frames.rotation_angle_rad(T[:3, :3], T_rival[:3, :3])
            sd_position_m = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:3, :3])[-1]), 0.0))
            sd_angle_rad = math.sqrt(max(float(np.linalg.eigvalsh(covariance[3:, 3:])[-1]), 0.0))
            if position_m > 3.0 * sd_position_m or angle_rad > 3.0 * sd_angle_rad:
                before = weak.get(m, (0.0, 0.0))
                weak[m] = (max(before[0], position_m), max(before[1], math.degrees(angle_rad)))
    return weak


def _adjust_again(adjustment: Adjustment, posed_frames, camera, free_ids, priors, options: SurveyOptions):
    """From an adjustment with the expected noise: measure the noise of each kind of point from the residuals;
    leave out the sightings whose errors that noise cannot explain; adjust again, each point weighted by its
    kind's noise (times its sighting's stated sigma over the kind's median)."""
    noise = _noise(adjustment, options)
    limits = chi2.ppf(GATE_PROBABILITY, 2 * np.diff(adjustment.sighting_starts))
    bad = {sighting for sighting, value, limit in zip(adjustment.sightings, adjustment.sighting_chi2(noise), limits)
           if value > limit}
    frames_left, cameras_left = [], []
    for k, frame in enumerate(posed_frames):
        sightings = tuple(s for s in frame.sightings if (k, s.marker_id) not in bad)
        if len(sightings) >= 2:
            frames_left.append(SurveyFrame(frame.walk, frame.index, frame.t_ns, sightings))
            cameras_left.append(adjustment.cameras[k])
    markers_left = {m for f in frames_left for m in f.marker_ids}
    start = {m: T for m, T in adjustment.markers.items() if m in markers_left}
    problem = BundleAdjustment(frames_left, camera, start, np.array(cameras_left),
                               [m for m in free_ids if m in markers_left], priors, noise)
    return problem.solve(options.max_iterations, options.progress, "adjusting again"), frames_left


def corner_misfit(adjustment: Adjustment, posed_frames) -> float:
    """How many times the noise the detector states for its square-path corners (the median sighting's) the
    adjusted map leaves them off by (NaN with too few of them to tell)."""
    stated = [s.sigma_px for f in posed_frames for s in f.sightings if s.path == "square" and s.sigma_px]
    if adjustment.points_of_kind.get("corner", 0) < MIN_POINTS_FOR_NOISE or not stated:
        return math.nan
    return adjustment.noise_px["corner"] / float(np.median(stated))


def _worst_fitting(markers: list[SurveyedMarker], on_wall: frozenset[int]) -> tuple[tuple[str, float, bool], ...]:
    """The ``WORST_NAMED`` markers with the largest RMS point error: (symbol, px, taken to hang on a vertical wall)."""
    fitted = [s for s in markers if math.isfinite(s.rms_px)]
    worst = sorted(fitted, key=lambda s: -s.rms_px)[:WORST_NAMED]
    return tuple((s.marker.symbol, s.rms_px, s.marker.id in on_wall) for s in worst)


def _noise(adjustment: Adjustment, options: SurveyOptions) -> dict[str, float]:
    """The noise of each kind of point as the adjustment's residuals show it (at least MIN_NOISE_PX); the
    expected ``options.sigma_px`` for a kind with too few points to tell."""
    noise = {kind: options.sigma_px for kind in POINT_KINDS}
    for kind, measured_px in adjustment.noise_px.items():
        if adjustment.points_of_kind[kind] >= MIN_POINTS_FOR_NOISE:
            noise[kind] = max(measured_px, MIN_NOISE_PX)
    return noise


def _result_markers(adjustment: Adjustment, posed_frames, fixed, anchors: FacilityMap, counts, sizes,
                    on_wall: frozenset[int], weak: dict[int, tuple[float, float]],
                    extend: bool) -> list[SurveyedMarker]:
    """Each marker with its uncertainty: the adjustment's covariance, widened for a weakly linked marker to
    cover where a rival adjustment put it; the anchors as ``_anchor_with_sd`` gives them."""
    rms = _marker_rms(adjustment)
    result = []
    for m, T in adjustment.markers.items():
        symbol = sizes.symbols[m]
        if m in fixed:
            marker = _anchor_with_sd(anchors.markers[m], anchors, extend)
            result.append(SurveyedMarker(marker, True, counts.get(m, 0), 0.0, 0.0, rms.get(m, math.nan), None))
            continue
        covariance = adjustment.covariance[m]
        if m in on_wall:
            T = _upright(T)
        sd_position_m = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:3, :3])[-1]), 0.0))
        sd_angle_deg = math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(covariance[3:, 3:])[-1]), 0.0)))
        if m in weak:
            sd_position_m, sd_angle_deg = max(sd_position_m, weak[m][0]), max(sd_angle_deg, weak[m][1])
        note = f"surveyed: sd {sd_position_m * 1000:.1f} mm, {sd_angle_deg:.2f} deg, {counts.get(m, 0)} frames"
        if m in weak:
            note += "; weakly linked to the anchors: survey again"
        elif placed_loosely(sd_position_m):
            note += "; placed loosely: survey again"
        marker = MapMarker(symbol, m, sizes(m), T, note, sd_position_m, sd_angle_deg)
        result.append(SurveyedMarker(marker, False, counts.get(m, 0), sd_position_m, sd_angle_deg, rms.get(m, math.nan),
                                     covariance, m in weak))
    return result


def _anchor_with_sd(anchor: MapMarker, anchors: FacilityMap, extend: bool) -> MapMarker:
    """An anchor as the map gives it, with how well it is known in the map. The anchors of an anchors file
    are the map frame: held exactly, every other marker placed from them, so exact in the map by definition
    (sd 0; how well they fit the site is the agreement test's, and every marker shares it). A marker of an
    existing map extended keeps its own ``sd``, else the stated ``survey.anchor_sd_m`` / ``anchor_sd_deg``."""
    if not extend:
        return replace(anchor, sd_position_m=0.0, sd_angle_deg=0.0)
    hints = anchors.survey
    return replace(anchor, sd_position_m=hints.anchor_sd_m if anchor.sd_position_m is None else anchor.sd_position_m,
                   sd_angle_deg=hints.anchor_sd_deg if anchor.sd_angle_deg is None else anchor.sd_angle_deg)


def _marker_rms(adjustment: Adjustment) -> dict[int, float]:
    sums: dict[int, list[float]] = {}
    for (_, m), rms in zip(adjustment.sightings, adjustment.sighting_rms_px):
        sums.setdefault(m, []).append(rms ** 2)
    return {m: math.sqrt(float(np.mean(v))) for m, v in sums.items()}


def _upright(T_map_marker: np.ndarray) -> np.ndarray:
    """The pose with its y axis exactly vertical (a wall marker's), facing the same heading."""
    z_axis = T_map_marker[:3, 2]
    heading_deg = math.degrees(math.atan2(z_axis[1], z_axis[0]))
    return frames.make_transform(frames.R_map_marker_on_wall(heading_deg), T_map_marker[:3, 3])
