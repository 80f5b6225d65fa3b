"""Pose accuracy on the committed recorded sequences and a rendered parity-4 one, through `companion localize`."""
import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion import cli
from companion.capture.replay import read_sequence_info
from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import load_map
from companion.geometry.pose import PoseSolver
from companion.localize import ReplayFailed, groundtruth, localize, resources
from companion.markers.layout import MarkerLayout
from companion.sim import degrade, raster

REPO = Path(__file__).resolve().parents[1]
# the hover flight is test data; the aisle flight ships with the package (the embedded default replays it)
SEQUENCES = {"warehouse_hover": REPO / "tests" / "data" / "sequences" / "warehouse_hover",
             "warehouse_aisle": REPO / "companion" / "data" / "sequences" / "warehouse_aisle"}


def run(name):
    sequence = SEQUENCES[name]
    facility_map, camera = resources(sequence, None, None)
    truth = groundtruth(sequence)
    results = list(localize(sequence, PoseSolver(facility_map, camera), truth))
    assert len(results) == len(truth)
    return results


def errors(results):
    posed = [r for r in results if r.solution.measurement is not None]
    return posed, np.array([r.error_m for r in posed]), np.array([r.yaw_error_deg for r in posed])


def test_hover_sequence_pose_accuracy():
    # Hovering 3.4 m from the dock wall, two markers in view.
    results = run("warehouse_hover")
    posed, position_m, yaw_deg = errors(results)
    assert len(posed) >= 0.6 * len(results)
    assert all(len(r.solution.marker_ids) == 2 for r in posed)
    assert np.median(position_m) < 0.06
    assert position_m.max() < 0.25
    assert np.median(yaw_deg) < 1.0


def test_aisle_sequence_has_no_outliers():
    # An 8 s flight along aisle 1 (video, occluders): mostly one marker at a time.
    results = run("warehouse_aisle")
    posed, position_m, yaw_deg = errors(results)
    assert len(posed) >= 0.5 * len(results)
    assert position_m.max() < 0.5
    assert np.median(position_m) < 0.12
    assert np.median(yaw_deg) < 1.0
    # Frames without a pose say why.
    reasons = {r.solution.status for r in results if r.solution.measurement is None}
    assert reasons <= {"no mapped markers", "ambiguous", "reprojection", "inconsistent markers", "implausible attitude"}


def test_localize_command_json(capsys):
    assert cli.main(["localize", str(SEQUENCES["warehouse_hover"]), "--json"]) == 0
    captured = capsys.readouterr()
    lines = [json.loads(line) for line in captured.out.splitlines()]
    assert [line["frame"] for line in lines] == list(range(31))
    posed = [line for line in lines if line["status"] == "ok"]
    assert posed
    for line in posed:
        assert len(line["position_ned_m"]) == 3 and len(line["covariance_ned"]) == 6
        assert line["error_m"] < 0.25
    assert "frames with a pose" in captured.err


