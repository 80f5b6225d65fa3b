"""The daemon's YAML configuration: loading, defaults and validation.

Every error is a :class:`ConfigError` naming the file, the key and what is
wrong (``config/x.yaml: mavlink.max_rate_hz: must be in (0, 50], got 60``).
Relative paths are resolved against the directory of the file that names
them. The ``camera`` section is parsed by ``CameraModel.from_config``, the
map file by ``companion.facility_map.load_map``. For a replay of a recorded
sequence folder, ``camera`` and ``map`` may be left out: the sequence's
``sequence.yaml`` supplies them.
"""
from __future__ import annotations

import dataclasses
import importlib.resources
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from companion.camera import CameraModel
from companion.facility_map import FacilityMap, load_map
from companion.fusion import FusionParams
from companion.mavlink_link import LinkParams, Origin
from companion.source import SEQUENCE_FILE, read_sequence_info

TOP_KEYS = {"source", "camera", "map", "detector", "fusion", "mavlink", "status"}
SOURCE_KINDS = ("replay", "v4l2")
REPLAY_KEYS = {"kind", "path", "realtime", "loop", "fps"}
V4L2_KEYS = {"kind", "device", "width", "height", "fps", "pixel_format", "stall_timeout_s"}
MESSAGES = {"VISION_POSITION_ESTIMATE": "send_vision_position",
            "VISION_SPEED_ESTIMATE": "send_vision_speed",
            "ODOMETRY": "send_odometry"}
# mavlink keys that are not LinkParams fields of the same name
MAVLINK_SPECIAL_KEYS = {"messages", "origin"}
LINK_FIELDS = {f.name for f in dataclasses.fields(LinkParams)} - {"origin"} - set(MESSAGES.values())
STATUS_KEYS = {"interval_s"}
DEFAULT_CONFIG = "config/default.yaml"


class ConfigError(ValueError):
    """A configuration that cannot work: names the file, the key and the problem."""


@dataclass(frozen=True)
class ReplayConfig:
    path: Path
    realtime: bool = True
    loop: bool = False
    fps: float | None = None


@dataclass(frozen=True)
class V4L2Config:
    device: str = "/dev/video0"
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    pixel_format: str | None = None
    stall_timeout_s: float = 2.0


@dataclass(frozen=True)
class Config:
    path: Path
    source: ReplayConfig | V4L2Config
    camera: CameraModel
    facility_map: FacilityMap
    detector: dict[str, Any]
    fusion: FusionParams
    mavlink: LinkParams
    status_interval_s: float = 0.5


