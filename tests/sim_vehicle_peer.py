"""A stand-in for ArduCopter SITL in tests: a simulated vehicle behind a real MAVLink socket (pymavlink).

Run as its own process::

    python tests/sim_vehicle_peer.py --companion-port P1 --gcs-port P2 --out peer.jsonl
        --home LAT,LON,ALT,HEADING [--duration 60]

Like SITL it listens on two TCP ports: the companion computer's (SITL's
SERIAL1, 5762) and the ground station's (SERIAL0, 5760), and it is system 1,
component 1, an ArduPilot quadrotor. It does not import companion: every
conversion here is written out on its own, from ArduPilot's sources.

* The vehicle starts on the ground at ``--home`` (latitude, longitude, altitude
  above mean sea level, heading in compass degrees), as SITL's ``--home``.
  It never turns; its position follows the target with first-order dynamics
  (time constant ``--tau``), its speed at most ``--max-speed`` and its
  acceleration at most ``--max-accel`` (ArduCopter's position controller
  limits both: WPNAV_SPEED, WPNAV_ACCEL), vertical as well.
* Every ``MAV_CMD_SET_MESSAGE_INTERVAL`` is answered with COMMAND_ACK and
  starts that stream on that port: SIM_STATE (108: the true attitude
  quaternion, lat_int/lon_int in degE7, alt above mean sea level, vn/ve/vd,
  and lat/lon as ArduPilot sends them: degE7 in a float), ATTITUDE (30),
  LOCAL_POSITION_NED (32: the newest vision position carried forward to now
  by the newest vision speed, the peer's stand-in for an EKF fed by vision
  only).
* SET_GPS_GLOBAL_ORIGIN is answered with GPS_GLOBAL_ORIGIN (ArduPilot sends it
  when its EKF takes the origin); MAV_CMD_REQUEST_MESSAGE(49) likewise.
* The start order's other messages, as ArduPilot: EKF_STATUS_REPORT at 2 Hz
  and on MAV_CMD_REQUEST_MESSAGE(193) (initialised 0.5 s after start);
  HOME_POSITION on MAV_CMD_REQUEST_MESSAGE(242) once home is set (at the
  first vision after the origin, or MAV_CMD_DO_SET_HOME); PARAM_VALUE for
  PARAM_REQUEST_READ of the vision parameters (set for external navigation,
  ``--viso-delay-ms``).
* Flight like ArduCopter: SET_MODE / MAV_CMD_DO_SET_MODE (GUIDED 4, LAND 9),
  arming (MAV_CMD_COMPONENT_ARM_DISARM) refused unless in GUIDED with an
  origin and vision for the last second (the EKF "is using external nav
  data"), MAV_CMD_NAV_TAKEOFF (armed, GUIDED: climbs to param7 above home),
  SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED: north, east, down from
  the EKF origin), LAND mode and MAV_CMD_NAV_LAND (descends, disarms on the
  ground). Every command gets a COMMAND_ACK.
* Records as JSON lines (``t_ns`` on the machine's monotonic clock): every
  vision message received, every SIM_STATE sent with the truth in NED from
  the EKF origin and the time the vehicle was there (``state_t_ns``: the
  physics clock's, which a send after a stall can trail by the stall),
  every command and its result.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import threading
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

# ArduPilot's Location: metres per 1e-7 degree of latitude, and the longitude's cos(latitude)
LOCATION_SCALING_FACTOR = 0.011131884502145034
GUIDED, LAND = 4, 9
ARMED_FLAG = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
CUSTOM_MODE_FLAG = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
STREAMS = {mavlink.MAVLINK_MSG_ID_SIM_STATE, mavlink.MAVLINK_MSG_ID_ATTITUDE,
           mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED}
VISION_FRESH_S = 1.0
STEP_S = 0.0025  # physics step: 400 Hz, as SITL's copter loop
EKF_INITIALISED_S = 0.5
EKF_STATUS_REPORT_ID, HOME_POSITION_ID = 193, 242
# EKF_STATUS_REPORT flags of an EKF with attitude, velocity and position (not uninitialised)
EKF_FLAGS = (mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_VELOCITY_VERT | mavlink.EKF_POS_HORIZ_REL
             | mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_POS_VERT_ABS | mavlink.EKF_PRED_POS_HORIZ_REL
             | mavlink.EKF_PRED_POS_HORIZ_ABS)


def offset_degrees(lat_deg: float, lon_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """ArduPilot's Location::offset: (lat, lon) moved by north/east metres."""
    dlat_e7 = north_m / LOCATION_SCALING_FACTOR
    dlon_e7 = east_m / LOCATION_SCALING_FACTOR / max(math.cos(math.radians(lat_deg + dlat_e7 * 0.5e-7)), 0.01)
    return lat_deg + dlat_e7 * 1e-7, lon_deg + dlon_e7 * 1e-7


