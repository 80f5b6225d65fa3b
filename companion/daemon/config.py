"""The daemon's YAML configuration: loading, defaults and validation.

Every error is a :class:`ConfigError` naming the file, the key and what is
wrong (``config/x.yaml: source.fps: must be >= 0.1, got 0``).
Relative paths are resolved against the directory of the file that names
them. The ``camera`` section is parsed by ``CameraModel.from_config``, the
map file by ``companion.geometry.facility_map.load_map``. For a replay of a recorded
sequence folder, ``camera`` and ``map`` may be left out: the sequence's
``sequence.yaml`` supplies them.
"""
from __future__ import annotations

import dataclasses
import importlib.resources
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, geodetic_origin, load_map
from companion.fusion import FusionParams
from companion.geometry.pose import PoseParams
from companion.mavlink.link import LinkError, LinkParams, Origin
from companion.capture.replay import SEQUENCE_FILE, TIMESTAMPS_FILE, read_sequence_info, sequence_map_path
from companion.capture.simulated import SimulatedCameraParams
from companion.daemon.record import RecordParams
from companion.sim.degrade import DegradationError, Degradations
from companion.yaml_input import Where, read_yaml

TOP_KEYS = {"source", "camera", "map", "detector", "pose", "fusion", "mavlink", "status", "record", "attitude"}
SOURCE_KINDS = ("replay", "v4l2", "simulated_camera")
REPLAY_KEYS = {"kind", "path", "realtime", "loop", "fps"}
V4L2_KEYS = {"kind", "device", "width", "height", "fps", "pixel_format", "stall_timeout_s"}
SIMULATED_KEYS = {"kind", "fps", "start_m", "start_heading_deg", "exposure_latency_ms", "render_delay_ms",
                  "state_rate_hz", "stall_timeout_s", "seed", "degradations", "occluders_per_minute"}
DEGRADATION_KEYS = {f.name for f in dataclasses.fields(Degradations)}
MESSAGES = {"VISION_POSITION_ESTIMATE": "send_vision_position",
            "VISION_SPEED_ESTIMATE": "send_vision_speed",
            "ODOMETRY": "send_odometry"}
# mavlink keys that are not LinkParams fields of the same name
MAVLINK_SPECIAL_KEYS = {"messages", "origin"}
LINK_FIELDS = {f.name for f in dataclasses.fields(LinkParams)} - {"origin"} - set(MESSAGES.values())
STATUS_KEYS = {"interval_s", "http"}
ATTITUDE_KEYS = {"source", "max_age_s", "rate_hz"}
ATTITUDE_SOURCES = ("auto", "link", "none")
DEFAULT_CONFIG = "default.yaml"


class ConfigError(ValueError):
    """A configuration that cannot work: names the file, the key and the problem."""


@dataclass(frozen=True)
class ReplayConfig:
    """fps_option: where the user gives ``fps`` (named in errors): the config's key, or ``--fps`` of
    ``companion run --replay``."""

    path: Path
    realtime: bool = True
    loop: bool = False
    fps: float | None = None
    fps_option: str = "source.fps"


@dataclass(frozen=True)
class V4L2Config:
    device: str = "/dev/video0"
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    pixel_format: str | None = None
    stall_timeout_s: float = 2.0


@dataclass(frozen=True)
class SimulatedCameraConfig:
    """``source: {kind: simulated_camera}``: frames rendered from the simulator's vehicle (docs/sitl.md).

    start_m: (3,) where the vehicle starts in the map (floor under it: z);
    start_heading_deg: its heading there (map frame, counter-clockwise from
    +x); both for ``companion sitl-home``. params: how it renders.
    """

    start_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start_heading_deg: float = 0.0
    params: SimulatedCameraParams = SimulatedCameraParams()


