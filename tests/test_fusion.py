"""PoseFilter on synthetic PoseMeasurements with known truth."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.daemon.config import ConfigError, config_from_dict
from companion.geometry import frames
from companion.fusion import (FusionError, FusionParams, PoseFilter, TrackState, covering, process_noise,
                              wrap_angle_rad)
from companion.types import PoseMeasurement

REPO = Path(__file__).resolve().parents[1]
POS_STD_M = 0.03
YAW_STD_RAD = math.radians(1.5)


def measurement(t_s: float, position_ned_m, yaw_rad: float, roll_rad: float = 0.0,
                pitch_rad: float = 0.0, pos_std_m: float = POS_STD_M,
                yaw_std_rad: float = YAW_STD_RAD) -> PoseMeasurement:
    R = frames.rotation_from_euler_321(roll_rad, pitch_rad, yaw_rad)
    T_ned_body = frames.make_transform(R, position_ned_m)
    cov = np.diag([pos_std_m ** 2] * 3 + [math.radians(1.0) ** 2] * 2 + [yaw_std_rad ** 2])
    return PoseMeasurement(
        t_ns=int(round(t_s * 1e9)),
        T_map_body=np.eye(4),  # not used by the filter
        T_ned_body=T_ned_body,
        covariance_ned=cov,
        marker_ids=(1,),
        reprojection_rms_px=0.3,
    )


def straight_line(t_s: float) -> np.ndarray:
    return np.array([1.0 + 0.8 * t_s, -2.0 + 0.3 * t_s, -1.5 - 0.05 * t_s])


def run(filter_, times_s, truth, yaw_of=lambda t: 0.3, noise=None, rng=None):
    estimates = []
    for t in times_s:
        p = truth(t)
        if noise is not None:
            p = p + rng.normal(0, noise, 3)
        estimates.append(filter_.step(int(round(t * 1e9)), measurement(t, p, yaw_of(t))))
    return estimates


def test_fused_track_is_closer_to_truth_than_raw_poses():
    rng = np.random.default_rng(1)
    times = np.arange(0, 6, 1 / 30)
    pf = PoseFilter()
    raw_err, fused_err, velocities = [], [], []
    for t in times:
        noisy = straight_line(t) + rng.normal(0, POS_STD_M, 3)
        est = pf.step(int(round(t * 1e9)), measurement(t, noisy, 0.3))
        if est is not None and t > 1.0:
            raw_err.append(np.linalg.norm(noisy - straight_line(t)))
            fused_err.append(np.linalg.norm(est.position_ned_m - straight_line(t)))
            velocities.append(est.velocity_ned_m_s)
    assert len(fused_err) > 100
    assert np.sqrt(np.mean(np.square(fused_err))) < 0.7 * np.sqrt(np.mean(np.square(raw_err)))
    np.testing.assert_allclose(np.mean(velocities, axis=0), [0.8, 0.3, -0.05], atol=0.05)
    assert pf.counters.rejected == 0
    assert est.tracking and pf.state is TrackState.TRACKING


def test_first_fix_needs_confirm_frames_consistent_poses():
    pf = PoseFilter(FusionParams(confirm_frames=3))
    out = run(pf, [0.0, 0.033, 0.066, 0.1], straight_line)
    assert out[0] is None and out[1] is None
    assert out[2] is not None and out[3] is not None
    assert out[2].reset_counter == 0


def test_variable_time_steps_track_the_motion():
    rng = np.random.default_rng(2)
    times = np.cumsum(rng.uniform(0.01, 0.12, 80))
    pf = PoseFilter()
    out = run(pf, times, straight_line)
    est = out[-1]
    assert np.linalg.norm(est.position_ned_m - straight_line(times[-1])) < 0.02
    np.testing.assert_allclose(est.velocity_ned_m_s, [0.8, 0.3, -0.05], atol=0.05)
    assert est.t_ns == int(round(times[-1] * 1e9))


def test_outlier_is_gated_counted_and_does_not_drag_the_estimate():
    pf = PoseFilter()
    times = np.arange(0, 2, 1 / 30)
    run(pf, times, straight_line)
    t = times[-1] + 1 / 30
    before = pf.counters.rejected
    est = pf.step(int(t * 1e9), measurement(t, straight_line(t) + [3.0, 0, 0], 0.3))
    assert pf.counters.rejected == before + 1
    assert est is not None and not est.tracking and pf.state is TrackState.COASTING
    assert np.linalg.norm(est.position_ned_m - straight_line(t)) < 0.05
    t += 1 / 30
    est = pf.step(int(t * 1e9), measurement(t, straight_line(t), 0.3))
    assert est.tracking and est.reset_counter == 0


def test_single_yaw_flip_is_rejected_and_output_yaw_never_jumps():
    pf = PoseFilter()
    times = np.arange(0, 3, 1 / 30)
    yaws = []
    for i, t in enumerate(times):
        yaw = 0.5 + (math.pi if i in (40, 41, 70) else 0.0)
        est = pf.step(int(t * 1e9), measurement(t, straight_line(t), yaw))
        if est is not None:
            yaws.append(est.yaw_rad)
    assert pf.counters.rejected == 3
    assert max(abs(wrap_angle_rad(b - a)) for a, b in zip(yaws, yaws[1:])) < math.radians(2)


def test_yaw_through_plus_minus_pi_is_continuous_not_rejected():
    pf = PoseFilter()
    times = np.arange(0, 4, 1 / 30)
    # 0.6 rad/s from 2.5 rad: crosses +pi at about 1.07 s
    yaw_of = lambda t: wrap_angle_rad(2.5 + 0.6 * t)
    out = [e for e in run(pf, times, straight_line, yaw_of=yaw_of) if e is not None]
    assert pf.counters.rejected == 0
    errors = [abs(wrap_angle_rad(e.yaw_rad - yaw_of(e.t_ns * 1e-9))) for e in out]
    assert max(errors) < math.radians(1)
    assert all(-math.pi <= e.yaw_rad < math.pi for e in out)


def test_coasting_is_bounded_then_nothing_is_sent():
    params = FusionParams(max_coast_s=0.2)
    pf = PoseFilter(params)
    times = np.arange(0, 2, 1 / 30)
    last = run(pf, times, straight_line)[-1]
    coast, losses = [], []
    t = times[-1]
    for _ in range(12):  # 0.4 s without markers
        t += 1 / 30
        coast.append(pf.step(int(t * 1e9), None))
        losses.append(pf.loss)
    sent = [e for e in coast if e is not None]
    # said once, at the frame that ended the track: frames kept coming, the poses stopped
    lost_at = [i for i, loss in enumerate(losses) if loss is not None]
    assert lost_at == [len(sent)] and not losses[len(sent)].no_frames
    assert 0.2 < losses[len(sent)].without_fix_s < 0.25 and losses[len(sent)].frame_gap_s == pytest.approx(1 / 30)
    assert 5 <= len(sent) <= 6 and all(e is not None for e in coast[:5])
    assert all(e is None for e in coast[7:])
    assert pf.state is TrackState.ACQUIRING and pf.counters.lost == 1
    # Prediction follows the motion and its variance grows.
    assert np.linalg.norm(sent[-1].position_ned_m - straight_line(sent[-1].t_ns * 1e-9)) < 0.02
    assert sent[-1].covariance_ned[0, 0] > 2 * last.covariance_ned[0, 0]
    assert not any(e.tracking for e in sent)


def test_reacquisition_after_a_jump_increments_reset_counter_and_snaps():
    pf = PoseFilter(FusionParams(max_coast_s=0.2, confirm_frames=2))
    run(pf, np.arange(0, 1, 1 / 30), straight_line)
    t = 1.0
    while pf.state is not TrackState.ACQUIRING:
        t += 1 / 30
        pf.step(int(t * 1e9), None)
    jumped = lambda s: straight_line(s) + np.array([2.0, -1.0, 0.0])
    t += 0.5
    first = pf.step(int(t * 1e9), measurement(t, jumped(t), 0.3))
    t += 1 / 30
    second = pf.step(int(t * 1e9), measurement(t, jumped(t), 0.3))
    assert first is None
    assert second.reset_counter == 1 and pf.counters.resets == 1
    assert np.linalg.norm(second.position_ned_m - jumped(t)) < 0.05


def test_a_jump_after_a_gap_in_the_frames_is_a_reacquisition_with_a_reset():
    """No frames for 2 s (a camera that stalled, a dropped stretch of a recording), then the vehicle is 2.8 m
    away: the prediction's covariance grew enough over the gap to pass the jump as tracking (reset 0)."""
    pf = PoseFilter(FusionParams(max_coast_s=0.25, confirm_frames=3))
    still = lambda s: np.array([6.7, -1.9, -1.5])
    last = run(pf, np.arange(0, 2, 1 / 30), still)[-1]
    assert last.tracking and last.reset_counter == 0
    moved = np.array([8.9, -0.2, -1.5])
    after_gap = [pf.step(int(4.0 * 1e9), measurement(4.0, moved, 0.3))]
    assert pf.loss.no_frames and pf.loss.frame_gap_s == pytest.approx(2.033, abs=0.01)  # the gap ended the track
    after_gap += [pf.step(int(t * 1e9), measurement(t, moved, 0.3)) for t in (4.033, 4.066)]
    assert pf.loss is None
    assert pf.counters.lost == 1 and after_gap[0] is None   # lost, then acquired again on its own poses
    assert after_gap[-1].reset_counter == 1 and np.linalg.norm(after_gap[-1].position_ned_m - moved) < 0.05
    # a gap in place: acquired again, no reset
    pf = PoseFilter(FusionParams(max_coast_s=0.25, confirm_frames=3))
    run(pf, np.arange(0, 2, 1 / 30), still)
    again = run(pf, [4.0, 4.033, 4.066], still)
    assert pf.counters.lost == 1 and again[-1].reset_counter == 0


