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
    min_rejected: left out in at least this many of them."""

    window: int = 30
    min_rejected: int = 20


class MapWatch:
    """Counts, per marker, the frames where the pose consistency gate left it out; says it once when it
    keeps happening. Runs on the pipeline thread: a few dictionary updates per frame."""

    def __init__(self, facility_map: FacilityMap, link: MavlinkLink | None, params: MapWatchParams = MapWatchParams(),
                 on_disagreement: Callable[[int, float, float], None] | None = None):
        """on_disagreement(marker id, position m, angle deg): called once per marker reported, with how far off
        it was seen."""
        self.facility_map, self.link, self.params = facility_map, link, params
        self.on_disagreement = on_disagreement
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
