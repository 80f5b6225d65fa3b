"""Pure builders of the MAVLink 2 messages the daemon sends (no sockets).

Each function returns a pymavlink message object from the MAVLink 2
``common`` dialect; ``companion.mavlink.link`` packs and sends them. The
link reads with the ``ardupilotmega`` dialect (``common`` plus ArduPilot's
messages, such as EKF_STATUS_REPORT), whose constants are ``ardupilot``. MAVLink 2
is required: ``covariance`` and ``reset_counter`` are extension fields that
MAVLink 1 silently drops, so ``MAVLINK20`` is set before pymavlink is
imported anywhere in the process through this module.

Timestamps are the frame's capture time on the monotonic clock, in
microseconds (ArduPilot and PX4 accept any monotonic time base; PX4 maps it
onto its own clock through TIMESYNC, answered with the same clock).
"""
from __future__ import annotations

import math
import os

os.environ["MAVLINK20"] = "1"

import struct  # noqa: E402

import numpy as np  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ardupilot  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from companion.geometry import frames  # noqa: E402
from companion.types import Estimate  # noqa: E402

STATUSTEXT_MAX_CHARS = 50
STATUSTEXT_MAX_CHUNKS = 5   # a text of more than 249 characters is cut: a STATUSTEXT is a line on a ground station
# Indices of the upper triangle of a 6x6 matrix, row by row (MAVLink's layout).
UPPER_TRIANGLE_6 = np.triu_indices(6)
# ODOMETRY.quality is 0 at this position standard deviation and 100 at zero.
QUALITY_ZERO_STD_M = 1.0

SEVERITY_CRITICAL = mavlink2.MAV_SEVERITY_CRITICAL
SEVERITY_WARNING = mavlink2.MAV_SEVERITY_WARNING
SEVERITY_INFO = mavlink2.MAV_SEVERITY_INFO
# EKF_STATUS_REPORT: the EKF has an attitude and has been healthy once (ArduPilot accepts an origin then).
EKF_READY_FLAG = ardupilot.EKF_ATTITUDE
EKF_UNINITIALIZED_FLAG = ardupilot.EKF_UNINITIALIZED
PARAM_ID_MAX_CHARS = 16
# MAV_PARAM_TYPE values whose PARAM_VALUE.param_value carries an integer's bytes when the
# autopilot encodes parameters bytewise (PX4), instead of the integer's value as a float (ArduPilot).
INTEGER_PARAM_TYPES = {mavlink2.MAV_PARAM_TYPE_UINT8: "<B", mavlink2.MAV_PARAM_TYPE_INT8: "<b",
                       mavlink2.MAV_PARAM_TYPE_UINT16: "<H", mavlink2.MAV_PARAM_TYPE_INT16: "<h",
                       mavlink2.MAV_PARAM_TYPE_UINT32: "<I", mavlink2.MAV_PARAM_TYPE_INT32: "<i"}

Message = mavlink2.MAVLink_message


def upper_triangle(covariance_6x6: np.ndarray) -> list[float]:
    """The 21 elements of a (6, 6) covariance's upper triangle, row-major.

    Index 0 is var(x), 6 var(y), 11 var(z), 15 var(roll), 18 var(pitch),
    20 var(yaw), as VISION_POSITION_ESTIMATE and ODOMETRY expect.
    """
    return [float(v) for v in np.asarray(covariance_6x6, dtype=float)[UPPER_TRIANGLE_6]]


def capture_time_usec(t_ns: int) -> int:
    return int(t_ns) // 1000


def vision_position_estimate(estimate: Estimate) -> Message:
    """VISION_POSITION_ESTIMATE (102): NED position, body->NED 3-2-1 attitude."""
    n, e, d = (float(v) for v in estimate.position_ned_m)
    return mavlink2.MAVLink_vision_position_estimate_message(
        usec=capture_time_usec(estimate.t_ns),
        x=n, y=e, z=d,
        roll=float(estimate.roll_rad), pitch=float(estimate.pitch_rad), yaw=float(estimate.yaw_rad),
        covariance=upper_triangle(estimate.covariance_ned),
        reset_counter=estimate.reset_counter % 256,
    )


def vision_speed_estimate(estimate: Estimate) -> Message:
    """VISION_SPEED_ESTIMATE (103): NED velocity with its (3, 3) covariance, row-major.

    An unknown covariance is sent as NaN in the first element (MAVLink's rule).
    """
    if estimate.velocity_covariance_ned is None:
        covariance = [math.nan] + [0.0] * 8
    else:
        covariance = [float(v) for v in np.asarray(estimate.velocity_covariance_ned, dtype=float).reshape(9)]
    vn, ve, vd = (float(v) for v in estimate.velocity_ned_m_s)
    return mavlink2.MAVLink_vision_speed_estimate_message(
        usec=capture_time_usec(estimate.t_ns), x=vn, y=ve, z=vd,
        covariance=covariance, reset_counter=estimate.reset_counter % 256,
    )


