"""The daemon's health judged from frame records and the wall clock (a clock we step by hand)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.daemon.health import Health
from companion.daemon.pipeline import FrameRecord
from companion.daemon.status import DaemonStatus
from companion.fusion import TrackLoss
from companion.geometry.pose import PoseSolution
from companion.mavlink import fc_params
from companion.types import Detection, Estimate

PERIOD_NS = 66_666_667  # 15 fps


class Clock:
    def __init__(self):
        self.now_ns = 1_000_000_000

    def __call__(self) -> int:
        return self.now_ns


def detection() -> Detection:
    return Detection(symbol="A", id=0, corners_px=np.zeros((4, 2)), path="square", corrected=0, quality=1.0)


def estimate(t_ns: int, tracking: bool = True, reset_counter: int = 0) -> Estimate:
    return Estimate(t_ns=t_ns, position_ned_m=np.zeros(3), velocity_ned_m_s=np.zeros(3), roll_rad=0.0,
                    pitch_rad=0.0, yaw_rad=0.0, covariance_ned=np.eye(6) * 1e-4, reset_counter=reset_counter,
                    tracking=tracking)


def record(t_ns: int, markers: int = 2, status: str | None = "ok", tracking: bool | None = True,
           reset_counter: int = 0, track_loss: TrackLoss | None = None) -> FrameRecord:
    solution = None
    if markers:
        measurement = object() if status == "ok" else None
        solution = PoseSolution(measurement, status)
    est = None if tracking is None else estimate(t_ns, tracking, reset_counter)
    return FrameRecord(index=0, t_ns=t_ns, done_ns=t_ns, stage_ns=(0, 0, 0, 0), sent=False, latency_ns=None,
                       detections=tuple(detection() for _ in range(markers)), solution=solution, estimate=est,
                       track_loss=track_loss)


@pytest.fixture
def health():
    clock = Clock()
    said = []
    monitor = Health(lambda text, severity, topic: said.append((text, severity)), clock_ns=clock)
    return monitor, clock, said


def play(monitor, clock, count: int, **kwargs) -> None:
    """``count`` frames at 15 fps, each processed when captured."""
    for _ in range(count):
        clock.now_ns += PERIOD_NS
        monitor.observe(None, record(clock.now_ns, **kwargs))


def test_a_stall_is_reported_within_a_second_once_and_cleared_when_frames_return(health):
    monitor, clock, said = health
    play(monitor, clock, 30)
    assert monitor.check().state == "tracking" and said == [("tracking markers", 6)]
    # 3 frame periods at 15 fps are 0.2 s: the threshold is its floor, 0.5 s
    clock.now_ns += 400_000_000
    assert monitor.check().state == "tracking"
    clock.now_ns += 200_000_000
    state = monitor.check()
    assert state.state == "camera stalled" and state.critical and state.since_s == pytest.approx(0.6)
    for _ in range(20):  # it stays stalled: said once
        clock.now_ns += 100_000_000
        monitor.check()
    assert [text for text, _ in said].count("camera stalled: no frame for 0.6 s") == 1
    assert said[1][1] == 2  # MAV_SEVERITY_CRITICAL
    play(monitor, clock, 1)
    assert not monitor.check().critical
    assert said[-1] == ("camera delivers frames again", 6)


def test_a_slow_camera_is_no_stall_but_one_second_without_frames_is(health):
    monitor, clock, _ = health
    for _ in range(10):  # 2.5 fps: 3 periods are 1.2 s, the threshold its ceiling of 1 s
        clock.now_ns += 400_000_000
        monitor.observe(None, record(clock.now_ns))
    clock.now_ns += 900_000_000
    assert monitor.check().state == "tracking"
    clock.now_ns += 200_000_000
    assert monitor.check().state == "camera stalled"


def test_a_lost_source_is_critical_and_names_its_reason(health):
    monitor, clock, said = health
    play(monitor, clock, 5)
    state = monitor.check(lost_reason="camera /dev/video0: cannot open: /dev/video0 does not exist")
    assert state.state == "camera lost" and state.critical
    assert said[-1][0] == "camera lost: camera /dev/video0: cannot open: /dev/video0 does not exist"


def test_a_source_back_from_lost_is_not_called_stalled_before_its_first_frame(health):
    """A replay's files back after 20 s: its lost reason clears before the pipeline has a frame; 'camera
    stalled: no frame for 20.2 s' (CRITICAL) then 'frames again' 50 ms later was a false alarm."""
    monitor, clock, said = health
    play(monitor, clock, 5)
    for _ in range(200):
        clock.now_ns += 100_000_000
        monitor.check(lost_reason="replay: no frames")
    clock.now_ns += 100_000_000
    assert monitor.check().state == "tracking"   # back, its first frame not here yet: no alarm
    play(monitor, clock, 2)
    assert [text for text, _ in said] == ["tracking markers", "camera lost: replay: no frames",
                                          "camera delivers frames again"]
    # back from lost and then silent: a stall after the usual time
    monitor.check(lost_reason="replay: no frames")
    clock.now_ns += 600_000_000
    assert monitor.check().state == "camera stalled"


