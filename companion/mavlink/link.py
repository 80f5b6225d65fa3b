"""The MAVLink link to the flight controller: connection, handshake, stream.

Threads (both stop on ``close()``):

* ``link`` owns the connection: opens it (reopening with backoff after a
  transport error, the backoff started again after a connection that worked:
  ``_connection_worked``), reads what the flight controller (FC) sends, answers
  TIMESYNC requests, runs the origin handshake and sends pending STATUSTEXTs;
* ``heartbeat`` sends HEARTBEAT at 1 Hz (type 18, autopilot 8), with
  ``system_status`` STANDBY before streaming, ACTIVE while streaming and
  CRITICAL while the daemon says so (``set_critical``: camera stalled or lost).

With an ``AttitudeStream`` (``companion.mavlink.attitude``) the link also asks
the flight controller for its attitude and files each ATTITUDE it sends, on
our clock, for the pose stage: that part lives in its own module.

Subscriptions (``subscribe``): a part of the daemon that needs other messages
of the autopilot (the simulated camera: the simulator's SIM_STATE,
``companion.capture.simulated``) registers a ``Subscriber``. The link thread
hands it every message of its ``message_types`` from the flight controller,
with the time it was received on our monotonic clock, and sends the requests
it asks for (``requests_due``: MAV_CMD_SET_MESSAGE_INTERVAL while its messages
are missing or slow). It shares the link's one connection.

The pipeline thread calls ``publish(estimate)``, which sends at once (lowest
latency) when the link is streaming, and never faster than ``max_rate_hz``
(50 Hz at most: ArduPilot drops samples closer than 20 ms), judged on capture
times with 2 ms of tolerance for a camera running at exactly that rate.

Start order, whatever comes up first (see docs/daemon.md, "Start order"):

1. wait for a FC heartbeat (at most ``origin_wait_s``);
2. ArduPilot: wait until its EKF_STATUS_REPORT says the EKF is initialised
   (asking for the report every ``origin_retry_s``; at most ``ekf_wait_s``).
   ArduPilot acknowledges an origin that arrives before, but its EKF drops
   it when it initialises: the vehicle never gets a global position or home;
3. send SET_GPS_GLOBAL_ORIGIN, wait for the FC's GPS_GLOBAL_ORIGIN (asking
   for it with MAV_CMD_REQUEST_MESSAGE and re-sending the origin every
   ``origin_retry_s``; at most ``origin_wait_s``), and only then stream
   vision (ArduPilot's EKF settles at a wrong height when the origin arrives
   after vision fusion began);
4. while streaming, ask for HOME_POSITION; none after ``home_wait_s``: send
   MAV_CMD_DO_SET_HOME (here), none after twice that: warn, saying whether
   the EKF has no position (it does not use vision) or dropped the origin.

Beside all of it, from the first FC heartbeat on (it needs neither the EKF
nor the origin): with an ``AttitudeStream`` the FC is asked for ATTITUDE,
and each sample is put on our clock for the pose stage.

Every bounded wait that runs out is logged and told by STATUSTEXT, and the
stream starts anyway. A FC seen again after it went silent for
``fc_timeout_s`` (a reboot) gets all of it again, and so does one whose
``time_boot_ms`` went back (in ATTITUDE, SYSTEM_TIME or a position message:
``BOOT_TIME_MESSAGES``): a FC that restarted without a pause in its heartbeat
that long (a fast boot on a UART, where no connection drops) has lost the
origin. A FC that sends none of those on its own (no attitude asked for, no
stream set up on the port) is asked for SYSTEM_TIME at ``BOOT_TIME_REQUEST_RATE_HZ``
once ``BOOT_TIME_REQUEST_RETRY_S`` have passed without any, and again whenever it
stops (a restarted FC forgets what it was asked to stream).

STATUSTEXT (``statustext``): one at most per ``statustext_interval_s`` (nothing
floods the FC nor the ground station), from a queue ordered by urgency:
a health change (a text with a topic: "camera", "attitude", "tracking", "fc") before
anything else, then by severity, then in order. A queued text is replaced by a newer
one of its topic (what it said is no longer true; the log keeps both), so a
fault reaches the operator within ``statustext_interval_s`` whatever waits; a
"no FC heard" still queued is dropped when the FC is heard.

Parameters: when a FC appears, the few parameters that decide whether it
fuses vision (``companion.mavlink.fc_params``) are read with
PARAM_REQUEST_READ; ``on_parameters(autopilot, values)`` gets them.

Two daemons: our HEARTBEAT carries a token of this process (its start time)
in ``custom_mode``. A HEARTBEAT with our system and component id and another
token is another companion on the same vehicle: the one started later
refuses to stream (state DUPLICATE, ``duplicate`` says why), and vision is
held for ``duplicate_listen_s`` after the connection opens so that it never
sends before it could have heard the other; only until the link has sent
vision once (``_listening_for_another``).
"""
from __future__ import annotations

import collections
import enum
import fcntl
import itertools
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

from companion.mavlink import messages as mm  # sets MAVLINK20 before pymavlink loads
from pymavlink import mavutil  # noqa: E402  (after mavlink_messages on purpose)
import serial  # noqa: E402  (pyserial, which pymavlink opens serial ports with)

from companion.mavlink import fc_params
from companion.mavlink.attitude import ATTITUDE_MESSAGES, AttitudeStream, restarted
from companion.mavlink.interval import StreamRequest
from companion.types import Estimate

log = logging.getLogger(__name__)

MAX_VISION_RATE_HZ = 50.0
# ArduPilot drops vision samples closer than 20 ms.
MIN_VISION_SPACING_NS = 20_000_000
# Capture stamps of a camera at exactly max_rate_hz jitter by a little: let them through.
RATE_JITTER_NS = 2_000_000
SEVERITY_INFO = mm.SEVERITY_INFO
SEVERITY_WARNING = mm.SEVERITY_WARNING
NETWORK_PREFIXES = ("udpout:", "udpin:", "udp:", "tcp:", "tcpin:")
SERIAL_PREFIXES = ("/", "COM")   # any absolute path: /dev/ttyAMA0, a udev link, a pty made by socat anywhere
PARAMETER_ATTEMPTS = 3  # PARAM_REQUEST_READ sent this many times before a parameter counts as absent
STATUSTEXT_QUEUE = 16   # STATUSTEXTs waiting for their turn; the least urgent is dropped beyond
# a serial write that waits this long for room is a flight controller that does not read (a hung FC on USB, flow
# control held): the link is lost, as for a write error, not the pipeline thread blocked inside the write (a
# 300-byte burst of vision messages takes 52 ms at 57600 baud; the tty's buffer takes several)
SERIAL_WRITE_TIMEOUT_S = 0.25
ARDUPILOT = mm.mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA
PX4 = mm.mavlink2.MAV_AUTOPILOT_PX4


