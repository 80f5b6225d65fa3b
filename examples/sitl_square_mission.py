#!/usr/bin/env python3
"""Fly a square in ArduPilot SITL on companion's markers alone, and say how well it went.

    companion sitl-home --config config/sitl-camera.yaml     # start SITL with this --home
    companion run --config config/sitl-camera.yaml           # the simulated camera in the loop
    python examples/sitl_square_mission.py --config config/sitl-camera.yaml

What it does (docs/sitl.md), over its own MAVLink connection to the autopilot
(SITL's ground-station port, tcp:127.0.0.1:5760 by default):

1. waits until the autopilot has a local position (LOCAL_POSITION_NED: its
   EKF uses our vision), then GUIDED, then arms (retrying while the autopilot
   refuses: "PreArm: Need Position Estimate");
2. takes off to ``--altitude-m`` (1.2 m);
3. flies a square of side ``--side-m`` (2 m) in the map frame around the
   config's ``source.start_m``, corner to corner, without turning (the yaw
   is commanded: the start heading);
4. lands (LAND mode) and waits for the autopilot to disarm;
5. prints the tracking error: the simulator's truth (SIM_STATE) against the
   commanded path (distance to the square's sides while on a leg, and to the
   corner on arrival) and against the autopilot's estimate built on ours
   (LOCAL_POSITION_NED, against the truth carried to its arrival by the
   truth's velocity, from arming to landing): median, 95th percentile and
   maximum.

Every wait is bounded (``--timeout-s``); a wait that runs out is one line
on stderr and exit status 1, as is an autopilot that goes away (its TCP
connection closed or reset, or no heartbeat for ``HEARTBEAT_LOST_S``: the
simulator stopped or died).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

os.environ.setdefault("MAVLINK20", "1")  # MAVLink 2 (SIM_STATE's lat_int/lon_int), before pymavlink loads
from pymavlink import mavutil  # noqa: E402

from companion.daemon.config import ConfigError, SimulatedCameraConfig, load_config  # noqa: E402
from companion.geometry import frames  # noqa: E402

GUIDED, LAND = 4, 9
# SET_POSITION_TARGET_LOCAL_NED: use x, y, z and yaw; ignore velocity, acceleration, yaw rate
POSITION_AND_YAW_MASK = 0b0000_1001_1111_1000
ARRIVED_M = 0.10
HEARTBEAT_LOST_S = 5.0   # the autopilot sends one a second: this long without one, it is gone


class MissionError(RuntimeError):
    """A bounded wait that ran out; the message says which."""


class AutopilotLost(MissionError):
    """The connection to the autopilot closed, or its heartbeat stopped."""


class Vehicle:
    """The autopilot over one connection: commands, and the newest truth and estimate (NED from the EKF origin)."""

    def __init__(self, connection: str, origin, timeout_s: float):
        self.mav = mavutil.mavlink_connection(connection, source_system=255, source_component=190,
                                              dialect="ardupilotmega")
        self.connection = connection
        # pymavlink's TCP connection, on an EOF or a reset, prints a line and reads the closed socket again (without
        # autoreconnect): a line per read at full speed, millions of them. Raise instead.
        if hasattr(self.mav, "handle_eof"):
            self.mav.handle_eof = self._connection_closed
            self.mav.handle_disconnect = self._connection_closed
        self.heartbeat_s: float | None = None  # the autopilot's newest heartbeat (monotonic)
        self.origin = origin
        self.timeout_s = timeout_s
        self.truth_ned: np.ndarray | None = None
        self.truth_velocity = np.zeros(3)
        self.truth_s = 0.0
        self.estimate_ned: np.ndarray | None = None
        self.armed = False
        self.samples: list[np.ndarray] = []  # truth per SIM_STATE
        self.estimate_errors: list[float] = []  # |estimate - truth| per LOCAL_POSITION_NED, in the air

    def _connection_closed(self) -> None:
        raise AutopilotLost(f"the autopilot closed the connection ({self.connection}): the simulator stopped?")

    def check_alive(self) -> None:
        """AutopilotLost once the autopilot's heartbeat has been missing for ``HEARTBEAT_LOST_S``."""
        if self.heartbeat_s is not None and time.monotonic() - self.heartbeat_s > HEARTBEAT_LOST_S:
            raise AutopilotLost(f"no heartbeat from the autopilot on {self.connection} for "
                                f"{time.monotonic() - self.heartbeat_s:.0f} s: the simulator stopped?")

    def wait(self, what: str, done, timeout_s: float | None = None) -> None:
        deadline = time.monotonic() + (timeout_s or self.timeout_s)
        while not done():
            if time.monotonic() > deadline:
                raise MissionError(f"timed out after {timeout_s or self.timeout_s:.0f} s waiting for {what}")
            self.pump(0.05)

    def pump(self, duration_s: float) -> None:
        """Read what arrives for ``duration_s``."""
        end = time.monotonic() + duration_s
        while True:
            message = self.mav.recv_match(blocking=True, timeout=max(0.0, end - time.monotonic()))
            if message is not None:
                self.handle(message)
            self.check_alive()
            if time.monotonic() >= end:
                return

    def handle(self, message) -> None:
        kind = message.get_type()
        if kind == "SIM_STATE" and (message.lat_int or message.lon_int):
            self.truth_ned = frames.ned_from_geodetic(message.lat_int * 1e-7, message.lon_int * 1e-7, message.alt,
                                                      *self.origin)
            self.truth_velocity = np.array([message.vn, message.ve, message.vd])
            self.truth_s = time.monotonic()
            self.samples.append(self.truth_ned)
        elif kind == "LOCAL_POSITION_NED":
            self.estimate_ned = np.array([message.x, message.y, message.z])
            if self.armed and self.truth_ned is not None:
                # the truth carried to now by its velocity: p + v (now - t_received)
                truth_now = self.truth_ned + self.truth_velocity * (time.monotonic() - self.truth_s)
                self.estimate_errors.append(float(np.linalg.norm(self.estimate_ned - truth_now)))
        elif kind == "HEARTBEAT" and message.get_srcComponent() == 1:
            self.heartbeat_s = time.monotonic()
            self.armed = bool(message.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        elif kind == "STATUSTEXT":
            print(f"autopilot: {message.text}", flush=True)

    def command(self, command: int, *params: float, attempts: int = 1, retry_s: float = 1.0) -> bool:
        """COMMAND_LONG until accepted (at most ``attempts``); True if accepted."""
        p = list(params) + [0.0] * (7 - len(params))
        for _ in range(attempts):
            self.mav.mav.command_long_send(self.mav.target_system, self.mav.target_component, command, 0, *p)
            deadline = time.monotonic() + retry_s
            while time.monotonic() < deadline:
                message = self.mav.recv_match(blocking=True, timeout=0.05)
                self.check_alive()
                if message is None:
                    continue
                if message.get_type() != "COMMAND_ACK":
                    self.handle(message)  # the heartbeat, the truth and the estimate go on
                elif message.command == command:
                    if message.result == mavutil.mavlink.MAV_RESULT_ACCEPTED:
                        return True
                    break
            self.pump(max(0.0, deadline - time.monotonic()))
        return False

    def ask_for(self, message_id: int, rate_hz: float) -> None:
        self.command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, 1e6 / rate_hz)

    def go_to(self, target_ned: np.ndarray, yaw_rad: float) -> None:
        self.mav.mav.set_position_target_local_ned_send(
            0, self.mav.target_system, self.mav.target_component, mavutil.mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_AND_YAW_MASK, *target_ned, 0, 0, 0, 0, 0, 0, yaw_rad, 0)