def test_markers_without_a_pose_for_two_seconds_name_the_reasons(health):
    monitor, clock, said = health
    play(monitor, clock, 20, status="uncertain", tracking=None)
    play(monitor, clock, 10, status="reprojection", tracking=None)
    # 30 frames = 2.0 s since the first: not yet
    assert monitor.check().state == "acquiring"
    play(monitor, clock, 2, status="uncertain", tracking=None)
    state = monitor.check()
    assert state.state == "no pose" and state.reasons == ("uncertain 22", "reprojection 10")
    assert said == [("no pose for 2.1 s: uncertain 22, reprojection 10", 4)]
    # a pose clears it (and the count)
    play(monitor, clock, 3)
    assert monitor.check().state == "tracking"


def test_no_markers_is_shown_and_the_filter_says_lost_and_reacquired(health):
    monitor, clock, said = health
    play(monitor, clock, 10)
    play(monitor, clock, 3, markers=0, tracking=False)   # coasting: no message
    play(monitor, clock, 6, markers=0, tracking=None)    # acquiring: markers lost
    assert monitor.check().state == "no markers"
    play(monitor, clock, 3, tracking=True, reset_counter=1)
    assert [text for text, _ in said] == ["tracking markers", "markers lost", "re-acquired (reset 1)"]


def test_a_reset_while_tracking_is_said_as_a_reacquisition(health):
    """After a gap in the frames an unambiguous pose is a fix at once: the filter goes from tracking to
    tracking, and only its reset counter says the position jumped."""
    monitor, clock, said = health
    play(monitor, clock, 10)
    play(monitor, clock, 5, reset_counter=1)
    assert [text for text, _ in said] == ["tracking markers", "re-acquired (reset 1)"]


def test_markers_lost_with_markers_in_view_says_why_the_pose_stage_gave_none(health):
    """A wrong camera or map loses the track while the markers stay in sight: 'markers lost' alone misleads."""
    monitor, clock, said = health
    play(monitor, clock, 10)
    play(monitor, clock, 3, status="implausible attitude", tracking=False)
    play(monitor, clock, 5, status="inconsistent markers", tracking=None)
    # the commonest since the last pose, when the filter gave up (the longest status still one STATUSTEXT)
    assert said[-1] == ("markers lost: implausible attitude", 4)
    assert len("companion: " + said[-1][0]) <= 50


def test_a_source_given_longer_for_its_first_frame_is_starting_until_then():
    """A simulated camera waits for the FC's first heartbeat (up to 1 s) before it asks for a state: health
    called a start whose first frame came 1.2 s in 'camera stalled' (CRITICAL, to the FC)."""
    clock = Clock()
    said = []
    monitor = Health(lambda text, severity, topic: said.append(text), clock_ns=clock, first_frame_within_s=2.0)
    clock.now_ns += 1_500_000_000
    assert monitor.check().state == "starting" and said == []
    clock.now_ns += 600_000_000
    assert monitor.check().state == "camera stalled"


def test_markers_lost_to_the_filter_gate_says_so(health):
    """Poses that the pose stage found but the filter gated off its track (a marker's map entry wrong, seen
    alone): 'markers lost' alone did not say why."""
    monitor, clock, said = health
    play(monitor, clock, 10)
    play(monitor, clock, 3, tracking=False)     # poses, gated: coasting
    play(monitor, clock, 1, tracking=None)      # the track ran out
    assert said[-1] == ("markers lost: filter gating", 4)


def test_markers_lost_after_a_gap_in_the_frames_says_the_gap_not_the_gate(health):
    """Frames stop for 3 s (a stalled camera) and the first pose after the gap waits to be confirmed as a new
    fix: the filter says the gap ended its track, which 'filter gating' misnamed (a recorded stall said
    'markers lost: filter gating'); a track the filter says ended with frames coming is the gate's."""
    monitor, clock, said = health
    play(monitor, clock, 10)
    clock.now_ns += 3_000_000_000
    play(monitor, clock, 1, tracking=None, track_loss=TrackLoss(3.07, 3.07, no_frames=True))  # a pose, not yet a fix
    assert said[-1] == ("markers lost: no frame for 3.1 s", 4)
    play(monitor, clock, 3, tracking=True)
    clock.now_ns += 100_000_000
    play(monitor, clock, 1, tracking=None, track_loss=TrackLoss(0.26, 0.17, no_frames=False))
    assert said[-1] == ("markers lost: filter gating", 4)
    assert len("companion: markers lost: no frame for 999.9 s") <= 50


