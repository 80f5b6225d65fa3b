"""The facility map: where each RS marker is, as a person measured it on site.

``load_map(path)`` reads and validates a ``maps/*.yaml`` file (format in
``docs/map-format.md``) into a ``FacilityMap``. Every error names the file,
the marker and the key. Marker orientations are turned into rotations by
``companion.geometry.frames``; this module holds no axis convention of its own.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.geometry import frames
from companion.yaml_input import REQUIRED, Where, read_yaml

TOP_KEYS = {"name", "frame", "dictionary", "parity", "default_size_m", "markers"}
FRAME_KEYS = {"origin", "x_bearing_deg", "geodetic_origin"}
GEODETIC_KEYS = {"latitude_deg", "longitude_deg", "altitude_m"}
MARKER_KEYS = {"symbol", "id", "size_m", "position_m", "facing", "rotation_deg", "rpy_deg", "quaternion_wxyz", "note"}
ROTATION_KEYS = ("facing", "rpy_deg", "quaternion_wxyz")
FACING_WORDS = {"+x": 0.0, "+y": 90.0, "-x": 180.0, "-y": -90.0, "up": "up", "down": "down"}
PARITIES = (2, 4)
QUATERNION_NORM_TOLERANCE = 0.01


class MapError(ValueError):
    """A facility map file is unreadable or invalid; the message says where."""


@dataclass(frozen=True)
class GeodeticOrigin:
    """WGS-84 position of the map origin (for SET_GPS_GLOBAL_ORIGIN)."""

    latitude_deg: float
    longitude_deg: float
    altitude_m: float  # above mean sea level


@dataclass(frozen=True)
class MapFrame:
    """How the map frame sits in the world.

    origin: a person's description of the origin point on site.
    x_bearing_deg: bearing of the map's +x axis from true north, clockwise.
    geodetic_origin: where the origin is on Earth, if known.
    """

    origin: str
    x_bearing_deg: float
    geodetic_origin: GeodeticOrigin | None

    @property
    def T_ned_map(self) -> np.ndarray:
        """(4, 4) map -> local NED (same origin)."""
        return frames.T_ned_map(self.x_bearing_deg)


@dataclass(frozen=True)
class MapMarker:
    """One surveyed marker.

    symbol, id: the dictionary symbol and its id.
    size_m: side of the printed inner black square, metres.
    T_map_marker: (4, 4) marker frame -> map frame.
    note: free text from the map (shelf, aisle, ...).
    """

    symbol: str
    id: int
    size_m: float
    T_map_marker: np.ndarray
    note: str = ""

    def corners_marker(self) -> np.ndarray:
        """(4, 3) inner-square corners TL, TR, BR, BL in the marker frame, metres."""
        return frames.marker_inner_corners_m(self.size_m)

    def corners_map(self) -> np.ndarray:
        """(4, 3) inner-square corners TL, TR, BR, BL in the map frame, metres."""
        return frames.transform_points(self.T_map_marker, self.corners_marker())

    @property
    def normal_map(self) -> np.ndarray:
        """(3,) unit normal of the printed face (marker +z) in the map frame."""
        return self.T_map_marker[:3, 2].copy()


@dataclass(frozen=True)
class FacilityMap:
    """A validated facility map.

    markers: by marker id.
    dictionary: dictionary name ("6x6"); parity: RS parity symbols per code
    (2 or 4), which fixes the marker layout (grid size, circles).
    """

    name: str
    path: str
    frame: MapFrame
    dictionary: str
    parity: int
    markers: dict[int, MapMarker]

    @property
    def T_ned_map(self) -> np.ndarray:
        """(4, 4) map -> local NED (same origin)."""
        return self.frame.T_ned_map

    def marker_by_symbol(self, symbol: str) -> MapMarker:
        """The marker printed with ``symbol``; KeyError if it is not mapped."""
        for marker in self.markers.values():
            if marker.symbol == symbol.upper():
                return marker
        raise KeyError(f"no marker {symbol!r} in map {self.path}")


# ----------------------------------------------------------------- loading

def load_map(path) -> FacilityMap:
    """Read and validate a facility map YAML file; raises MapError."""
    return map_from_dict(read_yaml(path, MapError, "map"), str(path))


def map_from_dict(data, path: str) -> FacilityMap:
    """Validate an already parsed map document; ``path`` names it in errors."""
    where = Where(path, MapError, style="labelled")
    data = where.mapping(data, "the map")
    where.reject_unknown(data, TOP_KEYS)
    dictionary = _dictionary(data, where)
    parity = data.get("parity", 2)
    if parity not in PARITIES:
        raise where.error(f"must be one of {PARITIES}, got {parity!r}", "parity")
    default_size_m = where.positive(data, "default_size_m", None)
    frame = _frame(where.value(data, "frame"), where.sub("frame"))
    markers = _markers(where.value(data, "markers"), where, dictionary, default_size_m)
    return FacilityMap(
        name=str(data.get("name", Path(path).stem)),
        path=path,
        frame=frame,
        dictionary=str(data.get("dictionary", "6x6")),
        parity=int(parity),
        markers=markers,
    )


def geodetic_origin(section, where: Where) -> GeodeticOrigin:
    """A ``latitude_deg, longitude_deg, altitude_m`` section (a map frame's, or the config's mavlink.origin)."""
    section = where.mapping(section, "latitude_deg, longitude_deg, altitude_m")
    where.reject_unknown(section, GEODETIC_KEYS)
    origin = GeodeticOrigin(*(where.number(section, key) for key in ("latitude_deg", "longitude_deg", "altitude_m")))
    if not -90.0 <= origin.latitude_deg <= 90.0:
        raise where.error(f"must be in [-90, 90], got {origin.latitude_deg}", "latitude_deg")
    if not -180.0 <= origin.longitude_deg <= 180.0:
        raise where.error(f"must be in [-180, 180], got {origin.longitude_deg}", "longitude_deg")
    return origin


def _dictionary(data: dict, where: Where):
    from companion.markers.dictionary import DictionaryError, load_dictionary

    name = data.get("dictionary", "6x6")
    try:
        return load_dictionary(str(name))
    except DictionaryError as error:
        raise where.error(str(error), "dictionary") from None


def _frame(section, where: Where) -> MapFrame:
    section = where.mapping(section, "origin, x_bearing_deg, geodetic_origin")
    where.reject_unknown(section, FRAME_KEYS)
    origin = where.value(section, "origin")
    if not isinstance(origin, str) or not origin.strip():
        raise where.error("describe where the origin is on site (non-empty text)", "origin")
    bearing = where.number(section, "x_bearing_deg")
    geodetic = section.get("geodetic_origin")
    if geodetic is not None:
        geodetic = geodetic_origin(geodetic, where.sub("geodetic_origin"))
    return MapFrame(origin=origin.strip(), x_bearing_deg=bearing, geodetic_origin=geodetic)


def _markers(section, where: Where, dictionary, default_size_m) -> dict[int, MapMarker]:
    if not isinstance(section, list) or not section:
        raise where.error("must be a non-empty list of markers", "markers")
    markers: dict[int, MapMarker] = {}
    for index, entry in enumerate(section):
        marker = _marker(entry, where, index, dictionary, default_size_m)
        if marker.id in markers:
            raise where.sub(_label(index, marker.symbol)).error(
                f"duplicate marker {marker.symbol!r} (id {marker.id}), already listed", "symbol"
            )
        markers[marker.id] = marker
    return markers


def _label(index: int, symbol: str | None) -> str:
    return f"marker {index}" + (f" ({symbol})" if symbol else "")


def _marker(entry, top: Where, index: int, dictionary, default_size_m) -> MapMarker:
    given = entry.get("symbol") if isinstance(entry, dict) else None
    where = top.sub(_label(index, given if isinstance(given, str) else None))
    entry = where.mapping(entry, "symbol, size_m, position_m, ...")
    where.reject_unknown(entry, MARKER_KEYS)
    symbol, marker_id = _identity(entry, where, dictionary)
    where = top.sub(_label(index, symbol))
    size_m = where.positive(entry, "size_m", REQUIRED if default_size_m is None else default_size_m)
    position_m = where.numbers(entry, "position_m", (3,))
    R_map_marker = _orientation(entry, where)
    return MapMarker(
        symbol=symbol,
        id=marker_id,
        size_m=size_m,
        T_map_marker=frames.make_transform(R_map_marker, position_m),
        note=str(entry.get("note", "")),
    )


def _identity(entry: dict, where: Where, dictionary) -> tuple[str, int]:
    symbols = list(dictionary.symbols)
    if "symbol" not in entry and "id" not in entry:
        raise where.error("missing (or give 'id')", "symbol")
    marker_id = None
    if "id" in entry:
        marker_id = entry["id"]
        if isinstance(marker_id, bool) or not isinstance(marker_id, int) or not 0 <= marker_id < len(symbols):
            raise where.error(f"must be an integer 0-{len(symbols) - 1}, got {marker_id!r}", "id")
    if "symbol" not in entry:
        return symbols[marker_id], marker_id
    symbol = str(entry["symbol"]).upper()
    if symbol not in symbols:
        raise where.error(f"unknown symbol {entry['symbol']!r} (dictionary has {', '.join(symbols)})", "symbol")
    if marker_id is not None and symbols.index(symbol) != marker_id:
        raise where.error(f"{marker_id} is not the id of symbol {symbol!r} ({symbols.index(symbol)})", "id")
    return symbol, symbols.index(symbol)


def _orientation(entry: dict, where: Where) -> np.ndarray:
    """(3, 3) R_map_marker from exactly one of facing / rpy_deg / quaternion_wxyz."""
    given = [key for key in ROTATION_KEYS if key in entry]
    if len(given) != 1:
        found = ", ".join(given) if given else "none"
        raise where.error(f"give exactly one of {', '.join(ROTATION_KEYS)} (found: {found})", "facing")
    if "rotation_deg" in entry and given[0] != "facing":
        raise where.error("only allowed with 'facing'", "rotation_deg")
    if given[0] == "facing":
        return _facing(entry, where)
    if given[0] == "rpy_deg":
        roll, pitch, yaw = np.radians(where.numbers(entry, "rpy_deg", (3,)))
        return frames.rotation_from_euler_321(roll, pitch, yaw)
    q = where.numbers(entry, "quaternion_wxyz", (4,))
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise where.error(f"must be a unit quaternion, norm is {norm:.4g}", "quaternion_wxyz")
    return frames.rotation_from_quaternion(q)


def _facing(entry: dict, where: Where) -> np.ndarray:
    """Base orientation for the facing direction, then the in-plane rotation."""
    facing = entry["facing"]
    if not isinstance(facing, str):
        facing = where.number(entry, "facing")  # a wall heading, degrees
    elif facing.strip().lower() in FACING_WORDS:
        facing = FACING_WORDS[facing.strip().lower()]
    else:
        raise where.error(
            f"{facing!r} is not a direction; use one of {', '.join(FACING_WORDS)} or a wall heading in degrees",
            "facing",
        )
    if facing == "up":
        R_base = frames.R_map_marker_facing_up()
    elif facing == "down":
        R_base = frames.R_map_marker_facing_down()
    else:
        R_base = frames.R_map_marker_on_wall(facing)
    rotation_deg = where.number(entry, "rotation_deg", 0.0)
    # In-plane rotation about the marker's own face normal (counter-clockwise as its viewer sees it).
    return R_base @ frames.rot_z(math.radians(rotation_deg))
