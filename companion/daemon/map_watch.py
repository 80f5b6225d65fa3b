"""The daemon's watch on the map: a marker that keeps disagreeing with the others is reported once.

``MapWatch`` is a pipeline observer (``Pipeline.observers``). The pose stage's
consistency gate leaves out, frame by frame, a marker whose corners do not
fit the pose the other markers agree on (``PoseSolution.rejected_ids``). Once
is noise; a marker left out in most of its recent frames has most likely been
moved, re-hung or swapped since the map was made. Then the watch says, once
per marker, "marker X disagrees with the map" in the log and by STATUSTEXT,
and the operator can run ``companion map check`` (docs/survey.md).
"""
from __future__ import annotations

import collections
import logging
from dataclasses import dataclass

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

    def __init__(self, facility_map: FacilityMap, link: MavlinkLink | None, params: MapWatchParams = MapWatchParams()):
        self.facility_map, self.link, self.params = facility_map, link, params
        self._judged: dict[int, collections.deque] = {}
        self.reported: list[int] = []

    def __call__(self, frame, record) -> None:
        solution = record.solution
        if solution is None:
            return
        self._count(solution.marker_ids, False)
        self._count(solution.rejected_ids, True)
        for marker_id in solution.rejected_ids:
            if marker_id not in self.reported and sum(self._judged[marker_id]) >= self.params.min_rejected:
                self._report(marker_id)

    def _count(self, marker_ids, rejected: bool) -> None:
        for marker_id in marker_ids:
            judged = self._judged.setdefault(marker_id, collections.deque(maxlen=self.params.window))
            judged.append(rejected)

    def _report(self, marker_id: int) -> None:
        self.reported.append(marker_id)
        text = f"marker {self.facility_map.markers[marker_id].symbol} disagrees with the map"
        log.warning("%s (left out by the pose consistency gate in %d of its last %d frames; "
                    "run companion map check)", text, sum(self._judged[marker_id]), len(self._judged[marker_id]))
        if self.link is not None:
            self.link.statustext(f"companion: {text}", SEVERITY_WARNING)