def distance_ne(lat0: float, lon0: float, lat1: float, lon1: float) -> tuple[float, float]:
    """ArduPilot's Location::get_distance_NE from (lat0, lon0) to (lat1, lon1), metres."""
    scale = max(math.cos(math.radians((lat0 + lat1) / 2)), 0.01)
    return (lat1 - lat0) * 1e7 * LOCATION_SCALING_FACTOR, (lon1 - lon0) * 1e7 * LOCATION_SCALING_FACTOR * scale


class Vehicle:
    """A copter that never turns: position (NED from home) following a target, first order."""

    def __init__(self, heading_deg: float, tau_s: float, max_speed_m_s: float, max_accel_m_s2: float):
        self.yaw_rad = math.radians(heading_deg)
        self.tau_s, self.max_speed, self.max_accel = tau_s, max_speed_m_s, max_accel_m_s2
        self.position = [0.0, 0.0, 0.0]
        self.velocity = [0.0, 0.0, 0.0]
        self.target: list[float] | None = None
        self.armed = False
        self.mode = 0  # STABILIZE
        self.t_s = time.monotonic()  # the time (monotonic clock) the state is for

    def step(self, dt_s: float) -> None:
        self.t_s += dt_s
        if self.target is None or not self.armed:
            self.velocity = [0.0, 0.0, 0.0]
            return
        # v = (target - p) / tau, at most max_speed, reached at most at max_accel; the ground stops a descent
        wanted = [(t - p) / self.tau_s for t, p in zip(self.target, self.position)]
        wanted = _limited(wanted, self.max_speed)
        change = _limited([w - v for w, v in zip(wanted, self.velocity)], self.max_accel * dt_s)
        self.velocity = [v + c for v, c in zip(self.velocity, change)]
        self.position = [p + v * dt_s for p, v in zip(self.position, self.velocity)]
        if self.position[2] > 0.0:
            self.position[2], self.velocity[2] = 0.0, 0.0
        if self.mode == LAND and self.position[2] > -0.02:
            self.armed, self.target = False, None

    def quaternion(self) -> list[float]:
        """Body -> NED of a level body at yaw (w, x, y, z)."""
        return [math.cos(self.yaw_rad / 2), 0.0, 0.0, math.sin(self.yaw_rad / 2)]


def _limited(vector: list[float], limit: float) -> list[float]:
    """``vector`` scaled down to length ``limit`` if it is longer."""
    length = math.sqrt(sum(v * v for v in vector))
    return vector if length <= limit else [v * limit / length for v in vector]


