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
  velocity and relative position;
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
"""
from __future__ import annotations

import argparse
import json
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
MAV_RESULT_ACCEPTED, MAV_RESULT_FAILED = 0, 4
MAV_PARAM_TYPE_REAL32 = 9


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--tcp", action="store_true")
    parser.add_argument("--origin-reply", choices=["never", "on_set", "on_request"], default="on_set")
    parser.add_argument("--timesync-period", type=float, default=0.0)
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--ekf-init-s", type=float, default=0.0)
    parser.add_argument("--home", choices=["auto", "command", "never"], default="auto")
    parser.add_argument("--params", default="{}", help="JSON object: parameter name -> value")
    parser.add_argument("--autopilot", type=int, default=3)
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

    def send(connection, name: str, fields: dict) -> None:
        connection.send(messages.create(name).set_from_dict(dict(fields)))
        record("sent", name, fields)

    def reply_origin(connection) -> None:
        if origin:
            send(connection, "GPS_GLOBAL_ORIGIN", origin)

    def ekf_report(connection) -> None:
        with state_lock:
            flags = EKF_INITIALISED if vehicle["ekf"] else EKF_UNINITIALIZED
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

    record("event", "listening", {})
    deadline = time.monotonic() + args.duration
    connection = None
    while connection is None and not stop.is_set() and time.monotonic() < deadline:
        try:
            connection = runtime.await_connection(200)
        except RuntimeError:
            connection = None
    if connection is None:
        return
    record("event", "connected", {})

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
            vehicle["vision"] = True
        elif message.name == "PARAM_REQUEST_READ" and fields["param_id"] in parameters:
            send(connection, "PARAM_VALUE", {"param_id": fields["param_id"],
                                             "param_value": float(parameters[fields["param_id"]]),
                                             "param_type": MAV_PARAM_TYPE_REAL32, "param_count": len(parameters),
                                             "param_index": list(parameters).index(fields["param_id"])})

    connection.add_message_callback(on_message)
    connection.send(heartbeat)  # at once, not at the runtime's next 1 Hz beat
    next_timesync = next_ekf_report = time.monotonic()
    while not stop.is_set() and time.monotonic() < deadline:
        now_s = time.monotonic()
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
        stop.wait(0.01)
    connection.remove_all_callbacks()
    runtime.stop()
    out.close()


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
        rows = [json.loads(line) for line in self.out.read_text().splitlines() if line.strip()]
        return [r for r in rows if r["kind"] == kind and (name is None or r["name"] == name)]

    def wait_for(self, name: str, count: int = 1, timeout_s: float = 10.0, kind: str = "received") -> list[dict]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            rows = self.records(name, kind)
            if len(rows) >= count:
                return rows
            time.sleep(0.05)
        raise AssertionError(f"peer got {len(self.records(name, kind))} {name}, wanted {count} within {timeout_s} s")

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
