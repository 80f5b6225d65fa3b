"""The facility map: where each RS marker is, as a person measured it on site.

``load_map(path)`` reads and validates a ``maps/*.yaml`` file (format in
``docs/map-format.md``) into a ``FacilityMap``; ``write_map(facility_map, path)``
writes one that ``load_map`` reads back to the same poses (``companion survey``
writes its maps with it). Every error names the file, the marker and the key.
Marker orientations are turned into rotations by ``companion.geometry.frames``;
this module holds no axis convention of its own.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from companion.geometry import frames
from companion.files import write_whole
from companion.yaml_input import REQUIRED, Where, read_yaml

TOP_KEYS = {"name", "frame", "dictionary", "parity", "default_size_m", "markers", "survey"}
SURVEY_KEYS = {"on_vertical_wall", "sizes_m", "anchor_sd_m", "anchor_sd_deg", "wall_sd_deg"}
FRAME_KEYS = {"origin", "x_bearing_deg", "geodetic_origin"}
GEODETIC_KEYS = {"latitude_deg", "longitude_deg", "altitude_m"}
MARKER_KEYS = {"symbol", "id", "size_m", "position_m", "facing", "rotation_deg", "rpy_deg", "quaternion_wxyz", "note",
               "sd"}
SD_KEYS = ("position_m", "angle_deg")  # a marker's ``sd`` section
SD_DIGITS = 4           # significant digits of a written sd
ROTATION_KEYS = ("facing", "rpy_deg", "quaternion_wxyz")
FACING_WORDS = {"+x": 0.0, "+y": 90.0, "-x": 180.0, "-y": -90.0, "up": "up", "down": "down"}
PARITIES = (2, 4)
# the largest inner square believed (as `companion markers` prints at most): a larger size was given in
# centimetres or millimetres, and a survey with it puts markers kilometres away
MAX_MARKER_SIZE_M = 10.0
# the farthest a marker is believed from the map's origin: a site a kilometre across; positions in millimetres
# (a marker 1.3 m up written 1300) lie beyond it
MAX_POSITION_M = 1000.0
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
    sd_position_m, sd_angle_deg: how well the pose is known, if the map says (its ``sd``): one standard
        deviation of the position along each axis and of the orientation about each axis; None: the pose
        stage's ``PoseParams.map_sd_m`` / ``map_sd_deg`` apply.
    """

    symbol: str
    id: int
    size_m: float
    T_map_marker: np.ndarray
    note: str = ""
    sd_position_m: float | None = None
    sd_angle_deg: float | None = None

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
class SurveyHints:
    """What ``companion survey`` is told beyond the listed markers' poses (the map's ``survey`` section).

    on_vertical_wall: symbols of markers hanging on a vertical wall (their y axis
        vertical), or "all".
    sizes_m: inner-square side (m) by symbol, for markers not listed under ``markers``.
    anchor_sd_m, anchor_sd_deg: how well the listed markers' positions and
        orientations were measured (one standard deviation).
    wall_sd_deg: how far from vertical a wall marker hangs (one standard deviation).
    """

    on_vertical_wall: frozenset[str] | str = frozenset()
    sizes_m: dict[str, float] = field(default_factory=dict)
    anchor_sd_m: float = 0.01
    anchor_sd_deg: float = 1.0
    wall_sd_deg: float = 0.2

    def on_wall(self, symbol: str) -> bool:
        """Whether the marker printed with ``symbol`` is stated to hang on a vertical wall."""
        return self.on_vertical_wall == "all" or symbol in self.on_vertical_wall


