"""Progress bars in a log: a few lines, not one redraw a tenth of a second (pytest's captured stderr is
not a terminal, as a pipe, a file or the journal is not)."""
from __future__ import annotations

import sys

from companion.progress import LOG_INTERVAL_S, progress_bar


def test_a_bar_whose_stderr_is_a_log_is_drawn_at_start_and_end_only(capsys):
    assert not sys.stderr.isatty()
    with progress_bar(5000, "frame", description="detecting") as bar:
        for _ in range(5000):
            bar.update(1)
    assert bar.mininterval == LOG_INTERVAL_S
    drawn = capsys.readouterr().err
    assert "detecting" in drawn and "5000/5000" in drawn
    assert drawn.count("\r") <= 3, drawn.count("\r")


def test_a_disabled_bar_draws_nothing(capsys):
    with progress_bar(10, "step", enabled=False) as bar:
        bar.update(10)
    assert capsys.readouterr().err == ""
