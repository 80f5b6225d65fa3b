"""Files written whole or not at all: a full disk, a killed process or a pulled card leaves the old file or
none, never a truncated one that a later command would read as a broken map, camera or marker."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path


def write_whole(path, data: bytes | str) -> None:
    """Write ``data`` (text is UTF-8) to ``path`` through a temporary file beside it, renamed over it once
    complete. An OSError names ``path`` (a full disk's write error names no file)."""
    path = Path(path)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data.encode() if isinstance(data, str) else data)
        os.replace(temporary, path)
    except OSError as error:
        raise OSError(error.errno, error.strerror, str(path)) from error
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)
