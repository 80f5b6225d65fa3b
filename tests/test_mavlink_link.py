"""MavlinkLink against an independent MAVLink peer (libmav, its own process) on loopback."""
from __future__ import annotations

import json
import logging
import re
import select
import threading
import time

import numpy as np
import pytest

from companion.mavlink import messages as mm
from companion.geometry.attitude import AttitudeHistory
from companion.mavlink.attitude import AttitudeStream
from companion.mavlink.link import (BOOT_TIME_REQUEST_RATE_HZ, BOOT_TIME_REQUEST_RETRY_S, LinkError, LinkParams, LinkState, MavlinkLink,
                                    Origin, parse_connection)
from companion.types import Estimate
from mavlink_peer import PeerProcess, free_port

ORIGIN = Origin(47.3977419, 8.5455938, 488.0)


def estimate(t_ns: int, reset_counter: int = 0) -> Estimate:
    return Estimate(
        t_ns=t_ns, position_ned_m=np.array([1.0, 2.0, -1.5]), velocity_ned_m_s=np.array([0.1, 0.0, 0.0]),
        roll_rad=0.01, pitch_rad=-0.02, yaw_rad=0.7, covariance_ned=np.diag([0.01, 0.01, 0.02, 0.001, 0.001, 0.003]),
        reset_counter=reset_counter, tracking=True,
    )


class Publisher:
    """Publishes synthetic estimates at ``rate_hz`` capture rate from a thread (like the pipeline)."""

    def __init__(self, link: MavlinkLink, rate_hz: float = 30.0):
        self.link, self.period_s = link, 1.0 / rate_hz
        self.sent_t_ns: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.wait(self.period_s):
            t_ns = time.monotonic_ns()
            if self.link.publish(estimate(t_ns)):
                self.sent_t_ns.append(t_ns)

    def stop(self):
        self._stop.set()
        self._thread.join()


@pytest.fixture
def peers(tmp_path):
    started = []

    def start(port, *extra, name="peer"):
        peer = PeerProcess(port, tmp_path / f"{name}{len(started)}.jsonl", *extra)
        started.append(peer)
        return peer.wait_listening()

    yield start
    for peer in started:
        peer.stop()


@pytest.fixture
def links():
    opened = []

    def open_link(attitude=None, **kwargs):
        link = MavlinkLink(LinkParams(**kwargs), attitude=attitude)
        link.start()
        opened.append(link)
        return link

    yield open_link
    for link in opened:
        link.close()


def first_time(records, name):
    return min(r["t_ns"] for r in records if r["name"] == name)


def test_origin_is_requested_confirmed_and_sent_before_any_vision(peers, links):
    port = free_port()
    peer = peers(port, "--origin-reply", "on_request")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_wait_s=10.0,
                 origin_retry_s=0.3, heartbeat_interval_s=0.2)
    publisher = Publisher(link)
    vision = peer.wait_for("VISION_POSITION_ESTIMATE", count=10)
    publisher.stop()
    received = peer.records()
    origin_msgs = peer.records("SET_GPS_GLOBAL_ORIGIN")
    request = [r for r in peer.records("COMMAND_LONG")
               if r["fields"]["command"] == 512 and r["fields"]["param1"] == 49]
    reply_t_ns = first_time(peer.records(kind="sent"), "GPS_GLOBAL_ORIGIN")
    assert origin_msgs[0]["t_ns"] < request[0]["t_ns"] < reply_t_ns < vision[0]["t_ns"]
    assert origin_msgs[0]["fields"]["latitude"] == 473977419
    assert origin_msgs[0]["fields"]["longitude"] == 85455938
    assert origin_msgs[0]["fields"]["altitude"] == 488000
    assert origin_msgs[0]["fields"]["target_system"] == 1
    assert request[0]["fields"]["param1"] == 49.0
    assert link.counters.origin_confirmed == 1 and link.confirmed_origin.latitude_deg == pytest.approx(47.3977419)
    # Identity of every message: vehicle's system id, component 197.
    assert {(r["sysid"], r["compid"]) for r in received} == {(1, 197)}
    heartbeats = peer.records("HEARTBEAT")
    assert all(h["fields"]["type"] == 18 and h["fields"]["autopilot"] == 8 for h in heartbeats)
    # What arrived is what was published: capture time in usec, covariance, reset counter.
    sent_usec = {t // 1000 for t in publisher.sent_t_ns}
    for row in vision:
        fields = row["fields"]
        assert fields["usec"] in sent_usec
        assert (fields["x"], fields["y"], fields["z"]) == pytest.approx((1.0, 2.0, -1.5))
        assert fields["yaw"] == pytest.approx(0.7)
        assert fields["covariance"][0] == pytest.approx(0.01) and fields["covariance"][20] == pytest.approx(0.003)
        assert fields["reset_counter"] == 0


def test_fc_that_never_confirms_does_not_block_the_stream(peers, links):
    port = free_port()
    peer = peers(port, "--origin-reply", "never")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_wait_s=1.0,
                 origin_retry_s=0.2, heartbeat_interval_s=0.2, statustext_interval_s=0.1)
    publisher = Publisher(link)
    peer.wait_for("VISION_POSITION_ESTIMATE", count=3)
    statustexts = peer.wait_for("STATUSTEXT")
    publisher.stop()
    assert link.counters.origin_timeouts == 1 and link.counters.origin_confirmed == 0
    assert len(peer.records("SET_GPS_GLOBAL_ORIGIN")) >= 2  # re-sent while waiting
    assert first_time(peer.records(), "SET_GPS_GLOBAL_ORIGIN") < first_time(peer.records(), "VISION_POSITION_ESTIMATE")
    assert "origin unconfirmed" in statustexts[0]["fields"]["text"]
    assert statustexts[0]["fields"]["severity"] == 4  # MAV_SEVERITY_WARNING


