"""The daemon's watch on the camera mount: the markers' level against the flight controller's, said once.

``MountWatch`` is a pipeline observer (``Pipeline.observers``); it has work only
while the daemon has the flight controller's roll and pitch (``FrameRecord.attitude``).
In each frame with a pose it measures the angle between "down" as the markers
put it (the pose's body attitude in NED) and "down" as the flight controller's
roll and pitch put it. A few tenths of a degree is the two estimates' noise
(0.2 degrees median on the bundled flights). A median over ``window`` frames of
``min_angle_deg`` or more is a misconfiguration: the camera's mount in the
config (``camera.mount``: a wrong facing, tilt or angle turns every pose the
daemon sends) or the flight controller's level (its accelerometer calibration,
ArduPilot's AHRS_TRIM). The pose stage then leaves the attitude out where it
disagrees with the markers, which nobody would notice; this says it once, in
the log with the roll and pitch differences and by STATUSTEXT.

A camera turned about the body's down axis against its config (a wrong yaw or
facing) shows only while the vehicle tilts: the markers then see the FC's tilt
turned by as much. Where the FC's tilts over the window spread by
``MIN_TILT_SPREAD_FOR_TURN_DEG`` or more, that turn is estimated (least squares
over the frames' tilts, a constant level error beside it), and one of
``MIN_REPORTED_TURN_DEG`` or more that explains the tilts (``MIN_TURN_EXPLAINED``
of them) is told as the camera's yaw error or the flight controller's board
orientation, which the tilts cannot tell apart: CRITICAL either way (with a
wrong camera yaw every heading sent is off by as much; with a wrong board
orientation the autopilot's own attitude is). Tilts that no turn explains
(a marker turned in the map and seen alone, an attitude stamped late) are
said as a level difference, with those causes among the ones to check.
"""
from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass

import numpy as np

from companion.geometry import frames
from companion.mavlink.link import MavlinkLink
from companion.mavlink.messages import SEVERITY_CRITICAL, SEVERITY_WARNING
from companion.types import AttitudeSample

log = logging.getLogger("companion")


MOUNT_WATCH_SDS = 3.0  # the daemon reports a median angle of this many ``PoseParams.attitude_sd_deg`` or more
MIN_TILT_SPREAD_FOR_TURN_DEG = 2.0  # the FC's tilts must spread this much (RMS) for a turn about the vertical
MIN_REPORTED_TURN_DEG = 10.0  # a turn this large is reported as the camera's yaw (CRITICAL: every heading is off)
# the turn must explain this share of the markers' tilts about their mean: a map entry turned on a lone marker,
# an attitude stamped late or early, give tilts that no turn takes one onto the other (it fitted +50 deg there)
MIN_TURN_EXPLAINED = 0.8


@dataclass(frozen=True)
class MountWatchParams:
    """window: the last frames with a pose and the FC's attitude that count; min_angle_deg: their median
    angle between the two "down"s that is reported (the daemon's: ``MOUNT_WATCH_SDS`` times the config's
    ``pose.attitude_sd_deg``, 1.5 degrees by default)."""

    window: int = 60
    min_angle_deg: float = 1.5