@dataclass(frozen=True)
class AttitudeConfig:
    """Where the flight controller's roll and pitch come from, and when they are too old.

    source: "auto" (a camera: the flight controller's ATTITUDE over MAVLink;
        a replay: its sequence's attitude.csv, if any), "link" (the FC's
        ATTITUDE over MAVLink whatever the source: a replay on a bench, whose
        frames have nothing to do with the live vehicle's attitude) or "none".
    max_age_s: at a frame's capture time, attitude older than this is stale:
        the pose is solved without it (and the daemon says so once).
    rate_hz: the rate ATTITUDE is requested at (MAV_CMD_SET_MESSAGE_INTERVAL).
    """

    source: str = "auto"
    max_age_s: float = 0.1
    rate_hz: float = 50.0


@dataclass(frozen=True)
class Config:
    path: Path
    source: ReplayConfig | V4L2Config | SimulatedCameraConfig
    camera: CameraModel
    facility_map: FacilityMap
    detector: dict[str, Any]
    pose: PoseParams
    fusion: FusionParams
    mavlink: LinkParams
    status_interval_s: float = 0.5
    http: tuple[str, int] | None = None     # status.http: the live view's (host, port); None: off
    record: RecordParams | None = None      # record: the flight recording; None: off
    attitude: AttitudeConfig = AttitudeConfig()


def default_config_path() -> Path:
    """The embedded default, ``companion/data/default.yaml``: the bundled sequence and the example map
    ship beside it as package data, so its relative paths hold in a clone and in an installed package."""
    return Path(str(importlib.resources.files("companion"))) / "data" / DEFAULT_CONFIG


def load_config(path=None, replay=None, replay_fps: float | None = None) -> Config:
    """Read, resolve and validate a config file (the default one when ``path`` is None).

    replay: a sequence folder, video or image folder to replay in real time instead of the
    config's source (the rest of the config as it is: try a site's config on a recording);
    replay_fps: its frame rate: an image folder's (without timestamps), or a video's instead of its own.
    """
    path = Path(path) if path is not None else default_config_path()
    data = read_yaml(path, ConfigError, "config")
    if replay is None:
        if replay_fps is not None:
            raise ConfigError("--fps is the frame rate of a --replay: give --replay PATH too")
        return config_from_dict(data, path)
    if not Path(replay).exists():  # named as the user gave it, not as the config's source.path
        raise ConfigError(f"--replay {replay}: no such file or folder")
    if replay_fps is not None and not replay_fps > 0:
        raise ConfigError(f"--fps must be positive, not {replay_fps}")
    if replay_fps is not None and (Path(replay) / TIMESTAMPS_FILE).is_file():
        raise ConfigError(f"--fps: --replay {replay} has its {TIMESTAMPS_FILE}, which gives every frame's time")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the config must be a mapping of sections")
    recorded = _replay_info(Path(replay))
    if "camera" not in data and "camera" not in recorded:
        config_name = "the embedded default config" if path == default_config_path() else str(path)
        raise ConfigError(f"--replay {replay}: which camera took it? {config_name} has no camera section, and the "
                          f"replay no {SEQUENCE_FILE} naming one (as companion run --record and simulate write): give "
                          "--config FILE with your camera's calibration (camera: calibration_file: ...)")
    if path == default_config_path() and "map" in recorded:
        data = _without_the_bundled_map(data)
    config = config_from_dict({**data, "source": {"kind": "replay", "path": str(Path(replay).resolve())}}, path)
    return dataclasses.replace(config, source=ReplayConfig(path=config.source.path, fps=replay_fps, fps_option="--fps"))


def _without_the_bundled_map(data: dict) -> dict:
    """The embedded default config for a recording that names its own map (``--replay`` without ``--config``):
    the recording's map is the one its markers hang on, not the bundled flight's, and what the default states
    of the bundled map (exact: the flight was rendered from it) is not said of it: a surveyed map's accuracy."""
    pose = {key: value for key, value in (data.get("pose") or {}).items() if key not in ("map_sd_m", "map_sd_deg")}
    return {**{key: value for key, value in data.items() if key != "map"}, "pose": pose}