# the FC's messages whose time_boot_ms ArduPilot and PX4 fill from their boot clock (watched for a restart)
BOOT_TIME_MESSAGES = ("ATTITUDE", "ATTITUDE_QUATERNION", "SYSTEM_TIME", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")
# without any of them for BOOT_TIME_REQUEST_RETRY_S, SYSTEM_TIME is asked for at this rate (12 bytes: nothing on a UART)
BOOT_TIME_REQUEST_RATE_HZ = 2.0
BOOT_TIME_REQUEST_RETRY_S = 2.0


# The least each period of the link may be (LinkParams), and why. Below it (0 above all) the link floods:
# 100 000 HEARTBEATs in 6 s, a refused TCP link reopened 6000 times a second at 77 % CPU, the origin re-sent
# and asked for at each turn of the link's loop, a FC that heartbeats at 1 Hz lost and "seen" at each beat.
MIN_PERIOD_S = {
    "heartbeat_interval_s": (0.1, "HEARTBEAT at 10 Hz at most"),
    "statustext_interval_s": (0.1, "STATUSTEXT at 10 Hz at most"),
    "origin_retry_s": (0.2, "the origin and the requests to the FC at 5 Hz at most"),
    "fc_timeout_s": (1.5, "the FC heartbeats at 1 Hz: less would lose it between two heartbeats"),
    "reconnect_initial_s": (0.05, "a lost link reopened at 20 Hz at most"),
    "reconnect_max_s": (0.05, "a lost link reopened at 20 Hz at most"),  # and >= reconnect_initial_s
}
# waits that may be 0 (no wait): none of them repeats anything
WAITS = ("origin_wait_s", "ekf_wait_s", "home_wait_s", "duplicate_listen_s")


class LinkError(ValueError):
    """A connection string or link parameter that cannot work.

    key: the LinkParams field at fault (None for a connection string); problem: what is wrong with it, without
    its name (``must be >= 0.1 s ..., got 0``), for a message that names the key its own way (the config's).
    """

    def __init__(self, message: str, key: str | None = None, problem: str | None = None):
        super().__init__(message)
        self.key, self.problem = key, problem if problem is not None else message

    @classmethod
    def of(cls, key: str, problem: str) -> "LinkError":
        return cls(f"{key} {problem}", key, problem)


class LinkState(enum.Enum):
    CONNECTING = "connecting"
    HANDSHAKE = "handshake"      # waiting for the FC, its EKF and its origin confirmation
    STREAMING = "streaming"
    DUPLICATE = "duplicate"      # another companion with our ids is on this link: we do not send


@dataclass(frozen=True)
class Origin:
    latitude_deg: float
    longitude_deg: float
    altitude_m: float


@dataclass(frozen=True)
class LinkParams:
    connection: str = "udpout:127.0.0.1:14550"
    system_id: int = 1
    component_id: int = mm.mavlink2.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    origin: Origin | None = None
    origin_wait_s: float = 5.0
    origin_retry_s: float = 1.0
    ekf_wait_s: float = 30.0
    home_wait_s: float = 5.0
    duplicate_listen_s: float = 1.5
    fc_timeout_s: float = 3.0
    max_rate_hz: float = 30.0
    statustext_interval_s: float = 1.0
    heartbeat_interval_s: float = 1.0
    reconnect_initial_s: float = 0.5
    reconnect_max_s: float = 8.0
    send_vision_position: bool = True
    send_vision_speed: bool = False
    send_odometry: bool = False

    def __post_init__(self) -> None:
        parse_connection(self.connection)
        if not 1 <= self.system_id <= 254:
            raise LinkError.of("system_id", f"must be 1..254 (255 is a ground station), got {self.system_id}")
        if not 1 <= self.component_id <= 255:
            raise LinkError.of("component_id", f"must be 1..255, got {self.component_id}")
        if not 0 < self.max_rate_hz <= MAX_VISION_RATE_HZ:
            raise LinkError.of("max_rate_hz", f"must be in (0, {MAX_VISION_RATE_HZ:g}], got {self.max_rate_hz}")
        for name in WAITS + tuple(MIN_PERIOD_S):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise LinkError.of(name, f"must be a number of seconds, got {value!r}")
            least, why = MIN_PERIOD_S.get(name, (0.0, "0: no wait"))
            if value < least:
                raise LinkError.of(name, f"must be >= {least:g} s ({why}), got {value!r}")
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise LinkError.of("reconnect_max_s", f"must be >= reconnect_initial_s ({self.reconnect_initial_s:g} s), "
                                                  f"got {self.reconnect_max_s!r}")


def _claim_serial_port(connection, device: str) -> None:
    """The flight controller's UART for this link alone while it is open (an advisory lock, as pyserial's
    ``exclusive``): two programs reading one tty split its bytes between them, and each sees a flight
    controller that goes silent and answers half its requests (``companion check-fc`` on the service's port).
    OSError, the connection closed, when another program holds it."""
    try:
        fcntl.flock(connection.port.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        connection.close()
        raise OSError(f"{device} is in use by another program (the companion service, companion check-fc or a "
                      "ground station: two readers split the flight controller's bytes; stop one)") from None


def _resolve(device: str) -> None:
    """OSError unless the host of ``udpout:HOST:PORT`` resolves: pymavlink resolves it at every send and drops
    the error, so a name that does not resolve would be an open link that sends nothing."""
    host = device.split(":")[1]
    try:
        socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)
    except socket.gaierror as error:
        raise OSError(f"cannot resolve {host}: {error.strerror}") from None


def _serial_write(port, device: str, data: bytes) -> None:
    """pyserial's write; its timeout (``SERIAL_WRITE_TIMEOUT_S``) an OSError that says what it means."""
    try:
        port.write(data)
    except serial.SerialTimeoutException:
        raise TimeoutError(f"{device} took no bytes for {SERIAL_WRITE_TIMEOUT_S:g} s (the flight controller does "
                           "not read)") from None


def parse_connection(text: str) -> tuple[str, int | None]:
    """(pymavlink device, baud or None) from a user's connection string.

    ``udpout:HOST:PORT``, ``udpin:HOST:PORT`` (``udp:`` is udpin),
    ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``, or a serial device with its baud
    rate: ``/dev/ttyAMA0,921600`` (57600 when no rate is given; any absolute path).
    """
    if not isinstance(text, str) or not text:
        raise LinkError.of("connection", f"must be a string such as udpout:127.0.0.1:14550, got {text!r}")
    if text.startswith(NETWORK_PREFIXES):
        kind, _, address = text.partition(":")
        host, _, port = address.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise LinkError.of("connection", f"{text!r}: want {kind}:HOST:PORT with a port in 1..65535")
        return text, None
    if text.startswith(SERIAL_PREFIXES):
        device, _, baud = text.partition(",")
        if baud and not baud.isdigit():
            raise LinkError.of("connection", f"{text!r}: the baud rate after the comma must be a number")
        return device, int(baud) if baud else 57600
    raise LinkError.of("connection", f"{text!r}: want udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT, "
                                     "tcpin:HOST:PORT or a serial device's absolute path such as "
                                     "/dev/ttyAMA0,921600")


@dataclass(frozen=True, order=True)
class QueuedText:
    """A STATUSTEXT waiting for its turn, ordered by urgency: a health change (topic) first,
    then the most severe (MAV_SEVERITY: lower is worse), then the oldest."""

    untopical: bool
    severity: int
    sequence: int
    text: str = field(compare=False)
    topic: str | None = field(compare=False, default=None)


@dataclass
class LinkCounters:
    sent: collections.Counter = field(default_factory=collections.Counter)
    received: collections.Counter = field(default_factory=collections.Counter)
    held_back: int = 0            # estimates not sent: not streaming yet / no connection
    rate_limited: int = 0         # estimates not sent: closer than 1 / max_rate_hz
    timesync_replies: int = 0
    connects: int = 0
    transport_errors: int = 0
    handshakes: int = 0
    origin_confirmed: int = 0
    origin_timeouts: int = 0
    ekf_timeouts: int = 0
    undecodable_bytes: int = 0    # bytes that were no MAVLink message (a wrong baud rate, another protocol)


class _TransportLost(ConnectionError):
    pass


class Subscriber(Protocol):
    """A part of the daemon that takes some of the flight controller's messages (see the module docstring).

    Both methods run on the link's thread and must return quickly.
    """

    message_types: tuple[str, ...]

    def on_message(self, message, receive_ns: int) -> None: ...

    def requests_due(self, now_s: float, target_system: int, target_component: int) -> list: ...


class MavlinkLink:
    """Owns the connection to the FC; see the module docstring for the threads.

    stream: False for a tool that only reads the FC (``companion check-fc``):
    no origin handshake, no home check, no vision.
    attitude: where the FC's ATTITUDE goes (requested once it is seen); None: not asked for.
    """

    def __init__(self, params: LinkParams, stream: bool = True, attitude: AttitudeStream | None = None):
        self.params = params
        self.stream = stream
        self.attitude = attitude
        self.counters = LinkCounters()
        self.state = LinkState.CONNECTING
        # why the transport is down (the last open failure, or how it was lost); None while it is open
        self.down_reason: str | None = None
        self.fc_system_id: int | None = None
        self.fc_component_id: int | None = None
        self.fc_autopilot: int | None = None
        self.confirmed_origin: Origin | None = None
        self.home: Origin | None = None
        self.ekf_flags: int | None = None
        self._ekf_report_s: float | None = None  # when the last EKF_STATUS_REPORT came (monotonic)
        self.duplicate: str | None = None
        # (autopilot, {name: value or None if the FC did not answer}) once read; see companion.mavlink.fc_params
        self.on_parameters: Callable[[int, dict[str, float | None]], None] | None = None
        # This process's token in our HEARTBEAT: its start time in ms (mod 2^32), to tell another companion apart.
        self.instance = time.time_ns() // 1_000_000 & 0xFFFFFFFF
        self._critical = False
        self._sent_vision = False   # a vision message went out on some connection of this link
        self._connection = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._transport_broken = threading.Event()
        self._send_error: str | None = None   # why the last send failed (the link's down reason)
        self._statustexts: list[QueuedText] = []  # sorted, most urgent first
        self._statustext_lock = threading.Lock()
        self._statustext_sequence = itertools.count()
        self._statustext_ids = itertools.count()   # of texts sent in chunks
        # (wall time s, severity, text) of the latest STATUSTEXTs, for the live view
        self.statustext_history: collections.deque = collections.deque(maxlen=20)
        self._last_statustext_s = -math.inf
        self._last_fc_heartbeat_s = -math.inf
        self._last_undecodable_s = -math.inf   # when bytes that were no MAVLink message last came
        self._told_unheard = False  # "no flight controller heard" said for this silence (_watch_fc_heard)
        self._fc_boot_ms: int | None = None   # the FC's newest time_boot_ms: going back, it restarted
        self._boot_time_request = StreamRequest(mm.mavlink2.MAVLINK_MSG_ID_SYSTEM_TIME, BOOT_TIME_REQUEST_RATE_HZ, BOOT_TIME_REQUEST_RETRY_S)
        self._connected_s = 0.0
        self._handshake_started_s = 0.0
        self._fc_seen_in_handshake_s: float | None = None
        self._last_ekf_request_s = -math.inf
        self._ekf_ready = False
        self._origin_first_sent_s: float | None = None
        self._last_origin_sent_s = -math.inf
        self._home_check_pending = False  # the home check starts with the first vision sent
        self._home_check_started_s: float | None = None
        self._last_home_request_s = -math.inf
        self._home_set_requested = False
        self._parameters: dict[str, float | None] = {}
        self._parameter_attempts = 0
        self._last_parameter_request_s = -math.inf
        self._last_vision_t_ns: int | None = None
        self._subscribers: list[Subscriber] = []
        self._threads = [
            threading.Thread(target=self._run_link, name="link", daemon=True),
            threading.Thread(target=self._run_heartbeat, name="heartbeat", daemon=True),
        ]

    # ------------------------------------------------------------ public

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def close(self, last_words: str | None = None) -> None:
        """Stop the link's threads and close the connection. If the link streams, first the STATUSTEXTs still
        queued (a fault said just before a stop would be lost) and then ``last_words`` (the daemon's "stopped":
        a ground station tells a stop from a crash, which falls silent) are sent at once."""
        if self.stream and self.state is not LinkState.DUPLICATE:
            with self._statustext_lock:
                queued, self._statustexts = self._statustexts, []
            final = [(q.severity, q.text) for q in queued]
            if last_words is not None:
                final.append((SEVERITY_WARNING, last_words))
            for severity, text in final:   # while the link's thread keeps the connection open
                self._send_text(severity, text)
        self._stop.set()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(timeout=5.0)
        self._close_connection()

    @property
    def alive(self) -> bool:
        """True while both link threads run (they only end on close() or a bug)."""
        return all(thread.is_alive() for thread in self._threads)

    @property
    def fc_seen(self) -> bool:
        return time.monotonic() - self._last_fc_heartbeat_s < self.params.fc_timeout_s

    @property
    def fc_unheard_s(self) -> float | None:
        """How long no flight controller has been heard on the open connection (since its last heartbeat, or
        since the connection opened), once that is ``fc_timeout_s`` or more; None while one is heard, and while
        the connection is down (``down_reason`` says why). Vision may stream meanwhile (the start order gives up
        waiting): this is what says the FC is not there (the status line)."""
        if self._connection is None:
            return None
        unheard_s = time.monotonic() - max(self._last_fc_heartbeat_s, self._connected_s)
        return unheard_s if unheard_s >= self.params.fc_timeout_s else None

    @property
    def fc_unheard_why(self) -> str | None:
        """While the open connection hears no FC: "undecodable bytes" when bytes that are no MAVLink message
        keep coming (the FC is there, but at another baud rate, or its port speaks another protocol); None
        otherwise."""
        if (self._connection is None or self.fc_seen
                or time.monotonic() - self._last_undecodable_s >= self.params.fc_timeout_s):
            return None
        return "undecodable bytes: a wrong baud rate, or not MAVLink?"

    def subscribe(self, subscriber: Subscriber) -> None:
        """Hand ``subscriber`` the flight controller's messages of its types; call before ``start``."""
        self._subscribers.append(subscriber)

    def publish(self, estimate: Estimate) -> bool:
        """Send the vision messages for one estimate now; False if held back."""
        if (self.state is not LinkState.STREAMING or self._connection is None or not self.stream
                or self._listening_for_another()):
            self.counters.held_back += 1
            return False
        min_interval_ns = max(MIN_VISION_SPACING_NS, 1e9 / self.params.max_rate_hz - RATE_JITTER_NS)
        if self._last_vision_t_ns is not None and estimate.t_ns - self._last_vision_t_ns < min_interval_ns:
            self.counters.rate_limited += 1
            return False
        self._last_vision_t_ns = estimate.t_ns
        messages = []
        if self.params.send_vision_position:
            messages.append(mm.vision_position_estimate(estimate))
        if self.params.send_vision_speed:
            messages.append(mm.vision_speed_estimate(estimate))
        if self.params.send_odometry:
            messages.append(mm.odometry(estimate))
        sent = all(self._send(message) for message in messages)
        self._sent_vision = self._sent_vision or sent
        if sent and self._home_check_pending:
            # the FC can set home only once it has a position: from our first vision sample on
            self._home_check_pending = False
            self._last_home_request_s = -math.inf
            self._home_set_requested = False
            self._home_check_started_s = time.monotonic()
        return sent

    def _listening_for_another(self) -> bool:
        """Whether vision is held to listen for another companion: for ``duplicate_listen_s`` after the connection
        opens, until this link has sent vision once. A link that has sent does not wait again when it reopens:
        that added the window to every outage (1.5 s more without vision), and a companion started while it was
        down gives way as soon as it hears this one (the one started later refuses)."""
        return not self._sent_vision and time.monotonic() - self._connected_s < self.params.duplicate_listen_s

    def statustext(self, text: str, severity: int = SEVERITY_INFO, topic: str | None = None) -> None:
        """Queue a STATUSTEXT; sent at most once per ``statustext_interval_s``, the most urgent first.

        topic: what a health change is about ("camera", "attitude", "tracking", "fc"): it goes before any text without
        one and replaces a queued text of the same topic (see the module docstring).
        """
        queued = QueuedText(topic is None, severity, next(self._statustext_sequence), text, topic)
        with self._statustext_lock:
            waiting = [q for q in self._statustexts if topic is None or q.topic != topic]
            superseded = len(self._statustexts) - len(waiting)
            waiting = sorted(waiting + [queued])
            dropped = waiting[STATUSTEXT_QUEUE:]
            self._statustexts = waiting[:STATUSTEXT_QUEUE]
        if superseded:
            log.debug("link: STATUSTEXT %r replaces %d queued of topic %s", text, superseded, topic)
        for q in dropped:
            log.warning("link: STATUSTEXT queue full: %r not sent", q.text)
        self.statustext_history.append((time.time(), severity, text))

    def _withdraw_statustext(self, topic: str) -> None:
        """Drop the queued text of ``topic``, if one has not gone out yet."""
        with self._statustext_lock:
            self._statustexts = [q for q in self._statustexts if q.topic != topic]

    def set_critical(self, critical: bool) -> None:
        """HEARTBEAT system_status CRITICAL while ``critical`` (the daemon's health: camera stalled or lost)."""
        self._critical = critical

    @property
    def system_status(self) -> int:
        """MAV_STATE of our HEARTBEAT: CRITICAL, else ACTIVE while streaming, else STANDBY."""
        if self._critical:
            return mm.mavlink2.MAV_STATE_CRITICAL
        return mm.mavlink2.MAV_STATE_ACTIVE if self.state is LinkState.STREAMING else mm.mavlink2.MAV_STATE_STANDBY

    # ----------------------------------------------------------- sending

    def _send(self, message) -> bool:
        with self._send_lock:
            connection = self._connection
            if connection is None or self._transport_broken.is_set():
                return False   # a connection a send failed on is about to be closed: no write waits on it again
            try:
                connection.mav.send(message)
            except OSError as error:
                log.warning("link: send failed: %s", error)
                self.counters.transport_errors += 1
                self._send_error = str(error)
                self._transport_broken.set()
                return False
            self.counters.sent[message.get_type()] += 1
        return True

    def _send_text(self, severity: int, text: str) -> bool:
        """One text as STATUSTEXT, in chunks when longer than one holds (their id: 1-65535 in turn)."""
        text_id = next(self._statustext_ids) % 65535 + 1
        return all([self._send(message) for message in mm.statustext_chunks(severity, text, text_id)])

    def _run_heartbeat(self) -> None:
        # The first beat goes out as soon as the connection is open: a FC that has
        # not heard from us yet (udpout) does not know where to answer.
        while not self._stop.is_set():
            # A companion that refuses to run as a duplicate says nothing more on the link.
            sent = self.state is not LinkState.DUPLICATE and self._send(mm.heartbeat(self.system_status, self.instance))
            self._stop.wait(self.params.heartbeat_interval_s if sent else 0.05)

    # ------------------------------------------------------- connection

    def _open_connection(self):
        device, baud = parse_connection(self.params.connection)
        kwargs = dict(source_system=self.params.system_id, source_component=self.params.component_id,
                      dialect="ardupilotmega", autoreconnect=False)
        if baud is not None:
            kwargs["baud"] = baud
        if device.startswith(("tcp:", "tcpin:")):
            kwargs["retries"] = 0
        if device.startswith("udpout:"):
            _resolve(device)
        connection = mavutil.mavlink_connection(device, **kwargs)
        if baud is not None:
            _claim_serial_port(connection, device)
            # pymavlink's serial write prints "Device ... is dead" on stdout (the status line's stream) and
            # returns -1: let pyserial's error (an OSError) through, to be handled as a lost transport
            connection.port.write_timeout = SERIAL_WRITE_TIMEOUT_S
            connection.write = lambda buf, port=connection.port: _serial_write(port, device, bytes(buf))
        # pymavlink's TCP/serial classes only print on EOF; make it an error we handle.
        connection.handle_eof = connection.handle_disconnect = self._raise_transport_lost
        return connection

    @staticmethod
    def _raise_transport_lost():
        raise _TransportLost("connection closed by the peer")

    def _close_connection(self) -> None:
        with self._send_lock:
            connection, self._connection = self._connection, None
        if connection is not None:
            try:
                connection.close()
            except OSError:
                pass

    def _run_link(self) -> None:
        backoff_s = self.params.reconnect_initial_s
        said = None  # the last "cannot open" reason logged: a new reason is logged, a repeat is not
        while not self._stop.is_set():
            try:
                connection = self._open_connection()
            except Exception as error:  # pymavlink raises OSError, serial errors, ValueError
                self.counters.transport_errors += 1
                log.log(logging.WARNING if str(error) != said else logging.DEBUG,
                        "link %s: cannot open (%s); retrying with backoff (%.1f s, up to %.0f s)",
                        self.params.connection, error, backoff_s, self.params.reconnect_max_s)
                self.down_reason = f"cannot open: {error}"
                said = str(error)
                self._stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, self.params.reconnect_max_s)
                continue
            said = self.down_reason = None
            self._connected_s = time.monotonic()  # before the connection is seen open (fc_unheard_s, publish)
            with self._send_lock:
                self._connection = connection
            self.counters.connects += 1
            self._transport_broken.clear()
            self._send_error = None
            log.info("link %s: open", self.params.connection)
            self._begin_handshake()
            try:
                self._serve(connection)
                backoff_s = self.params.reconnect_initial_s
            except (OSError, _TransportLost) as error:
                self.counters.transport_errors += 1
                self.down_reason = f"lost: {error}"
                if self._connection_worked():
                    backoff_s = self.params.reconnect_initial_s  # the backoff is for a link that keeps failing
                log.warning("link %s: lost (%s); reconnecting in %.1f s", self.params.connection, error, backoff_s)
            finally:
                self._close_connection()
                if self.state is not LinkState.DUPLICATE:
                    self.state = LinkState.CONNECTING
            if not self._stop.is_set():
                self._stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, self.params.reconnect_max_s)

    def _connection_worked(self) -> bool:
        """Whether the connection just lost worked: the FC was heard on it, or it stayed open for
        ``reconnect_max_s`` (reopened that seldom, nothing is hammered). A lost one that worked is reopened after
        ``reconnect_initial_s``, not after the backoff grown while nothing listened (8 s without vision)."""
        return (self._last_fc_heartbeat_s >= self._connected_s
                or time.monotonic() - self._connected_s >= self.params.reconnect_max_s)

    def _serve(self, connection) -> None:
        """Read and react until stopped; raises on a transport error."""
        while not self._stop.is_set():
            # pymavlink's serial class swallows write errors and only marks the port dead.
            if self._transport_broken.is_set() or getattr(connection, "portdead", False):
                raise _TransportLost(f"send failed: {self._send_error}" if self._send_error else "send failed")
            message = connection.recv_match(blocking=True, timeout=0.05)
            if message is not None and message.get_type() == "BAD_DATA":
                self.counters.undecodable_bytes += len(message.data)
                self._last_undecodable_s = time.monotonic()
            elif message is not None:
                self._handle(message)
                self._deliver(message)
            self._tick()
            self._request_for_subscribers()

    # ------------------------------------------------------ FC messages

    def _handle(self, message) -> None:
        kind = message.get_type()
        self.counters.received[kind] += 1
        if kind in ATTITUDE_MESSAGES:
            self._on_attitude(message)
        elif kind == "HEARTBEAT" and message.autopilot != mm.mavlink2.MAV_AUTOPILOT_INVALID:
            self._on_fc_heartbeat(message)
        elif kind == "HEARTBEAT":
            self._on_companion_heartbeat(message)
        elif mm.is_timesync_request(message):
            self._send(mm.timesync_reply(message.ts1, time.monotonic_ns()))
            self.counters.timesync_replies += 1
        elif kind == "GPS_GLOBAL_ORIGIN":
            self._on_origin(message)
        elif message.get_srcSystem() == self.fc_system_id:
            self._on_fc_report(kind, message)
        self._watch_boot_time(message)

    def _on_fc_report(self, kind: str, message) -> None:
        """What the start order and the parameter check wait for, from the FC's system."""
        if kind == "EKF_STATUS_REPORT":
            self._on_ekf_status(message)
        elif kind == "HOME_POSITION":
            self._on_home(message)
        elif kind == "PARAM_VALUE":
            self._on_parameter(message)
        elif kind == "COMMAND_ACK" and message.command == mm.mavlink2.MAV_CMD_DO_SET_HOME:
            accepted = message.result == mm.mavlink2.MAV_RESULT_ACCEPTED
            log.log(logging.INFO if accepted else logging.WARNING, "link: MAV_CMD_DO_SET_HOME %s by the flight "
                    "controller (result %d)", "accepted" if accepted else "refused", message.result)

    def _on_fc_heartbeat(self, message) -> None:
        now_s = time.monotonic()
        returning = now_s - self._last_fc_heartbeat_s >= self.params.fc_timeout_s
        self._last_fc_heartbeat_s = now_s
        if returning:
            self._fc_boot_ms = None  # a restart after a pause: told here, not again by its boot time
            self.fc_system_id, self.fc_component_id = message.get_srcSystem(), message.get_srcComponent()
            self.fc_autopilot = message.autopilot
            log.info("link: flight controller %d/%d seen (autopilot %d, type %d)",
                     self.fc_system_id, self.fc_component_id, message.autopilot, message.type)
            self._withdraw_statustext("fc")   # a "no FC heard" still queued is stale now
            if self.fc_system_id != self.params.system_id:
                log.warning("link: flight controller has system id %d but we send as %d",
                            self.fc_system_id, self.params.system_id)
            self._start_over(now_s)

    def _start_over(self, now_s: float | None = None) -> None:
        """A FC that appeared, or restarted: its parameters read again, the origin before any vision, its
        attitude asked for at once (SYSTEM_TIME only if nothing brings a boot time within BOOT_TIME_REQUEST_RETRY_S)."""
        self._begin_parameter_read()
        self._begin_handshake(now_s)
        self._boot_time_request.ask_after(time.monotonic() if now_s is None else now_s)
        if self.attitude is not None:
            self.attitude.autopilot_appeared()

    def _watch_boot_time(self, message) -> None:
        """A FC whose ``time_boot_ms`` went back restarted: the start order again (its EKF lost the origin)."""
        if message.get_type() not in BOOT_TIME_MESSAGES or (
                (message.get_srcSystem(), message.get_srcComponent()) != (self.fc_system_id, self.fc_component_id)):
            return
        self._boot_time_request.arrived(time.monotonic_ns())
        boot_ms = message.time_boot_ms
        if restarted(self._fc_boot_ms, int(boot_ms)):
            log.warning("link: the flight controller restarted (its time_boot_ms went back from %.1f to %.1f s); "
                        "the origin again before any vision", self._fc_boot_ms / 1000, boot_ms / 1000)
            # the ground station sees the vehicle's vision pause: this says why
            self.statustext("companion: FC restarted, sending the origin again", SEVERITY_WARNING)
            self._start_over()
        self._fc_boot_ms = int(boot_ms)

    def _on_companion_heartbeat(self, message) -> None:
        """A HEARTBEAT of a non-autopilot: another process with our ids is a second companion."""
        if (message.get_srcSystem(), message.get_srcComponent()) != (self.params.system_id, self.params.component_id):
            return
        if message.custom_mode == self.instance or self.duplicate is not None:
            return  # our own, routed back; or already said
        # Tokens are start times in ms mod 2^32: the signed difference says which started first.
        started_before_us_ms = (self.instance - message.custom_mode + 2**31) % 2**32 - 2**31
        self.duplicate = (f"another companion sends as system {self.params.system_id} component "
                          f"{self.params.component_id} on {self.params.connection} (started "
                          f"{abs(started_before_us_ms) / 1000:.1f} s {'before' if started_before_us_ms >= 0 else 'after'} "
                          "this one)")
        if started_before_us_ms >= 0:
            log.error("link: %s: refusing to stream; stop the other one, or give one of them another "
                      "mavlink.component_id", self.duplicate)
            self.state = LinkState.DUPLICATE
        else:
            log.warning("link: %s; it should refuse to stream, this one goes on", self.duplicate)

    def _on_origin(self, message) -> None:
        origin = Origin(message.latitude * 1e-7, message.longitude * 1e-7, message.altitude * 1e-3)
        self.confirmed_origin = origin
        wanted = self.params.origin
        if wanted is not None and (abs(origin.latitude_deg - wanted.latitude_deg) > 2e-7
                                   or abs(origin.longitude_deg - wanted.longitude_deg) > 2e-7):
            log.warning("link: flight controller's origin %.7f, %.7f differs from ours %.7f, %.7f "
                        "(an origin is accepted once: reboot the FC to change it)",
                        origin.latitude_deg, origin.longitude_deg, wanted.latitude_deg, wanted.longitude_deg)
        if self.state is LinkState.HANDSHAKE and self._origin_first_sent_s is not None:
            self.counters.origin_confirmed += 1
            log.info("link: origin confirmed by the flight controller; streaming vision")
            self._start_streaming()

    def _on_ekf_status(self, message) -> None:
        self.ekf_flags, self._ekf_report_s = message.flags, time.monotonic()
        # one that comes back from a silence may answer before its heartbeat says it is back, which starts
        # the handshake over: the EKF is judged from then on (it was said twice)
        if not self.fc_seen:
            return
        if not self._ekf_ready and mm.ekf_ready(message.flags):
            self._ekf_ready = True
            if self.state is LinkState.HANDSHAKE:
                log.info("link: the flight controller's EKF is initialised (flags 0x%x): sending the origin",
                         message.flags)

    def _on_home(self, message) -> None:
        home = Origin(message.latitude * 1e-7, message.longitude * 1e-7, message.altitude * 1e-3)
        if self.home is None:
            log.info("link: the flight controller has home at %.7f, %.7f, %.1f m", *vars(home).values())
        self.home = home

    # ------------------------------------------------------- parameters

    def _begin_parameter_read(self) -> None:
        self._parameters = dict.fromkeys(fc_params.parameter_names(self.fc_autopilot))
        self._parameter_attempts = 0
        self._last_parameter_request_s = -math.inf
        if not self._parameters:  # an autopilot whose parameters we do not know
            self._finish_parameter_read()

    def _on_parameter(self, message) -> None:
        name, value = mm.param_value(message, bytewise=self.fc_autopilot == PX4)
        if name in self._parameters and self._parameters[name] is None:
            self._parameters[name] = value
            if all(v is not None for v in self._parameters.values()):
                self._finish_parameter_read()

    def _parameter_step(self, now_s: float) -> None:
        """Ask for the parameters not yet answered every ``origin_retry_s``, PARAMETER_ATTEMPTS times."""
        if not self._parameters:
            return
        if now_s - self._last_parameter_request_s < self.params.origin_retry_s:
            return
        if self._parameter_attempts >= PARAMETER_ATTEMPTS:
            self._finish_parameter_read()
            return
        for name, value in self._parameters.items():
            if value is None:
                self._send(mm.param_request_read(self.fc_system_id, self.fc_component_id, name))
        self._parameter_attempts += 1
        self._last_parameter_request_s = now_s

    def _finish_parameter_read(self) -> None:
        values, self._parameters, self._parameter_attempts = self._parameters, {}, 0
        if self.on_parameters is not None:
            self.on_parameters(self.fc_autopilot, values)

    # ---------------------------------------------------------- attitude

    def _on_attitude(self, message) -> None:
        """The autopilot's attitude (not another component's) into the attitude stream."""
        receive_ns = time.monotonic_ns()
        if self.attitude is None or self.fc_system_id is None:
            return
        if (message.get_srcSystem(), message.get_srcComponent()) == (self.fc_system_id, self.fc_component_id):
            self.attitude.on_message(message, receive_ns)

    def _request_attitude(self, now_s: float) -> None:
        if self.attitude is not None and self.fc_seen:
            for message in self.attitude.requests_due(now_s, self.fc_system_id, self.fc_component_id):
                self._send(message)

    def _request_boot_time(self, now_s: float) -> None:
        """SYSTEM_TIME, while the FC sends none of BOOT_TIME_MESSAGES on its own (``_watch_boot_time``)."""
        if self.fc_seen:
            for message in self._boot_time_request.due(now_s, self.fc_system_id, self.fc_component_id):
                self._send(message)

    # ---------------------------------------------------- subscriptions

    def _deliver(self, message) -> None:
        """The flight controller's message (not another component's) to the subscribers of its type."""
        receive_ns = time.monotonic_ns()
        if not self._subscribers or self.fc_system_id is None:
            return
        if (message.get_srcSystem(), message.get_srcComponent()) != (self.fc_system_id, self.fc_component_id):
            return
        kind = message.get_type()
        for subscriber in self._subscribers:
            if kind in subscriber.message_types:
                subscriber.on_message(message, receive_ns)

    def _request_for_subscribers(self) -> None:
        if not self._subscribers or not self.fc_seen or self.state is LinkState.DUPLICATE:
            return  # a duplicate companion says nothing more on the link
        now_s = time.monotonic()
        for subscriber in self._subscribers:
            for request in subscriber.requests_due(now_s, self.fc_system_id, self.fc_component_id):
                self._send(request)

    # ------------------------------------------------------- periodic

    def _begin_handshake(self, now_s: float | None = None) -> None:
        self.counters.handshakes += 1
        self._handshake_started_s = time.monotonic() if now_s is None else now_s
        self._fc_seen_in_handshake_s = None
        self._last_ekf_request_s = -math.inf
        self._ekf_ready = False
        self._origin_first_sent_s = None
        self._last_origin_sent_s = -math.inf
        self._home_check_pending = False
        self._home_check_started_s = None
        if self.state is LinkState.DUPLICATE:
            return
        if not self.stream:
            self.state = LinkState.HANDSHAKE  # reading only: never streams
        elif self.params.origin is None:
            # said at the first handshake only: every reopen, FC return or restart would say it again
            log.log(logging.WARNING if self.counters.handshakes == 1 else logging.DEBUG,
                    "link: no geodetic origin configured: streaming without SET_GPS_GLOBAL_ORIGIN "
                    "(home, RTL and auto modes need one)")
            self.state = LinkState.STREAMING
        else:
            self.state = LinkState.HANDSHAKE

    def _start_streaming(self) -> None:
        """Stream vision; with an origin, check the FC's home from the first vision sample on."""
        self.state = LinkState.STREAMING
        self._home_check_pending = self.params.origin is not None and self.fc_system_id is not None

    def _tick(self) -> None:
        now_s = time.monotonic()
        if self.state is LinkState.DUPLICATE:
            return
        if self.fc_system_id is not None:
            self._parameter_step(now_s)
        if self.state is LinkState.STREAMING and self._fc_went_silent():
            # Hold vision until it is back (bounded like at start): a rebooted FC must get the origin first.
            log.warning("link: flight controller silent for %.1f s; holding vision until it returns (at most %.1f s)",
                        self.params.fc_timeout_s, self.params.origin_wait_s)
            self._begin_handshake(now_s)
        if self.state is LinkState.HANDSHAKE and self.stream:
            self._handshake_step(now_s)
        if self.state is LinkState.STREAMING and self._home_check_started_s is not None:
            self._home_step(now_s)
        self._watch_fc_heard()
        self._request_attitude(now_s)
        self._request_boot_time(now_s)
        if now_s - self._last_statustext_s >= self.params.statustext_interval_s:
            self._send_statustext(now_s)

    def _send_statustext(self, now_s: float) -> None:
        """The most urgent queued STATUSTEXT; it stays queued if it could not be sent."""
        with self._statustext_lock:
            queued = self._statustexts[0] if self._statustexts else None
        if queued is None or not self._send_text(queued.severity, queued.text):
            return
        self._last_statustext_s = now_s
        with self._statustext_lock:
            if queued in self._statustexts:  # (not replaced meanwhile)
                self._statustexts.remove(queued)

    def _watch_fc_heard(self) -> None:
        """Without an origin nothing waits for the FC (vision streams from the start), so nothing said that
        none is heard: said here, once per silence (the status line says it for as long as it lasts; heard
        again, its heartbeat is logged). With an origin the start order says it (vision held, then no
        flight controller seen)."""
        unheard_s = self.fc_unheard_s
        if unheard_s is None:
            self._told_unheard = False
        elif not self._told_unheard and self.params.origin is None and self.stream:
            self._told_unheard = True
            clue, text = self._unheard_clue()
            log.warning("link: no flight controller heard for %.1f s%s; vision goes on", unheard_s, clue)
            self.statustext(text, SEVERITY_WARNING, topic="fc")

    def _unheard_clue(self) -> tuple[str, str]:
        """(what to add to the log line, the STATUSTEXT) of a flight controller not heard."""
        why = self.fc_unheard_why
        if why is None:
            return "", "companion: no FC heard"
        return f" ({why} {self.counters.undecodable_bytes} so far)", "companion: no FC heard, bytes garbled (baud?)"

    def _fc_went_silent(self) -> bool:
        """True when a FC seen since the last handshake began has stopped sending heartbeats."""
        return (self.params.origin is not None and self._last_fc_heartbeat_s >= self._handshake_started_s
                and not self.fc_seen)

    def _handshake_step(self, now_s: float) -> None:
        """FC, then (ArduPilot) its EKF, then the origin confirmed: each wait bounded, then stream anyway."""
        if not self.fc_seen:
            if now_s - self._handshake_started_s > self.params.origin_wait_s:
                clue, text = self._unheard_clue()
                self._give_up(f"no flight controller seen after {self.params.origin_wait_s:.1f} s{clue}", text,
                              topic="fc")
            return
        if self._fc_seen_in_handshake_s is None:
            self._fc_seen_in_handshake_s = now_s
        if not self._ekf_ready and self.fc_autopilot == ARDUPILOT:
            self._ekf_step(now_s)
            return
        self._origin_step(now_s)

    def _ekf_step(self, now_s: float) -> None:
        """Ask for EKF_STATUS_REPORT until it says initialised; give up after ``ekf_wait_s``."""
        if now_s - self._fc_seen_in_handshake_s > self.params.ekf_wait_s:
            self.counters.ekf_timeouts += 1
            log.warning("link: the flight controller's EKF did not report initialised within %.1f s (flags %s); "
                        "sending the origin anyway: if it is dropped the vehicle gets no home (see HOME below)",
                        self.params.ekf_wait_s, "none" if self.ekf_flags is None else f"0x{self.ekf_flags:x}")
            self.statustext("companion: EKF not ready, origin sent", SEVERITY_WARNING)
            self._ekf_ready = True
            return
        if now_s - self._last_ekf_request_s >= self.params.origin_retry_s:
            self._send(mm.request_ekf_status(self.fc_system_id, self.fc_component_id))
            self._last_ekf_request_s = now_s

    def _origin_step(self, now_s: float) -> None:
        """SET_GPS_GLOBAL_ORIGIN and a request for the FC's origin, every ``origin_retry_s``: a FC that sets it
        answers the first, one that has one already (back from a silence, not restarted) ignores the SET
        (ArduPilot) and answers the request, from the first round on."""
        if now_s - self._last_origin_sent_s >= self.params.origin_retry_s:
            origin = self.params.origin
            self._send(mm.set_gps_global_origin(self.fc_system_id, origin.latitude_deg, origin.longitude_deg,
                                                origin.altitude_m, time.monotonic_ns()))
            self._send(mm.request_gps_global_origin(self.fc_system_id, self.fc_component_id))
            if self._origin_first_sent_s is None:
                self._origin_first_sent_s = now_s
            self._last_origin_sent_s = now_s
        if now_s - self._origin_first_sent_s > self.params.origin_wait_s:
            self._give_up(f"origin not confirmed after {self.params.origin_wait_s:.1f} s",
                          "companion: origin unconfirmed")

    def _give_up(self, what: str, text: str, topic: str | None = None) -> None:
        self.counters.origin_timeouts += 1
        log.warning("link: %s; streaming vision anyway", what)
        self.statustext(text, SEVERITY_WARNING, topic)
        self._start_streaming()

    def _home_step(self, now_s: float) -> None:
        """From the first vision sent: ask for HOME_POSITION; none after home_wait_s: set home here;
        none after twice that: warn."""
        waited_s = now_s - self._home_check_started_s
        if self.home is not None:
            self._home_check_started_s = None
            return
        if waited_s > 2 * self.params.home_wait_s:
            self._no_home(waited_s)
            self._home_check_started_s = None
            return
        if waited_s > self.params.home_wait_s and not self._home_set_requested:
            log.info("link: no HOME_POSITION from the flight controller after %.1f s: asking it to set home here",
                     waited_s)
            self._send(mm.set_home_here(self.fc_system_id, self.fc_component_id))
            self._home_set_requested = True
        if now_s - self._last_home_request_s >= self.params.origin_retry_s:
            self._send(mm.request_home_position(self.fc_system_id, self.fc_component_id))
            if self.fc_autopilot == ARDUPILOT:  # its EKF's report tells why no home comes (_no_home)
                self._send(mm.request_ekf_status(self.fc_system_id, self.fc_component_id))
            self._last_home_request_s = now_s

    def _no_home(self, waited_s: float) -> None:
        """No home twice home_wait_s after the first vision: why, as far as the EKF's latest report tells."""
        flags = "unknown" if self.ekf_flags is None else f"0x{self.ekf_flags:x}"
        reported = self._ekf_report_s is not None and self._ekf_report_s >= self._home_check_started_s
        if reported and not mm.ekf_has_horizontal_position(self.ekf_flags):
            log.warning("link: the flight controller's EKF has no horizontal position %.1f s after vision began "
                        "(EKF flags %s): it is not using the vision positions, so it sets no home either; check "
                        "its parameters (companion check-fc)", waited_s, flags)
            self.statustext("companion: FC EKF not using vision", SEVERITY_WARNING)
            return
        log.warning("link: the flight controller reports no home %.1f s after the origin (EKF flags %s): "
                    "GUIDED take-off, RTL and fences will be refused; if the origin reached it before its EKF "
                    "was initialised, reboot the flight controller", waited_s, flags)
        self.statustext("companion: FC has no home; reboot the FC", SEVERITY_WARNING)
