"""The daemon's health: what is wrong right now, said once when it changes.

Fed from two sides:

* the pipeline thread, through ``Pipeline.observers`` (``observe``): every
  frame with its FrameRecord (the detections, the pose stage's decision and
  the filter's estimate);
* the supervising thread, on the wall clock (``check(now_ns, lost_reason)``):
  a stalled camera delivers no frames, so nothing driven by frames could
  notice it.

States, worst first (``HealthState.state``; the status line shows it):

=================  ==========================================================  ========
camera lost        the source says why it delivers nothing (``lost_reason``)   critical
camera stalled     no frame for 3 frame periods (at least 0.5 s, at most 1 s)  critical
starting           no frame yet
no markers         no marker decoded in the frames of ``no_markers_after_s`` (0.5 s)
no pose            markers, but no pose for ``no_pose_after_s`` (2 s); the
                   reasons are the pose stage's statuses, counted
acquiring,         the filter's state (from the estimates it gave)
tracking, coasting
=================  ==========================================================  ========

While a critical state lasts the link's HEARTBEAT says MAV_STATE_CRITICAL.
Messages (``emit(text, severity, topic)``: the daemon logs them and sends them
as STATUSTEXT), one per change: the camera lost, stalled, and delivering again;
no pose with its reasons; and the filter's own changes (tracking markers,
markers lost, with the commonest reason when markers are still in view: the
pose stage's status or the filter's gate, or the gap in the frames that ended the
track; re-acquired with its reset counter). "no markers" is shown,
not sent: the filter's "markers lost" already says it. The camera's messages
have the topic "camera", the attitude's "attitude", the filter's and "no
pose" "tracking" (whether poses flow): the link sends such a health change
before anything else queued, and a newer one of a topic replaces a queued
older one (``MavlinkLink.statustext``).

The flight controller's attitude (when the daemon expects one,
``attitude_expected``) is judged beside the state, from each frame's
``FrameRecord.attitude`` (``HealthState.attitude``: "waiting" before the
first sample, "ok", "stale"; "off" when none is expected). Each change is
said once: "flight controller attitude in use" (or "no attitude yet: poses
without it" when the first frame has none), "attitude stale: poses without
it", "attitude back: poses use it".
"""
from __future__ import annotations

import collections
import dataclasses
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from companion.daemon.pipeline import FrameRecord
from companion.mavlink.messages import SEVERITY_CRITICAL, SEVERITY_INFO, SEVERITY_WARNING
from companion.types import Frame

CRITICAL_STATES = ("camera lost", "camera stalled")
# The stall threshold is this many frame periods, clamped to [STALL_MIN_S, STALL_MAX_S].
STALL_PERIODS = 3
STALL_MIN_S = 0.5
STALL_MAX_S = 1.0

Emit = Callable[[str, int, "str | None"], None]  # (text, MAV_SEVERITY, topic or None)
CAMERA, ATTITUDE, TRACKING = "camera", "attitude", "tracking"  # the topics of health changes

# (previous, new) attitude state -> what is said; "start": the first frame
ATTITUDE_MESSAGES = {
    ("start", "ok"): ("flight controller attitude in use", SEVERITY_INFO),
    ("start", "waiting"): ("no attitude yet: poses without it", SEVERITY_WARNING),
    ("waiting", "ok"): ("flight controller attitude in use", SEVERITY_INFO),
    ("ok", "stale"): ("attitude stale: poses without it", SEVERITY_WARNING),
    ("stale", "ok"): ("attitude back: poses use it", SEVERITY_INFO),
}


@dataclass(frozen=True)
class HealthState:
    """The daemon's health at one moment.

    state: see the module docstring; since_s: how long it has lasted (0 when
    not measured); reasons: what the state rests on ("reprojection 42", the
    source's lost reason), most frequent first.
    """

    state: str
    since_s: float = 0.0
    reasons: tuple[str, ...] = ()
    attitude: str = "off"

    @property
    def critical(self) -> bool:
        return self.state in CRITICAL_STATES


