"""Config loading: defaults, resolution of paths, and errors that name the file and key."""
from __future__ import annotations

import dataclasses
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.daemon.config import (ATTITUDE_KEYS, STATUS_KEYS, V4L2_KEYS, AttitudeConfig, ConfigError, ReplayConfig,
                                     V4L2Config, config_from_dict, load_config)
from companion.daemon.record import RecordParams
from companion.fusion import FusionParams
from companion.geometry.facility_map import load_map
from companion.geometry.pose import PoseParams
from companion.mavlink.link import LinkParams, Origin

REPO = Path(__file__).resolve().parent.parent
CAMERA = {"width": 640, "height": 480, "hfov_deg": 70.0,
          "mount": {"lever_arm_m": [0.1, 0.0, 0.05], "facing": "forward"}}


@pytest.fixture
def site(tmp_path):
    """A repository-like tree: maps/warehouse.yaml and a sequence folder under tests/data."""
    (tmp_path / "maps").mkdir()
    shutil.copy(REPO / "maps" / "warehouse.yaml", tmp_path / "maps" / "warehouse.yaml")
    seq = tmp_path / "tests" / "data" / "seq"
    (seq / "frames").mkdir(parents=True)
    cv2.imwrite(str(seq / "frames" / "000000.png"), np.zeros((480, 640), np.uint8))
    (seq / "timestamps.csv").write_text("frame,t_ns,file\n0,0,frames/000000.png\n")
    (seq / "sequence.yaml").write_text(yaml.safe_dump({"map": "maps/warehouse.yaml", "camera": CAMERA, "fps": 30}))
    (tmp_path / "config").mkdir()
    return tmp_path


def write(site: Path, data: dict, name: str = "test.yaml") -> Path:
    path = site / "config" / name
    path.write_text(yaml.safe_dump(data))
    return path


def base_config() -> dict:
    return {
        "source": {"kind": "replay", "path": "../tests/data/seq", "realtime": False},
        "camera": CAMERA,
        "map": "../maps/warehouse.yaml",
        "mavlink": {"connection": "udpout:127.0.0.1:14555", "messages": ["VISION_POSITION_ESTIMATE", "ODOMETRY"],
                    "max_rate_hz": 25, "origin_wait_s": 2.5},
        "fusion": {"max_coast_s": 0.4, "confirm_frames": 2},
        "status": {"interval_s": 1.0},
    }


def test_full_config_is_resolved_relative_to_its_file(site):
    config = load_config(write(site, base_config()))
    assert isinstance(config.source, ReplayConfig)
    assert config.source.path == site / "config" / "../tests/data/seq" and not config.source.realtime
    assert config.camera.width == 640
    np.testing.assert_allclose(config.camera.T_body_camera[:3, 3], [0.1, 0.0, 0.05])
    assert config.facility_map.markers.keys() == load_map(REPO / "maps" / "warehouse.yaml").markers.keys()
    link = config.mavlink
    assert link.connection == "udpout:127.0.0.1:14555" and link.max_rate_hz == 25 and link.origin_wait_s == 2.5
    assert link.send_vision_position and link.send_odometry and not link.send_vision_speed
    assert link.component_id == 197 and link.system_id == 1
    # The EKF origin defaults to the map's geodetic origin.
    assert link.origin == Origin(47.397742, 8.545594, 488.0)
    assert config.fusion.max_coast_s == 0.4 and config.fusion.confirm_frames == 2
    assert config.status_interval_s == 1.0


def test_replayed_sequence_supplies_camera_and_map(site):
    data = base_config()
    del data["camera"], data["map"]
    config = load_config(write(site, data))
    assert config.camera.width == 640
    # sequence.yaml names maps/warehouse.yaml relative to the repository above the sequence
    assert Path(config.facility_map.path).resolve() == (site / "maps" / "warehouse.yaml").resolve()


