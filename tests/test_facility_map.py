"""Facility map loading: the example map, orientations, and every validation error."""
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.geometry import frames
from companion.geometry.facility_map import MapError, load_map, write_map as write_facility_map

REPO = Path(__file__).resolve().parents[1]
WAREHOUSE = REPO / "maps" / "warehouse.yaml"


def write_map(tmp_path, markers, **top):
    document = {
        "frame": {"origin": "test origin", "x_bearing_deg": 0.0},
        "markers": markers,
        **top,
    }
    path = tmp_path / "test_map.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def one(**marker):
    base = {"symbol": "A", "size_m": 0.15, "position_m": [1.0, 2.0, 3.0], "facing": "+x"}
    base.update(marker)
    return [{k: v for k, v in base.items() if v is not None}]


# ----------------------------------------------------------- the example map

def test_warehouse_map_loads():
    facility = load_map(WAREHOUSE)
    assert len(facility.markers) >= 20
    sizes = [m.size_m for m in facility.markers.values()]
    assert min(sizes) >= 0.15 and max(sizes) <= 0.20
    heights = {round(m.T_map_marker[2, 3], 1) for m in facility.markers.values()}
    assert len(heights) >= 3
    assert facility.frame.geodetic_origin is not None
    assert facility.frame.x_bearing_deg == 35.0
    for marker_id, marker in facility.markers.items():
        assert marker.id == marker_id
        R = marker.T_map_marker[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)


def test_warehouse_alternative_rotation_forms_agree():
    facility = load_map(WAREHOUSE)
    # "3" is given as roll/pitch/yaw, "4" as a quaternion; both equal a tilted wall marker.
    tilted_east = frames.R_map_marker_on_wall(180.0) @ frames.rot_x(math.radians(20))
    tilted_west = frames.R_map_marker_on_wall(0.0) @ frames.rot_x(math.radians(15))
    np.testing.assert_allclose(facility.marker_by_symbol("3").T_map_marker[:3, :3], tilted_east, atol=1e-9)
    np.testing.assert_allclose(facility.marker_by_symbol("4").T_map_marker[:3, :3], tilted_west, atol=1e-5)
    # Numeric and word facings agree.
    np.testing.assert_allclose(
        facility.marker_by_symbol("T").T_map_marker[:3, :3], facility.marker_by_symbol("S").T_map_marker[:3, :3]
    )


def test_warehouse_ned_transform_uses_bearing():
    facility = load_map(WAREHOUSE)
    np.testing.assert_allclose(facility.T_ned_map, frames.T_ned_map(35.0))


# ------------------------------------------------------------- orientations

def test_wall_marker_corners_in_map(tmp_path):
    facility = load_map(write_map(tmp_path, one(facing="-y", size_m=0.2)))
    marker = facility.marker_by_symbol("A")
    # Facing -y: the viewer stands at -y looking +y, their right is +x.
    expected = np.array([[0.9, 2.0, 3.1], [1.1, 2.0, 3.1], [1.1, 2.0, 2.9], [0.9, 2.0, 2.9]])
    np.testing.assert_allclose(marker.corners_map(), expected, atol=1e-12)
    np.testing.assert_allclose(marker.normal_map, [0, -1, 0], atol=1e-12)