@dataclass(frozen=True)
class FacilityMap:
    """A validated facility map.

    markers: by marker id.
    dictionary: dictionary name ("6x6"); parity: RS parity symbols per code
    (2 or 4), which fixes the marker layout (grid size, circles).
    default_size_m: the size of markers that do not give one, if the file states it.
    survey: the optional hints for ``companion survey`` (unused by the pose stage).
    """

    name: str
    path: str
    frame: MapFrame
    dictionary: str
    parity: int
    markers: dict[int, MapMarker]
    default_size_m: float | None = None
    survey: SurveyHints = field(default_factory=SurveyHints)

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

    def differences(self, other: "FacilityMap") -> list[str]:
        """What ``other`` has otherwise (a millimetre, a tenth of a degree: below that a marker is where it was),
        as phrases naming the markers; [] for the same markers in the same places (a map and its copy)."""
        found = []
        if (self.dictionary, self.parity) != (other.dictionary, other.parity):
            found.append(f"markers {self.dictionary} p{self.parity} -> {other.dictionary} p{other.parity}")
        if (self.frame.x_bearing_deg, self.frame.geodetic_origin) != (other.frame.x_bearing_deg,
                                                                       other.frame.geodetic_origin):
            found.append("frame (bearing or geodetic origin)")
        ours, theirs = self.markers, other.markers
        for what, symbols in (
                ("moved or resized", [m.symbol for i, m in ours.items() if i in theirs and not _same_place(m, theirs[i])]),
                ("only in this one", [m.symbol for i, m in ours.items() if i not in theirs]),
                ("only in the other", [m.symbol for i, m in theirs.items() if i not in ours])):
            if symbols:
                found.append(f"{what}: {', '.join(symbols)}")
        return found