def test_replay_option_replaces_the_source_and_takes_its_frame_rate(site):
    """``--replay`` over a V4L2 config: a real-time replay of the folder, at ``--fps`` where given (an image
    folder without timestamps.csv needs it), named ``--fps`` in the errors of the replay."""
    data = base_config()
    data["source"] = {"kind": "v4l2", "device": "/dev/video0", "fps": 30}
    images = site / "images"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((480, 640), np.uint8))
    config = load_config(write(site, data), replay=images, replay_fps=12.5)
    assert config.source == ReplayConfig(path=images.resolve(), realtime=True, loop=False, fps=12.5, fps_option="--fps")
    assert load_config(write(site, data), replay=images).source.fps is None  # not the camera's 30


def test_a_replay_without_a_config_is_flown_on_the_map_it_names_not_the_bundled_flights(site):
    # the site's own map: the bundled warehouse with every marker 5 m along x
    moved = yaml.safe_load((site / "maps" / "warehouse.yaml").read_text())
    for marker in moved["markers"]:
        marker["position_m"][0] += 5.0
    (site / "maps" / "site.yaml").write_text(yaml.safe_dump(moved))
    sequence = site / "tests" / "data" / "seq"
    info = yaml.safe_load((sequence / "sequence.yaml").read_text())
    (sequence / "sequence.yaml").write_text(yaml.safe_dump({**info, "map": "maps/site.yaml"}))
    config = load_config(replay=sequence)
    assert Path(config.facility_map.path).resolve() == (site / "maps" / "site.yaml").resolve()
    # the embedded default says the bundled map is exact; of a recording's own map, a surveyed map's accuracy
    assert (config.pose.map_sd_m, config.pose.map_sd_deg) == (PoseParams().map_sd_m, PoseParams().map_sd_deg)
    # a map it names that is nowhere: an error that says how `run` is given one (it has no --map)
    (sequence / "sequence.yaml").write_text(yaml.safe_dump({**info, "map": "maps/gone.yaml"}))
    with pytest.raises(ConfigError, match=r"sequence.yaml: map: maps/gone.yaml is found neither beside the sequence "
                                          r"nor in a folder above it; give the map \(map: in a config given with "
                                          r"--config\)"):
        load_config(replay=sequence)
    (sequence / "sequence.yaml").write_text(yaml.safe_dump({**info, "map": "maps/site.yaml"}))
    # a config of the user's own says which map: it stays
    assert Path(load_config(write(site, base_config()), replay=sequence).facility_map.path).resolve() == \
        (site / "maps" / "warehouse.yaml").resolve()


def test_explicit_origin_overrides_the_map(site):
    data = base_config()
    data["mavlink"]["origin"] = {"latitude_deg": -33.5, "longitude_deg": 151.25, "altitude_m": 12.0}
    assert load_config(write(site, data)).mavlink.origin == Origin(-33.5, 151.25, 12.0)


def test_v4l2_source_and_serial_link(site):
    data = base_config()
    data["source"] = {"kind": "v4l2", "device": "/dev/video2", "width": 1280, "height": 720, "fps": 30,
                      "pixel_format": "YUYV"}
    data["mavlink"]["connection"] = "/dev/ttyAMA0,921600"
    config = load_config(write(site, data))
    assert config.source == V4L2Config(device="/dev/video2", width=1280, height=720, fps=30, pixel_format="YUYV")
    assert config.mavlink.connection == "/dev/ttyAMA0,921600"


def test_commented_raspberry_pi_example_is_a_valid_config(site):
    example = site / "config" / "example-raspberrypi.yaml"
    shutil.copy(REPO / "config" / "example-raspberrypi.yaml", example)
    shutil.copy(REPO / "maps" / "warehouse.yaml", site / "config" / "warehouse.yaml")
    storage = cv2.FileStorage(str(site / "config" / "calibration.yaml"), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]))
    storage.write("distortion_coefficients", np.zeros((1, 5)))
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.release()
    config = load_config(example)
    assert config.pose.corner_sigma_px == 0.5 and config.pose.attitude_sd_deg == 0.5
    assert config.attitude.source == "auto" and config.attitude.max_age_s == 0.1 and config.attitude.rate_hz == 50
    assert isinstance(config.source, V4L2Config) and config.source.pixel_format == "MJPG"
    assert config.mavlink.connection == "/dev/ttyAMA0,921600"
    assert config.camera.K[0, 0] == 600.0