def config_from_dict(data, path) -> Config:
    """Validate a parsed config; ``path`` names the file in errors and anchors relative paths."""
    path = Path(path)
    where = Where(str(path), ConfigError)
    data = where.mapping(data, "the config")
    where.reject_unknown(data, TOP_KEYS)
    source = _source(data.get("source"), where.sub("source"))
    sequence = _sequence_info(source, where.sub("source"))
    camera = _camera(data, where, path, sequence)
    facility_map = _map(data, where, sequence)
    if isinstance(source, SimulatedCameraConfig) and facility_map.frame.geodetic_origin is None:
        raise where.error(f"a simulated camera needs the map's frame.geodetic_origin to place the simulator's "
                          f"vehicle in the map; {facility_map.path} has none", "source.kind")
    status_where = where.sub("status")
    status = status_where.mapping(data.get("status"), "interval_s, http")
    status_where.reject_unknown(status, STATUS_KEYS)
    return Config(
        path=path,
        source=source,
        camera=camera,
        facility_map=facility_map,
        detector=where.sub("detector").mapping(data.get("detector"), "detector parameters"),
        pose=_parameters(data.get("pose"), where.sub("pose"), PoseParams, "pose parameters"),
        fusion=_parameters(data.get("fusion"), where.sub("fusion"), FusionParams, "fusion parameters"),
        mavlink=_mavlink(data.get("mavlink"), where.sub("mavlink"), facility_map),
        status_interval_s=status_where.number(status, "interval_s", 0.5, minimum=0.05),
        http=http_address(status.get("http"), status_where),
        record=_record(data.get("record"), where.sub("record")),
        attitude=_attitude(data.get("attitude"), where.sub("attitude")),
    )


# ------------------------------------------------ live view and recording (issue 12)

RECORD_KEYS = {f.name for f in dataclasses.fields(RecordParams)}


def http_address(value, where: Where) -> tuple[str, int] | None:
    """``status.http``: "HOST:PORT" (or a bare port, on 127.0.0.1) for the live view; None: off."""
    if value is None or value is False:
        return None
    if isinstance(value, int) and not isinstance(value, bool):
        host, port_text = "127.0.0.1", str(value)
    elif isinstance(value, str) and value.rpartition(":")[0]:
        host, _, port_text = value.rpartition(":")
        host = host.strip("[]")
    else:
        raise where.error(f"must be HOST:PORT such as 127.0.0.1:8080 (or false), got {value!r}", "http")
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise where.error(f"the port must be 0..65535, got {port_text!r}", "http")
    return host, int(port_text)


def _record(section, where: Where) -> RecordParams | None:
    """The ``record`` section: a folder path, or a mapping of ``RecordParams`` fields; None: off."""
    if section is None:
        return None
    section = {"path": section} if isinstance(section, str) else where.mapping(section, ", ".join(sorted(RECORD_KEYS)))
    where.reject_unknown(section, RECORD_KEYS)
    values = {key: section[key] for key in RECORD_KEYS - {"path"} if key in section}
    path = where.path(section, "path")   # its own error names the file and the key
    try:
        return RecordParams(path=path, **values)
    except (TypeError, ValueError) as error:
        raise where.error(str(error)) from None


def _attitude(section, where: Where) -> AttitudeConfig:
    section = where.mapping(section, "source, max_age_s, rate_hz")
    where.reject_unknown(section, ATTITUDE_KEYS)
    source = section.get("source", "auto")
    if source not in ATTITUDE_SOURCES:
        raise where.error(f"must be one of {', '.join(ATTITUDE_SOURCES)}, got {source!r}", "source")
    rate_hz = where.number(section, "rate_hz", 50.0, minimum=1.0)
    if rate_hz > 500.0:
        raise where.error(f"must be <= 500, got {rate_hz:g}", "rate_hz")
    return AttitudeConfig(source=source, max_age_s=where.number(section, "max_age_s", 0.1, minimum=0.005),
                          rate_hz=rate_hz)


