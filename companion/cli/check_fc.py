"""``companion check-fc CONNECTION``: read the flight controller's vision parameters and judge them.

Connects like the daemon (``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
``/dev/ttyAMA0,921600``, ...), waits for the flight controller's heartbeat,
reads the parameters that decide whether it fuses our vision
(``companion.mavlink.fc_params``) and prints a table: parameter, value,
expected, verdict, why. With ``--config`` the expectations follow that config
(the camera's lever arm, the messages sent). Exit status: 0 when nothing
blocks vision, 1 when a parameter blocks it, 2 when the check could not be
made (bad connection string or config, no flight controller heard).
"""
from __future__ import annotations

import argparse
import logging
import sys
import threading

from companion.mavlink import fc_params
from companion.mavlink.link import LinkError, LinkParams, MavlinkLink

# A tool, not the daemon: a component id of its own (MAV_COMP_ID_ONBOARD_COMPUTER), so that a running
# daemon (component 197) is no duplicate of it.
CHECK_COMPONENT_ID = 191
MAX_TIMEOUT_S = 3600.0  # an hour: waiting longer for a flight controller is a mistyped number


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("connection", help="udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or a serial "
                                           "device with its baud rate, e.g. /dev/ttyAMA0,921600")
    parser.add_argument("--config", metavar="FILE", help="judge against this daemon config (lever arm, messages)")
    parser.add_argument("--system-id", type=int, default=1, help="the vehicle's system id, 1 to 254 (default 1)")
    parser.add_argument("--latency-ms", type=float, default=None,
                        help="the daemon's measured median capture->send latency, to judge the vision delay "
                             f"(more than 0, at most {fc_params.MAX_DELAY_MS:g})")
    parser.add_argument("--timeout-s", type=float, default=15.0,
                        help="how long to wait for the flight controller and its answers (default 15, at most "
                             f"{MAX_TIMEOUT_S:g})")


def main(args: argparse.Namespace) -> int:
    try:
        check_numbers(args)
        expected = expectations(args.config, args.latency_ms)
        params = LinkParams(connection=args.connection, system_id=args.system_id, component_id=CHECK_COMPONENT_ID,
                            origin_retry_s=1.0)
    except (LinkError, ValueError) as error:
        print(f"companion check-fc: {error}", file=sys.stderr)
        return 2
    logging.getLogger("companion.mavlink").setLevel(logging.ERROR)  # the table says what matters
    result, down_reason, heard_system = read_parameters(params, args.timeout_s)
    if result is None:
        if heard_system is not None:   # it answered, but its parameter answers took longer
            print(f"companion check-fc: flight controller system {heard_system} answered on {args.connection}, but "
                  f"not every parameter within {args.timeout_s:g} s (a missing one is asked for again, three "
                  "times): give a longer --timeout-s", file=sys.stderr)
            return 2
        # a refused port or a missing serial device is retried to the end (a SITL or a USB FC may be starting)
        why = f" ({down_reason})" if down_reason else ""
        print(f"companion check-fc: no flight controller answered on {args.connection} within "
              f"{args.timeout_s:g} s{why}", file=sys.stderr)
        return 2
    autopilot, values, system_id = result
    checks = fc_params.check_parameters(autopilot, values, expected)
    name = fc_params.AUTOPILOT_NAMES.get(autopilot, f"autopilot {autopilot}")
    print(f"flight controller: system {system_id}, {name}")
    if system_id != args.system_id:
        print(f"system id: the flight controller is system {system_id}, the daemon's is {args.system_id} "
              f"(--system-id; the config's mavlink.system_id must be the FC's SYSID_THISMAV / MAV_SYS_ID)")
    if not checks:
        print("not ArduPilot or PX4: no parameters to check")
        return 0
    print(fc_params.table(checks), end="")
    blocking = fc_params.blocking(checks)
    degrading = [c for c in fc_params.problems(checks) if c not in blocking]
    print(f"{len(blocking)} parameter(s) block vision fusion, {len(degrading)} degrade it")
    return 1 if blocking else 0


def check_numbers(args: argparse.Namespace) -> None:
    """A ValueError naming the option for a number out of its range (NaN and infinity included)."""
    if not 1 <= args.system_id <= 254:
        raise ValueError(f"--system-id must be 1 to 254 (255 is a ground station), not {args.system_id}")
    latency_ms = args.latency_ms
    if latency_ms is not None and not 0 < latency_ms <= fc_params.MAX_DELAY_MS:
        raise ValueError(f"--latency-ms must be more than 0 and at most {fc_params.MAX_DELAY_MS:g} ms (where "
                         f"VISO_DELAY_MS and EKF2_EV_DELAY end), not {latency_ms:g}")
    if not 0 < args.timeout_s <= MAX_TIMEOUT_S:
        raise ValueError(f"--timeout-s must be more than 0 and at most {MAX_TIMEOUT_S:g} s, not {args.timeout_s:g}")


def expectations(config_path: str | None, latency_ms: float | None) -> fc_params.Expected:
    """What the daemon sends: from a config when given (its errors name the file and key)."""
    if config_path is None:
        return fc_params.Expected(latency_ms=latency_ms)
    from companion.daemon.config import load_config

    config = load_config(config_path)
    mavlink = config.mavlink
    return fc_params.Expected(lever_arm_m=tuple(float(v) for v in config.camera.T_body_camera[:3, 3]),
                              sends_velocity=mavlink.send_vision_speed or mavlink.send_odometry,
                              latency_ms=latency_ms)


def read_parameters(params: LinkParams, timeout_s: float
                    ) -> tuple[tuple[int, dict, int] | None, str | None, int | None]:
    """(autopilot, {name: value or None}, FC system id) read through a non-streaming link, None on timeout;
    why the link was down at the end (``MavlinkLink.down_reason``: it never opened), or None; and the system
    id of a flight controller that was heard (None: none)."""
    got: list = []
    done = threading.Event()
    link = MavlinkLink(params, stream=False)

    def on_parameters(autopilot: int, values: dict) -> None:
        got.append((autopilot, values, link.fc_system_id))
        done.set()

    link.on_parameters = on_parameters
    link.start()
    try:
        done.wait(timeout_s)
    finally:
        link.close()
    return (got[0] if got else None), link.down_reason, link.fc_system_id