def test_the_status_line_says_the_state_with_its_reasons():
    status = DaemonStatus(fps=0.0, markers=0, latency_ms=None, estimate=None, state="camera stalled", state_s=3.24,
                          reasons=("no frame for 3.2 s",), critical=True, track_state="acquiring",
                          link_state="streaming", frames=40, sent=30, rejected=0, resets=0)
    assert status.line() == ("  0.0 fps | markers 0 | no pose | latency - | camera stalled 3.2 s: no frame for 3.2 s"
                             " | link streaming | sent 30 rejected 0 resets 0")
    # a link that cannot open says why while it tries again (not once open: the reason is then old)
    down = dataclasses.replace(status, link_state="connecting", link_down="cannot open: [Errno 111] Connection refused")
    assert "| link connecting (cannot open: [Errno 111] Connection refused) | sent 30" in down.line()
    assert "(cannot open" not in dataclasses.replace(down, link_state="handshake").line()


def test_the_status_line_says_for_how_long_no_flight_controller_is_heard():
    """Vision may stream with no FC heard (the start order gives up waiting): the line says so beside the
    link's state, for as long as it lasts (not while the link is down: its reason is said then)."""
    status = DaemonStatus(fps=30.0, markers=3, latency_ms=6.0, estimate=None, state="tracking", state_s=0.0,
                          reasons=(), critical=False, track_state="tracking", link_state="streaming", frames=400,
                          sent=274, rejected=0, resets=0)
    assert "| link streaming | sent 274" in status.line()
    unheard = dataclasses.replace(status, fc_unheard_s=12.4)
    assert "| tracking | link streaming, no FC heard 12 s | sent 274 " in unheard.line()
    assert "| link handshake, no FC heard 12 s |" in dataclasses.replace(unheard, link_state="handshake").line()
    assert "no FC" not in dataclasses.replace(unheard, link_state="connecting", link_down="lost: x").line()
    garbled = dataclasses.replace(unheard, fc_unheard_why="undecodable bytes: a wrong baud rate, or not MAVLink?")
    assert "| link streaming, no FC heard 12 s (undecodable bytes: a wrong baud rate, or not MAVLink?) |" in \
        garbled.line()


# ---------------------------------------------------------------- parameters

GOOD = {"AHRS_EKF_TYPE": 3, "VISO_TYPE": 1, "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 6, "EK3_SRC1_YAW": 6,
        "EK3_SRC1_VELXY": 0, "VISO_DELAY_MS": 20, "VISO_POS_X": 0.0, "VISO_POS_Y": 0.0, "VISO_POS_Z": 0.0}
LEVER_ARM = (0.1, 0.0, 0.05)


def verdicts(values, **expected) -> dict[str, str]:
    checks = fc_params.check_parameters(fc_params.ARDUPILOT, values, fc_params.Expected(**expected))
    return {c.name: c.verdict for c in checks}


def test_a_vision_setup_by_the_docs_passes():
    assert set(verdicts(GOOD, lever_arm_m=LEVER_ARM, latency_ms=14.0).values()) == {"ok"}


@pytest.mark.parametrize("name, value, verdict", [
    ("VISO_TYPE", 0, "blocks"), ("VISO_TYPE", None, "blocks"), ("VISO_TYPE", 2, "degrades"),
    ("AHRS_EKF_TYPE", 2, "blocks"), ("EK3_SRC1_POSXY", 3, "blocks"), ("EK3_SRC1_POSZ", 1, "degrades"),
    ("EK3_SRC1_YAW", 1, "degrades"), ("EK3_SRC1_YAW", 0, "blocks"), ("EK3_SRC1_VELXY", 6, "degrades"),
    ("VISO_POS_X", 0.1, "degrades"), ("VISO_POS_Z", 0.05, "degrades"), ("VISO_DELAY_MS", 0, "degrades"),
    ("VISO_DELAY_MS", 80, "degrades"), ("VISO_DELAY_MS", 25, "ok"),
])
def test_each_ardupilot_parameter_is_judged_against_what_we_send(name, value, verdict):
    assert verdicts({**GOOD, name: value}, lever_arm_m=LEVER_ARM, latency_ms=20.0)[name] == verdict


def test_velocity_source_follows_the_messages_sent():
    assert verdicts({**GOOD, "EK3_SRC1_VELXY": 6}, sends_velocity=True)["EK3_SRC1_VELXY"] == "ok"
    assert verdicts({**GOOD, "EK3_SRC1_VELXY": 0}, sends_velocity=True)["EK3_SRC1_VELXY"] == "degrades"


