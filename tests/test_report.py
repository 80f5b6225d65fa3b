"""`companion report DIR`: a self-contained HTML report of a recorded flight."""
from __future__ import annotations

import base64
import csv
import html
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.daemon.config import config_from_dict
from companion.daemon.record import ESTIMATE_COLUMNS
from companion.daemon.service import Daemon
from companion.report.flight_log import ReportError, read_flight
from mavlink_peer import free_port

REPO = Path(__file__).resolve().parent.parent
HOVER = REPO / "tests" / "data" / "sequences" / "warehouse_hover"
MAP = REPO / "maps" / "warehouse.yaml"
SECTIONS = ("Summary", "Track over the map", "Position and yaw against time", "Vision availability",
            "Log while recording", "Capture → send latency", "Markers", "Error against the ground truth")


def report(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion", "report", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """The hover flight replayed by the daemon (as fast as possible) and recorded."""
    folder = tmp_path_factory.mktemp("report") / "flight"
    config = config_from_dict({
        "source": {"kind": "replay", "path": str(HOVER), "realtime": False},
        "map": str(MAP),
        "mavlink": {"connection": f"udpout:127.0.0.1:{free_port()}", "origin_wait_s": 0.0, "duplicate_listen_s": 0.0},
        "record": str(folder),
    }, folder.parent / "daemon.yaml")
    assert Daemon(config).run() == 0
    return folder


def test_report_of_a_recording_is_one_self_contained_page_with_every_section(recording):
    run = report(str(recording))
    assert run.returncode == 0, run.stderr
    page = (recording / "report.html").read_text()
    assert f"{recording / 'report.html'}: 31 frames" in run.stdout
    for title in SECTIONS:
        assert f"<h2>{title}</h2>" in page, title
    # self-contained: nothing fetched from elsewhere, every plot embedded and a real PNG
    assert not re.search(r'(src|href)="(?!data:)', page)
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 6   # every section but the summary
    for encoded in images:
        image = cv2.imdecode(np.frombuffer(base64.b64decode(encoded), np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 150 and image.shape[1] > 500
    # the summary's error comes from the copied ground truth: the hover is tracked within centimetres
    error = re.search(r"position error \(estimate\)</td><td>median ([0-9.]+) m", page)
    assert error and float(error.group(1)) < 0.05
    # the markers table lists what detections.csv holds: the hover sees A and 5 in every frame
    assert re.search(r"<td>A</td><td>0</td><td>31</td>", page) and re.search(r"<td>5</td><td>31</td><td>31</td>", page)


def write_estimates(folder: Path, verdicts: list[str], pose_status: dict[int, str] | None = None,
                    fps: float = 30.0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "estimates.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, ESTIMATE_COLUMNS)
        writer.writeheader()
        for i, verdict in enumerate(verdicts):
            writer.writerow({"frame": i, "t_ns": round(i * 1e9 / fps), "verdict": verdict,
                             "pose_status": (pose_status or {}).get(i, "ok"), "markers": 1, "sent": int(verdict == "ok"),
                             "detect_ns": 5_000_000, "pose_ns": 1_000_000, "fuse_ns": 100_000, "send_ns": 10_000,
                             "latency_ns": 7_000_000 if verdict == "ok" else ""})


def test_gaps_are_found_with_their_reason(tmp_path):
    """100 frames at 30 fps, written by hand: 20-39 no marker, 60-65 pose withheld (ambiguous),
    80 link (one frame: shorter than 0.2 s, no gap)."""
    verdicts = ["ok"] * 100
    verdicts[20:40] = ["no marker"] * 20
    verdicts[60:66] = ["pose withheld"] * 6
    verdicts[80] = "link"
    write_estimates(tmp_path / "flight", verdicts, {i: "ambiguous" for i in range(60, 66)})
    log = read_flight(tmp_path / "flight")
    gaps = log.gaps()
    assert [(g.frames, g.reason) for g in gaps] == [(20, "no marker"), (6, "pose withheld (ambiguous)")]
    # from the last fix before (frame 19) to the first after (frame 40): 21 periods
    assert gaps[0].start_s == pytest.approx(19 / 30) and gaps[0].duration_s == pytest.approx(21 / 30)
    assert gaps[1].duration_s == pytest.approx(7 / 30)
    assert gaps[1].reasons == {"pose withheld": 6, "pose withheld: ambiguous": 6}
    run = report(str(tmp_path / "flight"))
    assert run.returncode == 0, run.stderr
    assert "the track is drawn without markers" in run.stderr    # no sequence.yaml, no --map
    page = (tmp_path / "flight" / "report.html").read_text()
    assert "Error against the ground truth" not in page and "2 gap(s)" in run.stdout


def test_the_daemons_log_is_listed_at_its_frames(tmp_path):
    """events.csv written by hand: a line logged before the first frame, a warning whose text has a comma and
    quotes; times on estimates.csv's base (its first t_ns 1 s)."""
    folder = tmp_path / "flight"
    write_estimates(folder, ["ok"] * 60)
    with open(folder / "estimates.csv") as handle:
        lines = handle.read().splitlines()
    shifted = [lines[0]] + [f"{i},{1_000_000_000 + round(i * 1e9 / 30)}" + line[line.index(",", line.index(",") + 1):]
                            for i, line in enumerate(lines[1:])]
    (folder / "estimates.csv").write_text("\n".join(shifted) + "\n")
    text = 'markers lost: reprojection, "A" and "5" both far from the map (see map check)'
    with open(folder / "events.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerows([("frame", "t_ns", "level", "text"), ("", "", "WARNING", "link: no FC heard"),
                          (45, 2_500_000_000, "WARNING", text), (50, 2_666_666_667, "INFO", "re-acquired (reset 1)")])
    log = read_flight(folder)
    assert [(e.frame, e.level, e.text) for e in log.events] == [
        (None, "WARNING", "link: no FC heard"), (45, "WARNING", text), (50, "INFO", "re-acquired (reset 1)")]
    assert log.events[0].t_s is None and log.events[1].t_s == pytest.approx(1.5)
    run = report(str(folder))
    assert run.returncode == 0, run.stderr
    page = (folder / "report.html").read_text()
    assert "<td>log lines</td><td>3 (2 warnings or errors)</td>" in page
    assert "<tr class=warning><td>before the first frame</td><td></td><td>WARNING</td><td>link: no FC heard</td>" in page
    assert "<tr class=warning><td>1.50</td><td>45</td><td>WARNING</td><td>" + html.escape(text) + "</td>" in page
    assert "<tr><td>1.67</td><td>50</td><td>INFO</td><td>re-acquired (reset 1)</td>" in page  # the rest plain

    (folder / "events.csv").write_text("frame,t_ns,level,text\n4.5,100,INFO,x\n")
    with pytest.raises(ReportError, match=r"events.csv: row 2, column frame: must be an integer or empty, got '4.5'"):
        read_flight(folder)
    (folder / "events.csv").unlink()   # a recording from before events.csv: said, not an error
    assert read_flight(folder).events is None
    assert report(str(folder)).returncode == 0
    assert "<td>log lines</td><td>not recorded (no events.csv)</td>" in (folder / "report.html").read_text()


