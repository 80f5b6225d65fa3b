"""Pose accuracy on the committed recorded sequences, through `companion localize`."""
import json
from pathlib import Path

import numpy as np
import pytest

from companion import cli
from companion.localize import groundtruth, localize, resources
from companion.geometry.pose import PoseSolver

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
    assert reasons <= {"no mapped markers", "ambiguous", "uncertain", "reprojection", "inconsistent markers", "implausible attitude"}


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