def square_corners_map(start_m, side_m: float) -> np.ndarray:
    """(4, 2) corners of a square of side ``side_m`` centred on the start, counter-clockwise in the map."""
    h = side_m / 2
    return np.asarray(start_m[:2]) + np.array([[-h, -h], [h, -h], [h, h], [-h, h]])


def distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal distance (m) of point p from the segment a-b (all (2,))."""
    ab = b - a
    s = float(np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + s * ab)))


def fly(args) -> dict:
    config = load_config(args.config)
    if not isinstance(config.source, SimulatedCameraConfig):
        raise MissionError(f"{args.config}: source.kind is not simulated_camera")
    geodetic = config.facility_map.frame.geodetic_origin
    origin = (geodetic.latitude_deg, geodetic.longitude_deg, geodetic.altitude_m)
    R_ned_map = config.facility_map.T_ned_map[:3, :3]
    start = np.asarray(config.source.start_m)
    yaw_rad = math.radians(frames.yaw_ned_from_map_heading_deg(config.source.start_heading_deg,
                                                               config.facility_map.frame.x_bearing_deg))
    vehicle = Vehicle(args.connect, origin, args.timeout_s)
    if vehicle.mav.wait_heartbeat(timeout=args.timeout_s) is None:
        raise MissionError(f"no heartbeat from the autopilot on {args.connect} within {args.timeout_s:.0f} s")
    vehicle.heartbeat_s = time.monotonic()
    vehicle.ask_for(mavutil.mavlink.MAVLINK_MSG_ID_SIM_STATE, 50)
    vehicle.ask_for(mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20)
    print("waiting for the autopilot's position (its EKF using our vision)", flush=True)
    vehicle.wait("LOCAL_POSITION_NED (is companion running and the EKF set to use vision?)",
                 lambda: vehicle.estimate_ned is not None and vehicle.truth_ned is not None)
    if not vehicle.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                           GUIDED, attempts=5):
        raise MissionError("the autopilot refused GUIDED mode")
    print("GUIDED; arming", flush=True)
    if not vehicle.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, attempts=int(args.timeout_s)):
        raise MissionError(f"the autopilot refused to arm for {args.timeout_s:.0f} s (no position estimate?)")
    ground_down_m = float(vehicle.truth_ned[2])
    print(f"armed; taking off to {args.altitude_m} m", flush=True)
    vehicle.command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, args.altitude_m, attempts=3)
    vehicle.wait(f"the take-off to {args.altitude_m} m",
                 lambda: ground_down_m - vehicle.truth_ned[2] > args.altitude_m - ARRIVED_M)
    flight_down_m = ground_down_m - args.altitude_m
    corners = square_corners_map(start, args.side_m)
    # map (x, y) at the flight height: NED = R_ned_map (x, y, 0) + (0, 0, down)
    corners_ned = [R_ned_map @ np.array([x, y, 0.0]) + [0.0, 0.0, flight_down_m] for x, y in corners]
    path_errors, arrival_errors = [], []
    leg_start = vehicle.truth_ned[:2].copy()
    for leg, corner in enumerate(corners_ned + corners_ned[:1]):
        print(f"leg {leg + 1}: to map ({corners[leg % 4][0]:.2f}, {corners[leg % 4][1]:.2f})", flush=True)
        deadline = time.monotonic() + args.timeout_s
        first = len(vehicle.samples)
        while np.linalg.norm(vehicle.truth_ned - corner) > ARRIVED_M:
            if time.monotonic() > deadline:
                raise MissionError(f"leg {leg + 1} not reached within {args.timeout_s:.0f} s")
            vehicle.go_to(corner, yaw_rad)
            vehicle.pump(0.1)
        if leg > 0:  # the first leg starts wherever the take-off ended
            path_errors += [distance_to_segment(t[:2], leg_start, corner[:2]) for t in vehicle.samples[first:]]
        vehicle.go_to(corner, yaw_rad)
        vehicle.pump(args.settle_s)
        arrival_errors.append(float(np.linalg.norm(vehicle.truth_ned - corner)))
        leg_start = corner[:2].copy()
    estimate_errors = vehicle.estimate_errors[:]
    print("landing", flush=True)
    vehicle.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, LAND,
                    attempts=5)
    vehicle.wait("the landing (disarmed)", lambda: not vehicle.armed)
    return {"path": path_errors, "arrival": arrival_errors, "estimate": estimate_errors}


def summary(name: str, errors_m: list[float]) -> str:
    if not errors_m:
        return f"{name:<34} no samples"
    e = np.asarray(errors_m) * 100
    return (f"{name:<34} median {np.median(e):6.1f} cm  p95 {np.percentile(e, 95):6.1f} cm  "
            f"max {e.max():6.1f} cm  ({len(e)} samples)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="companion's config (source.kind: simulated_camera)")
    parser.add_argument("--connect", default="tcp:127.0.0.1:5760", help="the autopilot (SITL's GCS port)")
    parser.add_argument("--side-m", type=float, default=2.0)
    parser.add_argument("--altitude-m", type=float, default=1.2)
    parser.add_argument("--settle-s", type=float, default=1.0, help="hover at each corner")
    parser.add_argument("--timeout-s", type=float, default=60.0, help="bound of every wait")
    args = parser.parse_args(argv)
    try:
        errors = fly(args)
    except (MissionError, ConfigError, OSError) as error:
        print(f"sitl_square_mission: {error}", file=sys.stderr)
        return 1
    print("tracking error (truth: SIM_STATE)")
    print(summary("truth vs commanded path (legs)", errors["path"]))
    print(summary("truth vs corner on arrival", errors["arrival"]))
    print(summary("truth vs autopilot estimate", errors["estimate"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