def odometry_quality(estimate: Estimate) -> int:
    """ODOMETRY.quality in 1..100 from the position standard deviation (0 means unknown)."""
    position_std_m = math.sqrt(max(float(np.trace(estimate.covariance_ned[:3, :3])), 0.0) / 3.0)
    # quality = 100 (1 - sigma / sigma_zero), at least 1
    return int(max(1, min(100, round(100.0 * (1.0 - position_std_m / QUALITY_ZERO_STD_M)))))


def odometry(estimate: Estimate) -> Message:
    """ODOMETRY (331), frame MAV_FRAME_LOCAL_FRD, child MAV_FRAME_BODY_FRD.

    The local frame is the estimate's earth-fixed NED-like frame (for a map
    whose heading is not known it is the map's own forward-right-down frame,
    which is what LOCAL_FRD means); the velocity is expressed in the child
    (body FRD) frame as the message requires.
    """
    R_ned_body = frames.rotation_from_euler_321(estimate.roll_rad, estimate.pitch_rad, estimate.yaw_rad)
    q = frames.quaternion_from_rotation(R_ned_body)
    # v_body = R_ned_body^T v_ned
    v_body = R_ned_body.T @ np.asarray(estimate.velocity_ned_m_s, dtype=float)
    if estimate.velocity_covariance_ned is None:
        velocity_covariance = [math.nan] + [0.0] * 20
    else:
        C = np.full((6, 6), 0.0)
        # Cov(v_body) = R^T Cov(v_ned) R; angular rates are not estimated (0 covariance rows).
        C[:3, :3] = R_ned_body.T @ np.asarray(estimate.velocity_covariance_ned, dtype=float) @ R_ned_body
        velocity_covariance = upper_triangle(C)
    n, e, d = (float(v) for v in estimate.position_ned_m)
    return mavlink2.MAVLink_odometry_message(
        time_usec=capture_time_usec(estimate.t_ns),
        frame_id=mavlink2.MAV_FRAME_LOCAL_FRD,
        child_frame_id=mavlink2.MAV_FRAME_BODY_FRD,
        x=n, y=e, z=d,
        q=[float(v) for v in q],
        vx=float(v_body[0]), vy=float(v_body[1]), vz=float(v_body[2]),
        rollspeed=math.nan, pitchspeed=math.nan, yawspeed=math.nan,
        pose_covariance=upper_triangle(estimate.covariance_ned),
        velocity_covariance=velocity_covariance,
        reset_counter=estimate.reset_counter % 256,
        estimator_type=mavlink2.MAV_ESTIMATOR_TYPE_VISION,
        quality=odometry_quality(estimate),
    )


FC_HEARTBEAT_PERIOD_S = 1.0  # ArduPilot and PX4 send their HEARTBEAT at 1 Hz: a new link hears one within this


def heartbeat(system_status: int, instance: int = 0) -> Message:
    """HEARTBEAT of an onboard controller (type 18) that is no autopilot (8).

    system_status: MAV_STATE_STANDBY, ACTIVE or CRITICAL. instance: this
    process's token in ``custom_mode`` (free for a non-autopilot): another
    process sending our ids has a different one (``companion.mavlink.link``).
    """
    return mavlink2.MAVLink_heartbeat_message(
        type=mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
        autopilot=mavlink2.MAV_AUTOPILOT_INVALID,
        base_mode=0,
        custom_mode=int(instance) & 0xFFFFFFFF,
        system_status=system_status,
        mavlink_version=3,
    )


def set_gps_global_origin(target_system: int, latitude_deg: float, longitude_deg: float,
                          altitude_m: float, t_ns: int) -> Message:
    """SET_GPS_GLOBAL_ORIGIN (48): degE7 latitude/longitude, mm altitude (MSL)."""
    return mavlink2.MAVLink_set_gps_global_origin_message(
        target_system=target_system,
        latitude=int(round(latitude_deg * 1e7)),
        longitude=int(round(longitude_deg * 1e7)),
        altitude=int(round(altitude_m * 1000.0)),
        time_usec=capture_time_usec(t_ns),
    )


def request_message(target_system: int, target_component: int, message_id: int) -> Message:
    """COMMAND_LONG MAV_CMD_REQUEST_MESSAGE (512) asking for one message by id."""
    return mavlink2.MAVLink_command_long_message(
        target_system=target_system, target_component=target_component,
        command=mavlink2.MAV_CMD_REQUEST_MESSAGE, confirmation=0,
        param1=float(message_id), param2=0, param3=0, param4=0, param5=0, param6=0, param7=0,
    )