def test_a_gap_without_frames_is_said_as_such_not_by_its_few_frames_verdict(tmp_path):
    """The camera delivered nothing for 3 s (a stall, a lost camera): the gap's two frames after it say
    "filter gating" (the new fix waits to be confirmed), but the reason is the missing frames."""
    verdicts = ["ok"] * 60
    verdicts[30:32] = ["filter gating"] * 2
    write_estimates(tmp_path / "flight", verdicts)
    path = tmp_path / "flight" / "estimates.csv"
    rows = list(csv.DictReader(open(path)))
    for row in rows[30:]:
        row["t_ns"] = int(row["t_ns"]) + 3_000_000_000
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, ESTIMATE_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    gaps = read_flight(tmp_path / "flight").gaps()
    assert [(g.frames, g.reason, g.reasons) for g in gaps] == [(2, "no frames for 3.0 s", {"filter gating": 2})]
    assert gaps[0].duration_s == pytest.approx(3 + 3 / 30)


def test_a_folder_without_estimates_is_a_one_line_error(tmp_path):
    run = report(str(HOVER))
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "no estimates.csv" in run.stderr and "companion run --record" in run.stderr
    run = report(str(tmp_path / "nowhere"))
    assert run.returncode == 2 and "no such folder" in run.stderr


def test_a_bad_value_names_the_file_row_and_column(tmp_path):
    write_estimates(tmp_path / "flight", ["ok"] * 5)
    path = tmp_path / "flight" / "estimates.csv"
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace(",ok,", ",fine,", 1)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ReportError, match="row 4, column verdict: unknown value 'fine'"):
        read_flight(tmp_path / "flight")
    lines[3] = "2,abc" + lines[3][lines[3].index(",", 2):]
    path.write_text("\n".join(lines) + "\n")
    run = report(str(tmp_path / "flight"))
    assert run.returncode == 2 and "estimates.csv: row 4, column t_ns: not a number: 'abc'" in run.stderr
    assert "Traceback" not in run.stderr


def test_a_missing_map_file_is_named(recording, tmp_path):
    run = report(str(recording), "--map", str(tmp_path / "none.yaml"))
    assert run.returncode == 2 and "none.yaml" in run.stderr and run.stderr.count("\n") == 1


def test_a_report_that_does_not_fit_on_the_disk_is_one_line_exit_1_and_no_partial_page(recording, tmp_path):
    """The process may write no file over 50 kB (as a full disk refuses a write; the page is a few hundred
    kB): one line naming the file, exit status 1 as for every write that fails (README), and no page left."""
    import resource
    import signal

    def small_files_only():
        resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    out = tmp_path / "report.html"
    run = subprocess.run([sys.executable, "-m", "companion", "report", str(recording), "--out", str(out)],
                         capture_output=True, text=True, timeout=120, preexec_fn=small_files_only)
    assert run.returncode == 1
    assert run.stderr == f"companion report: cannot write {out}: File too large\n"
    assert list(tmp_path.iterdir()) == []
