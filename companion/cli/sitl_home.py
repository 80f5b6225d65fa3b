"""``companion sitl-home --config FILE``: the ``--home`` to start a simulator with (docs/sitl.md).

The config's simulated camera (``source: {kind: simulated_camera}``) names
where the vehicle starts in the map (``start_m``, its z the floor under it)
and its heading there (``start_heading_deg``, counter-clockwise from map +x).
Through the map's ``geodetic_origin`` and ``x_bearing_deg`` that is a
latitude, longitude, altitude above mean sea level and compass heading:
``LAT,LON,ALT,HEADING``, the form of ArduPilot SITL's ``--home`` (and of
``sim_vehicle.py -l``). PX4's gazebo-less SITL takes the same values from
PX4_HOME_LAT, PX4_HOME_LON and PX4_HOME_ALT (``--px4`` prints them).
"""
from __future__ import annotations

import sys

import numpy as np

from companion.daemon.config import ConfigError, SimulatedCameraConfig, load_config
from companion.geometry import frames


def configure_parser(parser) -> None:
    parser.add_argument("--config", metavar="FILE", required=True,
                        help="companion config whose source is a simulated_camera (e.g. config/sitl-camera.yaml)")
    parser.add_argument("--px4", action="store_true", help="print PX4_HOME_* environment assignments instead")


def home_of(config) -> tuple[float, float, float, float]:
    """(latitude_deg, longitude_deg, altitude_m, heading_deg) of the config's start position and heading."""
    source = config.source
    geodetic = config.facility_map.frame.geodetic_origin
    # NED = R_ned_map @ start (both frames share the map origin)
    start_ned = config.facility_map.T_ned_map[:3, :3] @ np.asarray(source.start_m, dtype=float)
    latitude, longitude, altitude = frames.geodetic_from_ned(start_ned, geodetic.latitude_deg,
                                                             geodetic.longitude_deg, geodetic.altitude_m)
    heading = frames.yaw_ned_from_map_heading_deg(source.start_heading_deg, config.facility_map.frame.x_bearing_deg)
    return latitude, longitude, altitude, heading


def main(args) -> int:
    try:
        config = load_config(args.config)
    except (ConfigError, ValueError) as error:
        print(f"companion sitl-home: {error}", file=sys.stderr)
        return 2
    if not isinstance(config.source, SimulatedCameraConfig):
        print(f"companion sitl-home: {args.config}: source.kind must be simulated_camera (it names the start "
              "position and heading)", file=sys.stderr)
        return 2
    latitude, longitude, altitude, heading = home_of(config)
    if args.px4:
        print(f"PX4_HOME_LAT={latitude:.9f} PX4_HOME_LON={longitude:.9f} PX4_HOME_ALT={altitude:.3f}")
    else:
        print(f"{latitude:.9f},{longitude:.9f},{altitude:.3f},{heading:.2f}")
    return 0
