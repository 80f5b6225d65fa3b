"""A stand-in flight controller for tests: an independent MAVLink implementation (libmav).

Run as its own process (libmav's blocking calls hold the GIL)::

    python tests/mavlink_peer.py --port 14600 --out peer.jsonl [--tcp]
        [--origin-reply never|on_set|on_request] [--timesync-period 0.3]

It heartbeats as an ArduPilot quadrotor (system 1, component 1), records
every message it receives as one JSON line (with its own receive time on the
monotonic clock, which is shared by all processes of the machine), answers
SET_GPS_GLOBAL_ORIGIN or MAV_CMD_REQUEST_MESSAGE(49) with GPS_GLOBAL_ORIGIN as
asked, and sends TIMESYNC requests. It stops after --duration seconds, or on
SIGTERM.

Attitude (``--attitude``): once asked with MAV_CMD_SET_MESSAGE_INTERVAL for
ATTITUDE, it streams ATTITUDE at the asked rate on its own time base
(``time_boot_ms`` counted from a boot ``--boot-age`` seconds before it
started), each message sent a random 0..``--attitude-jitter-ms`` after it was
stamped, and records every one it sends with its stamp time on the shared
monotonic clock (the truth the tests compare against). Roll and pitch come
from ``--attitude-csv`` (a sequence's attitude.csv whose t_ns 0 is monotonic
``--attitude-start-ns``), or a slow sine. ``--attitude-pause START,LENGTH``
(seconds after streaming began) stops it for a while.
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

COMMON_XML = Path(pymavlink.__file__).parent / "dialects" / "v20" / "common.xml"
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_SET_MESSAGE_INTERVAL = 511
GPS_GLOBAL_ORIGIN_ID = 49
ATTITUDE_ID = 30


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
    args = parser.parse_args()

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    messages = libmav.MessageSet(str(COMMON_XML))
    heartbeat = messages.create("HEARTBEAT").set_from_dict(
        {"type": 2, "autopilot": 3, "base_mode": 0, "custom_mode": 0, "system_status": 3, "mavlink_version": 3})
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

    def reply_origin(connection) -> None:
        if origin:
            reply = messages.create("GPS_GLOBAL_ORIGIN").set_from_dict(dict(origin))
            connection.send(reply)
            record("sent", "GPS_GLOBAL_ORIGIN", dict(origin))

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

    def on_message(message) -> None:
        fields = message.to_dict()
        header = message.header
        record("received", message.name, fields, sysid=header.system_id, compid=header.component_id)
        if message.name == "SET_GPS_GLOBAL_ORIGIN" and args.origin_reply != "never":
            origin.update(latitude=fields["latitude"], longitude=fields["longitude"],
                          altitude=fields["altitude"], time_usec=0)
            if args.origin_reply == "on_set":
                reply_origin(connection)
        elif (message.name == "COMMAND_LONG" and fields["command"] == MAV_CMD_REQUEST_MESSAGE
              and int(fields["param1"]) == GPS_GLOBAL_ORIGIN_ID and args.origin_reply == "on_request"):
            reply_origin(connection)
        elif (message.name == "COMMAND_LONG" and fields["command"] == MAV_CMD_SET_MESSAGE_INTERVAL
              and int(fields["param1"]) == ATTITUDE_ID and args.attitude):
            streamer.ask(fields["param2"] * 1e-6)

    streamer = AttitudeStreamer(args, messages, connection, record)
    connection.add_message_callback(on_message)
    connection.send(heartbeat)  # at once, not at the runtime's next 1 Hz beat
    next_timesync = time.monotonic()
    while not stop.is_set() and time.monotonic() < deadline:
        if args.timesync_period and time.monotonic() >= next_timesync:
            ts1 = time.monotonic_ns()
            connection.send(messages.create("TIMESYNC").set_from_dict({"tc1": 0, "ts1": ts1}))
            record("sent", "TIMESYNC", {"tc1": 0, "ts1": ts1})
            next_timesync += args.timesync_period
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