def set_message_interval(target_system: int, target_component: int, message_id: int, rate_hz: float) -> Message:
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (511): stream a message at ``rate_hz`` (interval in microseconds)."""
    return mavlink2.MAVLink_command_long_message(
        target_system=target_system, target_component=target_component,
        command=mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, confirmation=0,
        param1=float(message_id), param2=float(round(1e6 / rate_hz)), param3=0, param4=0, param5=0, param6=0,
        param7=0,
    )


def request_gps_global_origin(target_system: int, target_component: int) -> Message:
    return request_message(target_system, target_component, mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)


def request_home_position(target_system: int, target_component: int) -> Message:
    return request_message(target_system, target_component, mavlink2.MAVLINK_MSG_ID_HOME_POSITION)


def request_ekf_status(target_system: int, target_component: int) -> Message:
    """MAV_CMD_REQUEST_MESSAGE for ArduPilot's EKF_STATUS_REPORT (193), streamed only on some ports."""
    return request_message(target_system, target_component, ardupilot.MAVLINK_MSG_ID_EKF_STATUS_REPORT)


def set_home_here(target_system: int, target_component: int) -> Message:
    """COMMAND_LONG MAV_CMD_DO_SET_HOME (179) with param1 = 1: home at the vehicle's current position."""
    return mavlink2.MAVLink_command_long_message(
        target_system=target_system, target_component=target_component,
        command=mavlink2.MAV_CMD_DO_SET_HOME, confirmation=0,
        param1=1, param2=0, param3=0, param4=0, param5=0, param6=0, param7=0,
    )


def ekf_has_horizontal_position(flags: int) -> bool:
    """An EKF_STATUS_REPORT's flags say the EKF has a horizontal position (relative or absolute): from
    vision, when nothing else gives it one."""
    return bool(flags & (ardupilot.EKF_POS_HORIZ_REL | ardupilot.EKF_POS_HORIZ_ABS))


def ekf_ready(flags: int) -> bool:
    """An EKF_STATUS_REPORT's flags say the EKF has its attitude and has been initialised."""
    return bool(flags & EKF_READY_FLAG) and not flags & EKF_UNINITIALIZED_FLAG


def param_request_read(target_system: int, target_component: int, name: str) -> Message:
    """PARAM_REQUEST_READ (20) of one parameter by name (param_index -1)."""
    return mavlink2.MAVLink_param_request_read_message(
        target_system=target_system, target_component=target_component,
        param_id=name.encode("ascii")[:PARAM_ID_MAX_CHARS], param_index=-1,
    )


def param_value(message, bytewise: bool) -> tuple[str, float]:
    """(name, value) of a PARAM_VALUE. ``bytewise``: the autopilot puts an integer parameter's
    bytes into the float field (PX4); otherwise the float is the value (ArduPilot)."""
    name = message.param_id
    name = (name.decode("ascii", "replace") if isinstance(name, bytes) else str(name)).rstrip("\x00")
    value = float(message.param_value)
    fmt = INTEGER_PARAM_TYPES.get(message.param_type)
    if bytewise and fmt is not None:
        raw = struct.pack("<f", value)
        value = float(struct.unpack(fmt, raw[:struct.calcsize(fmt)])[0])
    return name, value


def statustext(severity: int, text: str) -> Message:
    """STATUSTEXT (253), ASCII, cut to the 50 characters of one chunk."""
    data = text.encode("ascii", "replace")[:STATUSTEXT_MAX_CHARS]
    return mavlink2.MAVLink_statustext_message(severity=severity, text=data, id=0, chunk_seq=0)


def statustext_chunks(severity: int, text: str, text_id: int) -> list[Message]:
    """The STATUSTEXTs of one text: itself (id 0) if it fits the 50 characters of one, else chunks of 50 that
    ground stations join by their ``id`` (``text_id``, 1-65535) and ``chunk_seq``, the last one ended by a NUL
    (an empty chunk after a text of whole chunks), at most ``STATUSTEXT_MAX_CHUNKS`` of them (the rest cut)."""
    data = text.encode("ascii", "replace")[:STATUSTEXT_MAX_CHUNKS * STATUSTEXT_MAX_CHARS - 1]
    if len(data) <= STATUSTEXT_MAX_CHARS:
        return [statustext(severity, text)]
    pieces = [data[start:start + STATUSTEXT_MAX_CHARS] for start in range(0, len(data) + 1, STATUSTEXT_MAX_CHARS)]
    return [mavlink2.MAVLink_statustext_message(severity=severity, text=piece, id=text_id, chunk_seq=seq)
            for seq, piece in enumerate(pieces)]


def timesync_reply(request_ts1: int, now_ns: int) -> Message:
    """TIMESYNC (111) answer: our time in tc1, the request's ts1 mirrored."""
    return mavlink2.MAVLink_timesync_message(tc1=int(now_ns), ts1=int(request_ts1))


def is_timesync_request(message) -> bool:
    return message.get_type() == "TIMESYNC" and message.tc1 == 0