def _source(section, where: Where) -> ReplayConfig | V4L2Config | SimulatedCameraConfig:
    section = where.mapping(section, "kind: replay, v4l2 or simulated_camera, ...")
    kind = section.get("kind", "replay")
    if kind not in SOURCE_KINDS:
        raise where.error(f"must be one of {', '.join(SOURCE_KINDS)}, got {kind!r}", "kind")
    if kind == "replay":
        where.reject_unknown(section, REPLAY_KEYS)
        if "path" not in section:
            raise where.error("missing (a sequence folder, video file or image folder)", "path")
        replay_path = where.path(section, "path")
        if not replay_path.exists():
            raise where.error(f"{replay_path} does not exist", "path")
        return ReplayConfig(
            path=replay_path,
            realtime=where.flag(section, "realtime", True),
            loop=where.flag(section, "loop", False),
            fps=where.number(section, "fps", None, minimum=0.1),
        )
    if kind == "simulated_camera":
        return _simulated_camera(section, where)
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
        width=where.positive(section, "width", None, integer=True),
        height=where.positive(section, "height", None, integer=True),
        fps=where.number(section, "fps", None, minimum=0.1),
        pixel_format=pixel_format,
        stall_timeout_s=where.number(section, "stall_timeout_s", 2.0, minimum=0.1),
    )


def _simulated_camera(section: dict, where: Where) -> SimulatedCameraConfig:
    where.reject_unknown(section, SIMULATED_KEYS)
    state_rate_hz = where.number(section, "state_rate_hz", 100.0, minimum=1.0)
    if state_rate_hz > 400.0:
        raise where.error(f"must be <= 400, got {state_rate_hz:g}", "state_rate_hz")
    seed = where.number(section, "seed", 0, minimum=0)
    if not seed.is_integer():
        raise where.error(f"must be a whole number, got {section['seed']!r}", "seed")
    params = SimulatedCameraParams(
        fps=where.positive(section, "fps", 30.0),
        exposure_latency_ms=where.number(section, "exposure_latency_ms", 5.0, minimum=0.0),
        render_delay_ms=where.number(section, "render_delay_ms", 20.0, minimum=0.0),
        state_rate_hz=state_rate_hz,
        stall_timeout_s=where.number(section, "stall_timeout_s", 1.0, minimum=0.1),
        seed=int(seed),
        degradations=_degradations(section.get("degradations"), where.sub("degradations")),
        occluders_per_minute=where.number(section, "occluders_per_minute", 0.0, minimum=0.0),
    )
    if params.fps > 120.0:
        raise where.error(f"must be <= 120, got {params.fps:g}", "fps")
    start = where.numbers(section, "start_m", (2, 3), [0.0, 0.0, 0.0], " (x, y[, z] in the map, metres)")
    return SimulatedCameraConfig(start_m=tuple(float(v) for v in (*start, 0.0)[:3]),
                                 start_heading_deg=where.number(section, "start_heading_deg", 0.0), params=params)


def _degradations(section, where: Where) -> Degradations:
    section = where.mapping(section, ", ".join(sorted(DEGRADATION_KEYS)))
    where.reject_unknown(section, DEGRADATION_KEYS)
    values = {}
    for key, value in section.items():
        if key == "motion_blur":
            values[key] = where.flag(section, key, False)
        elif key == "jpeg_quality":
            values[key] = int(where.number(section, key, 0, minimum=0))
        else:
            values[key] = where.number(section, key)
    try:
        return Degradations(**values)
    except DegradationError as error:
        raise where.error(str(error).removeprefix("degradations: ")) from None