def test_reacquisition_in_place_keeps_reset_counter():
    pf = PoseFilter(FusionParams(max_coast_s=0.2, confirm_frames=2))
    still = lambda s: np.array([1.0, 2.0, -1.0])
    run(pf, np.arange(0, 1, 1 / 30), still)
    t = 1.0
    for _ in range(20):
        t += 1 / 30
        pf.step(int(t * 1e9), None)
    assert pf.state is TrackState.ACQUIRING
    out = run(pf, [t + 0.1, t + 0.133, t + 0.166], still)
    assert out[-1].reset_counter == 0 and pf.counters.acquisitions == 2


def test_lone_flipped_pose_while_acquiring_never_makes_a_fix():
    pf = PoseFilter(FusionParams(confirm_frames=2))
    seq = [(0.0, 0.3), (0.033, 0.3 + math.pi), (0.066, 0.3), (0.1, 0.3)]
    out = [pf.step(int(t * 1e9), measurement(t, straight_line(t), yaw)) for t, yaw in seq]
    assert out[:3] == [None, None, None]
    assert out[3] is not None and abs(out[3].yaw_rad - 0.3) < 0.02


def test_out_of_order_frames_are_counted_and_ignored():
    pf = PoseFilter(FusionParams(confirm_frames=1))
    run(pf, [0.0, 0.1], straight_line)
    assert pf.step(int(0.05e9), measurement(0.05, straight_line(0.05), 0.3)) is None
    assert pf.counters.out_of_order == 1


