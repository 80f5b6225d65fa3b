"""The daemon's watch on the map: a marker that keeps disagreeing with the others is reported once.

``MapWatch`` is a pipeline observer (``Pipeline.observers``). The pose stage's
consistency gate leaves out, frame by frame, a marker whose corners do not
fit the pose the other markers agree on (``PoseSolution.rejected_ids``). Once
is noise; a marker left out in most of its recent frames has most likely been
moved, re-hung or swapped since the map was made. Then the watch says, once
per marker, "marker X disagrees with the map" in the log and by STATUSTEXT,
and the operator can run ``companion map check`` (docs/survey.md).

Two markers that disagree leave the frame without a pose ("inconsistent
markers"): neither outvotes the other. If one of them has been seen agreeing
with a third marker in an accepted pose and the other never has, the other
is counted as left out, as if the third had been in view.

It also says how far off: the median, over the frames that left the marker
out, of where its own corners put it (``PoseSolution.rejected_offsets``),
and hands that to ``on_disagreement`` (the daemon's: ``PoseSolver.loosen``).
From then on the pose stage leaves the marker out beside others and, seen
alone, weighs it as that uncertain: a marker 10 cm off gives poses whose
sd says 10 cm, for the filter and the autopilot to weigh, where before they
said 2.4 cm (docs/survey.md, "The daemon's watch").

The map as a whole: when markers keep disagreeing all over the site, not one
marker in most of it (a tape-measured map under a config that states a
surveyed one's accuracy), the watch says once that the map is less accurate
than stated, and hands half the median disagreement to ``on_map_error``
(the daemon's: ``PoseSolver.loosen_all``): every marker is weighed as that
uncertain from then on.
"""
from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from companion.geometry.facility_map import FacilityMap
from companion.mavlink.link import SEVERITY_WARNING, MavlinkLink

log = logging.getLogger("companion")


@dataclass(frozen=True)
class MapWatchParams:
    """window: a marker's last frames that count (those where the gate judged it: used or left out);
    min_rejected: left out in at least this many of them.
    map_window: the last frames of two or more mapped markers that count for the map as a whole;
    map_min_disagreeing: markers disagreed in at least this many of them, map_max_share: and no one marker was
    left out in more than this share of those (one moved marker is said as itself): the map is less accurate
    than stated."""

    window: int = 30
    min_rejected: int = 20
    map_window: int = 60
    map_min_disagreeing: int = 30
    map_max_share: float = 0.67


