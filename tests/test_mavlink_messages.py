"""Message builders: field values, units, layouts, and MAVLink 2 framing (no sockets)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.geometry import frames
from companion.mavlink import messages as mm
from companion.types import Estimate


def estimate(**overrides) -> Estimate:
    cov = np.diag([0.01, 0.02, 0.03, 0.004, 0.005, 0.006])
    cov[0, 1] = cov[1, 0] = 0.001
    cov[2, 5] = cov[5, 2] = 0.0007
    values = dict(
        t_ns=12_345_678_901, position_ned_m=np.array([1.5, -2.25, -1.0]),
        velocity_ned_m_s=np.array([0.5, 0.25, -0.1]), roll_rad=0.05, pitch_rad=-0.1, yaw_rad=1.2,
        covariance_ned=cov, reset_counter=3, tracking=True,
    )
    values.update(overrides)
    return Estimate(**values)


def roundtrip(message):
    """Pack as a MAVLink 2 frame (sysid 1, compid 197) and parse it back."""
    mav = mm.mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    frame = message.pack(mav)
    assert frame[0] == 0xFD, "not a MAVLink 2 frame"
    parser = mm.mavlink2.MAVLink(None)
    decoded = parser.parse_char(frame)
    assert decoded is not None
    return decoded, frame


def test_upper_triangle_layout_matches_mavlink_indices():
    C = np.arange(36, dtype=float).reshape(6, 6)
    C = C + C.T
    tri = mm.upper_triangle(C)
    assert len(tri) == 21
    for index, (row, col) in {0: (0, 0), 1: (0, 1), 5: (0, 5), 6: (1, 1), 11: (2, 2),
                              15: (3, 3), 18: (4, 4), 20: (5, 5)}.items():
        assert tri[index] == C[row, col]


def test_vision_position_estimate_fields_and_extensions_survive_the_wire():
    est = estimate()
    decoded, frame = roundtrip(mm.vision_position_estimate(est))
    assert decoded.get_type() == "VISION_POSITION_ESTIMATE"
    assert decoded.usec == 12_345_678  # capture time in microseconds
    assert (decoded.x, decoded.y, decoded.z) == pytest.approx((1.5, -2.25, -1.0))
    assert (decoded.roll, decoded.pitch, decoded.yaw) == pytest.approx((0.05, -0.1, 1.2))
    assert decoded.covariance[0] == pytest.approx(0.01)
    assert decoded.covariance[1] == pytest.approx(0.001)
    assert decoded.covariance[6] == pytest.approx(0.02)
    assert decoded.covariance[11] == pytest.approx(0.03)
    assert decoded.covariance[14] == pytest.approx(0.0007)  # (2, 5)
    assert decoded.covariance[20] == pytest.approx(0.006)
    assert decoded.reset_counter == 3
    # ArduPilot's scalar position error from the same message
    pos_err = math.sqrt(decoded.covariance[0] + decoded.covariance[6] + decoded.covariance[11])
    assert pos_err == pytest.approx(math.sqrt(0.06), rel=1e-5)


def test_reset_counter_wraps_at_uint8():
    assert mm.vision_position_estimate(estimate(reset_counter=257)).reset_counter == 1


def test_vision_speed_estimate_with_and_without_covariance():
    Cv = np.diag([0.04, 0.05, 0.06])
    decoded, _ = roundtrip(mm.vision_speed_estimate(estimate(velocity_covariance_ned=Cv)))
    assert (decoded.x, decoded.y, decoded.z) == pytest.approx((0.5, 0.25, -0.1))
    assert decoded.covariance[0] == pytest.approx(0.04) and decoded.covariance[4] == pytest.approx(0.05)
    assert decoded.covariance[8] == pytest.approx(0.06) and decoded.reset_counter == 3
    unknown = mm.vision_speed_estimate(estimate(velocity_covariance_ned=None))
    assert math.isnan(unknown.covariance[0])


def test_odometry_frames_quaternion_body_velocity_and_quality():
    est = estimate(velocity_covariance_ned=np.eye(3) * 0.01)
    decoded, _ = roundtrip(mm.odometry(est))
    assert decoded.frame_id == 20 and decoded.child_frame_id == 12  # LOCAL_FRD, BODY_FRD
    assert decoded.estimator_type == mm.mavlink2.MAV_ESTIMATOR_TYPE_VISION
    R = frames.rotation_from_quaternion(decoded.q)
    assert frames.euler_321_from_rotation(R) == pytest.approx((0.05, -0.1, 1.2), abs=1e-6)
    v_ned = R @ np.array([decoded.vx, decoded.vy, decoded.vz])
    np.testing.assert_allclose(v_ned, [0.5, 0.25, -0.1], atol=1e-6)
    assert decoded.pose_covariance[0] == pytest.approx(0.01) and decoded.pose_covariance[20] == pytest.approx(0.006)
    assert decoded.velocity_covariance[0] == pytest.approx(0.01)
    assert decoded.reset_counter == 3
    # sigma = sqrt(0.06 / 3) = 0.141 m -> quality 86
    assert decoded.quality == 86


def test_odometry_quality_falls_with_uncertainty_but_stays_known():
    sharp = mm.odometry_quality(estimate(covariance_ned=np.eye(6) * 1e-6))
    vague = mm.odometry_quality(estimate(covariance_ned=np.eye(6) * 25.0))
    assert sharp == 100 and vague == 1


def test_heartbeat_is_an_onboard_controller_not_an_autopilot():
    decoded, _ = roundtrip(mm.heartbeat(mm.mavlink2.MAV_STATE_ACTIVE, instance=0xDEADBEEF))
    assert decoded.type == 18 and decoded.autopilot == 8
    assert decoded.system_status == mm.mavlink2.MAV_STATE_ACTIVE
    assert decoded.custom_mode == 0xDEADBEEF  # the process's token travels in custom_mode
    assert mm.heartbeat(mm.mavlink2.MAV_STATE_CRITICAL).system_status == 5  # MAV_STATE_CRITICAL in common.xml
    assert decoded.get_srcSystem() == 1 and decoded.get_srcComponent() == 197


def test_ekf_is_ready_with_its_attitude_once_initialised():
    # EKF_STATUS_FLAGS of ardupilotmega.xml: EKF_ATTITUDE = 1, EKF_UNINITIALIZED = 1024
    assert mm.ekf_ready(1 | 2 | 4)
    assert not mm.ekf_ready(1024) and not mm.ekf_ready(1 | 1024) and not mm.ekf_ready(2 | 4)


def test_param_value_as_ardupilot_and_as_px4_encode_it():
    # ArduPilot: the float is the value; PX4 (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): an INT32
    # parameter's bytes sit in the float field.
    import struct
    ardupilot = mm.mavlink2.MAVLink_param_value_message(b"VISO_TYPE", 1.0, 2, 100, 7)
    assert mm.param_value(ardupilot, bytewise=False) == ("VISO_TYPE", 1.0)
    bits_of_15 = struct.unpack("<f", struct.pack("<i", 15))[0]
    px4 = mm.mavlink2.MAVLink_param_value_message(b"EKF2_EV_CTRL", bits_of_15, 6, 900, 3)
    decoded, _ = roundtrip(px4)
    assert mm.param_value(decoded, bytewise=True) == ("EKF2_EV_CTRL", 15.0)
    delay = mm.mavlink2.MAVLink_param_value_message(b"EKF2_EV_DELAY", 35.5, 9, 900, 4)  # REAL32: a float
    assert mm.param_value(delay, bytewise=True) == ("EKF2_EV_DELAY", 35.5)


def test_set_gps_global_origin_units():
    decoded, _ = roundtrip(mm.set_gps_global_origin(7, 47.3977419, 8.5455938, 488.25, 5_000_000_000))
    assert decoded.target_system == 7
    assert decoded.latitude == 473977419 and decoded.longitude == 85455938
    assert decoded.altitude == 488250 and decoded.time_usec == 5_000_000


def test_request_message_asks_for_gps_global_origin():
    decoded, _ = roundtrip(mm.request_gps_global_origin(1, 1))
    assert decoded.command == 512 and decoded.param1 == 49.0
    assert (decoded.target_system, decoded.target_component) == (1, 1)


def test_statustext_is_cut_to_one_chunk():
    decoded, _ = roundtrip(mm.statustext(4, "companion: markers lost " + "x" * 80))
    assert decoded.severity == 4
    assert decoded.text.startswith("companion: markers lost") and len(decoded.text) == 50


@pytest.mark.parametrize("length", [51, 100, 149, 249, 400])
def test_a_text_longer_than_one_statustext_goes_in_chunks_a_ground_station_joins(length):
    text = ("companion: camera lost: camera /dev/video0: cannot open it " * 8)[:length]
    chunks = [roundtrip(m)[0] for m in mm.statustext_chunks(4, text, text_id=7)]
    assert {(c.id, c.severity) for c in chunks} == {(7, 4)}
    assert [c.chunk_seq for c in chunks] == list(range(len(chunks)))
    assert all(len(c.text) == 50 for c in chunks[:-1]) and len(chunks[-1].text) < 50   # the last ends with a NUL
    joined = "".join(c.text for c in chunks)
    assert joined == text[:mm.STATUSTEXT_MAX_CHUNKS * 50 - 1]
    assert [c.text for c in map(lambda m: roundtrip(m)[0], mm.statustext_chunks(4, text[:50], 8))] == [text[:50]]
    assert roundtrip(mm.statustext_chunks(4, text[:50], 8)[0])[0].id == 0   # one that fits is no chunk


def test_timesync_reply_mirrors_ts1_and_is_not_a_request():
    reply = mm.timesync_reply(request_ts1=111_222_333, now_ns=999_000_000_000)
    decoded, _ = roundtrip(reply)
    assert decoded.ts1 == 111_222_333 and decoded.tc1 == 999_000_000_000
    assert not mm.is_timesync_request(decoded)
    assert mm.is_timesync_request(mm.mavlink2.MAVLink_timesync_message(tc1=0, ts1=5))