class Health:
    """Judges the daemon's health from its frames and the wall clock; see the module docstring."""

    def __init__(self, emit: Emit, no_markers_after_s: float = 0.5, no_pose_after_s: float = 2.0,
                 clock_ns: Callable[[], int] = time.monotonic_ns, attitude_expected: bool = False,
                 first_frame_within_s: float = STALL_MAX_S):
        """first_frame_within_s: how long the first frame may take before it is a stall (a simulated camera
        waits for the flight controller's first heartbeat, up to a second, before it can ask for a state)."""
        self._emit = emit
        self.no_markers_after_s = no_markers_after_s
        self.no_pose_after_s = no_pose_after_s
        self.first_frame_within_s = first_frame_within_s
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._started_ns = clock_ns()
        self._last_frame_ns: int | None = None        # when the newest frame was processed
        self._last_capture_ns: int | None = None      # its capture time
        self._periods_ns: collections.deque = collections.deque(maxlen=30)
        self._last_markers_ns: int | None = None
        self._markers_without_pose_ns: int | None = None  # first frame with markers since the last pose
        self._pose_statuses: collections.Counter = collections.Counter()  # since the last pose the filter took
        self._track = "acquiring"
        self._acquisitions = 0
        self._resets = 0   # the filter's reset counter as last seen
        self._lost_ns: int | None = None   # when the source last said it was lost
        self._reported = "starting"
        self._attitude = "waiting" if attitude_expected else "off"
        self._frames_seen = False

    # ------------------------------------------------- the pipeline's side

    def observe(self, frame: Frame, record: FrameRecord) -> None:
        """``Pipeline.observers`` entry: note what this frame showed (pipeline thread)."""
        now_ns = self._clock_ns()
        with self._lock:
            if self._last_capture_ns is not None and record.t_ns > self._last_capture_ns:
                self._periods_ns.append(record.t_ns - self._last_capture_ns)
            self._last_capture_ns = record.t_ns
            self._last_frame_ns = now_ns
            if record.markers:
                self._last_markers_ns = now_ns
            if record.measurement is not None:
                self._markers_without_pose_ns = None
                if record.estimate is not None and record.estimate.tracking:
                    self._pose_statuses.clear()
                else:  # a pose the filter did not take: gated off its track, or one of a new fix's first
                    self._pose_statuses["filter gating"] += 1
            elif record.solution is not None:
                if self._markers_without_pose_ns is None:
                    self._markers_without_pose_ns = now_ns
                self._pose_statuses[record.solution.status] += 1
        self._follow_the_filter(record)
        self._follow_the_attitude(record)

    def _follow_the_filter(self, record: FrameRecord) -> None:
        """The filter's state from its estimate, and a message when it acquires or loses the markers."""
        estimate = record.estimate
        track = "acquiring" if estimate is None else "tracking" if estimate.tracking else "coasting"
        previous, self._track = self._track, track
        # a track lost and found again within one frame (after a gap in the frames, an unambiguous pose is a
        # fix at once) shows only as a new reset: said like any re-acquisition
        reset = estimate is not None and estimate.reset_counter > self._resets
        if estimate is not None:
            self._resets = estimate.reset_counter
        if track == previous and not reset:
            return
        if track == "tracking" and (previous == "acquiring" or reset):
            self._acquisitions += 1
            if self._acquisitions == 1:
                self._emit("tracking markers", SEVERITY_INFO, TRACKING)
            else:
                self._emit(f"re-acquired (reset {estimate.reset_counter})", SEVERITY_INFO, TRACKING)
        elif track == "acquiring":
            self._emit(self._lost_text(record), SEVERITY_WARNING, TRACKING)
        # tracking <-> coasting flickers frame to frame: not worth a message

    def _lost_text(self, record: FrameRecord) -> str:
        """'markers lost', with the commonest reason since the filter last took a pose when markers are still in
        view: the pose stage's status, or 'filter gating' (a wrong camera or map loses the track with markers in
        sight; short enough for one STATUSTEXT); when the filter says a gap in the frames ended its track, the
        gap (the first pose after it waits to be confirmed: not the gate's doing)."""
        with self._lock:
            statuses = self._pose_statuses.most_common(1)
        if record.track_loss is not None and record.track_loss.no_frames:
            return f"markers lost: no frame for {record.track_loss.frame_gap_s:.1f} s"
        if not record.markers or not statuses:
            return "markers lost"
        return f"markers lost: {statuses[0][0]}"

    def _follow_the_attitude(self, record: FrameRecord) -> None:
        """The attitude's state from this frame's, and a message when it changes (pipeline thread)."""
        previous = self._attitude
        if previous == "off":
            return
        if record.attitude is not None:
            state = "ok"
        else:
            state = "stale" if previous in ("ok", "stale") else "waiting"
        self._attitude = state
        message = ATTITUDE_MESSAGES.get((previous if self._frames_seen else "start", state))
        self._frames_seen = True
        if message is not None:
            self._emit(*message, ATTITUDE)

    # ---------------------------------------------- the supervisor's side

    def check(self, now_ns: int | None = None, lost_reason: str | None = None) -> HealthState:
        """The health now (supervising thread); emits a message when a reported state begins or ends."""
        now_ns = self._clock_ns() if now_ns is None else now_ns
        state = self.assess(now_ns, lost_reason)
        self._report(state)
        return state

    def assess(self, now_ns: int, lost_reason: str | None = None) -> HealthState:
        """The health at ``now_ns`` (monotonic), without reporting it."""
        return dataclasses.replace(self._assess_state(now_ns, lost_reason), attitude=self._attitude)

    def _assess_state(self, now_ns: int, lost_reason: str | None) -> HealthState:
        with self._lock:
            last_frame_ns, last_markers_ns = self._last_frame_ns, self._last_markers_ns
            no_pose_since_ns = self._markers_without_pose_ns
            statuses = self._pose_statuses.most_common()
            stall_after_s = self._stall_after_s()
            if lost_reason is not None:
                self._lost_ns = now_ns
            lost_ns = self._lost_ns
        if lost_reason is not None:
            return HealthState("camera lost", _seconds(now_ns - (last_frame_ns or self._started_ns)), (lost_reason,))
        if last_frame_ns is None:
            waited_s = _seconds(now_ns - self._started_ns)
            return HealthState("camera stalled" if waited_s > self.first_frame_within_s else "starting", waited_s)
        # a source back from lost gets its stall time to deliver (it was lost, not stalled, until now)
        silent_s = _seconds(now_ns - max(last_frame_ns, lost_ns or 0))
        if silent_s > stall_after_s:
            return HealthState("camera stalled", silent_s, (f"no frame for {silent_s:.1f} s",))
        # judged on the frames that came: a slow camera between two frames is not "no markers"
        markers_ns = last_markers_ns or self._started_ns
        if _seconds(last_frame_ns - markers_ns) > self.no_markers_after_s:
            return HealthState("no markers", _seconds(now_ns - markers_ns))
        if no_pose_since_ns is not None and _seconds(now_ns - no_pose_since_ns) > self.no_pose_after_s:
            return HealthState("no pose", _seconds(now_ns - no_pose_since_ns),
                               tuple(f"{status} {count}" for status, count in statuses))
        return HealthState(self._track)

    def _stall_after_s(self) -> float:
        """STALL_PERIODS median frame periods, clamped to [STALL_MIN_S, STALL_MAX_S] (lock held)."""
        if not self._periods_ns:
            return STALL_MAX_S
        period_s = float(np.median(self._periods_ns)) * 1e-9
        return min(max(STALL_PERIODS * period_s, STALL_MIN_S), STALL_MAX_S)

    def _report(self, state: HealthState) -> None:
        """One message when the camera is lost, stalls or comes back, and when 'no pose' begins."""
        previous, self._reported = self._reported, state.state
        if state.state == previous:
            return
        if state.critical:
            self._emit(f"{state.state}: {state.reasons[0]}" if state.reasons else state.state, SEVERITY_CRITICAL,
                       CAMERA)
        elif previous in CRITICAL_STATES:
            self._emit("camera delivers frames again", SEVERITY_INFO, CAMERA)
        if state.state == "no pose":
            self._emit(f"no pose for {state.since_s:.1f} s: {', '.join(state.reasons)}", SEVERITY_WARNING, TRACKING)


def _seconds(ns: int) -> float:
    return max(ns, 0) * 1e-9