def test_timesync_requests_are_answered_on_the_monotonic_clock(peers, links):
    port = free_port()
    peer = peers(port, "--timesync-period", "0.2")
    link = links(connection=f"udpout:127.0.0.1:{port}", heartbeat_interval_s=0.2)
    replies = peer.wait_for("TIMESYNC", count=3)
    requests = {r["fields"]["ts1"]: r["t_ns"] for r in peer.records("TIMESYNC", kind="sent")}
    for reply in replies:
        ts1, tc1 = reply["fields"]["ts1"], reply["fields"]["tc1"]
        assert ts1 in requests  # mirrored unchanged
        # Our time stamp lies between the request leaving and the reply arriving (one shared clock).
        assert ts1 <= tc1 <= reply["t_ns"]
    assert link.counters.timesync_replies >= 3


def test_vision_never_exceeds_the_rate_limit(peers, links):
    port = free_port()
    peer = peers(port)
    link = links(connection=f"udpout:127.0.0.1:{port}", max_rate_hz=25.0, heartbeat_interval_s=0.2)
    publisher = Publisher(link, rate_hz=100.0)
    vision = peer.wait_for("VISION_POSITION_ESTIMATE", count=15)
    publisher.stop()
    usec = sorted(r["fields"]["usec"] for r in vision)
    assert min(np.diff(usec)) >= 38_000  # 1 / 25 Hz less 2 ms of tolerance for capture jitter
    assert np.median(np.diff(usec)) >= 40_000
    assert link.counters.rate_limited > 0


def test_statustext_is_rate_limited_and_ordered(peers, links):
    port = free_port()
    peer = peers(port)
    link = links(connection=f"udpout:127.0.0.1:{port}", heartbeat_interval_s=0.2, statustext_interval_s=0.3)
    peer.wait_for("HEARTBEAT")
    for text in ("companion: tracking", "companion: markers lost", "companion: re-acquired"):
        link.statustext(text)
    rows = peer.wait_for("STATUSTEXT", count=3)
    assert [r["fields"]["text"] for r in rows] == ["companion: tracking", "companion: markers lost",
                                                   "companion: re-acquired"]
    assert min(np.diff([r["t_ns"] for r in rows])) >= 0.25e9


def test_a_no_fc_heard_still_queued_when_the_fc_is_heard_is_not_sent(peers, links):
    """A FC that connects just after the start order gave up waiting for it: the 'no FC heard' queued behind
    another text went out seconds after the FC was heard (a TCP link, by hand)."""
    port = free_port()
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_wait_s=0.3,
                 heartbeat_interval_s=0.2, statustext_interval_s=4.0)
    link.statustext("companion: camera stalled", mm.SEVERITY_CRITICAL, topic="camera")   # takes the first turn
    deadline = time.monotonic() + 10
    while link.counters.origin_timeouts == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert link.counters.origin_timeouts == 1   # "no FC heard" is queued, its turn seconds away
    peer = peers(port)                          # the FC comes
    deadline = time.monotonic() + 10
    while not link.fc_seen and time.monotonic() < deadline:
        time.sleep(0.05)
    assert link.fc_seen
    time.sleep(5.0)   # past the text's turn
    assert "companion: no FC heard" not in [r["fields"]["text"] for r in peer.records("STATUSTEXT")]


def test_a_long_text_reaches_the_ground_station_whole_in_chunks(peers, links):
    port = free_port()
    peer = peers(port)
    link = links(connection=f"udpout:127.0.0.1:{port}", heartbeat_interval_s=0.2, statustext_interval_s=0.3)
    peer.wait_for("HEARTBEAT")
    text = "companion: camera lost: camera /dev/video0: cannot open it (no such device); retrying with backoff"
    link.statustext(text)
    assert len(text) == 98   # two chunks, the second ended by a NUL
    rows = [r["fields"] for r in peer.wait_for("STATUSTEXT", count=2)]
    assert len({r["id"] for r in rows}) == 1 and rows[0]["id"] != 0
    assert [r["chunk_seq"] for r in rows] == [0, 1] and "".join(r["text"] for r in rows) == text


def test_a_health_change_goes_out_before_queued_texts_and_replaces_its_stale_one(peers):
    """Texts queued before the link runs: the health changes (texts with a topic) go first, worst first;
    a newer text of a topic replaces the queued one (the camera came back before 'stalled' went out);
    then the rest by severity, in order; one per interval."""
    port = free_port()
    peer = peers(port)
    link = MavlinkLink(LinkParams(connection=f"udpout:127.0.0.1:{port}", heartbeat_interval_s=0.2,
                                  statustext_interval_s=0.3))
    for text in ("companion: w1", "companion: w2"):
        link.statustext(text, mm.SEVERITY_WARNING)
    link.statustext("companion: VISO_TYPE=0 blocks vision", mm.SEVERITY_CRITICAL)
    link.statustext("companion: camera stalled", mm.SEVERITY_CRITICAL, topic="camera")
    link.statustext("companion: w3", mm.SEVERITY_WARNING)
    link.statustext("companion: attitude stale", mm.SEVERITY_WARNING, topic="attitude")
    link.statustext("companion: camera delivers frames again", mm.SEVERITY_INFO, topic="camera")
    link.start()
    try:
        rows = peer.wait_for("STATUSTEXT", count=6, timeout_s=15)
        time.sleep(0.6)
        rows = peer.records("STATUSTEXT")
    finally:
        link.close()
    # "camera stalled" was replaced, never sent
    assert [r["fields"]["text"] for r in rows] == [
        "companion: attitude stale", "companion: camera delivers frames again",
        "companion: VISO_TYPE=0 blocks vision", "companion: w1", "companion: w2", "companion: w3"]
    assert min(np.diff([r["t_ns"] for r in rows])) >= 0.25e9


