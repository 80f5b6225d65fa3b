"""A stand-in flight controller for tests: an independent MAVLink implementation (libmav).

Run as its own process (libmav's blocking calls hold the GIL)::

    python tests/mavlink_peer.py --port 14600 --out peer.jsonl [--tcp]
        [--origin-reply never|on_set|on_request] [--timesync-period 0.3]
        [--ekf-init-s 8] [--home auto|command|never] [--params '{"VISO_TYPE": 1}']
        [--autopilot 3]

It heartbeats as an ArduPilot quadrotor (system 1, component 1), records
every message it receives as one JSON line (with its own receive time on the
monotonic clock, which is shared by all processes of the machine), answers
SET_GPS_GLOBAL_ORIGIN or MAV_CMD_REQUEST_MESSAGE(49) with GPS_GLOBAL_ORIGIN as
asked, and sends TIMESYNC requests. It stops after --duration seconds, or on
SIGTERM.

It behaves like ArduCopter (master of 2026-03) in the start order
(AP_NavEKF3 and GCS_MAVLink, read in ArduPilot's source):

* EKF_STATUS_REPORT at 2 Hz and on MAV_CMD_REQUEST_MESSAGE(193):
  EKF_UNINITIALIZED for ``--ekf-init-s`` seconds after start, then attitude,
  velocity and relative position; with ``--ekf-ignores-vision`` an EKF that
  never fuses the vision positions (attitude, vertical velocity and height,
  constant position mode: no position, so no home either);
* SET_GPS_GLOBAL_ORIGIN is taken once ("origin already set" after that) and
  acknowledged with GPS_GLOBAL_ORIGIN; one that arrives before the EKF has
  initialised is acknowledged too, but lost when the EKF initialises (event
  "origin lost"): no global position and no home ever;
* home (``--home``): ``auto`` sets it by itself once it has a valid origin
  and a vision position; ``command`` only on MAV_CMD_DO_SET_HOME (with a
  valid origin and a vision position; else MAV_RESULT_FAILED); ``never``
  refuses MAV_CMD_DO_SET_HOME. HOME_POSITION is sent when home is set and
  on MAV_CMD_REQUEST_MESSAGE(242) once it is;
* PARAM_REQUEST_READ by name: PARAM_VALUE for a name in ``--params``, nothing
  for another (as ArduPilot does for an unknown name).

Events (kind "event"): listening, connected, ekf initialised, origin set,
origin lost, home set.

Attitude (``--attitude``): once asked with MAV_CMD_SET_MESSAGE_INTERVAL for
ATTITUDE, it streams ATTITUDE at the asked rate on its own time base
(``time_boot_ms`` counted from a boot ``--boot-age`` seconds before it
started), each message sent a random 0..``--attitude-jitter-ms`` after it was
stamped, and records every one it sends with its stamp time on the shared
monotonic clock (the truth the tests compare against). Roll and pitch come
from ``--attitude-csv`` (a sequence's attitude.csv whose t_ns 0 is monotonic
``--attitude-start-ns``), or a slow sine. ``--attitude-pause START,LENGTH``
(seconds after streaming began) stops it for a while.

SYSTEM_TIME: once asked with MAV_CMD_SET_MESSAGE_INTERVAL for it (whatever
the options), it is streamed at the asked rate, ``time_boot_ms`` on the same
boot clock.

``--reboot-at S``: S seconds after the link connected, the pretend autopilot
restarts without a pause in its heartbeat (a fast boot on a UART): its
``time_boot_ms`` starts again from 0 and it forgets the origin, home and the
streams it was asked for (ATTITUDE, SYSTEM_TIME) (event "rebooted").
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import random
import signal
import threading
import time
from pathlib import Path

import libmav
import pymavlink

# ardupilotmega.xml includes common.xml and adds ArduPilot's messages (EKF_STATUS_REPORT)
DIALECT_XML = Path(pymavlink.__file__).parent / "dialects" / "v20" / "ardupilotmega.xml"
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_DO_SET_HOME = 179
GPS_GLOBAL_ORIGIN_ID = 49
EKF_STATUS_REPORT_ID = 193
HOME_POSITION_ID = 242
EKF_UNINITIALIZED = 1024
EKF_INITIALISED = 1 | 2 | 4 | 8 | 32  # attitude, horizontal and vertical velocity, relative position, height
EKF_WITHOUT_POSITION = 1 | 4 | 32 | 128  # attitude, vertical velocity, height, constant position mode
MAV_RESULT_ACCEPTED, MAV_RESULT_FAILED = 0, 4
MAV_PARAM_TYPE_REAL32 = 9
MAV_CMD_SET_MESSAGE_INTERVAL = 511
ATTITUDE_ID = 30
SYSTEM_TIME_ID = 2


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--tcp", action="store_true")
    parser.add_argument("--origin-reply", choices=["never", "on_set", "on_request"], default="on_set")
    parser.add_argument("--timesync-period", type=float, default=0.0)
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--attitude", action="store_true", help="stream ATTITUDE once asked for it")
    parser.add_argument("--boot-age", type=float, default=1234.5, help="seconds since the pretend boot")
    parser.add_argument("--attitude-jitter-ms", type=float, default=0.0)
    parser.add_argument("--attitude-csv", help="t_ns,roll_deg,pitch_deg to stream (t_ns 0 at --attitude-start-ns)")
    parser.add_argument("--attitude-start-ns", type=int, default=0)
    parser.add_argument("--attitude-pause", help="START,LENGTH seconds after streaming began: a gap")
    parser.add_argument("--ekf-init-s", type=float, default=0.0)
    parser.add_argument("--ekf-ignores-vision", action="store_true", help="an EKF that never fuses vision")
    parser.add_argument("--home", choices=["auto", "command", "never"], default="auto")
    parser.add_argument("--params", default="{}", help="JSON object: parameter name -> value")
    parser.add_argument("--autopilot", type=int, default=3)
    parser.add_argument("--reboot-at", type=float, default=None, help="seconds after connecting: restart")
    args = parser.parse_args()

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    messages = libmav.MessageSet(str(DIALECT_XML))
    heartbeat = messages.create("HEARTBEAT").set_from_dict(
        {"type": 2, "autopilot": args.autopilot, "base_mode": 0, "custom_mode": 0, "system_status": 3,
         "mavlink_version": 3})
    parameters = json.loads(args.params)
    started_s = time.monotonic()
    interface = libmav.TCPServer(args.port) if args.tcp else libmav.UDPServer(args.port)
    runtime = libmav.NetworkRuntime(libmav.Identifier(1, 1), messages, heartbeat, interface)
    out = open(args.out, "a", buffering=1)
    write_lock = threading.Lock()

    def record(kind: str, name: str, fields: dict, **extra) -> None:
        line = json.dumps({"t_ns": time.monotonic_ns(), "kind": kind, "name": name, "fields": fields, **extra},
                          default=str)
        with write_lock:
            out.write(line + "\n")

    origin: dict = {}
    # the vehicle: ekf (initialised?), origin_valid (the EKF core's), vision (a position came), home (dict)
    vehicle = {"ekf": args.ekf_init_s <= 0, "origin_valid": False, "vision": False, "home": None}
    state_lock = threading.Lock()
    system_time = {"interval_s": None, "next_s": 0.0}  # the SYSTEM_TIME stream asked for

    def send(connection, name: str, fields: dict) -> None:
        connection.send(messages.create(name).set_from_dict(dict(fields)))
        record("sent", name, fields)

    def reply_origin(connection) -> None:
        if origin:
            send(connection, "GPS_GLOBAL_ORIGIN", origin)

    def ekf_report(connection) -> None:
        with state_lock:
            flags = ((EKF_WITHOUT_POSITION if args.ekf_ignores_vision else EKF_INITIALISED) if vehicle["ekf"]
                     else EKF_UNINITIALIZED)
        send(connection, "EKF_STATUS_REPORT", {"flags": flags})

    def set_home(connection) -> bool:
        """Home at the vehicle's position (here: the origin), if it has a global position."""
        with state_lock:
            if vehicle["home"] is not None:
                return True
            if not (vehicle["origin_valid"] and vehicle["vision"]):
                return False
            vehicle["home"] = {"latitude": origin["latitude"], "longitude": origin["longitude"],
                               "altitude": origin["altitude"], "x": 0.0, "y": 0.0, "z": 0.0, "q": [1.0, 0.0, 0.0, 0.0],
                               "approach_x": 0.0, "approach_y": 0.0, "approach_z": 0.0, "time_usec": 0}
        record("event", "home set", {})
        send(connection, "HOME_POSITION", vehicle["home"])
        return True

    connection = streamer = None
    connected = threading.Event()
    connecting = threading.Lock()

    def on_set_origin(fields: dict) -> None:
        with state_lock:
            if origin:
                return  # "EKF3: origin already set": ignored, not acknowledged
            origin.update(latitude=fields["latitude"], longitude=fields["longitude"],
                          altitude=fields["altitude"], time_usec=0)
            vehicle["origin_valid"] = vehicle["ekf"]
        if vehicle["origin_valid"]:
            record("event", "origin set", {})
        if args.origin_reply == "on_set":
            reply_origin(connection)

    def on_command(fields: dict) -> None:
        command, param1 = fields["command"], int(fields["param1"])
        if command == MAV_CMD_REQUEST_MESSAGE and param1 == GPS_GLOBAL_ORIGIN_ID and args.origin_reply == "on_request":
            reply_origin(connection)
        elif command == MAV_CMD_REQUEST_MESSAGE and param1 == EKF_STATUS_REPORT_ID:
            ekf_report(connection)
        elif command == MAV_CMD_REQUEST_MESSAGE and param1 == HOME_POSITION_ID and vehicle["home"] is not None:
            send(connection, "HOME_POSITION", vehicle["home"])
        elif command == MAV_CMD_SET_MESSAGE_INTERVAL and param1 == ATTITUDE_ID and args.attitude:
            streamer.ask(fields["param2"] * 1e-6)
        elif command == MAV_CMD_SET_MESSAGE_INTERVAL and param1 == SYSTEM_TIME_ID:
            system_time.update(interval_s=fields["param2"] * 1e-6, next_s=time.monotonic())
        elif command == MAV_CMD_DO_SET_HOME:
            done = args.home != "never" and set_home(connection)
            send(connection, "COMMAND_ACK", {"command": command,
                                             "result": MAV_RESULT_ACCEPTED if done else MAV_RESULT_FAILED})

    def on_message(message) -> None:
        fields = message.to_dict()
        header = message.header
        record("received", message.name, fields, sysid=header.system_id, compid=header.component_id)
        if message.name == "SET_GPS_GLOBAL_ORIGIN":
            on_set_origin(fields)
        elif message.name == "COMMAND_LONG":
            on_command(fields)
        elif message.name == "VISION_POSITION_ESTIMATE":
            vehicle["vision"] = not args.ekf_ignores_vision
        elif message.name == "PARAM_REQUEST_READ" and fields["param_id"] in parameters:
            send(connection, "PARAM_VALUE", {"param_id": fields["param_id"],
                                             "param_value": float(parameters[fields["param_id"]]),
                                             "param_type": MAV_PARAM_TYPE_REAL32, "param_count": len(parameters),
                                             "param_index": list(parameters).index(fields["param_id"])})

    def on_connection(partner) -> None:
        # called by libmav's receive thread before it hands over the partner's first message: a callback
        # added once await_connection has returned misses what arrives meanwhile (the link's first texts)
        nonlocal connection, streamer
        with connecting:  # libmav's thread and the main thread (below) may both hand it over
            if connection is not None:
                return
            connection, streamer = partner, AttitudeStreamer(args, messages, partner, record)
            partner.add_message_callback(on_message)
        connected.set()

    runtime.on_connection(on_connection)
    # A partner heard before that (a link already sending when this peer starts: a test's second peer) got no
    # callback, and none comes later: the peer would hear nothing, ever. await_connection hands it over (what
    # it sent before this line is not recorded).
    try:
        on_connection(runtime.await_connection(1))
    except RuntimeError:  # "Timeout while waiting for first connection": none yet, the callback will come
        pass
    record("event", "listening", {})
    deadline = time.monotonic() + args.duration
    while not connected.wait(0.2):
        if stop.is_set() or time.monotonic() >= deadline:
            return
    record("event", "connected", {})
    connection.send(heartbeat)  # at once, not at the runtime's next 1 Hz beat
    next_timesync = next_ekf_report = connected_s = time.monotonic()
    reboot_s = None if args.reboot_at is None else connected_s + args.reboot_at
    while not stop.is_set() and time.monotonic() < deadline:
        now_s = time.monotonic()
        if reboot_s is not None and now_s >= reboot_s:
            reboot_s = None
            with state_lock:
                origin.clear()
                vehicle.update(origin_valid=False, vision=False, home=None)
            streamer.boot_ns = time.monotonic_ns()
            streamer.interval_s = system_time["interval_s"] = None
            record("event", "rebooted", {})
        if args.timesync_period and now_s >= next_timesync:
            ts1 = time.monotonic_ns()
            connection.send(messages.create("TIMESYNC").set_from_dict({"tc1": 0, "ts1": ts1}))
            record("sent", "TIMESYNC", {"tc1": 0, "ts1": ts1})
            next_timesync += args.timesync_period
        if not vehicle["ekf"] and now_s - started_s >= args.ekf_init_s:
            with state_lock:
                vehicle["ekf"] = True
                lost = bool(origin)  # the EKF's initialisation drops an origin it was given before
            record("event", "ekf initialised", {})
            if lost:
                record("event", "origin lost", {})
        if now_s >= next_ekf_report:
            ekf_report(connection)
            next_ekf_report += 0.5
        if args.home == "auto" and vehicle["home"] is None:
            set_home(connection)
        if system_time["interval_s"] and now_s >= system_time["next_s"]:
            system_time["next_s"] += system_time["interval_s"]
            send(connection, "SYSTEM_TIME", {"time_unix_usec": 0,
                                             "time_boot_ms": (time.monotonic_ns() - streamer.boot_ns) // 1_000_000})
        streamer.step()
        stop.wait(0.001 if args.attitude else 0.01)
    connection.remove_all_callbacks()
    runtime.stop()
    out.close()


class AttitudeStreamer:
    """ATTITUDE on the pretend autopilot's clock, at the asked interval, with send jitter (see the docstring)."""

    def __init__(self, args, messages, connection, record):
        self.args, self.messages, self.connection, self.record = args, messages, connection, record
        self.boot_ns = time.monotonic_ns() - int(args.boot_age * 1e9)
        self.interval_s = None
        self.started_s = self.next_s = 0.0
        self.track = _read_track(args.attitude_csv) if args.attitude_csv else None
        self.pause = tuple(float(v) for v in args.attitude_pause.split(",")) if args.attitude_pause else None
        self.rng = random.Random(7)

    def ask(self, interval_s: float) -> None:
        if self.interval_s is None:
            self.started_s = self.next_s = time.monotonic()
        self.interval_s = interval_s

    def step(self) -> None:
        now_s = time.monotonic()
        if self.interval_s is None or now_s < self.next_s:
            return
        self.next_s += self.interval_s
        since_s = now_s - self.started_s
        if self.pause and self.pause[0] <= since_s < self.pause[0] + self.pause[1]:
            return
        stamp_ns = time.monotonic_ns()
        attitude = self._attitude(stamp_ns)
        if attitude is None:
            return
        roll, pitch = attitude
        fields = {"time_boot_ms": (stamp_ns - self.boot_ns) // 1_000_000, "roll": roll, "pitch": pitch, "yaw": 0.5,
                  "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0}
        time.sleep(self.rng.uniform(0.0, self.args.attitude_jitter_ms) * 1e-3)
        self.connection.send(self.messages.create("ATTITUDE").set_from_dict(fields))
        self.record("sent", "ATTITUDE", fields, stamp_ns=stamp_ns)

    def _attitude(self, stamp_ns: int):
        """(roll, pitch) radians at the stamp: the track's (None outside it) or a slow sine."""
        if self.track is None:
            t_s = stamp_ns * 1e-9
            return 0.05 * math.sin(2.0 * t_s), -0.03 * math.cos(1.3 * t_s)
        t_ns = stamp_ns - self.args.attitude_start_ns
        times = self.track[0]
        if not times[0] <= t_ns <= times[-1]:
            return None
        i = max(k for k in range(len(times)) if times[k] <= t_ns)
        j = min(i + 1, len(times) - 1)
        f = 0.0 if j == i else (t_ns - times[i]) / (times[j] - times[i])
        return tuple(math.radians(v[i] + f * (v[j] - v[i])) for v in self.track[1:])


def _read_track(path):
    """(t_ns list, roll_deg list, pitch_deg list) of an attitude.csv."""
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    return ([int(r["t_ns"]) for r in rows], [float(r["roll_deg"]) for r in rows],
            [float(r["pitch_deg"]) for r in rows])


if __name__ == "__main__":
    main()


# ------------------------------------------------------- test-side helper

class PeerProcess:
    """Runs this file as a subprocess and reads what it recorded."""

    def __init__(self, port: int, out: Path, *extra: str, duration_s: float = 30.0):
        import subprocess
        import sys
        self.port, self.out = port, Path(out)
        self.process = subprocess.Popen(
            [sys.executable, __file__, "--port", str(port), "--out", str(out), "--duration", str(duration_s), *extra])

    def wait_listening(self, timeout_s: float = 10.0) -> "PeerProcess":
        self.wait_for("listening", kind="event", timeout_s=timeout_s)
        return self

    def records(self, name: str | None = None, kind: str = "received") -> list[dict]:
        if not self.out.exists():
            return []
        text = self.out.read_text()
        # the peer may be writing its last line right now: only whole lines (ending in a newline) are read
        rows = [json.loads(line) for line in text[:text.rfind("\n") + 1].splitlines() if line.strip()]
        return [r for r in rows if r["kind"] == kind and (name is None or r["name"] == name)]

    def wait_for(self, name: str, count: int = 1, timeout_s: float = 10.0, kind: str = "received") -> list[dict]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            rows = self.records(name, kind)
            if len(rows) >= count:
                return rows
            time.sleep(0.05)
        got = self.records(name, kind)
        seen = sorted({r["name"] for r in self.records(kind=kind)})
        raise AssertionError(f"peer got {len(got)} {name}, wanted {count} within {timeout_s} s: "
                             f"{[r['fields'] for r in got][-8:]}; {kind} kinds {seen}")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except Exception:
                self.process.kill()
                self.process.wait()


def free_port(kind: str = "udp") -> int:
    import socket
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM if kind == "udp" else socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    return port


class UdpRouter:
    """A MAVLink router on loopback, like mavlink-router or MAVProxy's outputs: every datagram
    from one client goes to the flight controller and to every other client; the flight
    controller's go to every client. Raw bytes, untouched (ids and sequence numbers stay).

    ``sent_by``: for each client (in order of first datagram), the MAVLink 2 message ids it sent.
    """

    def __init__(self, port: int, fc_port: int):
        import socket
        self.fc_address = ("127.0.0.1", fc_port)
        self.clients: list[tuple[str, int]] = []
        self.sent_by: list[list[int]] = []
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.bind(("127.0.0.1", port))
        self._socket.settimeout(0.05)
        self._upstream = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._upstream.settimeout(0.05)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._from_clients, daemon=True),
                         threading.Thread(target=self._from_fc, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _from_clients(self) -> None:
        while not self._stop.is_set():
            try:
                data, address = self._socket.recvfrom(65536)
            except OSError:
                continue
            if address not in self.clients:
                self.clients.append(address)
                self.sent_by.append([])
            if len(data) >= 10 and data[0] == 0xFD:  # MAVLink 2: the message id is bytes 7..9
                self.sent_by[self.clients.index(address)].append(int.from_bytes(data[7:10], "little"))
            self._upstream.sendto(data, self.fc_address)
            for other in self.clients:
                if other != address:
                    self._socket.sendto(data, other)

    def _from_fc(self) -> None:
        while not self._stop.is_set():
            try:
                data, _ = self._upstream.recvfrom(65536)
            except OSError:
                continue
            for client in list(self.clients):
                self._socket.sendto(data, client)

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join()
        self._socket.close()
        self._upstream.close()
