"""Where the commands write, checked before any work: a one-line error naming the option and the path.

A folder is created if needed and a file is written and removed in it (the
only honest test of "may I write here": permissions, read-only mounts,
``/proc``); a file's folder must exist and take a file the same way. A file
is then written whole or not at all (``companion.files.write_whole``).
"""
from __future__ import annotations

import contextlib
import sys
import tempfile
from pathlib import Path


class OutputError(ValueError):
    """An output path that cannot be written; the message names the option and the path."""


def output_dir(path: Path, option: str) -> Path:
    """The folder ``path`` (created with its parents), known to be writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{option} {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(f"{option} {path}: cannot create the folder: {error.strerror}") from None
    _probe(path, option, path)
    return path


@contextlib.contextmanager
def removed_if_left_empty(folder: Path | None):
    """A folder this block creates (``output_dir``, with any parents it makes), removed again if the block
    leaves it empty: a refused, failed or interrupted command, or one that had nothing to write, leaves no
    empty folder behind."""
    made = [] if folder is None else [p for p in (Path(folder), *Path(folder).parents) if not p.exists()]
    try:
        yield
    finally:
        for path in made:  # the deepest first; each only if empty
            with contextlib.suppress(OSError):
                path.rmdir()


def output_file(path: Path, option: str) -> Path:
    """The file ``path`` to be (over)written, whose folder exists and is writable."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{option} {path}: is a folder, not a file name")
    if not path.parent.is_dir():
        raise OutputError(f"{option} {path}: the folder {path.parent} does not exist")
    _probe(path.parent, option, path)
    return path


def write_failed(command: str, error: OSError, path) -> int:
    """Say "companion COMMAND: cannot write PATH: why" for an OSError raised while writing ``path`` (a full
    disk's error names no file); the exit status 1: the input was good, the disk failed (README)."""
    print(f"companion {command}: cannot write {error.filename or path}: {error.strerror or error}", file=sys.stderr)
    return 1


def _probe(folder: Path, option: str, named: Path) -> None:
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".companion-write-test-"):
            pass
    except OSError as error:
        raise OutputError(f"{option} {named}: cannot write in {folder}: {error.strerror}") from None