def test_estimate_covariance_is_symmetric_positive_definite_and_carries_rotation():
    pf = PoseFilter(FusionParams(confirm_frames=1))
    est = run(pf, np.arange(0, 1, 0.05), straight_line)[-1]
    C = est.covariance_ned
    np.testing.assert_allclose(C, C.T)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    assert C[3, 3] == pytest.approx(math.radians(1.0) ** 2)
    assert 0 < C[5, 5] < YAW_STD_RAD ** 2
    Cv = est.velocity_covariance_ned
    assert Cv.shape == (3, 3) and np.all(np.linalg.eigvalsh(Cv) > 0)


def test_covering_is_above_both_and_equal_to_the_larger_where_one_is():
    rng = np.random.default_rng(3)
    for _ in range(50):
        A, B = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
        P, M = A @ A.T + 0.01 * np.eye(4), B @ B.T  # M of rank 2: below P in two directions at least
        C = covering(P, M)
        np.testing.assert_allclose(C, C.T, atol=1e-12)
        assert np.linalg.eigvalsh(C - P).min() > -1e-9 and np.linalg.eigvalsh(C - M).min() > -1e-9
        np.testing.assert_allclose(covering(P, 0.5 * P), P, atol=1e-12)
        np.testing.assert_allclose(covering(P, 2.0 * P), 2.0 * P, atol=1e-12)
        assert np.trace(C) < np.trace(P + M)  # not the sum: no more than needed


def test_the_maps_share_of_a_poses_error_is_not_averaged_away():
    """Sixty frames that see the same markers, each pose 3 cm sd of which 2.5 cm (and 1 deg of yaw) is the map's
    error (the same in every frame): the filter averages the rest, but what it sends still states at least the
    map's share. Without a share stated, the covariance shrinks well below it, as it should for noise alone."""
    share = np.diag([0.025 ** 2] * 3 + [0.0] * 2 + [math.radians(1.0) ** 2])

    def with_share(m):
        return PoseMeasurement(m.t_ns, m.T_map_body, m.T_ned_body, m.covariance_ned, m.marker_ids,
                               m.reprojection_rms_px, map_covariance_ned=share)

    times_s = np.arange(0, 2, 1 / 30)
    plain, shared = PoseFilter(FusionParams(confirm_frames=1)), PoseFilter(FusionParams(confirm_frames=1))
    for t in times_s:
        p = straight_line(t)
        last_plain = plain.step(int(round(t * 1e9)), measurement(t, p, 0.3))
        last_shared = shared.step(int(round(t * 1e9)), with_share(measurement(t, p, 0.3)))
    assert np.sqrt(last_plain.covariance_ned[0, 0]) < 0.02  # below the 2.5 cm share
    sent = last_shared.covariance_ned[np.ix_([0, 1, 2, 5], [0, 1, 2, 5])]
    assert np.linalg.eigvalsh(sent - share[np.ix_([0, 1, 2, 5], [0, 1, 2, 5])]).min() > -1e-12
    assert np.sqrt(sent[0, 0]) == pytest.approx(0.025, rel=0.1)
    np.testing.assert_allclose(last_shared.position_ned_m, last_plain.position_ned_m)  # weighed as before