def test_px4_vision_control_bits():
    def px4(ctrl):
        values = {"EKF2_EV_CTRL": ctrl, "EKF2_HGT_REF": 3, "EKF2_EV_DELAY": 15, "EKF2_EV_POS_X": 0,
                  "EKF2_EV_POS_Y": 0, "EKF2_EV_POS_Z": 0}
        checks = fc_params.check_parameters(fc_params.PX4, values, fc_params.Expected(latency_ms=12.0))
        return {c.name: c for c in checks}["EKF2_EV_CTRL"]
    assert px4(15).verdict == "ok" and px4(11).verdict == "ok"
    assert px4(14).verdict == "blocks"                       # bit 0 (horizontal position) off
    assert px4(9).verdict == "degrades" and "height" in px4(9).why


def test_an_unknown_autopilot_has_nothing_to_check():
    assert fc_params.parameter_names(12345) == () and fc_params.check_parameters(12345, {}, fc_params.Expected()) == []


def statustexts(values) -> list[tuple[str, int]]:
    return fc_params.statustexts(fc_params.check_parameters(fc_params.ARDUPILOT, values,
                                                            fc_params.Expected(lever_arm_m=LEVER_ARM)))


def test_a_flight_controller_that_answers_nothing_gets_two_statustexts_not_ten():
    """No parameter answered: ten problems in the log, but two STATUSTEXTs: the blocking one first
    (CRITICAL), then how many went unanswered."""
    assert statustexts({}) == [("companion: VISO_TYPE=? blocks vision", 2),
                               ("companion: FC did not report 9 params", 4)]


def test_every_blocking_parameter_is_told_first_and_the_rest_counted_within_50_characters():
    bad = {"AHRS_EKF_TYPE": 2, "VISO_TYPE": 0, "EK3_SRC1_POSXY": 3, "EK3_SRC1_POSZ": 1, "EK3_SRC1_YAW": 0,
           "EK3_SRC1_VELXY": 3, "VISO_DELAY_MS": 0, "VISO_POS_X": 0.1, "VISO_POS_Y": 0.2, "VISO_POS_Z": 0.3}
    texts = statustexts(bad)
    assert all(len(text) <= 50 for text, _ in texts), texts
    severities = [severity for _, severity in texts]
    assert severities == sorted(severities) and severities.count(2) == len(texts) - 1  # CRITICAL first, one WARNING
    told = " ".join(text for text, _ in texts)
    for name in ("AHRS_EKF_TYPE", "VISO_TYPE", "EK3_SRC1_POSXY", "EK3_SRC1_YAW"):  # the four that block
        assert name in told, texts
    assert texts[-1] == ("companion: EK3_SRC1_POSZ=1, +5 degrade vision", 4)  # six degrade: one named, five counted
    assert len(texts) <= 4
    assert statustexts(GOOD) == []


def test_the_attitude_is_judged_beside_the_state_and_each_change_said_once():
    """Frames without attitude at first, then with, then a gap, then back: 'waiting', 'ok', 'stale', 'ok'
    in the health and the status line, one message per change; no attitude expected: nothing said or shown."""
    from companion.mavlink.messages import SEVERITY_INFO, SEVERITY_WARNING
    from companion.types import AttitudeSample

    clock, said = Clock(), []
    monitor = Health(lambda text, severity, topic: said.append((text, severity)), clock_ns=clock, attitude_expected=True)
    states = []
    for attitude_present in [False] * 3 + [True] * 5 + [False] * 4 + [True] * 3:
        clock.now_ns += PERIOD_NS
        frame = record(clock.now_ns)
        if attitude_present:
            frame = dataclasses.replace(frame, attitude=AttitudeSample(clock.now_ns, 0.01, -0.02))
        monitor.observe(None, frame)
        states.append(monitor.assess(clock.now_ns).attitude)
    assert states == ["waiting"] * 3 + ["ok"] * 5 + ["stale"] * 4 + ["ok"] * 3
    attitude_said = [(t, s) for t, s in said if "attitude" in t]
    assert attitude_said == [("no attitude yet: poses without it", SEVERITY_WARNING),
                             ("flight controller attitude in use", SEVERITY_INFO),
                             ("attitude stale: poses without it", SEVERITY_WARNING),
                             ("attitude back: poses use it", SEVERITY_INFO)]
    status = DaemonStatus(fps=15.0, markers=2, latency_ms=None, estimate=None, state="tracking", state_s=0.0,
                          reasons=(), critical=False, track_state="tracking", link_state="streaming", frames=15,
                          sent=0, rejected=0, resets=0, attitude="stale")
    assert "| tracking | attitude stale | link streaming |" in status.line()

    quiet, quiet_said = Health(lambda text, severity, topic: quiet_said.append(text), clock_ns=clock), []
    quiet.observe(None, record(clock.now_ns + PERIOD_NS))
    assert quiet.assess(clock.now_ns + PERIOD_NS).attitude == "off" and not any("attitude" in t for t in quiet_said)
    assert "attitude" not in dataclasses.replace(status, attitude="off").line()