def example_lines(path: Path) -> dict[str, dict[str, tuple[str, str]]]:
    """{section: {key: (value, comment)}} of a commented config, commented-out keys included: a section is a
    key at the line's start (``# record:`` too), its keys the indented ``key: value  # comment`` lines."""
    sections: dict[str, dict[str, tuple[str, str]]] = {}
    section = None
    for line in path.read_text().splitlines():
        top = re.match(r"^#? ?(\w+):", line)
        if top and not line.startswith("#  "):
            section = sections.setdefault(top.group(1), {})
            continue
        entry = re.match(r"^(?:\s*#)?\s{1,}(\w+):\s*([^#]*?)\s*(#.*)?$", line)
        if entry and section is not None:
            section.setdefault(entry.group(1), (entry.group(2), entry.group(3) or ""))
    return sections


def test_the_raspberry_pi_example_shows_every_key_and_the_default_of_every_unmarked_one():
    """The example says it shows every key, with the defaults except where a comment says "site" or "example"."""
    sections = example_lines(REPO / "config" / "example-raspberrypi.yaml")
    defaults = {"pose": PoseParams(), "fusion": FusionParams(), "attitude": AttitudeConfig(),
                "mavlink": LinkParams(), "record": RecordParams(path=Path("unused"))}
    accepted = {"source": V4L2_KEYS, "status": STATUS_KEYS, "attitude": ATTITUDE_KEYS,
                "pose": {f.name for f in dataclasses.fields(PoseParams)},
                "fusion": {f.name for f in dataclasses.fields(FusionParams)},
                "mavlink": {f.name for f in dataclasses.fields(LinkParams) if not f.name.startswith("send_")}
                | {"messages"},
                "record": {f.name for f in dataclasses.fields(RecordParams)}}
    for name, keys in accepted.items():
        assert keys <= set(sections[name]), f"{name}: not shown: {sorted(keys - set(sections[name]))}"
    for name, params in defaults.items():
        for key, (value, comment) in sections[name].items():
            if "site" in comment or "example" in comment or not hasattr(params, key) or key == "path":
                continue
            default = getattr(params, key)
            shown = yaml.safe_load(value)
            assert shown == default or (isinstance(default, float) and shown == pytest.approx(default, abs=1e-4)), \
                f"{name}.{key}: the example shows {shown!r}, the default is {default!r}"


