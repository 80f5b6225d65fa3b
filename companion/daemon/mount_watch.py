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
"""
from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass

import numpy as np

from companion.geometry import frames
from companion.mavlink.link import SEVERITY_WARNING, MavlinkLink
from companion.types import AttitudeSample

log = logging.getLogger("companion")


MOUNT_WATCH_SDS = 3.0  # the daemon reports a median angle of this many ``PoseParams.attitude_sd_deg`` or more


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
        self._differences: collections.deque = collections.deque(maxlen=params.window)
        self.reported = False

    def __call__(self, frame, record) -> None:
        solution, attitude = record.solution, record.attitude
        if self.reported or attitude is None or solution is None or solution.measurement is None:
            return
        self._differences.append(level_difference_deg(solution.measurement.T_ned_body[:3, :3], attitude))
        if len(self._differences) == self.params.window:
            angle_deg, roll_deg, pitch_deg = np.median(np.array(self._differences), axis=0)
            if angle_deg >= self.params.min_angle_deg:
                self._report(float(angle_deg), float(roll_deg), float(pitch_deg))

    def _report(self, angle_deg: float, roll_deg: float, pitch_deg: float) -> None:
        self.reported = True
        log.warning("the markers and the flight controller disagree on level by %.1f deg (median of the last %d "
                    "frames; markers - FC: roll %+.1f, pitch %+.1f deg): the pose stage leaves the FC's attitude "
                    "out where they disagree. Check the camera's mount in the config (camera.mount: facing, "
                    "tilt_down_deg or roll/pitch/yaw_deg) and the FC's level calibration",
                    angle_deg, len(self._differences), roll_deg, pitch_deg)
        if self.link is not None:
            self.link.statustext(f"companion: camera mount? level {angle_deg:.1f} deg off FC", SEVERITY_WARNING)


def level_difference_deg(R_ned_body: np.ndarray, attitude: AttitudeSample) -> tuple[float, float, float]:
    """(angle, roll, pitch) degrees: the angle between down from the markers' pose (R_ned_body (3, 3)) and down
    from the FC's roll and pitch, and their roll and pitch differences (markers - FC)."""
    down_markers = R_ned_body[2]
    down_fc = frames.down_in_body(attitude.roll_rad, attitude.pitch_rad)
    angle_deg = math.degrees(math.acos(min(1.0, float(down_markers @ down_fc))))
    roll, pitch = frames.roll_pitch_321(R_ned_body)
    return (angle_deg, math.degrees(math.remainder(roll - attitude.roll_rad, 2 * math.pi)),
            math.degrees(pitch - attitude.pitch_rad))