def _replay_info(replay: Path) -> dict:
    """The parsed sequence.yaml of a ``--replay`` sequence folder ({} for a video or a folder without one)."""
    try:
        return read_sequence_info(replay) if replay.is_dir() else {}
    except ValueError as error:
        raise ConfigError(f"--replay {replay}: {error}") from None


def _sequence_info(source, where: Where) -> tuple[dict, Path] | None:
    """(sequence.yaml contents, its path) for a replay of a sequence folder, else None."""
    if not isinstance(source, ReplayConfig) or not source.path.is_dir():
        return None
    info_path = source.path / SEQUENCE_FILE
    try:
        info = read_sequence_info(source.path)
    except ValueError as error:
        raise where.error(str(error), "path") from None
    return (info, info_path) if info else None


def _camera(data: dict, where: Where, path: Path, sequence) -> CameraModel:
    if "camera" in data:
        section, origin = data["camera"], str(path)
    elif sequence is not None and "camera" in sequence[0]:
        section, origin = sequence[0]["camera"], str(sequence[1])
    else:
        raise where.error("missing (needed unless the replayed sequence's sequence.yaml has one)", "camera")
    return CameraModel.from_config(section, origin)


def _map(data: dict, where: Where, sequence) -> FacilityMap:
    if "map" in data:
        map_path = where.path(data, "map")
    elif sequence is not None and "map" in sequence[0]:
        try:
            map_path = sequence_map_path(sequence[1].parent, sequence[0], "map: in a config given with --config")
        except ValueError as error:
            raise ConfigError(str(error)) from None
    else:
        raise where.error("missing (a facility map file, unless the replayed sequence names one)", "map")
    if not map_path.is_file():
        raise where.error(f"{map_path} {'is not a file' if map_path.exists() else 'does not exist'}", "map")
    return load_map(map_path)


def _parameters(section, where: Where, params_type, what: str):
    """A section whose keys are the fields of a parameters dataclass (all optional).

    A key the dataclass lists in ``RENAMED_KEYS`` is an error naming its successor.
    """
    section = where.mapping(section, what)
    for old_key, successor in getattr(params_type, "RENAMED_KEYS", {}).items():
        if old_key in section:
            raise where.error(f"replaced by {successor}", old_key)
    where.reject_unknown(section, {f.name for f in dataclasses.fields(params_type)})
    try:
        return params_type(**section)
    except (TypeError, ValueError) as error:
        raise where.error(str(error)) from None


def _mavlink(section, where: Where, facility_map: FacilityMap) -> LinkParams:
    section = where.mapping(section, "connection, ...")
    where.reject_unknown(section, LINK_FIELDS | MAVLINK_SPECIAL_KEYS)
    values = {key: section[key] for key in LINK_FIELDS if key in section}
    for key in sorted(values.keys() - {"connection"}):
        if isinstance(LinkParams.__dataclass_fields__[key].default, int):
            where.positive(section, key, integer=True)
        else:
            where.number(section, key)
    messages = section.get("messages", ["VISION_POSITION_ESTIMATE"])
    if not isinstance(messages, list) or not messages or any(m not in MESSAGES for m in messages):
        raise where.error(f"must be a non-empty list of {', '.join(MESSAGES)}, got {messages!r}", "messages")
    for message, flag in MESSAGES.items():
        values[flag] = message in messages
    values["origin"] = _origin(section.get("origin"), where.sub("origin"), facility_map)
    try:
        return LinkParams(**values)
    except LinkError as error:  # the key it names is one of this section's
        raise where.error(error.problem, error.key) from None
    except ValueError as error:
        raise where.error(str(error)) from None


def _origin(section, where: Where, facility_map: FacilityMap) -> Origin | None:
    """The EKF origin: the config's, else the map's geodetic origin, else None."""
    geodetic = facility_map.frame.geodetic_origin if section is None else geodetic_origin(section, where)
    if geodetic is None:
        return None
    return Origin(geodetic.latitude_deg, geodetic.longitude_deg, geodetic.altitude_m)