def _same_place(a: MapMarker, b: MapMarker) -> bool:
    return (abs(a.size_m - b.size_m) < 1e-3
            and float(np.linalg.norm(a.T_map_marker[:3, 3] - b.T_map_marker[:3, 3])) < 1e-3
            and math.degrees(frames.rotation_angle_rad(a.T_map_marker[:3, :3], b.T_map_marker[:3, :3])) < 0.1)


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
    default_size_m = _size_m(where, data, "default_size_m", None)
    frame = _frame(where.value(data, "frame"), where.sub("frame"))
    markers = _markers(where.value(data, "markers"), where, dictionary, default_size_m)
    survey = _survey(data.get("survey"), where.sub("survey"), dictionary)
    _check_survey_sizes(survey, markers, where.sub("survey.sizes_m"))
    return FacilityMap(
        name=str(data.get("name", Path(path).stem)),
        path=path,
        frame=frame,
        dictionary=str(data.get("dictionary", "6x6")),
        parity=int(parity),
        markers=markers,
        default_size_m=default_size_m,
        survey=survey,
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


def _survey(section, where: Where, dictionary) -> SurveyHints:
    """The optional ``survey`` section; every symbol it names must be in the dictionary."""
    section = where.mapping(section, ", ".join(sorted(SURVEY_KEYS)))
    where.reject_unknown(section, SURVEY_KEYS)
    symbols = set(dictionary.symbols)

    def known(symbol, key: str) -> str:
        name = str(symbol).upper()
        if name not in symbols:
            raise where.error(f"unknown symbol {symbol!r} (dictionary has {', '.join(dictionary.symbols)})", key)
        return name

    walls = section.get("on_vertical_wall", [])
    if isinstance(walls, str) and walls.strip().lower() == "all":
        on_vertical_wall: frozenset[str] | str = "all"
    elif isinstance(walls, list):
        on_vertical_wall = frozenset(known(symbol, "on_vertical_wall") for symbol in walls)
    else:
        raise where.error(f"must be 'all' or a list of symbols, got {walls!r}", "on_vertical_wall")
    sizes = where.mapping(section.get("sizes_m"), "symbol: size_m")
    sizes_m = {known(symbol, "sizes_m"): _size_m(where.sub("sizes_m"), sizes, symbol) for symbol in sizes}
    defaults = SurveyHints()
    return SurveyHints(
        on_vertical_wall=on_vertical_wall,
        sizes_m=sizes_m,
        anchor_sd_m=where.positive(section, "anchor_sd_m", defaults.anchor_sd_m),
        anchor_sd_deg=where.positive(section, "anchor_sd_deg", defaults.anchor_sd_deg),
        wall_sd_deg=where.positive(section, "wall_sd_deg", defaults.wall_sd_deg),
    )


def _check_survey_sizes(survey: SurveyHints, markers: dict[int, MapMarker], where: Where) -> None:
    """A size in ``survey.sizes_m`` is for a marker the survey places: one of the map's own markers keeps its
    entry's ``size_m``, and a different one there would be dropped without a word."""
    for marker in markers.values():
        size_m = survey.sizes_m.get(marker.symbol)
        if size_m is not None and size_m != marker.size_m:
            raise where.error(f"{size_m:g} m, but {marker.symbol} is a marker of this map, of size_m {marker.size_m:g} "
                              f"(its entry's size is the one used)", marker.symbol)


def _size_m(where: Where, mapping: dict, key: str, default=REQUIRED) -> float | None:
    """A marker size in metres: positive, at most ``MAX_MARKER_SIZE_M`` (None for an absent key, default None)."""
    size_m = where.positive(mapping, key, default)
    if size_m is not None and size_m > MAX_MARKER_SIZE_M:
        raise where.error(f"must be at most {MAX_MARKER_SIZE_M:g} m (the printed inner square's side in metres), got "
                          f"{size_m:g}: centimetres or millimetres given?", key)
    return size_m


def _markers(section, where: Where, dictionary, default_size_m) -> dict[int, MapMarker]:
    if not isinstance(section, list) or not section:
        raise where.error("must be a non-empty list of markers", "markers")
    markers: dict[int, MapMarker] = {}
    for index, entry in enumerate(section):
        marker = _marker(entry, where, index, dictionary, default_size_m)
        if marker.id in markers:
            raise where.sub(_label(index, marker.symbol)).error(
                f"duplicate marker {marker.symbol!r} (id {marker.id}), already listed",
                "symbol" if "symbol" in entry else "id"
            )
        markers[marker.id] = marker
    return markers


def _label(index: int, symbol: str | None) -> str:
    """The list entry counted from 1, as a person counts them in the file ("marker 3" would read as an id)."""
    return f"markers entry {index + 1}" + (f" ({symbol})" if symbol else "")


def _marker(entry, top: Where, index: int, dictionary, default_size_m) -> MapMarker:
    given = entry.get("symbol") if isinstance(entry, dict) else None
    where = top.sub(_label(index, given if isinstance(given, str) else None))
    entry = where.mapping(entry, "symbol, size_m, position_m, ...")
    where.reject_unknown(entry, MARKER_KEYS)
    symbol, marker_id = _identity(entry, where, dictionary)
    where = top.sub(_label(index, symbol))
    size_m = _size_m(where, entry, "size_m", REQUIRED if default_size_m is None else default_size_m)
    position_m = where.numbers(entry, "position_m", (3,))
    if np.abs(position_m).max() > MAX_POSITION_M:
        raise where.error(f"must be within {MAX_POSITION_M:g} m of the map's origin on each axis (metres), got "
                          f"{np.round(position_m, 3).tolist()}: millimetres given?", "position_m")
    R_map_marker = _orientation(entry, where)
    sd_position_m, sd_angle_deg = _sd(entry.get("sd"), where)
    return MapMarker(
        symbol=symbol,
        id=marker_id,
        size_m=size_m,
        T_map_marker=frames.make_transform(R_map_marker, position_m),
        note=str(entry.get("note", "")),
        sd_position_m=sd_position_m,
        sd_angle_deg=sd_angle_deg,
    )


def _sd(section, where: Where) -> tuple[float | None, float | None]:
    """(position m, angle deg) of a marker's optional ``sd: {position_m, angle_deg}``, each optional and >= 0
    (0: exact, as the one anchor of a survey, which defines the map frame); errors name the key as
    ``sd.position_m``."""
    if section is None:
        return None, None
    if not isinstance(section, dict):
        raise where.error(f"must be a mapping ({', '.join(SD_KEYS)}), got {section!r}", "sd")
    flat = {f"sd.{key}": value for key, value in section.items()}
    where.reject_unknown(flat, {f"sd.{key}" for key in SD_KEYS})
    return where.number(flat, "sd.position_m", None, minimum=0.0), where.number(flat, "sd.angle_deg", None, minimum=0.0)


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


# ----------------------------------------------------------------- writing

POSITION_DECIMALS = 5   # 10 micrometres
ANGLE_DECIMALS = 5      # 1e-5 degrees
EXACT_AXIS = 1e-9       # an axis this close to map up/down is exactly vertical (a pose built from ``facing``)


def write_map(facility_map: FacilityMap, path, header: str = "") -> None:
    """Write ``facility_map`` as a map file that ``load_map`` reads back to the same poses, whole or not at all.

    ``header``: comment lines put above the map (without the ``#``).
    """
    comments = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    text = yaml.safe_dump(map_to_dict(facility_map), sort_keys=False, default_flow_style=None, width=120,
                          allow_unicode=True)
    write_whole(path, comments + text)


def map_to_dict(facility_map: FacilityMap) -> dict:
    """The map as a plain document in the format ``map_from_dict`` reads.

    ``default_size_m`` is the map's, else the most common marker size; a marker upright
    on a wall is written with ``facing`` (its heading), one on the floor or
    ceiling with ``facing: up``/``down`` and ``rotation_deg``, any other with ``rpy_deg``.
    """
    sizes = [m.size_m for m in facility_map.markers.values()]
    default_size_m = facility_map.default_size_m or max(set(sizes), key=sizes.count)
    frame: dict = {"origin": facility_map.frame.origin, "x_bearing_deg": float(facility_map.frame.x_bearing_deg)}
    if facility_map.frame.geodetic_origin is not None:
        g = facility_map.frame.geodetic_origin
        frame["geodetic_origin"] = {"latitude_deg": g.latitude_deg, "longitude_deg": g.longitude_deg,
                                    "altitude_m": g.altitude_m}
    document = {"name": facility_map.name, "frame": frame, "dictionary": facility_map.dictionary,
                "parity": facility_map.parity, "default_size_m": float(default_size_m), "markers": []}
    for marker in sorted(facility_map.markers.values(), key=lambda m: m.id):
        entry = {"symbol": marker.symbol, "position_m": _rounded(marker.T_map_marker[:3, 3], POSITION_DECIMALS)}
        if marker.size_m != default_size_m:
            entry["size_m"] = float(marker.size_m)
        entry.update(_orientation_entry(marker.T_map_marker[:3, :3]))
        if marker.note:
            entry["note"] = marker.note
        sd = {key: float(f"{value:.{SD_DIGITS}g}") for key, value in
              (("position_m", marker.sd_position_m), ("angle_deg", marker.sd_angle_deg)) if value is not None}
        if sd:
            entry["sd"] = sd
        document["markers"].append(entry)
    survey = _survey_entry(facility_map.survey)
    if survey:
        document["survey"] = survey
    return document


def _orientation_entry(R_map_marker: np.ndarray) -> dict:
    """``facing`` (+ ``rotation_deg``) when the marker is upright on a wall or flat on the floor or ceiling,
    else ``rpy_deg``."""
    x_axis, y_axis, z_axis = R_map_marker.T
    if abs(y_axis[2] - 1.0) < EXACT_AXIS:
        heading_deg = math.degrees(math.atan2(z_axis[1], z_axis[0]))
        return {"facing": round(heading_deg, ANGLE_DECIMALS)}
    for word, R_base in (("up", frames.R_map_marker_facing_up()), ("down", frames.R_map_marker_facing_down())):
        if abs(float(z_axis @ R_base[:, 2]) - 1.0) < EXACT_AXIS:
            # R = R_base Rz(rotation): the in-plane angle of the marker's x axis on the base's axes
            x_in_base = R_base.T @ x_axis
            return {"facing": word, "rotation_deg": round(math.degrees(math.atan2(x_in_base[1], x_in_base[0])),
                                                          ANGLE_DECIMALS)}
    roll, pitch, yaw = frames.euler_321_from_rotation(R_map_marker)
    return {"rpy_deg": _rounded(np.degrees([roll, pitch, yaw]), ANGLE_DECIMALS)}


def _survey_entry(hints: SurveyHints) -> dict:
    """The non-default fields of a ``survey`` section."""
    defaults, entry = SurveyHints(), {}
    if hints.on_vertical_wall:
        entry["on_vertical_wall"] = "all" if hints.on_vertical_wall == "all" else sorted(hints.on_vertical_wall)
    if hints.sizes_m:
        entry["sizes_m"] = {symbol: float(size) for symbol, size in sorted(hints.sizes_m.items())}
    for key in ("anchor_sd_m", "anchor_sd_deg", "wall_sd_deg"):
        if getattr(hints, key) != getattr(defaults, key):
            entry[key] = float(getattr(hints, key))
    return entry


def _rounded(values, decimals: int) -> list[float]:
    # + 0.0 turns -0.0 into 0.0
    return [round(float(v), decimals) + 0.0 for v in np.asarray(values).reshape(-1)]
