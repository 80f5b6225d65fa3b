"""Files written whole or not at all: a full disk, a killed process or a pulled card leaves the old file or
none, never a truncated one that a later command would read as a broken map, camera or marker."""
from __future__ import annotations

import os
import secrets
import stat
from pathlib import Path


def write_whole(path, data: bytes | str) -> None:
    """Write ``data`` (text is UTF-8) to ``path`` through a temporary file beside it, renamed over it once
    complete. The file gets the permissions ``open`` would give it (the umask's for a new file, the old
    file's when replacing one: a map written by root stays readable by the service's user). An OSError
    names ``path`` (a full disk's write error names no file)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{secrets.token_hex(4)}")
    try:
        handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(handle, "wb") as file:
            file.write(data.encode() if isinstance(data, str) else data)
        if path.exists():
            os.chmod(temporary, stat.S_IMODE(path.stat().st_mode))
        os.replace(temporary, path)
    except OSError as error:
        raise OSError(error.errno, error.strerror, str(path)) from error
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)