class MountWatch:
    """Compares the markers' level with the flight controller's frame by frame; says it once when they keep
    disagreeing. Runs on the pipeline thread: a few arithmetic operations per frame."""

    def __init__(self, link: MavlinkLink | None, params: MountWatchParams = MountWatchParams()):
        self.link, self.params = link, params
        # per frame, 9 values: the angle, roll and pitch differences (degrees), the markers' down, the FC's down
        self._frames: collections.deque = collections.deque(maxlen=params.window)
        self.reported = False

    def __call__(self, frame, record) -> None:
        solution, attitude = record.solution, record.attitude
        if self.reported or attitude is None or solution is None or solution.measurement is None:
            return
        self._frames.append(level_row(solution.measurement.T_ned_body[:3, :3], attitude))
        if len(self._frames) == self.params.window:
            table = np.array(self._frames)
            angle_deg, roll_deg, pitch_deg = np.median(table[:, :3], axis=0)
            if angle_deg >= self.params.min_angle_deg:
                self._report(float(angle_deg), float(roll_deg), float(pitch_deg),
                             tilt_turn_deg(table[:, 3:6], table[:, 6:9]))

    def _report(self, angle_deg: float, roll_deg: float, pitch_deg: float, turn: float | None) -> None:
        self.reported = True
        turned = turn is not None and abs(turn) >= MIN_REPORTED_TURN_DEG
        why = (f"the tilt the markers see is the FC's turned by {turn:+.0f} deg about the body's down axis: the "
               f"camera's yaw in the config is {turn:+.0f} deg off (camera.mount yaw_deg or facing; every heading "
               f"sent is off by as much), or the FC's board orientation is (ArduPilot AHRS_ORIENTATION, PX4 "
               f"SENS_BOARD_ROT)" if turned else
               "check the camera's mount in the config (camera.mount: facing, tilt_down_deg or roll/pitch/yaw_deg), "
               "the FC's level calibration, the map entries of the markers in view (one turned in the map tilts "
               "every pose from it) and the attitude's time stamps")
        log.log(logging.ERROR if turned else logging.WARNING, "the markers and the flight controller disagree on "
                "level by %.1f deg (median of the last %d frames; markers - FC: roll %+.1f, pitch %+.1f deg); the "
                "pose stage leaves the FC's attitude out where they disagree; %s",
                angle_deg, len(self._frames), roll_deg, pitch_deg, why)
        if self.link is not None:
            self.link.statustext(f"companion: camera/FC board yaw off by {turn:+.0f} deg" if turned else
                                 f"companion: camera mount? level {angle_deg:.1f} deg off FC",
                                 SEVERITY_CRITICAL if turned else SEVERITY_WARNING)


def level_row(R_ned_body: np.ndarray, attitude: AttitudeSample) -> np.ndarray:
    """(9,): the angle between down from the markers' pose (R_ned_body (3, 3)) and down from the FC's roll and
    pitch, their roll and pitch differences (markers - FC), degrees; the markers' down, the FC's down."""
    down_markers = frames.down_in_body(R_ned_body)
    down_fc = frames.down_in_body_at(attitude.roll_rad, attitude.pitch_rad)
    angle_deg = math.degrees(math.acos(min(1.0, float(down_markers @ down_fc))))
    roll, pitch = frames.roll_pitch_321(R_ned_body)
    return np.array([angle_deg, math.degrees(math.remainder(roll - attitude.roll_rad, 2 * math.pi)),
                     math.degrees(pitch - attitude.pitch_rad), *down_markers, *down_fc])


def level_difference_deg(R_ned_body: np.ndarray, attitude: AttitudeSample) -> tuple[float, float, float]:
    """(angle, roll, pitch) degrees of ``level_row``."""
    angle_deg, roll_deg, pitch_deg = level_row(R_ned_body, attitude)[:3]
    return float(angle_deg), float(roll_deg), float(pitch_deg)


def tilt_turn_deg(down_markers: np.ndarray, down_fc: np.ndarray, min_spread_deg: float = MIN_TILT_SPREAD_FOR_TURN_DEG
                  ) -> float | None:
    """The turn about the body's down axis that best takes the FC's tilts onto the markers' (degrees, positive
    from body x towards y), from (N, 3) downs in body axes, a constant tilt offset between them allowed (a
    level error); None unless the FC's tilts spread by ``min_spread_deg`` or more (RMS about their mean): on
    tilts that hardly change, a turn does not show."""
    fc, markers = down_fc[:, :2], down_markers[:, :2]  # the tilts: down's part across the body's down axis
    fc, markers = fc - fc.mean(axis=0), markers - markers.mean(axis=0)
    if math.degrees(math.asin(min(float(np.sqrt(np.mean(np.sum(fc * fc, axis=1)))), 1.0))) < min_spread_deg:
        return None
    # the least-squares turn: atan2 of the summed cross and dot products
    cross = float(np.sum(fc[:, 0] * markers[:, 1] - fc[:, 1] * markers[:, 0]))
    turn = math.atan2(cross, float(np.sum(fc * markers)))
    # a turn, or tilts that no turn explains (None): the share of the markers' tilts left over after it
    c, s = math.cos(turn), math.sin(turn)
    left = markers - np.column_stack([c * fc[:, 0] - s * fc[:, 1], s * fc[:, 0] + c * fc[:, 1]])
    if float(np.sum(left * left)) > (1.0 - MIN_TURN_EXPLAINED) * float(np.sum(markers * markers)):
        return None
    return math.degrees(turn)