def test_texts_still_queued_at_close_go_out_before_the_last_words(peers):
    """A fault said just before the daemon stops (a fast replay's last frames) waits its turn in the queue:
    close sends what is queued, most urgent first, then the last words, not just the last words."""
    port = free_port()
    peer = peers(port)
    link = MavlinkLink(LinkParams(connection=f"udpout:127.0.0.1:{port}", heartbeat_interval_s=0.2,
                                  statustext_interval_s=30.0))
    link.start()
    peer.wait_for("HEARTBEAT")
    link.statustext("companion: first", mm.SEVERITY_WARNING)
    peer.wait_for("STATUSTEXT")
    link.statustext("companion: w1", mm.SEVERITY_WARNING)
    link.statustext("companion: camera/FC board yaw off by +30 deg", mm.SEVERITY_CRITICAL)
    link.close("companion: stopped, no more vision")
    rows = peer.wait_for("STATUSTEXT", count=4)
    assert [(r["fields"]["text"], r["fields"]["severity"]) for r in rows] == [
        ("companion: first", mm.SEVERITY_WARNING), ("companion: camera/FC board yaw off by +30 deg", mm.SEVERITY_CRITICAL),
        ("companion: w1", mm.SEVERITY_WARNING), ("companion: stopped, no more vision", mm.SEVERITY_WARNING)]


def test_udp_peer_going_away_and_coming_back_gets_the_origin_again(peers, links):
    port = free_port()
    first = peers(port, "--origin-reply", "on_set", name="first")
    # fc_timeout_s above the peer's 1 Hz heartbeat period, as in flight (default 3 s)
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, fc_timeout_s=1.5,
                 heartbeat_interval_s=0.2, origin_retry_s=0.2)
    publisher = Publisher(link)
    first.wait_for("VISION_POSITION_ESTIMATE", count=5)
    first.stop()
    time.sleep(2.0)  # longer than fc_timeout_s: the FC is gone
    assert not link.fc_seen
    assert link.state is LinkState.HANDSHAKE  # vision held until the FC is back and has the origin
    second = peers(port, "--origin-reply", "on_set", name="second")
    vision = second.wait_for("VISION_POSITION_ESTIMATE", count=5)
    publisher.stop()
    assert first_time(second.records(), "SET_GPS_GLOBAL_ORIGIN") < vision[0]["t_ns"]
    assert link.counters.origin_confirmed == 2 and link.state is LinkState.STREAMING


def test_a_flight_controller_back_from_a_silence_confirms_its_origin_in_the_first_round(peers, links, caplog):
    """A FC silent for longer than fc_timeout_s and back, not restarted (a radio dropout; SIGSTOP here): vision is
    held until it confirms the origin, and it has one, so it ignores a SET (ArduPilot) and answers the request
    for it. The request goes with the first SET: vision resumed only at the second round, origin_retry_s (2 s
    here) later, or after origin_wait_s for a FC that answers only a SET it takes."""
    import signal
    caplog.set_level(logging.INFO, logger="companion.mavlink.link")
    port = free_port()
    peer = peers(port, "--origin-reply", "on_request")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, fc_timeout_s=1.5, heartbeat_interval_s=0.2,
                 origin_retry_s=2.0, origin_wait_s=20.0)
    publisher = Publisher(link)
    peer.wait_for("VISION_POSITION_ESTIMATE", count=5)
    publisher.stop()
    peer.process.send_signal(signal.SIGSTOP)
    try:
        deadline = time.monotonic() + 10
        while link.state is not LinkState.HANDSHAKE and time.monotonic() < deadline:
            time.sleep(0.02)
        assert link.state is LinkState.HANDSHAKE   # vision held: the FC may be restarting
        sets_while_silent = link.counters.sent["SET_GPS_GLOBAL_ORIGIN"]
    finally:
        peer.process.send_signal(signal.SIGCONT)
    deadline = time.monotonic() + 15
    while not link.publish(estimate(time.monotonic_ns())) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert link.state is LinkState.STREAMING and link.counters.origin_confirmed == 2
    assert link.counters.sent["SET_GPS_GLOBAL_ORIGIN"] - sets_while_silent == 1
    said = [r.getMessage() for r in caplog.records]
    assert sum("EKF is initialised" in text for text in said) == 2, said   # at the start, and once back


def test_a_udp_flight_controller_killed_without_an_origin_is_said_unheard_once_and_vision_goes_on(
        peers, links, caplog):
    """No origin: nothing waits for the FC, vision streams from the start. The UDP peer is killed (no goodbye,
    the link stays open): from fc_timeout_s on the link says how long no FC has been heard (the status line's
    'no FC heard'), logs it once and sends one STATUSTEXT, and streams on; a FC heard again clears it.
    Before, nothing at all said it."""
    caplog.set_level(logging.INFO, logger="companion.mavlink.link")
    port = free_port()
    first = peers(port, name="first")
    link = links(connection=f"udpout:127.0.0.1:{port}", fc_timeout_s=1.5, heartbeat_interval_s=0.2,
                 statustext_interval_s=0.1)
    publisher = Publisher(link)
    try:
        first.wait_for("VISION_POSITION_ESTIMATE", count=5)
        assert link.fc_seen and link.fc_unheard_s is None
        first.process.kill()
        first.process.wait()
        wait_for_log(caplog, r"no flight controller heard for 1\.\d s; vision goes on")
        assert link.fc_unheard_s >= 1.5 and link.state is LinkState.STREAMING
        sent = len(publisher.sent_t_ns)
        deadline = time.monotonic() + 10
        while (link.fc_unheard_s or 0) < 3.0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.fc_unheard_s >= 3.0 and len(publisher.sent_t_ns) > sent  # still said; vision goes on
        assert len([r for r in caplog.records if "no flight controller heard" in r.getMessage()]) == 1
        # told once on the link (a ground station behind a router hears it; the FC is not there to)
        assert [text for _, _, text in link.statustext_history] == ["companion: no FC heard"]
        assert link.counters.sent["STATUSTEXT"] == 1
        peers(port, name="second")
        deadline = time.monotonic() + 10
        while link.fc_unheard_s is not None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.fc_unheard_s is None and link.fc_seen
        deadline = time.monotonic() + 10
        while link.counters.handshakes < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.counters.handshakes >= 2   # the FC back: the start order again
        # the missing origin is said at the first handshake, not again at each (it was, at every return)
        assert len([r for r in caplog.records if r.levelno == logging.WARNING
                    and "no geodetic origin configured" in r.getMessage()]) == 1
    finally:
        publisher.stop()


