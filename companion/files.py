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
    file's when replacing one: a map written by root stays readable by the service's user). Through a
    symbolic link, the file it names is replaced and the link kept; a device or pipe (``/dev/stdout``, a
    FIFO) is written into, as there is no file to rename over it. An OSError names ``path`` (a full disk's
    write error names no file)."""
    path = Path(path)
    target = Path(os.path.realpath(path))
    content = data.encode() if isinstance(data, str) else data
    if target.exists() and not target.is_file() and not target.is_dir():
        try:
            with open(target, "wb") as stream:
                stream.write(content)
        except OSError as error:
            raise OSError(error.errno, error.strerror, str(path)) from error
        return
    temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}")
    try:
        handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(handle, "wb") as file:
            file.write(content)
        if target.exists():
            os.chmod(temporary, stat.S_IMODE(target.stat().st_mode))
        os.replace(temporary, target)
    except OSError as error:
        raise OSError(error.errno, error.strerror, str(path)) from error
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)