def test_floor_marker_with_in_plane_rotation(tmp_path):
    facility = load_map(write_map(tmp_path, one(facing="up", rotation_deg=90.0, size_m=0.2, position_m=[0, 0, 0])))
    corners = facility.marker_by_symbol("A").corners_map()
    # Rotated 90 ccw seen from above: the top edge (TL -> TR) now runs along +y at x = -0.1.
    np.testing.assert_allclose(corners[0], [-0.1, -0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(corners[1], [-0.1, 0.1, 0.0], atol=1e-12)


def test_ceiling_marker_faces_down(tmp_path):
    facility = load_map(write_map(tmp_path, one(facing="down", position_m=[0, 0, 4])))
    np.testing.assert_allclose(facility.marker_by_symbol("A").normal_map, [0, 0, -1], atol=1e-12)


def test_id_instead_of_symbol_and_lowercase_symbol(tmp_path):
    markers = one(symbol=None, id=2) + one(symbol="b", position_m=[0, 0, 0])
    facility = load_map(write_map(tmp_path, markers))
    assert facility.markers[2].symbol == "C"
    assert facility.markers[1].symbol == "B"


def test_default_size(tmp_path):
    facility = load_map(write_map(tmp_path, one(size_m=None), default_size_m=0.17))
    assert facility.marker_by_symbol("A").size_m == 0.17


def test_marker_sd_reads_and_round_trips_through_the_writer(tmp_path):
    """A marker's ``sd`` (both keys optional) reads as given, a marker without one reads as None, and the map
    writer writes it back so that the map reads the same again."""
    markers = (one(sd={"position_m": 0.004, "angle_deg": 0.05})
               + [{"symbol": "B", "size_m": 0.15, "position_m": [2, 2, 1], "facing": "+y", "sd": {"angle_deg": 0.3}},
                  {"symbol": "C", "size_m": 0.15, "position_m": [3, 2, 1], "facing": "+y"},
                  {"symbol": "D", "size_m": 0.15, "position_m": [4, 2, 1], "facing": "+y",
                   "sd": {"position_m": 0, "angle_deg": 0}}])  # exact: the one anchor of a survey
    facility = load_map(write_map(tmp_path, markers))
    a, b, c, d = (facility.marker_by_symbol(s) for s in "ABCD")
    assert (a.sd_position_m, a.sd_angle_deg) == (0.004, 0.05)
    assert (d.sd_position_m, d.sd_angle_deg) == (0.0, 0.0)
    assert (b.sd_position_m, b.sd_angle_deg) == (None, 0.3)
    assert (c.sd_position_m, c.sd_angle_deg) == (None, None)
    write_facility_map(facility, tmp_path / "again.yaml")
    written = {m["symbol"]: m for m in yaml.safe_load((tmp_path / "again.yaml").read_text())["markers"]}
    assert written["A"]["sd"] == {"position_m": 0.004, "angle_deg": 0.05}
    assert written["B"]["sd"] == {"angle_deg": 0.3} and "sd" not in written["C"]
    assert written["D"]["sd"] == {"position_m": 0.0, "angle_deg": 0.0}
    again = load_map(tmp_path / "again.yaml")
    for symbol in "ABCD":
        first, second = facility.marker_by_symbol(symbol), again.marker_by_symbol(symbol)
        assert (second.sd_position_m, second.sd_angle_deg) == (first.sd_position_m, first.sd_angle_deg)


# --------------------------------------------------------------- validation

@pytest.mark.parametrize(
    "marker, key, words",
    [
        (dict(symbol="NOPE"), "symbol", "unknown symbol"),
        (dict(size_m=0.0), "size_m", "positive"),
        (dict(size_m=-0.1), "size_m", "positive"),
        (dict(size_m="big"), "size_m", "finite number"),
        (dict(size_m=None), "size_m", "missing"),
        (dict(position_m=[1, 2]), "position_m", "3 numbers"),
        (dict(position_m=[1, 2, float("nan")]), "position_m", "finite"),
        (dict(position_m=[4000, 3500, 1300]), "position_m", "within 1000 m of the map's origin on each axis (metres), "
                                                           "got [4000.0, 3500.0, 1300.0]: millimetres given?"),
        (dict(facing="sideways"), "facing", "not a direction"),
        (dict(facing=None), "facing", "exactly one"),
        (dict(rpy_deg=[0, 0, 0]), "facing", "exactly one"),
        (dict(facing=None, rpy_deg=[0, 0]), "rpy_deg", "3 numbers"),
        (dict(facing=None, quaternion_wxyz=[1, 0, 0]), "quaternion_wxyz", "4 numbers"),
        (dict(facing=None, quaternion_wxyz=[2, 0, 0, 0]), "quaternion_wxyz", "unit quaternion"),
        (dict(facing=None, quaternion_wxyz=[0, 0, 0, 0]), "quaternion_wxyz", "unit quaternion"),
        (dict(facing=None, rpy_deg=[0, 0, 0], rotation_deg=10), "rotation_deg", "only allowed"),
        (dict(colour="red"), "colour", "unknown key"),
        (dict(id=99), "id", "integer 0-49"),
        (dict(id=5), "id", "not the id"),
        (dict(sd={"position_m": -0.004}), "sd.position_m", "must be >= 0, got -0.004"),
        (dict(sd={"angle_deg": -1}), "sd.angle_deg", "must be >= 0, got -1"),
        (dict(sd={"angle_deg": "small"}), "sd.angle_deg", "finite number"),
        (dict(sd={"position_mm": 4}), "sd.position_mm", "unknown key"),
        (dict(sd=0.004), "sd", "must be a mapping (position_m, angle_deg)"),
    ],
)
def test_marker_errors_name_file_marker_and_key(tmp_path, marker, key, words):
    path = write_map(tmp_path, [{"symbol": "Z", "size_m": 0.2, "position_m": [0, 0, 0], "facing": "up"}] + one(**marker))
    with pytest.raises(MapError) as info:
        load_map(path)
    message = str(info.value)
    assert str(path) in message
    assert "markers entry 2 (" in message   # the second entry, counted as a person counts them
    assert f"'{key}'" in message
    assert words in message


def test_duplicate_marker(tmp_path):
    path = write_map(tmp_path, one() + one(position_m=[5, 5, 1]))
    with pytest.raises(MapError, match=r"markers entry 2 \(A\): key 'symbol': duplicate marker 'A'"):
        load_map(path)
    path = write_map(tmp_path, one() + one(symbol=None, id=0, position_m=[5, 5, 1]))   # the key it was given by
    with pytest.raises(MapError, match=r"markers entry 2 \(A\): key 'id': duplicate marker 'A' \(id 0\)"):
        load_map(path)


@pytest.mark.parametrize(
    "frame, key",
    [
        ({"x_bearing_deg": 0.0}, "origin"),
        ({"origin": "corner"}, "x_bearing_deg"),
        ({"origin": "corner", "x_bearing_deg": "north"}, "x_bearing_deg"),
        ({"origin": "corner", "x_bearing_deg": 0.0, "datum": 1}, "datum"),
        ({"origin": "corner", "x_bearing_deg": 0.0, "geodetic_origin": {"latitude_deg": 95.0, "longitude_deg": 0.0, "altitude_m": 0.0}}, "latitude_deg"),
        ({"origin": "corner", "x_bearing_deg": 0.0, "geodetic_origin": {"latitude_deg": 45.0, "altitude_m": 0.0}}, "longitude_deg"),
    ],
)
def test_frame_errors(tmp_path, frame, key):
    path = write_map(tmp_path, one())
    document = yaml.safe_load(path.read_text())
    document["frame"] = frame
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(MapError) as info:
        load_map(path)
    assert str(path) in str(info.value) and "frame" in str(info.value) and f"'{key}'" in str(info.value)


def test_top_level_errors(tmp_path):
    with pytest.raises(MapError, match="unknown key 'marker'"):
        load_map(write_map(tmp_path, one(), marker=[]))
    with pytest.raises(MapError, match="'parity'"):
        load_map(write_map(tmp_path, one(), parity=3))
    with pytest.raises(MapError, match="'dictionary'"):
        load_map(write_map(tmp_path, one(), dictionary="7x7"))
    with pytest.raises(MapError, match="'markers'"):
        load_map(write_map(tmp_path, []))


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(MapError, match="cannot read"):
        load_map(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("frame: [unclosed\n")
    with pytest.raises(MapError, match="not valid YAML"):
        load_map(bad)
    bad.write_text("- just a list\n")
    with pytest.raises(MapError, match="must be a mapping"):
        load_map(bad)


def test_a_key_given_twice_is_an_error_naming_the_key_and_its_line(tmp_path):
    # PyYAML keeps the last of two equal keys: a second markers: list would drop the first without a word
    path = tmp_path / "twice.yaml"
    path.write_text("frame: {origin: here, x_bearing_deg: 0}\n"
                    "markers:\n  - {symbol: A, position_m: [1, 2, 3], facing: +y, size_m: 0.18}\n"
                    "markers:\n  - {symbol: B, position_m: [1, 2, 3], facing: +y, size_m: 0.18}\n")
    with pytest.raises(MapError, match=r"twice.yaml: not valid YAML: line 4, column 1: key 'markers' given twice"):
        load_map(path)
    path.write_text("frame: {origin: here, x_bearing_deg: 0}\n"
                    "markers:\n  - {symbol: A, position_m: [1, 2, 3], facing: +y, size_m: 0.18, size_m: 0.2}\n")
    with pytest.raises(MapError, match=r"line 3, column \d+: key 'size_m' given twice"):
        load_map(path)


def test_numbers_with_an_exponent_and_no_dot_are_numbers(tmp_path):
    # YAML 1.1 (PyYAML) reads 2e-1 as a string; a person writes it as a number
    path = tmp_path / "exp.yaml"
    path.write_text("frame: {origin: here, x_bearing_deg: 0}\ndefault_size_m: 2e-1\n"
                    "markers:\n  - {symbol: A, position_m: [1e0, 2, 3E-1], facing: +y}\n")
    marker = load_map(path).marker_by_symbol("A")
    assert marker.size_m == 0.2
    assert np.allclose(marker.T_map_marker[:3, 3], [1.0, 2.0, 0.3])


@pytest.mark.parametrize("top, marker, place", [({"default_size_m": 180}, {}, "key 'default_size_m'"),
                                                 ({}, {"size_m": 18.0}, r"\(A\): key 'size_m'"),
                                                 ({"survey": {"sizes_m": {"B": 150}}}, {}, "survey.sizes_m: key 'B'")])
def test_a_marker_size_in_centimetres_or_millimetres_is_refused(tmp_path, top, marker, place):
    with pytest.raises(MapError, match=rf"{place}: must be at most 10 m .* got (180|18|150): centimetres or millimetres given"):
        load_map(write_map(tmp_path, one(**marker), **top))


def test_a_survey_size_for_one_of_the_maps_own_markers_must_be_its_entrys(tmp_path):
    with pytest.raises(MapError, match=r"survey.sizes_m: key 'A': 0.2 m, but A is a marker of this map, of size_m 0.15"):
        load_map(write_map(tmp_path, one(), survey={"sizes_m": {"A": 0.2}}))
    assert load_map(write_map(tmp_path, one(), survey={"sizes_m": {"A": 0.15, "B": 0.2}})).survey.sizes_m["B"] == 0.2


def test_two_maps_differ_by_the_markers_moved_resized_or_missing_not_by_their_file(tmp_path):
    document = yaml.safe_load(WAREHOUSE.read_text())
    (tmp_path / "copy.yaml").write_text(yaml.safe_dump(document))
    facility = load_map(WAREHOUSE)
    assert facility.differences(load_map(tmp_path / "copy.yaml")) == []   # a copy (a recording keeps one)
    document["markers"][0]["position_m"][2] += 0.0005                     # half a millimetre: the same place
    document["markers"][1]["position_m"][0] += 0.05
    document["markers"][2]["size_m"] = 0.25
    gone = document["markers"].pop(3)
    (tmp_path / "other.yaml").write_text(yaml.safe_dump(document))
    moved, resized = (str(document["markers"][k]["symbol"]) for k in (1, 2))
    assert facility.differences(load_map(tmp_path / "other.yaml")) == [
        f"moved or resized: {moved}, {resized}", f"only in this one: {gone['symbol']}"]
