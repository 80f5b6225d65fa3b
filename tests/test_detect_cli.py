"""`companion detect`: JSON lines, directory expansion, annotated copies, unreadable files."""
from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
GOLDEN = REPO / "tests" / "data" / "detector"
DETECTION_KEYS = {"symbol", "id", "corners", "path", "corrected"}


def run_detect(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "companion", "detect", *args], capture_output=True,
                          text=True, env=env, timeout=120)


@pytest.fixture(scope="module")
def parity2_images(tmp_path_factory) -> Path:
    """The golden parity-2 frames of the default detector (not the survey's) in a folder of their own, plus a
    file that is not an image."""
    folder = tmp_path_factory.mktemp("images")
    for png in GOLDEN.glob("*.png"):
        expected = json.loads(png.with_suffix(".json").read_text())
        if expected["parity"] == 2 and "params" not in expected:
            shutil.copy(png, folder / png.name)
            shutil.copy(png.with_suffix(".json"), folder / png.with_suffix(".json").name)
    return folder


def test_json_lines_for_a_directory_match_the_golden_markers(parity2_images, tmp_path):
    draw = tmp_path / "drawn"
    result = run_detect(str(parity2_images), "--json", "--draw", str(draw))
    assert result.returncode == 0, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    pngs = sorted(parity2_images.glob("*.png"))
    assert [Path(line["image"]) for line in lines] == pngs  # the directory expanded, sorted, JSON files skipped
    for line in lines:
        assert set(line) == {"image", "detections", "ms"} and line["ms"] > 0
        expected = json.loads(Path(line["image"]).with_suffix(".json").read_text())["markers"]
        assert sorted(d["id"] for d in line["detections"]) == sorted(m["id"] for m in expected)
        for d in line["detections"]:
            assert set(d) == DETECTION_KEYS
            marker = next(m for m in expected if m["id"] == d["id"])
            assert (d["symbol"], d["path"]) == (marker["symbol"], marker["path"])
            assert np.abs(np.array(d["corners"]) - np.array(marker["corners"])).max() < 0.75
            assert isinstance(d["corrected"], int) and d["corrected"] >= 0
    drawn = sorted(draw.glob("*.png"))
    assert [p.name for p in drawn] == [p.name for p in pngs]
    annotated = cv2.imread(str(drawn[0]), cv2.IMREAD_UNCHANGED)
    original = cv2.imread(str(pngs[0]), cv2.IMREAD_GRAYSCALE)
    assert annotated.shape == original.shape + (3,)


def test_unreadable_and_missing_files_are_named_skipped_and_counted(tmp_path):
    broken = tmp_path / "broken.png"
    broken.write_text("not a PNG")
    good = GOLDEN / "square_rotations.png"
    result = run_detect(str(broken), str(tmp_path / "missing.png"), str(good))
    assert result.returncode == 1
    assert "broken.png: not a readable image" in result.stderr
    assert "missing.png: no such file" in result.stderr
    assert "2 of 3 images could not be read" in result.stderr
    (line,) = result.stdout.splitlines()  # the good image was still processed, as text
    assert line.startswith(str(good)) and "square" in line and line.count("id ") == 4


def test_parity_option_and_empty_folder(tmp_path):
    result = run_detect(str(GOLDEN / "strip_1_4_parity4.png"), "--json", "--parity", "4")
    assert result.returncode == 0, result.stderr
    (line,) = [json.loads(text) for text in result.stdout.splitlines()]
    assert [(d["symbol"], d["path"]) for d in line["detections"]] == [("L", "circles")]
    empty = run_detect(str(tmp_path))
    assert empty.returncode == 2 and "no images found" in empty.stderr


def test_annotated_copies_never_replace_the_images_read(parity2_images, tmp_path):
    folder = tmp_path / "frames"
    shutil.copytree(parity2_images, folder)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    result = run_detect(str(folder), "--draw", str(folder))
    assert result.returncode == 2 and result.stdout == "", result.stderr
    assert result.stderr.startswith(f"companion detect: --draw {folder}: an annotated copy would replace an image")
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    # a JPEG's copy is a PNG of the same stem: beside it, the PNG read from the same folder would be replaced
    jpeg = tmp_path / "mixed"
    jpeg.mkdir()
    image = cv2.imread(str(next(folder.glob("*.png"))), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(jpeg / "a.jpg"), image)
    assert run_detect(str(jpeg / "a.jpg"), "--draw", str(jpeg)).returncode == 0     # a.png is no input
    cv2.imwrite(str(jpeg / "b.png"), image)
    cv2.imwrite(str(jpeg / "b.jpg"), image)
    assert run_detect(str(jpeg), "--draw", str(jpeg)).returncode == 2


def test_annotated_copies_that_do_not_fit_are_said_apart_from_unreadable_images(parity2_images, tmp_path):
    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # a write past the limit fails, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    draw = tmp_path / "drawn"
    result = subprocess.run([sys.executable, "-m", "companion", "detect", str(parity2_images), "--draw", str(draw)],
                            capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)),
                            preexec_fn=small_files, timeout=120)
    images = len(list(parity2_images.glob("*.png")))
    assert result.returncode == 1 and len(result.stdout.splitlines()) == images   # every image read and detected
    assert f"{images} of {images} annotated copies could not be written" in result.stderr, result.stderr
    assert "could not be read" not in result.stderr and "libpng" not in result.stderr
    assert "cannot write: File too large" in result.stderr
    assert not draw.exists()   # no truncated copy, and the folder the run made is gone