class Peer:
    def __init__(self, args):
        lat, lon, alt, heading = (float(v) for v in args.home.split(","))
        self.home = (lat, lon, alt)
        self.vehicle = Vehicle(heading, args.tau, args.max_speed, args.max_accel)
        self.origin: tuple[float, float, float] | None = None
        self.vision_times: list[float] = []
        self.last_vision: tuple[float, float, float] | None = None
        self.last_vision_t_s = 0.0
        self.last_vision_speed = (0.0, 0.0, 0.0)
        self.lock = threading.Lock()
        self.out = open(args.out, "a", buffering=1)
        self.boot_s = time.monotonic()
        self.home_set = False
        self.parameters = {"AHRS_EKF_TYPE": 3, "VISO_TYPE": 1, "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 6,
                           "EK3_SRC1_YAW": 6, "EK3_SRC1_VELXY": 6, "VISO_DELAY_MS": args.viso_delay_ms,
                           "VISO_POS_X": 0.0, "VISO_POS_Y": 0.0, "VISO_POS_Z": 0.0}
        self.ports = {}
        for name, port in (("companion", args.companion_port), ("gcs", args.gcs_port)):
            connection = mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1,
                                                    source_component=1, dialect="ardupilotmega")
            self.ports[name] = {"connection": connection, "streams": {}}

    def record(self, kind: str, name: str, fields: dict, **extra) -> None:
        line = json.dumps({"t_ns": time.monotonic_ns(), "kind": kind, "name": name, "fields": fields, **extra},
                          default=float)
        self.out.write(line + "\n")

    # ---------------------------------------------------------- sending

    def send(self, port: dict, message) -> None:
        try:
            port["connection"].mav.send(message)
        except OSError:
            pass  # not connected yet, or gone

    def ekf_status(self):
        initialised = time.monotonic() - self.boot_s > EKF_INITIALISED_S
        flags = EKF_FLAGS if initialised else mavlink.EKF_UNINITIALIZED
        return mavlink.MAVLink_ekf_status_report_message(flags, 0.0, 0.0, 0.0, 0.0, 0.0)

    def home_message(self):
        lat, lon, alt = self.home
        return mavlink.MAVLink_home_position_message(int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                     int(round(alt * 1000)), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0],
                                                     0.0, 0.0, 0.0)

    def heartbeat(self) -> None:
        v = self.vehicle
        base_mode = CUSTOM_MODE_FLAG | (ARMED_FLAG if v.armed else 0)
        for port in self.ports.values():
            self.send(port, mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, v.mode,
                mavlink.MAV_STATE_ACTIVE if v.armed else mavlink.MAV_STATE_STANDBY, 3))

    def stream_message(self, message_id: int):
        v = self.vehicle
        if message_id == mavlink.MAVLINK_MSG_ID_SIM_STATE:
            lat, lon = offset_degrees(self.home[0], self.home[1], v.position[0], v.position[1])
            alt = self.home[2] - v.position[2]
            q = v.quaternion()
            truth = self.truth_from_origin(lat, lon, alt)
            # state_t_ns: when the vehicle was there. A send can leave well after: a process stopped between
            # the physics step and the send (a stalled simulator) sends the state from before the stall
            self.record("sent", "SIM_STATE", {"lat": lat, "lon": lon, "alt": alt, "yaw": v.yaw_rad,
                                              "ned_from_origin": truth, "state_t_ns": int(v.t_s * 1e9)})
            return mavlink.MAVLink_sim_state_message(
                q[0], q[1], q[2], q[3], 0.0, 0.0, v.yaw_rad, 0.0, 0.0, -9.81, 0.0, 0.0, 0.0,
                lat * 1e7, lon * 1e7, alt, 0.0, 0.0, *v.velocity, int(round(lat * 1e7)), int(round(lon * 1e7)))
        if message_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            return mavlink.MAVLink_attitude_message(self.boot_ms(), 0.0, 0.0, v.yaw_rad, 0.0, 0.0, 0.0)
        if self.last_vision is None:
            return None
        # p(now) = p_vision + v_vision (now - t_capture)
        age_s = time.monotonic() - self.last_vision_t_s
        position = [p + v * age_s for p, v in zip(self.last_vision, self.last_vision_speed)]
        return mavlink.MAVLink_local_position_ned_message(self.boot_ms(), *position, *self.last_vision_speed)

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.boot_s) * 1000)

    def truth_from_origin(self, lat: float, lon: float, alt: float) -> list[float] | None:
        if self.origin is None:
            return None
        north, east = distance_ne(self.origin[0], self.origin[1], lat, lon)
        return [north, east, self.origin[2] - alt]

    # --------------------------------------------------------- receiving

    def handle(self, port: dict, message) -> None:
        kind = message.get_type()
        if kind in ("BAD_DATA", "HEARTBEAT", "TIMESYNC", "STATUSTEXT"):
            return
        if kind in ("VISION_POSITION_ESTIMATE", "VISION_SPEED_ESTIMATE", "ODOMETRY"):
            self.on_vision(kind, message)
        elif kind == "SET_GPS_GLOBAL_ORIGIN":
            self.origin = (message.latitude * 1e-7, message.longitude * 1e-7, message.altitude * 1e-3)
            self.record("received", kind, message.to_dict())
            self.send(port, self.origin_message())
        elif kind == "COMMAND_LONG":
            self.on_command(port, message)
        elif kind == "SET_MODE":
            self.set_mode(int(message.custom_mode))
            self.record("received", kind, message.to_dict())
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self.on_position_target(message)
        elif kind == "PARAM_REQUEST_READ":
            name = message.param_id if isinstance(message.param_id, str) else message.param_id.decode()
            if name in self.parameters:
                self.send(port, mavlink.MAVLink_param_value_message(
                    name.encode(), float(self.parameters[name]), mavlink.MAV_PARAM_TYPE_REAL32,
                    len(self.parameters), list(self.parameters).index(name)))

    def origin_message(self):
        lat, lon, alt = self.origin
        return mavlink.MAVLink_gps_global_origin_message(int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                         int(round(alt * 1000)), 0)

    def on_vision(self, kind: str, message) -> None:
        fields = message.to_dict()
        self.record("received", kind, fields, sysid=message.get_srcSystem(), compid=message.get_srcComponent())
        if kind == "VISION_POSITION_ESTIMATE":
            self.home_set |= self.origin is not None
            with self.lock:
                self.vision_times.append(time.monotonic())
                self.last_vision = (message.x, message.y, message.z)
                self.last_vision_t_s = message.usec * 1e-6  # capture time: the machine's monotonic clock
        elif kind == "VISION_SPEED_ESTIMATE":
            self.last_vision_speed = (message.x, message.y, message.z)

    def vision_fresh(self) -> bool:
        with self.lock:
            recent = [t for t in self.vision_times[-200:] if time.monotonic() - t < VISION_FRESH_S]
        return len(recent) >= 5

    def set_mode(self, mode: int) -> bool:
        if mode not in (0, GUIDED, LAND):
            return False
        self.vehicle.mode = mode
        if mode == LAND and self.vehicle.target is not None:
            self.vehicle.target = [self.vehicle.position[0], self.vehicle.position[1], 0.0]
        return True

    def on_command(self, port: dict, message) -> None:
        command, v = int(message.command), self.vehicle
        result = mavlink.MAV_RESULT_ACCEPTED
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            message_id, interval_us = int(message.param1), message.param2
            if message_id in STREAMS and interval_us > 0:
                port["streams"][message_id] = [interval_us * 1e-6, time.monotonic()]
            elif message_id in STREAMS and interval_us < 0:
                port["streams"].pop(message_id, None)
            else:
                result = mavlink.MAV_RESULT_DENIED
        elif command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(message.param1) == 49:
            if self.origin is None:
                result = mavlink.MAV_RESULT_FAILED
            else:
                self.send(port, self.origin_message())
        elif command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(message.param1) == EKF_STATUS_REPORT_ID:
            self.send(port, self.ekf_status())
        elif command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(message.param1) == HOME_POSITION_ID:
            if self.home_set:
                self.send(port, self.home_message())
            else:
                result = mavlink.MAV_RESULT_FAILED
        elif command == mavlink.MAV_CMD_DO_SET_HOME:
            self.home_set = self.origin is not None
            result = mavlink.MAV_RESULT_ACCEPTED if self.home_set else mavlink.MAV_RESULT_FAILED
        elif command == mavlink.MAV_CMD_DO_SET_MODE:
            result = mavlink.MAV_RESULT_ACCEPTED if self.set_mode(int(message.param2)) else mavlink.MAV_RESULT_DENIED
        elif command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if message.param1 == 1 and not (v.mode == GUIDED and self.origin is not None and self.vision_fresh()):
                result = mavlink.MAV_RESULT_FAILED  # "PreArm: Need Position Estimate"
            else:
                v.armed = message.param1 == 1
                v.target = list(v.position) if v.armed else None
        elif command == mavlink.MAV_CMD_NAV_TAKEOFF:
            if not v.armed or v.mode != GUIDED:
                result = mavlink.MAV_RESULT_FAILED
            else:
                v.target = [v.position[0], v.position[1], -float(message.param7)]
        elif command == mavlink.MAV_CMD_NAV_LAND:
            self.set_mode(LAND)
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        self.record("received", "COMMAND_LONG", {"command": command, "param1": message.param1,
                                                 "param2": message.param2, "param7": message.param7},
                    result=result)
        self.send(port, mavlink.MAVLink_command_ack_message(command, result))

    def on_position_target(self, message) -> None:
        v = self.vehicle
        self.record("received", "SET_POSITION_TARGET_LOCAL_NED", message.to_dict())
        if not v.armed or v.mode != GUIDED or self.origin is None or message.coordinate_frame != 1:
            return
        # the target is from the EKF origin; the vehicle's position is from home
        home_n, home_e = distance_ne(self.origin[0], self.origin[1], self.home[0], self.home[1])
        home_d = self.origin[2] - self.home[2]
        v.target = [message.x - home_n, message.y - home_e, message.z - home_d]

    # --------------------------------------------------------------- loop

    def run(self, duration_s: float, stop: threading.Event) -> None:
        self.record("event", "listening", {})
        deadline = time.monotonic() + duration_s
        next_beat = next_step = next_ekf_report = time.monotonic()
        self.vehicle.t_s = next_step
        while not stop.is_set() and time.monotonic() < deadline:
            now = time.monotonic()
            while next_step <= now:
                self.vehicle.step(STEP_S)
                next_step += STEP_S
            if now >= next_beat:
                self.heartbeat()
                next_beat = now + 1.0
            if now >= next_ekf_report:
                for port in self.ports.values():
                    self.send(port, self.ekf_status())
                next_ekf_report = now + 0.5
            for port in self.ports.values():
                for message_id, due in port["streams"].items():
                    if now >= due[1]:
                        # ArduPilot's GCS_MAVLINK::update_send: on its regular clock, but a stream more than an
                        # interval behind skips the missed sends and starts its clock again from now
                        due[1] = now + due[0] if now - due[1] > due[0] else due[1] + due[0]
                        message = self.stream_message(message_id)
                        if message is not None:
                            self.send(port, message)
                while True:
                    try:
                        message = port["connection"].recv_match(blocking=False)
                    except (OSError, ConnectionError):
                        message = None
                    if message is None:
                        break
                    self.handle(port, message)
            time.sleep(0.001)
        for port in self.ports.values():
            port["connection"].close()
        self.out.close()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--companion-port", type=int, required=True)
    parser.add_argument("--gcs-port", type=int, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--home", required=True, help="LAT,LON,ALT,HEADING as SITL's --home")
    parser.add_argument("--tau", type=float, default=0.5, help="position time constant, s")
    parser.add_argument("--max-speed", type=float, default=1.5, help="m/s")
    parser.add_argument("--max-accel", type=float, default=1.5, help="m/s^2")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--viso-delay-ms", type=float, default=90.0, help="the VISO_DELAY_MS it reports")
    args = parser.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    Peer(args).run(args.duration, stop)


if __name__ == "__main__":
    main()