def test_a_flight_controller_that_restarts_without_a_heartbeat_pause_gets_the_origin_again(peers, links):
    """A fast boot on a UART: the FC's heartbeat never pauses for fc_timeout_s and no connection drops, but its
    time_boot_ms (ATTITUDE's, here) starts again from 0, its EKF has lost the origin and it forgot the ATTITUDE
    stream. The link asks for ATTITUDE again, sees the restart, holds vision, sends the origin again and
    streams on once it is confirmed (before, it went on streaming to an EKF with no origin: no position, no
    arming)."""
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--attitude", "--reboot-at", "2.0")
    link = links(attitude=AttitudeStream(AttitudeHistory(0.1), 50.0), connection=f"udpout:127.0.0.1:{port}",
                 origin=ORIGIN, heartbeat_interval_s=0.2, origin_retry_s=0.2)
    rebooted_ns = stream_through_a_restart(peer, link)
    # handshakes: the link opened, the FC seen, its restart (once: every later time_boot_ms is newer)
    assert link.counters.origin_confirmed == 2 and link.counters.handshakes == 3
    assert link.state is LinkState.STREAMING and link.fc_seen
    assert any(r["t_ns"] > rebooted_ns for r in peer.records("COMMAND_LONG")
               if r["fields"]["command"] == 511 and r["fields"]["param1"] == 30)
    assert_vision_after_the_origin_again(peer, rebooted_ns)


def stream_through_a_restart(peer, link, timeout_s: float = 15.0) -> int:
    """Publish until the peer restarted and the link had the origin confirmed again; the restart's time."""
    publisher = Publisher(link)
    try:
        rebooted_ns = peer.wait_for("rebooted", kind="event", timeout_s=timeout_s)[0]["t_ns"]
        deadline = time.monotonic() + 10
        while link.counters.origin_confirmed < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
    finally:
        publisher.stop()
    return rebooted_ns


def assert_vision_after_the_origin_again(peer, rebooted_ns: int) -> None:
    origin_again_ns = min(r["t_ns"] for r in peer.records("SET_GPS_GLOBAL_ORIGIN") if r["t_ns"] > rebooted_ns)
    assert any(r["t_ns"] > origin_again_ns for r in peer.records("VISION_POSITION_ESTIMATE"))


def test_a_flight_controller_that_streams_no_boot_time_is_asked_for_one_and_its_restart_seen(peers, links):
    """No attitude asked for and nothing streamed with a time_boot_ms: after BOOT_TIME_REQUEST_RETRY_S the link asks
    for SYSTEM_TIME (not before: an autopilot that streams ATTITUDE on its own is not asked), so a restart
    without a heartbeat pause is seen there; the restarted FC forgot the stream and is asked again (before,
    the origin was confirmed once and vision streamed on to an EKF without one)."""
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--reboot-at", "5.0")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, heartbeat_interval_s=0.2,
                 origin_retry_s=0.2)
    rebooted_ns = stream_through_a_restart(peer, link)
    assert link.counters.origin_confirmed == 2 and link.state is LinkState.STREAMING
    asked = [r["t_ns"] for r in peer.records("COMMAND_LONG") if r["fields"]["command"] == 511
             and r["fields"]["param1"] == 2 and r["fields"]["param2"] == 1e6 / BOOT_TIME_REQUEST_RATE_HZ]
    connected_ns = peer.wait_for("connected", kind="event")[0]["t_ns"]
    assert asked[0] - connected_ns >= BOOT_TIME_REQUEST_RETRY_S * 1e9 * 0.9
    assert any(t > rebooted_ns for t in asked)
    assert_vision_after_the_origin_again(peer, rebooted_ns)
    told = [r["t_ns"] for r in peer.records("STATUSTEXT")
            if r["fields"]["text"] == "companion: FC restarted, sending the origin again"]
    assert len(told) == 1 and told[0] > rebooted_ns


def test_tcp_link_reconnects_after_the_peer_goes_away(peers, links):
    port = free_port("tcp")
    first = peers(port, "--tcp", name="first")
    link = links(connection=f"tcp:127.0.0.1:{port}", heartbeat_interval_s=0.2, fc_timeout_s=1.5,
                 reconnect_initial_s=0.1, reconnect_max_s=0.4)
    publisher = Publisher(link)
    first.wait_for("VISION_POSITION_ESTIMATE", count=5)
    assert link.down_reason is None
    first.stop()
    deadline = time.monotonic() + 5
    while link.counters.transport_errors == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    # lost, then refused while nothing listens: the reason the status line gives
    while "refused" not in (link.down_reason or "") and time.monotonic() < deadline:
        time.sleep(0.05)
    assert link.down_reason.startswith("cannot open: ") and "refused" in link.down_reason, link.down_reason
    second = peers(port, "--tcp", name="second")
    second.wait_for("VISION_POSITION_ESTIMATE", count=5)
    publisher.stop()
    assert link.counters.transport_errors >= 1 and link.counters.connects >= 2
    assert link.down_reason is None


def test_vision_waits_to_listen_for_another_companion_on_the_first_connection_only(peers, links):
    """duplicate_listen_s (3 s here) holds a newcomer's vision until it could have heard another companion.
    A link that has sent vision and reconnects (the flight controller's TCP server restarted) sends at once:
    it held every reconnection's vision for the window too, an outage longer by 1.5 s by default."""
    port = free_port("tcp")
    first = peers(port, "--tcp", name="first")
    link = links(connection=f"tcp:127.0.0.1:{port}", heartbeat_interval_s=0.2, duplicate_listen_s=3.0,
                 reconnect_initial_s=0.1, reconnect_max_s=0.4)

    def wait_streaming(connects: int) -> None:
        deadline = time.monotonic() + 10
        while not (link.counters.connects >= connects and link.down_reason is None
                   and link.state is LinkState.STREAMING) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert link.state is LinkState.STREAMING and link.counters.connects == connects

    wait_streaming(1)
    assert not link.publish(estimate(time.monotonic_ns()))   # listening: a newcomer sends nothing yet
    deadline = time.monotonic() + 10
    while not link.publish(estimate(time.monotonic_ns())) and time.monotonic() < deadline:
        time.sleep(0.05)
    first.wait_for("VISION_POSITION_ESTIMATE")
    first.stop()
    deadline = time.monotonic() + 10
    while link.counters.transport_errors == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    second = peers(port, "--tcp", name="second")
    wait_streaming(2)
    assert link.publish(estimate(time.monotonic_ns()))       # reopened: sent at once
    second.wait_for("VISION_POSITION_ESTIMATE")


