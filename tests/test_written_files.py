"""Files the commands write: whole or not at all, with the permissions any file would get.

A disk that fills up while a command writes: one line naming the file, exit 1, and no truncated file
or half-written sequence left behind (a rerun with room starts clean). The disk is filled for real by
the kernel: the command runs in a child process whose file size limit (RLIMIT_FSIZE) makes a write
past it fail with EFBIG, as a full disk's fails with ENOSPC."""
from __future__ import annotations

import os
import resource
import signal
import stat
import subprocess
import sys
import threading
from pathlib import Path

from companion.files import write_whole

REPO = Path(__file__).resolve().parent.parent
MAP = REPO / "maps" / "warehouse.yaml"


def run_with_file_limit(args: list[str], limit_bytes: int | None) -> subprocess.CompletedProcess:
    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of the process being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run([sys.executable, "-m", "companion", *args], capture_output=True, text=True,
                          preexec_fn=limit if limit_bytes else None, timeout=300)


def test_markers_that_do_not_fit_leave_no_truncated_file(tmp_path):
    out = tmp_path / "markers"
    # the first PNG is about 2.6 kB and its sidecar about 1 kB: the PNG cannot be written whole
    result = run_with_file_limit(["markers", "--symbols", "A,B", "--out", str(out)], 2000)
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"companion markers: {out / 'marker-A-p2.png'}: "), lines
    assert not out.exists()   # nothing whole was written: the folder the run made is gone too
    assert run_with_file_limit(["markers", "--symbols", "A,B", "--out", str(out)], None).returncode == 0
    assert sorted(p.name for p in out.iterdir()) == ["marker-A-p2.json", "marker-A-p2.png",
                                                     "marker-B-p2.json", "marker-B-p2.png"]


def test_a_simulation_that_does_not_fit_is_removed_and_can_be_run_again(tmp_path):
    out = tmp_path / "seq"
    args = ["simulate", str(out), "--map", str(MAP), "--fps", "10", "--duration", "0.5", "--no-progress"]
    # the map copy (about 9 kB) and the CSVs fit, a 640x480 PNG frame does not
    assert MAP.stat().st_size < 30_000
    result = run_with_file_limit(args, 30_000)
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"companion simulate: {out / 'frames' / '000000.png'}: "), lines
    assert not out.exists()   # the folder the run made is gone too
    again = run_with_file_limit(args, None)
    assert again.returncode == 0, again.stderr
    assert len(list((out / "frames").glob("*.png"))) == 6 and (out / "sequence.yaml").is_file()


def test_a_file_written_whole_gets_the_permissions_open_gives_and_keeps_a_replaced_files(tmp_path):
    """A temporary file is private (0600) by default: renamed over a map, it would lock the service's
    user out of a map that root surveyed."""
    plain, whole = tmp_path / "plain.yaml", tmp_path / "whole.yaml"
    previous = os.umask(0o022)
    try:
        plain.write_text("a: 1\n")
        write_whole(whole, "a: 1\n")
    finally:
        os.umask(previous)
    assert whole.read_text() == "a: 1\n"
    assert whole.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777 == 0o644
    whole.chmod(0o640)
    write_whole(whole, b"a: 2\n")
    assert whole.read_bytes() == b"a: 2\n" and whole.stat().st_mode & 0o777 == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain.yaml", "whole.yaml"]


def test_a_file_written_whole_through_a_link_replaces_what_it_names_and_a_pipe_is_written_into(tmp_path):
    # the rename would put a plain file in place of the link (leaving the file it names as it was) or of the pipe
    (tmp_path / "real").mkdir()
    real = tmp_path / "real" / "camera.yaml"
    real.write_text("old\n")
    link = tmp_path / "camera.yaml"
    link.symlink_to(real)
    write_whole(link, "new\n")
    assert link.is_symlink() and real.read_text() == "new\n"
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()))
    reader.start()
    write_whole(fifo, b"through the pipe\n")
    reader.join(10)
    assert received == [b"through the pipe\n"] and stat.S_ISFIFO(fifo.stat().st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.yaml", "fifo", "real"]


def test_a_marker_whose_sidecar_does_not_fit_leaves_no_png_without_it(tmp_path, monkeypatch, capsys):
    """A full disk after the PNG (ENOSPC raised where the sidecar is written: a file size limit cannot refuse the
    1 kB sidecar and pass the larger PNG): no PNG is left without the sidecar that states its print size."""
    from companion import cli
    from companion.cli import markers as markers_command

    def sidecar_refused(path, data):
        if Path(path).suffix == ".json":
            raise OSError(28, "No space left on device", str(path))
        write_whole(path, data)

    monkeypatch.setattr(markers_command, "write_whole", sidecar_refused)
    out = tmp_path / "markers"
    assert cli.main(["markers", "--symbols", "A", "--out", str(out)]) == 1
    assert f"{out / 'marker-A-p2.json'}: No space left on device" in capsys.readouterr().err
    assert not out.exists()