class _Where:
    """Builds error messages for one file and one dotted key prefix."""

    def __init__(self, path, prefix: str = ""):
        self.path, self.prefix = str(path), prefix

    def sub(self, key: str) -> "_Where":
        return _Where(self.path, f"{self.prefix}.{key}" if self.prefix else key)

    def error(self, message: str, key: str | None = None) -> ConfigError:
        name = self.sub(key).prefix if key else self.prefix
        return ConfigError(f"{self.path}: {name}: {message}" if name else f"{self.path}: {message}")

    def mapping(self, value, what: str) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.error(f"must be a mapping ({what}), got {type(value).__name__}")
        return value

    def reject_unknown(self, section: dict, known: set[str]) -> None:
        for key in section:
            if key not in known:
                raise self.error(f"unknown key (known: {', '.join(sorted(known))})", str(key))

    def number(self, section: dict, key: str, default=None, minimum: float | None = None,
               integer: bool = False):
        value = section.get(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(f"must be a number, got {value!r}", key)
        if integer and int(value) != value:
            raise self.error(f"must be an integer, got {value!r}", key)
        if minimum is not None and value < minimum:
            raise self.error(f"must be >= {minimum:g}, got {value!r}", key)
        return int(value) if integer else value

    def flag(self, section: dict, key: str, default: bool) -> bool:
        value = section.get(key, default)
        if not isinstance(value, bool):
            raise self.error(f"must be true or false, got {value!r}", key)
        return value

    def path_value(self, value, key: str, base: Path) -> Path:
        if not isinstance(value, str) or not value:
            raise self.error(f"must be a path, got {value!r}", key)
        path = Path(value).expanduser()
        return path if path.is_absolute() else (base / path)


def default_config_path() -> Path:
    """``config/default.yaml`` from the installed package's data, else from the source tree."""
    packaged = Path(str(importlib.resources.files("companion"))) / "data" / DEFAULT_CONFIG
    if packaged.is_file():
        return packaged
    return Path(__file__).resolve().parent.parent / DEFAULT_CONFIG


def load_config(path=None) -> Config:
    """Read, resolve and validate a config file (the default one when ``path`` is None)."""
    path = Path(path) if path is not None else default_config_path()
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"{path}: cannot read config: {error.strerror or error}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    return config_from_dict(data, path)


def config_from_dict(data, path) -> Config:
    """Validate a parsed config; ``path`` names the file in errors and anchors relative paths."""
    path = Path(path)
    where = _Where(path)
    data = where.mapping(data, "the config")
    where.reject_unknown(data, TOP_KEYS)
    base = path.resolve().parent
    source = _source(where.mapping(data.get("source"), "kind: replay or v4l2, ..."), where.sub("source"), base)
    sequence = _sequence_info(source, where.sub("source"))
    camera = _camera(data, where, path, sequence)
    facility_map = _map(data, where, base, sequence)
    status = where.mapping(data.get("status"), "interval_s")
    where.sub("status").reject_unknown(status, STATUS_KEYS)
    return Config(
        path=path,
        source=source,
        camera=camera,
        facility_map=facility_map,
        detector=where.mapping(data.get("detector"), "detector parameters"),
        fusion=_fusion(where.mapping(data.get("fusion"), "fusion parameters"), where.sub("fusion")),
        mavlink=_mavlink(where.mapping(data.get("mavlink"), "connection, ..."), where.sub("mavlink"), facility_map),
        status_interval_s=where.sub("status").number(status, "interval_s", 0.5, minimum=0.05),
    )


def _source(section: dict, where: _Where, base: Path) -> ReplayConfig | V4L2Config:
    kind = section.get("kind", "replay")
    if kind not in SOURCE_KINDS:
        raise where.error(f"must be one of {', '.join(SOURCE_KINDS)}, got {kind!r}", "kind")
    if kind == "replay":
        where.reject_unknown(section, REPLAY_KEYS)
        if "path" not in section:
            raise where.error("missing (a sequence folder, video file or image folder)", "path")
        replay_path = where.path_value(section["path"], "path", base)
        if not replay_path.exists():
            raise where.error(f"{replay_path} does not exist", "path")
        return ReplayConfig(
            path=replay_path,
            realtime=where.flag(section, "realtime", True),
            loop=where.flag(section, "loop", False),
            fps=where.number(section, "fps", None, minimum=0.1),
        )
    where.reject_unknown(section, V4L2_KEYS)
    device = section.get("device", "/dev/video0")
    if isinstance(device, bool) or not isinstance(device, (str, int)):
        raise where.error(f"must be a device path or index, got {device!r}", "device")
    pixel_format = section.get("pixel_format")
    if pixel_format is not None and (not isinstance(pixel_format, str) or len(pixel_format) != 4):
        raise where.error(f"must be a four-character code such as MJPG or YUYV, got {pixel_format!r}",
                          "pixel_format")
    return V4L2Config(
        device=device,
        width=where.number(section, "width", None, minimum=1, integer=True),
        height=where.number(section, "height", None, minimum=1, integer=True),
        fps=where.number(section, "fps", None, minimum=0.1),
        pixel_format=pixel_format,
        stall_timeout_s=where.number(section, "stall_timeout_s", 2.0, minimum=0.1),
    )


def _sequence_info(source, where: _Where) -> tuple[dict, Path] | None:
    """(sequence.yaml contents, its path) for a replay of a sequence folder, else None."""
    if not isinstance(source, ReplayConfig) or not source.path.is_dir():
        return None
    info_path = source.path / SEQUENCE_FILE
    try:
        info = read_sequence_info(source.path)
    except ValueError as error:
        raise where.error(str(error), "path") from None
    return (info, info_path) if info else None


def _camera(data: dict, where: _Where, path: Path, sequence) -> CameraModel:
    if "camera" in data:
        section, origin = data["camera"], str(path)
    elif sequence is not None and "camera" in sequence[0]:
        section, origin = sequence[0]["camera"], str(sequence[1])
    else:
        raise where.error("missing (needed unless the replayed sequence's sequence.yaml has one)", "camera")
    return CameraModel.from_config(section, origin)


def _map(data: dict, where: _Where, base: Path, sequence) -> FacilityMap:
    if "map" in data:
        map_path = where.path_value(data["map"], "map", base)
    elif sequence is not None and "map" in sequence[0]:
        map_path = _sequence_map_path(sequence[0]["map"], sequence[1], where)
    else:
        raise where.error("missing (a facility map file, unless the replayed sequence names one)", "map")
    if not map_path.is_file():
        raise where.error(f"{map_path} does not exist", "map")
    return load_map(map_path)


def _sequence_map_path(name, info_path: Path, where: _Where) -> Path:
    """A sequence's map: relative to the sequence folder, else to a folder above it (the repository)."""
    if not isinstance(name, str) or not name:
        raise _Where(info_path).error(f"must be a path, got {name!r}", "map")
    candidate = Path(name)
    if candidate.is_absolute():
        return candidate
    for folder in [info_path.parent, *info_path.parent.resolve().parents]:
        if (folder / candidate).is_file():
            return folder / candidate
    raise _Where(info_path).error(f"{name} found neither in {info_path.parent} nor in a folder above it", "map")


def _fusion(section: dict, where: _Where) -> FusionParams:
    known = {f.name for f in dataclasses.fields(FusionParams)}
    where.reject_unknown(section, known)
    try:
        return FusionParams(**section)
    except ValueError as error:
        raise where.error(str(error)) from None


def _mavlink(section: dict, where: _Where, facility_map: FacilityMap) -> LinkParams:
    where.reject_unknown(section, LINK_FIELDS | MAVLINK_SPECIAL_KEYS)
    values = {key: section[key] for key in LINK_FIELDS if key in section}
    for key, value in values.items():
        if key != "connection":
            where.number(section, key, integer=isinstance(LinkParams.__dataclass_fields__[key].default, int))
    messages = section.get("messages", ["VISION_POSITION_ESTIMATE"])
    if not isinstance(messages, list) or not messages or any(m not in MESSAGES for m in messages):
        raise where.error(f"must be a non-empty list of {', '.join(MESSAGES)}, got {messages!r}", "messages")
    for message, flag in MESSAGES.items():
        values[flag] = message in messages
    values["origin"] = _origin(section.get("origin"), where.sub("origin"), facility_map)
    try:
        return LinkParams(**values)
    except ValueError as error:
        raise where.error(str(error)) from None


def _origin(section, where: _Where, facility_map: FacilityMap) -> Origin | None:
    """The EKF origin: the config's, else the map's geodetic origin, else None."""
    if section is None:
        geodetic = facility_map.frame.geodetic_origin
        if geodetic is None:
            return None
        return Origin(geodetic.latitude_deg, geodetic.longitude_deg, geodetic.altitude_m)
    section = where.mapping(section, "latitude_deg, longitude_deg, altitude_m")
    keys = {"latitude_deg", "longitude_deg", "altitude_m"}
    where.reject_unknown(section, keys)
    for key in sorted(keys - set(section)):
        raise where.error("missing", key)
    latitude = where.number(section, "latitude_deg")
    longitude = where.number(section, "longitude_deg")
    if not -90 <= latitude <= 90:
        raise where.error(f"must be in [-90, 90], got {latitude}", "latitude_deg")
    if not -180 <= longitude <= 180:
        raise where.error(f"must be in [-180, 180], got {longitude}", "longitude_deg")
    return Origin(latitude, longitude, where.number(section, "altitude_m"))