def test_roll_and_pitch_pass_through_from_the_newest_pose():
    pf = PoseFilter(FusionParams(confirm_frames=1))
    est = pf.step(0, measurement(0.0, [0, 0, -1], 1.0, roll_rad=0.1, pitch_rad=-0.2))
    assert est.roll_rad == pytest.approx(0.1) and est.pitch_rad == pytest.approx(-0.2)
    assert est.yaw_rad == pytest.approx(1.0)


@pytest.mark.parametrize("bad", [dict(gate_probability=0), dict(gate_probability=1.5), dict(confirm_frames=0), dict(max_coast_s=-1),
                                 dict(accel_noise_m_s2=float("nan")), dict(confirm_frames=True),
                                 dict(reset_distance_m=True)])
def test_bad_parameters_name_the_parameter(bad):
    with pytest.raises(FusionError, match=next(iter(bad))):
        FusionParams(**bad)


def test_gate_is_the_chi2_quantile_of_its_probability():
    # 99.9 % and 99 % points of the chi-square distribution with 4 dof (printed tables)
    assert PoseFilter().gate_chi2 == pytest.approx(18.467, abs=1e-3)
    assert PoseFilter(FusionParams(gate_probability=0.99)).gate_chi2 == pytest.approx(13.277, abs=1e-3)


def test_replaced_gate_chi2_key_names_its_successor():
    config = {"source": {"kind": "v4l2"}, "map": str(REPO / "maps" / "warehouse.yaml"),
              "camera": {"width": 640, "height": 480, "hfov_deg": 70.0}, "fusion": {"gate_chi2": 18.47}}
    with pytest.raises(ConfigError, match=r"^site.yaml: fusion.gate_chi2: replaced by gate_probability"):
        config_from_dict(config, "site.yaml")


@pytest.mark.parametrize("dt, accel, yaw_accel", [(1 / 30, 3.0, 3.0), (0.2, 1.5, 0.4), (1.0, 0.7, 2.5)])
def test_process_noise_is_the_white_noise_acceleration_closed_form(dt, accel, yaw_accel):
    # Per axis, an acceleration a held over dt moves the state by G a with G = [dt^2 / 2, dt]:
    # Q_axis = G G^T sigma_a^2; the state is [n, e, d, yaw, vn, ve, vd, yaw_rate].
    Q = process_noise(dt, FusionParams(accel_noise_m_s2=accel, yaw_accel_noise_rad_s2=yaw_accel))
    expected = np.zeros((8, 8))
    for axis, sigma in enumerate([accel, accel, accel, yaw_accel]):
        G = np.zeros(8)
        G[axis], G[axis + 4] = dt ** 2 / 2, dt
        expected += np.outer(G, G) * sigma ** 2
    np.testing.assert_allclose(Q, expected, rtol=1e-12, atol=0)


def test_a_pose_the_pose_stage_found_unambiguous_is_a_fix_at_once():
    """confirm_frames guards against a lone flipped pose; one the pose stage ruled every rival out for needs none."""
    from dataclasses import replace

    pf = PoseFilter(FusionParams(confirm_frames=3))
    assert pf.step(0, measurement(0.0, straight_line(0.0), 0.3)) is None          # an ordinary pose waits
    pf = PoseFilter(FusionParams(confirm_frames=3))
    first = replace(measurement(0.0, straight_line(0.0), 0.3), unambiguous=True)
    estimate = pf.step(0, first)
    assert estimate is not None and pf.state is TrackState.TRACKING
    np.testing.assert_allclose(estimate.position_ned_m, straight_line(0.0))
    # lost for a second, then an unambiguous pose 2 m away: a fix at once, and a reset
    pf.step(int(1.2e9), None)
    later = replace(measurement(1.2, straight_line(0.0) + [2.0, 0.0, 0.0], 0.3), unambiguous=True)
    again = pf.step(int(1.3e9), replace(later, t_ns=int(1.3e9)))
    assert again is not None and again.reset_counter == 1