def wait_for_log(caplog, pattern: str, after: int = 0, timeout_s: float = 15.0) -> tuple[int, re.Match]:
    """(index, match) of the first log record from ``after`` on whose message matches ``pattern``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for index, record in enumerate(list(caplog.records)[after:], after):
            match = re.search(pattern, record.getMessage())
            if match:
                return index, match
        time.sleep(0.05)
    raise AssertionError(f"no log line matching {pattern!r} within {timeout_s} s: "
                         f"{[r.getMessage() for r in caplog.records][-6:]}")


LOST = r"lost \(.*\); reconnecting in ([\d.]+) s"


def test_a_tcp_link_that_worked_is_reopened_after_reconnect_initial_s_whatever_the_backoff_before(
        peers, links, caplog):
    """Nothing listens for long enough that the backoff grows to reconnect_max_s; then a flight controller
    comes, is heard, and goes away (killed): the link reopens after reconnect_initial_s, and reaches the FC
    started again. Before, the backoff was reset only when the link was closed, and the loss waited
    reconnect_max_s (8 s without vision by default)."""
    caplog.set_level(logging.DEBUG, logger="companion.mavlink.link")
    port = free_port("tcp")
    link = links(connection=f"tcp:127.0.0.1:{port}", heartbeat_interval_s=0.2,
                 reconnect_initial_s=0.1, reconnect_max_s=1.6)
    wait_for_log(caplog, r"cannot open .*retrying with backoff \(1\.6 s")  # 0.1, 0.2, 0.4, 0.8, 1.6
    first = peers(port, "--tcp", name="first")
    deadline = time.monotonic() + 15
    while not link.fc_seen and time.monotonic() < deadline:
        time.sleep(0.02)
    assert link.fc_seen
    seen = len(caplog.records)
    first.process.kill()  # kill -9: no goodbye
    first.process.wait()
    _, lost = wait_for_log(caplog, LOST, after=seen)
    assert float(lost.group(1)) == pytest.approx(0.1), lost.group(0)
    second = peers(port, "--tcp", name="second")
    second.wait_for("HEARTBEAT")
    assert link.counters.connects == 2


def test_a_tcp_connection_that_never_worked_does_not_reset_the_backoff(links, caplog):
    """A listener that takes the connection and closes it at once (nothing heard, open for less than
    reconnect_max_s) is no working link: the backoff goes on doubling, not reopening at reconnect_initial_s."""
    import socket
    caplog.set_level(logging.DEBUG, logger="companion.mavlink.link")
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    listener.settimeout(0.1)
    stop = threading.Event()

    def refuse_politely():
        while not stop.is_set():
            try:
                connection, _ = listener.accept()
            except OSError:
                continue
            connection.close()

    closer = threading.Thread(target=refuse_politely, daemon=True)
    closer.start()
    try:
        links(connection=f"tcp:127.0.0.1:{listener.getsockname()[1]}", heartbeat_interval_s=0.2,
              reconnect_initial_s=0.1, reconnect_max_s=5.0)
        waits, after = [], 0
        while len(waits) < 4:
            after, lost = wait_for_log(caplog, LOST, after=after)
            waits.append(float(lost.group(1)))
            after += 1
    finally:
        stop.set()
        closer.join()
        listener.close()
    assert waits == pytest.approx([0.1, 0.2, 0.4, 0.8]), waits


@pytest.mark.parametrize("text, expected", [
    ("udpout:127.0.0.1:14550", ("udpout:127.0.0.1:14550", None)),
    ("tcp:127.0.0.1:5760", ("tcp:127.0.0.1:5760", None)),
    ("udpin:0.0.0.0:14551", ("udpin:0.0.0.0:14551", None)),
    ("/dev/ttyAMA0,921600", ("/dev/ttyAMA0", 921600)),
    ("/dev/ttyACM0", ("/dev/ttyACM0", 57600)),
    ("/tmp/ttyFC,115200", ("/tmp/ttyFC", 115200)),   # a pty socat made outside /dev (it was refused)
])
def test_connection_strings_as_users_write_them(text, expected):
    assert parse_connection(text) == expected


@pytest.mark.parametrize("text", ["udpout:127.0.0.1", "tcp::5760", "udpout:host:99999", "serial0", "ttyUSB0,57600",
                                  "/dev/ttyAMA0,fast", ""])
def test_bad_connection_strings_are_rejected_with_the_string(text):
    with pytest.raises(LinkError, match="connection"):
        parse_connection(text)


@pytest.mark.parametrize("bad", [dict(system_id=255), dict(max_rate_hz=60), dict(origin_wait_s=-1)])
def test_bad_link_parameters_are_rejected(bad):
    with pytest.raises(LinkError, match=next(iter(bad))):
        LinkParams(**bad)


@pytest.mark.parametrize("key, least", [("heartbeat_interval_s", 0.1), ("statustext_interval_s", 0.1),
                                        ("origin_retry_s", 0.2), ("fc_timeout_s", 1.5),
                                        ("reconnect_initial_s", 0.05), ("reconnect_max_s", 0.05)])
def test_a_period_of_zero_or_below_its_least_is_refused_naming_the_key_and_the_bound(key, least):
    """0 was accepted (>= 0) and flooded: 109 379 HEARTBEATs in 6 s, a refused TCP link reopened 37 506 times
    in 6 s at 77 % CPU, 546 COMMAND_LONG and 111 SET_GPS_GLOBAL_ORIGIN in 6 s. Each period has a least value,
    said in the error; that value itself is taken."""
    others = dict(reconnect_initial_s=least) if key == "reconnect_max_s" else {}
    for bad in (0, 0.0, least / 2):
        with pytest.raises(LinkError) as error:
            LinkParams(**others, **{key: bad})
        assert error.value.key == key and str(error.value).startswith(f"{key} must be >= {least:g} s ("), error.value
        assert error.value.problem.startswith(f"must be >= {least:g} s (")
    assert getattr(LinkParams(**others, **{key: least}), key) == least


def test_reconnect_max_below_reconnect_initial_is_refused():
    with pytest.raises(LinkError, match=r"reconnect_max_s must be >= reconnect_initial_s \(2 s\), got 1") as error:
        LinkParams(reconnect_initial_s=2.0, reconnect_max_s=1.0)
    assert error.value.key == "reconnect_max_s"


@pytest.mark.parametrize("key", ["origin_wait_s", "ekf_wait_s", "home_wait_s", "duplicate_listen_s"])
def test_a_wait_may_be_zero_but_not_negative(key):
    assert getattr(LinkParams(**{key: 0}), key) == 0
    with pytest.raises(LinkError, match=f"{key} must be >= 0 s"):
        LinkParams(**{key: -0.5})


def test_serial_device_with_baud_rate_over_a_pseudo_terminal(links):
    """`/dev/pts/N,921600` opens a real tty through pyserial: heartbeats go out, a FC
    heartbeat coming in starts the origin handshake, and a vanished device is retried."""
    import os
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo or newline translation before pyserial opens it
    device = os.ttyname(slave)
    link = links(connection=f"{device},921600", origin=ORIGIN, heartbeat_interval_s=0.1,
                 reconnect_initial_s=0.05, reconnect_max_s=0.1)
    fc = mm.mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mm.mavlink2.MAVLink(None)
    parser.robust_parsing = True
    seen = []
    deadline = time.monotonic() + 10
    while "SET_GPS_GLOBAL_ORIGIN" not in {m.get_type() for m in seen} and time.monotonic() < deadline:
        os.write(master, mm.mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(fc))
        # an ArduPilot FC's EKF says it is initialised: the origin may go now
        os.write(master, mm.ardupilot.MAVLink_ekf_status_report_message(mm.EKF_READY_FLAG, 0, 0, 0, 0, 0).pack(fc))
        time.sleep(0.05)
        while True:
            ready = select.select([master], [], [], 0)[0]
            if not ready:
                break
            seen += [m for m in parser.parse_buffer(os.read(master, 4096)) or [] if m.get_type() != "BAD_DATA"]
    kinds = {m.get_type() for m in seen}
    assert {"HEARTBEAT", "SET_GPS_GLOBAL_ORIGIN"} <= kinds
    assert all((m.get_srcSystem(), m.get_srcComponent()) == (1, 197) for m in seen)
    assert link.fc_system_id == 1
    os.close(master)  # the device goes away
    os.close(slave)
    deadline = time.monotonic() + 5
    while link.counters.transport_errors < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert link.counters.transport_errors >= 2  # lost, then a failed reopen at least
    assert all(thread.is_alive() for thread in link._threads)


def test_a_write_to_a_vanished_serial_device_is_an_error_not_a_line_on_stdout(capsys):
    """pymavlink's serial write printed "Device ... is dead" on stdout (the daemon's status line stream) and
    returned -1, so the link saw the loss only on a later read: now it is pyserial's error, an OSError the
    link handles as a lost transport."""
    import os
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    link = MavlinkLink(LinkParams(connection=f"{os.ttyname(slave)},921600"))
    connection = link._open_connection()
    try:
        os.close(master)   # the device goes away: writes to it fail (EIO)
        os.close(slave)
        with pytest.raises(OSError):
            for _ in range(3):
                connection.write(b"\xfd" * 64)
    finally:
        connection.close()
    assert capsys.readouterr().out == ""


def test_a_flight_controller_that_takes_no_bytes_fails_the_write_it_does_not_hold_it(links):
    """A hung FC on USB (or flow control held) stops reading: the tty's buffer fills and a write waited for
    room for ever, on the pipeline's thread (the daemon froze, blamed the camera and ignored SIGTERM). Now the
    write fails after SERIAL_WRITE_TIMEOUT_S and the link is lost, saying why."""
    import os
    import tty
    master, slave = os.openpty()   # nobody reads the master side: the FC takes no bytes
    tty.setraw(slave)
    link = MavlinkLink(LinkParams(connection=f"{os.ttyname(slave)},921600"))
    connection = link._open_connection()
    outcome = []

    def fill():
        try:
            for _ in range(10_000):   # 40 MB: far more than any tty buffers
                connection.write(b"\xfd" * 4096)
            outcome.append("all written")
        except OSError as error:
            outcome.append(error)

    writer = threading.Thread(target=fill, daemon=True)
    writer.start()
    writer.join(30)
    try:
        assert not writer.is_alive(), "the write is still waiting for room"
        assert isinstance(outcome[0], TimeoutError), outcome
        assert "took no bytes for 0.25 s (the flight controller does not read)" in str(outcome[0])
    finally:
        os.close(master)
        connection.close()
        os.close(slave)


def test_a_link_whose_flight_controller_takes_no_bytes_is_lost_saying_so_and_vision_does_not_wait(links, caplog):
    import os
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    link = links(connection=f"{os.ttyname(slave)},921600", heartbeat_interval_s=0.1, origin_wait_s=0,
                 duplicate_listen_s=0, reconnect_initial_s=0.05, reconnect_max_s=0.1)
    fc = mm.mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    sender = Publisher(link, rate_hz=200.0)   # on its own thread, as the pipeline sends
    try:
        deadline = time.monotonic() + 30
        while "took no bytes" not in str(link.down_reason) and time.monotonic() < deadline:
            os.write(master, mm.mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(fc))  # heard, never read
            time.sleep(0.05)
        assert "lost: send failed: " in str(link.down_reason)
        assert "took no bytes for 0.25 s (the flight controller does not read)" in str(link.down_reason)
        deadline = time.monotonic() + 30
        while link.counters.connects < 3 and time.monotonic() < deadline:   # reopened, lost again: a few rounds
            os.write(master, mm.mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(fc))
            time.sleep(0.05)
        # one write waits per connection: the sends after it give up at once (not 0.25 s each, nor a line each)
        failed = [r for r in caplog.records if "link: send failed" in r.getMessage()]
        assert len(failed) <= link.counters.connects, [r.getMessage() for r in failed]
    finally:
        sender._stop.set()
        sender._thread.join(5)
        os.close(master)
        os.close(slave)
    assert not sender._thread.is_alive()   # the publishing thread is not held in a write


def test_a_udpout_host_that_does_not_resolve_is_a_link_that_cannot_open_not_an_open_one(links):
    # pymavlink resolves the name at every send and drops the error: the link said open and streaming
    link = links(connection="udpout:nosuch.invalid:14550", reconnect_initial_s=0.05, reconnect_max_s=0.1)
    deadline = time.monotonic() + 20
    while link.down_reason is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (link.down_reason or "").startswith("cannot open: cannot resolve nosuch.invalid: "), link.down_reason
    assert link.counters.connects == 0 and link.state is LinkState.CONNECTING


def test_a_flight_controller_at_another_baud_rate_is_said_to_send_undecodable_bytes(links, caplog):
    """A wrong baud rate (the commonest set-up fault on a UART): the FC's bytes arrive garbled. Said beside
    'no FC heard', in the log, the STATUSTEXT and the status line (``fc_unheard_why``), not just 'no FC heard'."""
    import os
    import tty
    caplog.set_level(logging.INFO, logger="companion.mavlink.link")
    master, slave = os.openpty()
    tty.setraw(slave)
    link = links(connection=f"{os.ttyname(slave)},921600", fc_timeout_s=1.5, heartbeat_interval_s=0.2,
                 statustext_interval_s=0.1)
    garbage = np.random.default_rng(3).integers(0, 256, 200, np.uint8).tobytes().replace(b"\xfd", b"\x00")
    try:
        deadline = time.monotonic() + 15
        while not link.statustext_history and time.monotonic() < deadline:
            os.write(master, garbage)   # what a FC's frames look like read at the wrong baud rate
            while select.select([master], [], [], 0)[0]:
                os.read(master, 4096)   # the link's own bytes, read so its writes never wait
            time.sleep(0.05)
        assert link.counters.undecodable_bytes > 0 and not link.fc_seen
        assert link.fc_unheard_why == "undecodable bytes: a wrong baud rate, or not MAVLink?"
        assert [text for _, _, text in link.statustext_history] == ["companion: no FC heard, bytes garbled (baud?)"]
        assert any("no flight controller heard for 1." in r.getMessage() and "undecodable bytes" in r.getMessage()
                   for r in caplog.records)
    finally:
        os.close(master)
        os.close(slave)


def test_the_start_order_giving_up_on_a_flight_controller_at_another_baud_rate_says_why(links, caplog):
    import os
    import tty
    caplog.set_level(logging.INFO, logger="companion.mavlink.link")
    master, slave = os.openpty()
    tty.setraw(slave)
    link = links(connection=f"{os.ttyname(slave)},921600", origin=ORIGIN, origin_wait_s=2.0,
                 heartbeat_interval_s=0.2, statustext_interval_s=0.1)
    garbage = np.random.default_rng(4).integers(0, 256, 200, np.uint8).tobytes().replace(b"\xfd", b"\x00")
    try:
        deadline = time.monotonic() + 15
        while link.counters.origin_timeouts == 0 and time.monotonic() < deadline:
            os.write(master, garbage)
            while select.select([master], [], [], 0)[0]:
                os.read(master, 4096)
            time.sleep(0.05)
        assert link.counters.origin_timeouts == 1
        assert any("no flight controller seen after 2.0 s (undecodable bytes: a wrong baud rate, or not MAVLink? "
                   in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]
        assert [text for _, _, text in link.statustext_history] == ["companion: no FC heard, bytes garbled (baud?)"]
    finally:
        os.close(master)
        os.close(slave)


def test_a_serial_port_another_link_holds_is_not_opened_and_says_why(links):
    """`companion check-fc` on the UART of a running service: two readers split the tty's bytes, and both saw
    a flight controller going silent and parameters not reported. The second opener now stays out, saying why;
    it gets the port once the first lets it go."""
    import os
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    device = os.ttyname(slave)
    first = links(connection=f"{device},921600", heartbeat_interval_s=0.1, reconnect_initial_s=0.05,
                  reconnect_max_s=0.1)
    deadline = time.monotonic() + 10
    while first.counters.connects == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert first.counters.connects >= 1
    second = links(connection=f"{device},921600", heartbeat_interval_s=0.1, reconnect_initial_s=0.05,
                   reconnect_max_s=0.1)
    deadline = time.monotonic() + 10
    while second.down_reason is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert second.counters.connects == 0
    assert f"{device} is in use by another program" in (second.down_reason or ""), second.down_reason
    first.close()
    deadline = time.monotonic() + 10
    while second.counters.connects == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert second.counters.connects >= 1   # the port let go: the second link has it
    os.close(master)
    os.close(slave)


# ------------------------------------------------ issue 11: start order, parameters, two companions

def event_time(peer: PeerProcess, name: str, timeout_s: float = 15.0) -> int:
    return peer.wait_for(name, kind="event", timeout_s=timeout_s)[0]["t_ns"]


def test_origin_waits_for_the_ekf_so_the_vehicle_ends_up_with_origin_and_home(peers, links):
    """Companion and FC power up together: the FC's EKF initialises 3 s later. An origin sent
    before that is acknowledged but lost (ArduPilot), so the link waits for EKF_STATUS_REPORT."""
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--ekf-init-s", "3", "--home", "auto")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_wait_s=5.0, origin_retry_s=0.3,
                 heartbeat_interval_s=0.2)
    publisher = Publisher(link)
    home_ns = event_time(peer, "home set")
    publisher.stop()
    initialised_ns = event_time(peer, "ekf initialised")
    assert not peer.records("origin lost", kind="event")
    assert first_time(peer.records(), "SET_GPS_GLOBAL_ORIGIN") > initialised_ns
    assert first_time(peer.records(), "VISION_POSITION_ESTIMATE") > event_time(peer, "origin set")
    assert initialised_ns < home_ns
    # the EKF was asked for while waiting, and the home the FC reports is known to the link
    assert [r for r in peer.records("COMMAND_LONG") if r["fields"]["param1"] == 193]
    deadline = time.monotonic() + 5
    while link.home is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert link.home is not None and link.home.latitude_deg == pytest.approx(ORIGIN.latitude_deg)


def test_a_fc_without_home_is_asked_to_set_it_here(peers, links):
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--home", "command")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_retry_s=0.3,
                 heartbeat_interval_s=0.2, home_wait_s=1.0)
    publisher = Publisher(link)
    event_time(peer, "home set")
    publisher.stop()
    set_home = [r for r in peer.records("COMMAND_LONG") if r["fields"]["command"] == 179]
    assert set_home and set_home[0]["fields"]["param1"] == 1.0  # MAV_CMD_DO_SET_HOME, at the current position
    assert set_home[0]["t_ns"] > first_time(peer.records(), "VISION_POSITION_ESTIMATE")


def test_a_fc_that_gets_no_home_is_reported(peers, links):
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--home", "never")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_retry_s=0.2,
                 heartbeat_interval_s=0.2, home_wait_s=0.5, statustext_interval_s=0.1)
    publisher = Publisher(link)
    texts = [r["fields"]["text"] for r in peer.wait_for("STATUSTEXT")]
    publisher.stop()
    assert texts == ["companion: FC has no home; reboot the FC"], texts  # its EKF has a position: not vision
    assert link.home is None


def test_a_fc_whose_ekf_does_not_use_the_vision_is_told_so_not_to_reboot(peers, links):
    """An EKF that never fuses the vision positions (its EKF_STATUS_REPORT has no horizontal position) sets no
    home either: the link says the EKF is not using vision and points to the parameters (before, it said
    "reboot the FC", the remedy for an origin that reached the FC before its EKF initialised)."""
    port = free_port()
    peer = peers(port, "--origin-reply", "on_set", "--ekf-ignores-vision")
    link = links(connection=f"udpout:127.0.0.1:{port}", origin=ORIGIN, origin_retry_s=0.2,
                 heartbeat_interval_s=0.2, home_wait_s=0.5, statustext_interval_s=0.1)
    publisher = Publisher(link)
    texts = [r["fields"]["text"] for r in peer.wait_for("STATUSTEXT")]
    publisher.stop()
    assert texts == ["companion: FC EKF not using vision"], texts
    assert link.home is None and link.state is LinkState.STREAMING


def test_parameters_are_read_when_the_fc_appears(peers, links):
    port = free_port()
    served = {"AHRS_EKF_TYPE": 3, "VISO_TYPE": 0, "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 1, "EK3_SRC1_YAW": 6,
              "EK3_SRC1_VELXY": 0, "VISO_DELAY_MS": 10, "VISO_POS_X": 0.1, "VISO_POS_Y": 0.0}  # no VISO_POS_Z
    peer = peers(port, "--params", json.dumps(served))
    link = MavlinkLink(LinkParams(connection=f"udpout:127.0.0.1:{port}", origin_retry_s=0.2,
                                  heartbeat_interval_s=0.2))
    got = []
    link.on_parameters = lambda autopilot, values: got.append((autopilot, values))
    link.start()
    try:
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        link.close()
    assert got, "no parameters reported"
    autopilot, values = got[0]
    assert autopilot == 3
    assert values == {**{k: pytest.approx(float(v)) for k, v in served.items()}, "VISO_POS_Z": None}
    requests = [r["fields"]["param_id"] for r in peer.records("PARAM_REQUEST_READ")]
    assert requests.count("VISO_POS_Z") == 3 and requests.count("VISO_TYPE") == 1


def test_a_second_companion_with_our_ids_refuses_to_stream(tmp_path, links):
    """Two companions through one router to the FC: the one started later sees the first's
    HEARTBEAT (same system and component id, another process) and never sends vision."""
    from mavlink_peer import UdpRouter
    fc_port, router_port = free_port(), free_port()
    fc = PeerProcess(fc_port, tmp_path / "fc.jsonl").wait_listening()
    router = UdpRouter(router_port, fc_port)
    try:
        first = links(connection=f"udpout:127.0.0.1:{router_port}", heartbeat_interval_s=0.3)
        first_publisher = Publisher(first)
        fc.wait_for("VISION_POSITION_ESTIMATE", count=5)
        time.sleep(0.01)  # a later start time
        second = links(connection=f"udpout:127.0.0.1:{router_port}", heartbeat_interval_s=0.3)
        second_publisher = Publisher(second)
        deadline = time.monotonic() + 10
        while second.state is not LinkState.DUPLICATE and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        second_publisher.stop()
        first_publisher.stop()
    finally:
        router.stop()
        fc.stop()
    assert second.state is LinkState.DUPLICATE and "another companion" in second.duplicate
    assert "before this one" in second.duplicate
    assert first.state is LinkState.STREAMING and first.duplicate is not None  # told, and goes on
    vision_id = mm.mavlink2.MAVLINK_MSG_ID_VISION_POSITION_ESTIMATE
    first_ids, second_ids = router.sent_by[0], router.sent_by[1]
    assert first_ids.count(vision_id) > 30 and vision_id not in second_ids
    assert second.counters.held_back > 0
