"""Every command with wrong or missing input: a one-line error naming what is wrong, a non-zero exit,
never a traceback (an exception escaping cli.main fails the test). Issue 11, items 7 and 9."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion import cli
from companion.sim import simulate

REPO = Path(__file__).resolve().parent.parent
MAP = REPO / "maps" / "warehouse.yaml"
HOVER = REPO / "tests" / "data" / "sequences" / "warehouse_hover"


@pytest.fixture
def place(tmp_path):
    """A working folder with a file (not a folder), a folder of two plain images and nothing else."""
    (tmp_path / "a-file").write_text("not a folder")
    images = tmp_path / "images"
    images.mkdir()
    for name in ("one.png", "two.png"):
        cv2.imwrite(str(images / name), np.full((120, 160), 200, np.uint8))
    (tmp_path / "camera-1280x720.yaml").write_text(yaml.safe_dump({"camera": {
        "width": 1280, "height": 720, "hfov_deg": 70.0, "mount": {"facing": "forward"}}}))
    return tmp_path


CASES = [
    # (arguments, exit status, the start of the one line on stderr); {tmp} is the working folder
    (["markers", "--symbols", "A", "--out", "/proc/companion-test"], 2,
     "companion markers: --out /proc/companion-test: cannot create the folder"),
    (["markers", "--symbols", "A", "--out", "{tmp}/a-file"], 2, "companion markers: --out {tmp}/a-file: exists and is not a folder"),
    (["markers", "--symbols", "A", "--out", "{tmp}/a-file/below"], 2, "companion markers: --out {tmp}/a-file/below: cannot create"),
    (["markers", "--symbols", "A", "--size-mm", "1e6", "--out", "{tmp}/m"], 2,
     "companion markers: error: a 1000000 mm marker at 300 dpi is a 23622000 px square PNG"),
    (["markers", "--symbols", "A", "--size-mm", "3000", "--out", "{tmp}/m"], 2,
     "companion markers: error: a 3000 mm marker at 300 dpi is a 70866 px square PNG"),
    (["detect", "{tmp}/images", "--draw", "/proc/companion-test"], 2,
     "companion detect: --draw /proc/companion-test: cannot create the folder"),
    (["detect", "{tmp}/images", "--draw", "{tmp}/a-file"], 2, "companion detect: --draw {tmp}/a-file: exists and is not a folder"),
    # checked before the work: these images hold no chessboard, yet the --out error comes first
    (["calibrate", "{tmp}/images", "--out", "/proc/camera.yaml"], 2,
     "companion calibrate: --out /proc/camera.yaml: cannot write in /proc"),
    (["calibrate", "{tmp}/images", "--out", "{tmp}/no-folder/camera.yaml"], 2,
     "companion calibrate: --out {tmp}/no-folder/camera.yaml: the folder {tmp}/no-folder does not exist"),
    (["calibrate", "{tmp}/images", "--out", "{tmp}/images"], 2, "companion calibrate: --out {tmp}/images: is a folder"),
    # a camera number and its path are one device: missing, said at once (no retries, no OpenCV warnings)
    (["calibrate", "--device", "97", "--out", "{tmp}/camera.yaml"], 2,
     "companion calibrate: /dev/video97 does not exist (camera unplugged or another number?"),
    (["calibrate", "--device", "/dev/video97", "--out", "{tmp}/camera.yaml"], 2,
     "companion calibrate: /dev/video97 does not exist (camera unplugged or another number?"),
    (["simulate", "{tmp}/s", "--map", str(MAP), "--duration", "-1"], 2,
     "companion simulate: --duration must be a positive number of seconds, not -1.0"),
    (["simulate", "{tmp}/s", "--map", str(MAP), "--duration", "1e9"], 2,
     "companion simulate: 1e+09 s at 30 fps is 30000000001 frames, more than 1000000"),
    (["simulate", "{tmp}/s", "--map", str(MAP), "--pattern", "figure8", "--period", "0"], 2,
     "companion simulate: --period must be a positive number of seconds, not 0.0"),
    (["simulate", "{tmp}/s", "--map", str(MAP), "--fps", "nan"], 2, "companion simulate: --fps must be positive, got nan"),
    (["simulate", "/proc/companion-test", "--map", str(MAP), "--duration", "0.1"], 2,
     "companion simulate: OUT /proc/companion-test: cannot create the folder"),
    (["simulate", "{tmp}/a-file", "--map", str(MAP), "--duration", "0.1"], 2,
     "companion simulate: OUT {tmp}/a-file: exists and is not a folder"),
    (["simulate", "{tmp}/images", "--map", str(MAP), "--duration", "0.1"], 2,
     "companion simulate: {tmp}/images: not empty and not a sequence written by companion simulate"),
    (["localize", "{tmp}/missing"], 2, "companion localize: {tmp}/missing: no such file or folder"),
    (["localize", str(MAP)], 2, f"companion localize: {MAP}: not a sequence folder, image folder or video"),
    # the camera's size, as the survey checks it (a 1280x720 calibration on the 640x480 hover)
    (["localize", str(HOVER), "--camera", "{tmp}/camera-1280x720.yaml"], 2,
     f"companion localize: {HOVER}: the frames are 640x480 but the camera file describes a 1280x720 camera"),
    (["report", str(MAP)], 2, f"companion report: {MAP}: not a folder"),
    (["localize", "{tmp}/images", "--map", str(MAP), "--camera", str(REPO / "config" / "camera-example.yaml")], 2,
     "companion localize: {tmp}/images: an image folder without timestamps.csv needs --fps"),
    (["localize", str(HOVER), "--max-markers", "0"], 2, "companion localize: --max-markers must be 1 or more, not 0"),
    (["localize", str(HOVER), "--fps", "-3"], 2, "companion localize: --fps must be positive, not -3.0"),
    # before the survey's work, not after it
    (["survey", str(HOVER), "--camera", str(REPO / "config" / "camera-example.yaml"), "--map", str(MAP),
      "--out", "/proc/companion-map.yaml", "--no-progress"], 2,
     "companion survey: --out /proc/companion-map.yaml: cannot write in /proc"),
    (["survey", str(HOVER), "--camera", str(REPO / "config" / "camera-example.yaml"), "--map", str(MAP),
      "--out", "{tmp}/map.yaml", "--report", "{tmp}/a-file", "--no-progress"], 2,
     "companion survey: --report {tmp}/a-file: exists and is not a folder"),
    # the option the command takes, not the daemon config's source.fps
    (["survey", "{tmp}/images", "--camera", str(REPO / "config" / "camera-example.yaml"), "--map", str(MAP),
      "--out", "{tmp}/map.yaml", "--no-progress"], 2,
     "companion survey: {tmp}/images: an image folder without timestamps.csv needs --fps"),
    (["map", "check", "{tmp}/images", "--camera", str(REPO / "config" / "camera-example.yaml"), "--map", str(MAP),
      "--no-progress"], 2,
     "companion map check: {tmp}/images: an image folder without timestamps.csv needs --fps"),
    # a missing walk is missing, with or without --camera (not 'which camera filmed it?')
    (["survey", str(HOVER), "{tmp}/missing", "--map", str(MAP), "--out", "{tmp}/map.yaml", "--no-progress"], 2,
     "companion survey: {tmp}/missing: no such file or folder"),
    (["map", "check", "{tmp}/missing", "--map", str(MAP), "--no-progress"], 2,
     "companion map check: {tmp}/missing: no such file or folder"),
    (["survey", "{tmp}/images", "--fps", "nan", "--camera", str(REPO / "config" / "camera-example.yaml"), "--map",
      str(MAP), "--out", "{tmp}/map.yaml", "--no-progress"], 2, "companion survey: --fps must be positive, not nan"),
    (["map", "check", "{tmp}/images", "--fps", "-1", "--camera", str(REPO / "config" / "camera-example.yaml"),
      "--map", str(MAP), "--no-progress"], 2, "companion map check: --fps must be positive, not -1.0"),
    (["check-fc", "serial0"], 2, "companion check-fc: connection 'serial0': want udpout:HOST:PORT"),
    (["check-fc", "udpout:127.0.0.1:9", "--config", "{tmp}/missing.yaml"], 2,
     "companion check-fc: {tmp}/missing.yaml: cannot read config"),
]


@pytest.mark.parametrize("args, status, message", CASES, ids=[" ".join(c[0][:3]) for c in CASES])
def test_bad_input_is_one_line_naming_what_is_wrong(place, capsys, args, status, message):
    tmp = str(place)
    code = cli.main([a.replace("{tmp}", tmp) for a in args])
    err = capsys.readouterr().err
    assert code == status, err
    assert err.startswith(message.replace("{tmp}", tmp)), err
    assert err.count("\n") == 1, err


def test_run_with_bad_input_logs_one_error_and_exits_2(place, capsys):
    for args, message in ((["--config", str(place)], f"{place}: cannot read config: Is a directory"),
                          (["--config", str(place / "a-file")], f"{place / 'a-file'}: must be a mapping (the config)"),
                          (["--replay", str(place / "missing")], f"--replay {place / 'missing'}: no such file or folder"),
                          # the option that sets it with --replay (the config's source section is not used)
                          # the default config takes its camera from a sequence's sequence.yaml
                          (["--replay", str(place / "images")], f"--replay {place / 'images'}: which camera took it?"),
                          (["--config", str(REPO / "config" / "example-raspberrypi.yaml"), "--replay", str(place / "images")],
                           f"{place / 'images'}: an image folder without timestamps.csv needs --fps"),
                          (["--replay", str(place / "images"), "--fps", "-1"], "--fps must be positive, not -1.0"),
                          (["--fps", "10"], "--fps is the frame rate of a --replay: give --replay PATH too"),
                          (["--replay", str(HOVER), "--fps", "10"],
                           f"--fps: --replay {HOVER} has its timestamps.csv, which gives every frame's time")):
        assert cli.main(["run", *args]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and " ERROR companion: " in lines[0] and message in lines[0], lines


def test_simulating_again_into_a_folder_leaves_no_stale_frames(tmp_path):
    """A 1 s run, then a 0.3 s run into the same folder: 10 frames, not the 31 of the first run
    with the last 21 stale."""
    out = tmp_path / "seq"
    base = ["simulate", str(out), "--map", str(MAP), "--fps", "10", "--no-progress"]
    assert cli.main([*base, "--duration", "3"]) == 0
    assert len(list((out / "frames").glob("*.png"))) == 31
    assert cli.main([*base, "--duration", "0.9"]) == 0
    assert sorted(p.name for p in (out / "frames").glob("*.png")) == [f"{i:06d}.png" for i in range(10)]
    assert len(simulate.read_sequence(out).t_ns) == 10
    # and a video run replaces the frames
    assert cli.main([*base, "--duration", "0.4", "--video"]) == 0
    assert not list((out / "frames").glob("*.png")) and (out / "video.avi").is_file()


def test_a_copied_sequence_is_localized_with_the_map_it_carries(tmp_path, capsys):
    """sequence.yaml names the map beside the sequence (a copy made by simulate): the folder copied
    anywhere else is localized as it was (the landed code stored '../../maps/x.yaml')."""
    made = tmp_path / "made" / "deep" / "seq"
    assert cli.main(["simulate", str(made), "--map", str(MAP), "--fps", "10", "--duration", "0.4",
                     "--no-progress"]) == 0
    info = yaml.safe_load((made / "sequence.yaml").read_text())
    assert info["map"] == "map.yaml" and (made / "map.yaml").read_bytes() == MAP.read_bytes()
    copied = tmp_path / "elsewhere"
    shutil.copytree(made, copied)
    shutil.rmtree(tmp_path / "made")
    capsys.readouterr()
    assert cli.main(["localize", str(copied)]) == 0
    out = capsys.readouterr().out
    assert "5/5 frames with a pose" in out


def test_an_old_sequence_naming_the_repository_map_is_still_read(tmp_path, capsys):
    """The committed hover flight names ../../../../maps/warehouse.yaml: found in place, and copied
    below the repository's parent too; copied away from it, an error naming sequence.yaml and --map."""
    assert yaml.safe_load((HOVER / "sequence.yaml").read_text())["map"].startswith("../")
    assert cli.main(["localize", str(HOVER)]) == 0
    capsys.readouterr()
    away = tmp_path / "away"
    shutil.copytree(HOVER, away)
    assert cli.main(["localize", str(away)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"companion localize: {away / 'sequence.yaml'}: map: ../../../../maps/warehouse.yaml is found "
                          "neither beside the sequence nor in a folder above it") and "--map" in err
    assert cli.main(["localize", str(away), "--map", str(MAP)]) == 0


def test_a_reader_that_goes_away_stops_a_command_quietly(tmp_path):
    """`companion detect FOLDER --json | head -1`: when the pipe's reader exits, the command stops without a
    word on stderr and with the status a shell gives a tool SIGPIPE stopped (128 + 13), as `grep` and `cat` do."""
    import subprocess
    import sys

    image = np.full((240, 320), 255, np.uint8)
    for index in range(400):
        cv2.imwrite(str(tmp_path / f"frame{index:03d}.png"), image)
    process = subprocess.Popen([sys.executable, "-m", "companion", "detect", str(tmp_path), "--json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = process.stdout.readline()
    process.stdout.close()  # the reader goes away after one line, as `head -1` does
    stderr = process.stderr.read()
    assert process.wait(timeout=120) == 141
    assert first.startswith('{"image": ') and stderr == ""