class MapWatch:
    """Counts, per marker, the frames where the pose consistency gate left it out, and for the map as a whole
    the frames where markers disagreed; says each once when it keeps happening. Runs on the pipeline thread: a
    few dictionary updates per frame."""

    def __init__(self, facility_map: FacilityMap, link: MavlinkLink | None, params: MapWatchParams = MapWatchParams(),
                 on_disagreement: Callable[[int, float, float], None] | None = None,
                 on_map_error: Callable[[float, float], None] | None = None):
        """on_disagreement(marker id, position m, angle deg): called once per marker reported, with how far off
        it was seen; on_map_error(sd m, sd deg): called once if the map as a whole is found less accurate than
        stated, with how uncertain each marker is taken to be."""
        self.facility_map, self.link, self.params = facility_map, link, params
        self.on_disagreement, self.on_map_error = on_disagreement, on_map_error
        self._map_frames: collections.deque = collections.deque(maxlen=params.map_window)  # the ids left out
        self._map_offsets: collections.deque = collections.deque(maxlen=2 * params.map_window)
        self.map_reported = False
        self._judged: dict[int, collections.deque] = {}
        self._offsets: dict[int, collections.deque] = {}  # (position m, angle deg) of the frames that left it out
        self._agreed: set[int] = set()  # markers used beside another in an accepted pose, not reported since
        self.reported: list[int] = []

    def __call__(self, frame, record) -> None:
        solution = record.solution
        if solution is None:
            return
        if solution.status == "ok":
            if len(solution.marker_ids) > 1:
                self._agreed.update(solution.marker_ids)
            self._count(solution.marker_ids, False)
            self._left_out(solution.rejected_ids, solution.rejected_offsets)
        elif solution.status == "inconsistent markers":
            self._left_out(*self._outvoted(solution))
        else:
            return
        if len(solution.marker_ids) + len(solution.rejected_ids) > 1 and not self.map_reported:
            self._judge_map(solution)

    def _judge_map(self, solution) -> None:
        """The map as a whole, from a frame of two or more markers: did any disagree (reported ones aside)?"""
        left_out = [o for o in solution.rejected_offsets if o.marker_id not in self.reported]
        self._map_frames.append(frozenset(o.marker_id for o in left_out))
        self._map_offsets.extend(o for o in left_out if math.isfinite(o.position_m) and math.isfinite(o.angle_deg))
        disagreeing = [ids for ids in self._map_frames if ids]
        if len(self._map_frames) < self.params.map_window or len(disagreeing) < self.params.map_min_disagreeing:
            return
        most = collections.Counter(i for ids in disagreeing for i in ids).most_common(1)[0][1]
        if most <= self.params.map_max_share * len(disagreeing) and self._map_offsets:
            self._report_map(len(disagreeing))

    def _report_map(self, disagreeing: int) -> None:
        self.map_reported = True
        position_m, angle_deg = np.median([(o.position_m, o.angle_deg) for o in self._map_offsets], axis=0)
        # each of two markers that disagree carries about half of what separates them
        sd_m, sd_deg = float(position_m) / 2, float(angle_deg) / 2
        log.warning("markers disagree with each other by %.1f cm and %.1f deg (median, in %d of the last %d frames "
                    "with two or more, not one marker's doing): the map is less accurate than the config states "
                    "(pose.map_sd_m, map_sd_deg); every marker weighed as %.1f cm and %.1f deg uncertain from now "
                    "on; state the map's accuracy, or survey the site (companion survey)",
                    100 * position_m, angle_deg, disagreeing, len(self._map_frames), 100 * sd_m, sd_deg)
        if self.on_map_error is not None:
            self.on_map_error(sd_m, sd_deg)
        if self.link is not None:
            self.link.statustext(f"companion: markers disagree by {100 * position_m:.0f} cm {angle_deg:.0f} deg",
                                 SEVERITY_WARNING)

    def _outvoted(self, solution) -> tuple[tuple[int, ...], tuple]:
        """Of two markers that disagree, the one never seen to agree with another marker, when the other has
        been: (its id, its offset seen from the other), or nothing to count."""
        doubtful = [i for i, marker_id in enumerate(solution.rejected_ids) if marker_id not in self._agreed]
        if len(solution.rejected_ids) != 2 or len(doubtful) != 1:
            return (), ()
        i = doubtful[0]
        return solution.rejected_ids[i:i + 1], solution.rejected_offsets[i:i + 1]

    def _left_out(self, marker_ids: tuple[int, ...], offsets) -> None:
        self._count(marker_ids, True)
        for offset in offsets:
            if math.isfinite(offset.position_m) and math.isfinite(offset.angle_deg):  # (NaN: its corners gave no pose)
                kept = self._offsets.setdefault(offset.marker_id, collections.deque(maxlen=self.params.window))
                kept.append((offset.position_m, offset.angle_deg))
        for marker_id in marker_ids:
            if marker_id not in self.reported and sum(self._judged[marker_id]) >= self.params.min_rejected:
                self._report(marker_id)

    def _count(self, marker_ids, rejected: bool) -> None:
        for marker_id in marker_ids:
            judged = self._judged.setdefault(marker_id, collections.deque(maxlen=self.params.window))
            judged.append(rejected)

    def _report(self, marker_id: int) -> None:
        self.reported.append(marker_id)
        self._agreed.discard(marker_id)
        text = f"marker {self.facility_map.markers[marker_id].symbol} disagrees with the map"
        judged = self._judged[marker_id]
        offsets = self._offsets.get(marker_id)
        if not offsets:  # no frame said how far (its corners gave no pose of their own): weighed as before
            log.warning("%s (left out by the pose consistency gate in %d of its last %d frames; "
                        "run companion map check)", text, sum(judged), len(judged))
        else:
            position_m, angle_deg = np.median(np.array(offsets), axis=0)
            log.warning("%s by %.1f cm and %.1f deg (left out by the pose consistency gate in %d of its last %d "
                        "frames): weighed as that uncertain from now on; run companion map check", text,
                        100 * position_m, angle_deg, sum(judged), len(judged))
            if self.on_disagreement is not None:
                self.on_disagreement(marker_id, float(position_m), float(angle_deg))
        if self.link is not None:
            self.link.statustext(f"companion: {text}", SEVERITY_WARNING)