def test_localize_command_table(capsys):
    assert cli.main(["localize", str(SEQUENCES["warehouse_hover"]), "--max-markers", "1"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:5] == ["frame", "t_ms", "seen", "used", "status"]
    assert len(out) == 1 + 31 + 1
    assert out[-1].startswith(tuple("0123456789")) and "frames with a pose" in out[-1]


def test_localize_command_errors_name_the_file(tmp_path, capsys):
    assert cli.main(["localize", str(SEQUENCES["warehouse_hover"]), "--map", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml" in capsys.readouterr().err
    bad_camera = tmp_path / "camera.yaml"
    bad_camera.write_text("camera: {width: 640, height: 480, hfov_deg: -3}\n")
    assert cli.main(["localize", str(SEQUENCES["warehouse_hover"]), "--camera", str(bad_camera)]) == 2
    assert "camera.yaml: key 'camera.hfov_deg'" in capsys.readouterr().err
    assert cli.main(["localize", str(tmp_path)]) == 2
    assert "no --map given" in capsys.readouterr().err


# --------------------------------------------------------- a parity-4 site

PARITY4_FRAMES = 6


@pytest.fixture(scope="module")
def parity4_sequence(tmp_path_factory) -> Path:
    """The first frames of the hover flight, rendered with the warehouse's markers printed at parity 4.

    A sequence folder as `companion simulate` writes it: PNG frames, timestamps.csv, groundtruth.csv
    (the hover's), sequence.yaml naming the parity-4 map and the hover's camera.
    """
    folder = tmp_path_factory.mktemp("parity4")
    map_text = (REPO / "maps" / "warehouse.yaml").read_text()
    assert "\nparity: 2\n" in map_text
    (folder / "warehouse_p4.yaml").write_text(map_text.replace("\nparity: 2\n", "\nparity: 4\n"))
    facility_map = load_map(folder / "warehouse_p4.yaml")
    hover = SEQUENCES["warehouse_hover"]
    info = read_sequence_info(hover)
    camera = CameraModel.from_config(info["camera"], str(hover / "sequence.yaml"))
    truth = groundtruth(hover)
    layout = MarkerLayout(parity=4)
    renderer = raster.Renderer.from_camera(camera)
    quads = [raster.marker_quad(raster.rs_marker_texture(layout, m.id), m.size_m, m.T_map_marker, gain=0.85,
                                offset=15.0) for m in facility_map.markers.values()]
    rng = np.random.default_rng(4)
    rows = []
    with open(hover / "timestamps.csv", newline="") as handle:
        for row in list(csv.DictReader(handle))[:PARITY4_FRAMES]:
            frame = int(row["frame"])
            T_camera_map = camera.T_camera_body @ frames.invert_transform(truth[frame])
            image = renderer.render(quads, T_camera_map, 120.0).image
            image = degrade.sensor_noise(degrade.gaussian_blur(image, 0.6), rng, 1.0, 0.02)
            cv2.imwrite(str(folder / f"{frame:06d}.png"), image)
            rows.append(f"{frame},{row['t_ns']},{frame:06d}.png")
    (folder / "timestamps.csv").write_text("frame,t_ns,file\n" + "\n".join(rows) + "\n")
    truth_lines = (hover / "groundtruth.csv").read_text().splitlines()[:PARITY4_FRAMES + 1]
    (folder / "groundtruth.csv").write_text("\n".join(truth_lines) + "\n")
    (folder / "sequence.yaml").write_text(yaml.safe_dump({"map": "warehouse_p4.yaml", "camera": info["camera"]}))
    return folder


def test_a_parity_4_site_is_localized_with_its_own_marker_layout(parity4_sequence):
    facility_map, camera = resources(parity4_sequence, None, None)
    assert facility_map.parity == 4
    results = list(localize(parity4_sequence, PoseSolver(facility_map, camera), groundtruth(parity4_sequence)))
    assert len(results) == PARITY4_FRAMES
    posed, position_m, yaw_deg = errors(results)
    assert all(len(r.detected_ids) == 2 for r in results)  # the hover sees two markers
    assert len(posed) >= PARITY4_FRAMES - 1
    assert np.median(position_m) < 0.06 and np.median(yaw_deg) < 1.0


def test_localize_command_on_a_parity_4_site(parity4_sequence, capsys):
    assert cli.main(["localize", str(parity4_sequence), "--json"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(lines) == PARITY4_FRAMES
    assert sum(line["status"] == "ok" for line in lines) >= PARITY4_FRAMES - 1


def test_a_replay_with_unreadable_frames_exits_non_zero(parity4_sequence, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(parity4_sequence, broken)
    (broken / "000002.png").write_bytes(b"not a PNG")
    code = cli.main(["localize", str(broken)])
    captured = capsys.readouterr()
    assert code == 1
    assert f"{PARITY4_FRAMES - 1}/{PARITY4_FRAMES - 1} frames with a pose" in captured.out  # the frames read
    errors_printed = [line for line in captured.err.splitlines() if line.startswith("companion localize:")]
    assert errors_printed == [f"companion localize: {broken}: 1 of {PARITY4_FRAMES} frames could not be read "
                              "(skipped)"]
    facility_map, camera = resources(broken, None, None)
    with pytest.raises(ReplayFailed):
        list(localize(broken, PoseSolver(facility_map, camera)))


def test_a_replay_that_reads_nothing_exits_non_zero(tmp_path, capsys):
    hover = tmp_path / "hover"
    shutil.copytree(SEQUENCES["warehouse_hover"], hover)
    (hover / "video.avi").write_bytes(b"garbage")
    map_path = REPO / "maps" / "warehouse.yaml"
    code = cli.main(["localize", str(hover), "--map", str(map_path)])
    captured = capsys.readouterr()
    assert code == 1
    assert captured.out.splitlines()[-1] == "0/0 frames with a pose"
    assert [line for line in captured.err.splitlines() if line.startswith("companion localize:")] == [
        f"companion localize: {hover}: 31 of 31 frames could not be read (skipped)"]


def test_a_sequence_says_its_map_is_exact_and_localize_weighs_by_it(tmp_path, capsys):
    from companion.geometry.pose import PoseParams
    from companion.localize import LocalizeError, sequence_pose_params

    hover = SEQUENCES["warehouse_hover"]
    # the committed rendered sequence states 0 (rendered from its map); a given --map is not the sequence's
    exact = sequence_pose_params(hover, None, max_markers=1)
    assert (exact.map_sd_m, exact.map_sd_deg, exact.max_markers) == (0.0, 0.0, 1)
    other = sequence_pose_params(hover, str(REPO / "maps" / "warehouse.yaml"))
    assert (other.map_sd_m, other.map_sd_deg) == (PoseParams().map_sd_m, PoseParams().map_sd_deg) == (0.005, 0.2)
    # without the keys: the default (a surveyed site)
    copy = tmp_path / "hover"
    shutil.copytree(hover, copy)
    info = yaml.safe_load((copy / "sequence.yaml").read_text())
    info["map"] = str((hover / info["map"]).resolve())
    del info["map_sd_m"], info["map_sd_deg"]
    (copy / "sequence.yaml").write_text(yaml.safe_dump(info))
    assert sequence_pose_params(copy, None).map_sd_m == 0.005
    # what the CLI prints with the exact map is the solver told the map is exact, frame by frame
    facility_map, camera = resources(hover, None, None)
    truth = groundtruth(hover)
    expected = [r.error_m for r in localize(hover, PoseSolver(facility_map, camera, PoseParams(map_sd_m=0.0, map_sd_deg=0.0)), truth)]
    assert cli.main(["localize", str(hover), "--json"]) == 0
    printed = [json.loads(line).get("error_m") for line in capsys.readouterr().out.splitlines()]
    assert printed == [None if e is None else round(e, 5) for e in expected]
    # a bad value: one line naming the file and the key
    info["map_sd_m"] = "tape"
    (copy / "sequence.yaml").write_text(yaml.safe_dump(info))
    with pytest.raises(LocalizeError, match=r"sequence.yaml: map_sd_m must be a number >= 0"):
        sequence_pose_params(copy, None)
    assert cli.main(["localize", str(copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert "map_sd_m" in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_a_truncated_or_headless_groundtruth_is_an_error_naming_the_file_and_line(tmp_path, capsys):
    from companion.localize import LocalizeError

    hover = SEQUENCES["warehouse_hover"]
    lines = (hover / "groundtruth.csv").read_text().splitlines()
    (tmp_path / "groundtruth.csv").write_text("\n".join(lines[:3] + [lines[3][:8]]) + "\n")  # a write cut short
    with pytest.raises(LocalizeError, match=r"groundtruth.csv: line 4: bad row"):
        groundtruth(tmp_path)
    (tmp_path / "groundtruth.csv").write_text("junk\n" + "\n".join(lines[1:]) + "\n")
    with pytest.raises(LocalizeError, match=r"groundtruth.csv: line 1: no column frame, x_m, y_m, z_m, qw, qx, qy, qz"):
        groundtruth(tmp_path)
    folder = tmp_path / "hover"
    shutil.copytree(hover, folder)
    (folder / "groundtruth.csv").write_text("\n".join(lines[:3] + [lines[3][:8]]) + "\n")
    assert cli.main(["localize", str(folder), "--map", str(REPO / "maps" / "warehouse.yaml")]) == 2
    assert "groundtruth.csv: line 4: bad row" in capsys.readouterr().err
