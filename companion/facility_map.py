"""The facility map: where each RS marker is, as a person measured it on site.

``load_map(path)`` reads and validates a ``maps/*.yaml`` file (format in
``docs/map-format.md``) into a ``FacilityMap``. Every error names the file,
the marker and the key. Marker orientations are turned into rotations by
``companion.frames``; this module holds no axis convention of its own.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from companion import frames

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
        h = self.size_m / 2.0
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

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
    path = str(path)
    try:
        text = Path(path).read_text()
    except OSError as error:
        raise MapError(f"{path}: cannot read map: {error.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise MapError(f"{path}: not valid YAML: {error}") from None
    return map_from_dict(data, path)


def map_from_dict(data, path: str) -> FacilityMap:
    """Validate an already parsed map document; ``path`` names it in errors."""
    where = _Where(path)
    if not isinstance(data, dict):
        raise where.error("the document must be a mapping with 'frame' and 'markers'")
    where.reject_unknown(data, TOP_KEYS)
    dictionary = _dictionary(data, where)
    parity = data.get("parity", 2)
    if parity not in PARITIES:
        raise where.error(f"key 'parity': must be one of {PARITIES}, got {parity!r}")
    default_size_m = data.get("default_size_m")
    if default_size_m is not None:
        default_size_m = _positive(default_size_m, where, "default_size_m")
    frame = _frame(where.require(data, "frame"), where.sub("frame"))
    markers = _markers(where.require(data, "markers"), where, dictionary, default_size_m)
    return FacilityMap(
        name=str(data.get("name", Path(path).stem)),
        path=path,
        frame=frame,
        dictionary=str(data.get("dictionary", "6x6")),
        parity=int(parity),
        markers=markers,
    )


class _Where:
    """Where in the file we are, for error messages."""

    def __init__(self, path: str, context: str = ""):
        self.path, self.context = path, context

    def sub(self, context: str) -> "_Where":
        return _Where(self.path, context)

    def error(self, message: str) -> MapError:
        prefix = f"{self.path}: {self.context}: " if self.context else f"{self.path}: "
        return MapError(prefix + message)

    def require(self, mapping: dict, key: str):
        if key not in mapping:
            raise self.error(f"missing key '{key}'")
        return mapping[key]

    def reject_unknown(self, mapping: dict, known: set[str]) -> None:
        unknown = sorted(str(k) for k in mapping if k not in known)
        if unknown:
            raise self.error(f"unknown key '{unknown[0]}' (known keys: {', '.join(sorted(known))})")


def _dictionary(data: dict, where: _Where):
    from companion.dictionary import DictionaryError, load_dictionary

    name = data.get("dictionary", "6x6")
    try:
        return load_dictionary(str(name))
    except DictionaryError as error:
        raise where.error(f"key 'dictionary': {error}") from None


def _frame(section, where: _Where) -> MapFrame:
    if not isinstance(section, dict):
        raise where.error("must be a mapping with 'origin' and 'x_bearing_deg'")
    where.reject_unknown(section, FRAME_KEYS)
    origin = where.require(section, "origin")
    if not isinstance(origin, str) or not origin.strip():
        raise where.error("key 'origin': describe where the origin is on site (non-empty text)")
    bearing = _number(where.require(section, "x_bearing_deg"), where, "x_bearing_deg")
    geodetic = section.get("geodetic_origin")
    if geodetic is not None:
        geodetic = _geodetic(geodetic, where.sub("frame.geodetic_origin"))
    return MapFrame(origin=origin.strip(), x_bearing_deg=bearing, geodetic_origin=geodetic)


def _geodetic(section, where: _Where) -> GeodeticOrigin:
    if not isinstance(section, dict):
        raise where.error("must be a mapping with latitude_deg, longitude_deg, altitude_m")
    where.reject_unknown(section, GEODETIC_KEYS)
    values = {key: _number(where.require(section, key), where, key) for key in sorted(GEODETIC_KEYS)}
    if not -90.0 <= values["latitude_deg"] <= 90.0:
        raise where.error(f"key 'latitude_deg': must be in [-90, 90], got {values['latitude_deg']}")
    if not -180.0 <= values["longitude_deg"] <= 180.0:
        raise where.error(f"key 'longitude_deg': must be in [-180, 180], got {values['longitude_deg']}")
    return GeodeticOrigin(**values)


def _markers(section, where: _Where, dictionary, default_size_m) -> dict[int, MapMarker]:
    if not isinstance(section, list) or not section:
        raise where.error("key 'markers': must be a non-empty list of markers")
    markers: dict[int, MapMarker] = {}
    for index, entry in enumerate(section):
        marker = _marker(entry, where, index, dictionary, default_size_m)
        if marker.id in markers:
            raise where.sub(_label(index, marker.symbol)).error(
                f"key 'symbol': duplicate marker {marker.symbol!r} (id {marker.id}), already listed"
            )
        markers[marker.id] = marker
    return markers


def _label(index: int, symbol: str | None) -> str:
    return f"marker {index}" + (f" ({symbol})" if symbol else "")


def _marker(entry, where: _Where, index: int, dictionary, default_size_m) -> MapMarker:
    if not isinstance(entry, dict):
        raise where.sub(_label(index, None)).error("must be a mapping (symbol, size_m, position_m, ...)")
    symbol = entry.get("symbol")
    where = where.sub(_label(index, symbol if isinstance(symbol, str) else None))
    where.reject_unknown(entry, MARKER_KEYS)
    symbol, marker_id = _identity(entry, where, dictionary)
    where = where.sub(_label(index, symbol))
    if "size_m" in entry or default_size_m is None:
        size_m = _positive(where.require(entry, "size_m"), where, "size_m")
    else:
        size_m = default_size_m
    position_m = _vector(where.require(entry, "position_m"), 3, where, "position_m")
    R_map_marker = _orientation(entry, where)
    return MapMarker(
        symbol=symbol,
        id=marker_id,
        size_m=size_m,
        T_map_marker=frames.make_transform(R_map_marker, position_m),
        note=str(entry.get("note", "")),
    )


def _identity(entry: dict, where: _Where, dictionary) -> tuple[str, int]:
    symbols = list(dictionary.symbols)
    if "symbol" not in entry and "id" not in entry:
        raise where.error("missing key 'symbol' (or 'id')")
    marker_id = None
    if "id" in entry:
        marker_id = entry["id"]
        if isinstance(marker_id, bool) or not isinstance(marker_id, int) or not 0 <= marker_id < len(symbols):
            raise where.error(f"key 'id': must be an integer 0-{len(symbols) - 1}, got {marker_id!r}")
    if "symbol" not in entry:
        return symbols[marker_id], marker_id
    symbol = str(entry["symbol"]).upper()
    if symbol not in symbols:
        raise where.error(f"key 'symbol': unknown symbol {entry['symbol']!r} (dictionary has {', '.join(symbols)})")
    if marker_id is not None and symbols.index(symbol) != marker_id:
        raise where.error(f"key 'id': {marker_id} is not the id of symbol {symbol!r} ({symbols.index(symbol)})")
    return symbol, symbols.index(symbol)


def _orientation(entry: dict, where: _Where) -> np.ndarray:
    """(3, 3) R_map_marker from exactly one of facing / rpy_deg / quaternion_wxyz."""
    given = [key for key in ROTATION_KEYS if key in entry]
    if len(given) != 1:
        found = ", ".join(given) if given else "none"
        raise where.error(f"key 'facing': give exactly one of {', '.join(ROTATION_KEYS)} (found: {found})")
    if "rotation_deg" in entry and given[0] != "facing":
        raise where.error("key 'rotation_deg': only allowed with 'facing'")
    if given[0] == "facing":
        return _facing(entry, where)
    if given[0] == "rpy_deg":
        roll, pitch, yaw = np.radians(_vector(entry["rpy_deg"], 3, where, "rpy_deg"))
        return frames.rotation_from_euler_321(roll, pitch, yaw)
    q = _vector(entry["quaternion_wxyz"], 4, where, "quaternion_wxyz")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise where.error(f"key 'quaternion_wxyz': must be a unit quaternion, norm is {norm:.4g}")
    return frames.rotation_from_quaternion(q)


def _facing(entry: dict, where: _Where) -> np.ndarray:
    """Base orientation for the facing direction, then the in-plane rotation."""
    facing = entry["facing"]
    if isinstance(facing, str):
        if facing.strip().lower() not in FACING_WORDS:
            raise where.error(
                f"key 'facing': {facing!r} is not a direction; use one of "
                f"{', '.join(FACING_WORDS)} or a wall heading in degrees"
            )
        facing = FACING_WORDS[facing.strip().lower()]
    if facing == "up":
        R_base = frames.R_map_marker_facing_up()
    elif facing == "down":
        R_base = frames.R_map_marker_facing_down()
    else:
        R_base = frames.R_map_marker_on_wall(_number(facing, where, "facing"))
    rotation_deg = _number(entry.get("rotation_deg", 0.0), where, "rotation_deg")
    # In-plane rotation about the marker's own face normal (counter-clockwise as its viewer sees it).
    return R_base @ frames.rot_z(math.radians(rotation_deg))


def _number(value, where: _Where, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise where.error(f"key '{key}': must be a finite number, got {value!r}")
    return float(value)


def _positive(value, where: _Where, key: str) -> float:
    number = _number(value, where, key)
    if number <= 0.0:
        raise where.error(f"key '{key}': must be positive, got {number:g}")
    return number


def _vector(value, length: int, where: _Where, key: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != length:
        raise where.error(f"key '{key}': must be a list of {length} numbers, got {value!r}")
    return np.array([_number(v, where, key) for v in value])
