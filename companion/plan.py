"""The top view of a facility (the map's x-y plane, z up): markers and vehicle poses.

Shared by the live view's map panel (``companion.daemon.web``) and the flight
report's track plot (``companion.report``). NED positions and attitudes are
turned into the map frame through ``companion.geometry.frames``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.geometry import frames
from companion.geometry.facility_map import FacilityMap


@dataclass(frozen=True)
class MarkerPlan:
    """One marker seen from above.

    centre_m: (x, y) of the inner square's centre; half_width_m: (dx, dy) from
    the centre to its right edge (along the marker's x axis projected onto the
    floor; zero for a marker on the floor or ceiling seen edge-on in plan);
    normal: (nx, ny) unit horizontal direction it faces (zero if it faces up or down).
    """

    symbol: str
    id: int
    centre_m: tuple[float, float]
    half_width_m: tuple[float, float]
    normal: tuple[float, float]
    height_m: float


def markers_plan(facility_map: FacilityMap) -> list[MarkerPlan]:
    plans = []
    for marker in sorted(facility_map.markers.values(), key=lambda m: m.id):
        T = marker.T_map_marker
        normal = T[:2, 2]
        norm = float(np.linalg.norm(normal))
        normal = normal / norm if norm > 1e-6 else np.zeros(2)
        half = T[:2, 0] * marker.size_m / 2
        plans.append(MarkerPlan(marker.symbol, marker.id, (float(T[0, 3]), float(T[1, 3])),
                                (float(half[0]), float(half[1])), (float(normal[0]), float(normal[1])),
                                float(T[2, 3])))
    return plans


def map_bounds_m(facility_map: FacilityMap, margin_m: float = 1.0) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) around every marker, ``margin_m`` wider."""
    xy = np.array([m.T_map_marker[:2, 3] for m in facility_map.markers.values()]).reshape(-1, 2)
    if len(xy) == 0:
        return (-margin_m, margin_m, -margin_m, margin_m)
    return (float(xy[:, 0].min() - margin_m), float(xy[:, 0].max() + margin_m),
            float(xy[:, 1].min() - margin_m), float(xy[:, 1].max() + margin_m))


class MapPlane:
    """NED poses -> the map's plan view, for one facility map."""

    def __init__(self, facility_map: FacilityMap):
        self.T_map_ned = frames.invert_transform(facility_map.T_ned_map)

    def positions_m(self, positions_ned_m) -> np.ndarray:
        """(N, 3) map-frame positions of (N, 3) NED positions."""
        return frames.transform_points(self.T_map_ned, np.asarray(positions_ned_m, dtype=float).reshape(-1, 3))

    def heading_rad(self, roll_rad: float, pitch_rad: float, yaw_rad: float) -> float:
        """Direction of the body's forward axis in the map plane, from +x toward +y."""
        R_map_body = self.T_map_ned[:3, :3] @ frames.rotation_from_euler_321(roll_rad, pitch_rad, yaw_rad)
        forward = R_map_body[:, 0]
        return math.atan2(forward[1], forward[0])
