"""Progress bars of the long commands (simulate, survey, map check), on stderr.

Live on a terminal; where stderr is a log (a pipe, a file, the journal) a bar that redraws ten times a
second would put thousands of updates on one line, so there it is drawn at most every ``LOG_INTERVAL_S``.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

LOG_INTERVAL_S = 30.0


def progress_bar(total: int, unit: str, enabled: bool = True, description: str | None = None) -> tqdm:
    """A tqdm bar of ``total`` ``unit``s (disabled: counts, draws nothing); use it as a context manager."""
    terminal = sys.stderr.isatty()
    return tqdm(total=total, unit=unit, desc=description, disable=not enabled, file=sys.stderr,
                mininterval=0.1 if terminal else LOG_INTERVAL_S)