@pytest.mark.parametrize("change, key, words", [
    (lambda d: d.update(extra=1), "extra", "unknown key"),
    (lambda d: d["source"].update(kind="webcam"), "source.kind", "replay, v4l2"),
    (lambda d: d["source"].update(path="../nowhere"), "source.path", "does not exist"),
    (lambda d: d["source"].update(realtime="yes"), "source.realtime", "true or false"),
    (lambda d: d["source"].update(device="/dev/video0"), "source.device", "unknown key"),
    (lambda d: d["mavlink"].update(max_rate_hz=60), "mavlink", "max_rate_hz"),
    (lambda d: d["mavlink"].update(connection="udp-out:1.2.3.4"), "mavlink", "connection"),
    (lambda d: d["mavlink"].update(messages=["GPS_INPUT"]), "mavlink.messages", "VISION_POSITION_ESTIMATE"),
    (lambda d: d["mavlink"].update(heartbeat_interval_s=0), "mavlink.heartbeat_interval_s", "must be >= 0.1 s"),
    (lambda d: d["mavlink"].update(reconnect_initial_s=0), "mavlink.reconnect_initial_s", "must be >= 0.05 s"),
    (lambda d: d["mavlink"].update(origin_retry_s=0), "mavlink.origin_retry_s", "must be >= 0.2 s"),
    (lambda d: d["mavlink"].update(reconnect_max_s=0.2), "mavlink.reconnect_max_s", "reconnect_initial_s (0.5 s)"),
    (lambda d: d["mavlink"].update(system_id=1.5), "mavlink.system_id", "integer"),
    (lambda d: d["mavlink"].update(origin={"latitude_deg": 91, "longitude_deg": 0, "altitude_m": 0}),
     "mavlink.origin.latitude_deg", "[-90, 90]"),
    (lambda d: d["mavlink"].update(origin={"latitude_deg": 1, "longitude_deg": 0}), "mavlink.origin.altitude_m",
     "missing"),
    (lambda d: d["fusion"].update(gate_probability=-1), "fusion", "gate_probability"),
    (lambda d: d["fusion"].update(gate=3), "fusion.gate", "unknown key"),
    (lambda d: d.update(pose={"corner_sigma": 0.2}), "pose.corner_sigma", "unknown key"),
    (lambda d: d["status"].update(interval_s="fast"), "status.interval_s", "number"),
    (lambda d: d.update(map="../maps/missing.yaml"), "map", "does not exist"),
    (lambda d: d.update(source={"kind": "v4l2"}, camera=None) or d.pop("camera"), "camera", "missing"),
])
def test_errors_name_the_file_and_the_key(site, change, key, words):
    data = base_config()
    change(data)
    path = write(site, data, "broken.yaml")
    with pytest.raises(ConfigError) as error:
        load_config(path)
    message = str(error.value)
    assert message.startswith(f"{path}: {key}"), message
    assert words in message


@pytest.mark.parametrize("content, words", [
    (None, "key 'camera.calibration_file': {file}: no such file"),
    ("", "{file}: not an OpenCV FileStorage file: empty or not YAML/XML"),
    (bytes(range(256)), "{file}: not an OpenCV FileStorage file: empty or not YAML/XML"),
    ((REPO / "config" / "calibration.yaml").read_text().replace("rows: 3", "rows: 2"),
     "{file}: key 'camera_matrix': must be an !!opencv-matrix"),
    ((REPO / "config" / "calibration.yaml").read_text().replace("data: [ 457.", "data: [ abc"),
     "{file}: key 'camera_matrix': must be an !!opencv-matrix"),
])
def test_a_missing_or_malformed_calibration_file_is_one_line_naming_it(site, content, words):
    """A zero-byte, binary or miscounted calibration raised OpenCV's SystemError / cv2.error (a traceback)."""
    calibration = site / "config" / "cal.yaml"
    if isinstance(content, bytes):
        calibration.write_bytes(content)
    elif content is not None:
        calibration.write_text(content)
    data = base_config()
    data["camera"] = {"calibration_file": "cal.yaml", "mount": {"facing": "forward"}}
    with pytest.raises(ValueError) as error:
        load_config(write(site, data, "camera.yaml"))
    assert words.format(file=calibration) in str(error.value), str(error.value)


def test_errors_inside_the_camera_section_name_the_file(site):
    data = base_config()
    data["camera"] = {"width": 640}
    path = write(site, data, "camera.yaml")
    with pytest.raises(ValueError, match="camera.yaml"):
        load_config(path)


def test_unreadable_and_invalid_files(site):
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(site / "config" / "absent.yaml")
    bad = site / "config" / "bad.yaml"
    bad.write_text("source: [unclosed\n")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="list.yaml: must be a mapping"):
        config_from_dict([1, 2], "list.yaml")


@pytest.mark.parametrize("path, kind", [("companion/data/default.yaml", "udpout"), ("config/sitl.yaml", "tcp")])
def test_shipped_configs_load(path, kind):
    config = load_config(REPO / path)
    assert isinstance(config.source, ReplayConfig) and config.source.path.is_dir()
    assert config.mavlink.connection.startswith(kind)
    assert config.mavlink.origin is not None  # from the map


def test_default_config_is_found_without_a_path():
    assert load_config(None).path.name == "default.yaml"
