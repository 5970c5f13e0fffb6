"""Input files are read only when they are regular files under a size limit, so that a device
(`/dev/zero`), a named pipe with no writer or a huge file given by mistake is refused in one line
at once instead of hanging or filling memory.

The limits are settings: environment variables CELL_MAX_<KIND>_MB override the defaults below
(a task or material file is a few kB; a CAD mesh may be large).
"""

from __future__ import annotations

import os
import stat
from os import PathLike
from pathlib import Path

from cell.core.errors import TaskError

# kind -> (what the messages call it, default limit [MB])
KINDS = {"yaml": ("YAML", 1.0), "mesh": ("mesh", 256.0), "csv": ("goniometer CSV", 50.0)}


def limit_bytes(kind: str) -> int:
    """The size limit of a kind of input file [bytes]: CELL_MAX_<KIND>_MB or the default."""
    name = f"CELL_MAX_{kind.upper()}_MB"
    raw = os.environ.get(name)
    try:
        mb = float(raw) if raw is not None else KINDS[kind][1]
    except ValueError:
        raise TaskError("environment", name, repr(raw), "a size in MB") from None
    if not mb > 0:
        raise TaskError("environment", name, repr(raw), "a positive size in MB")
    return int(mb * 2**20)


def _size(n):
    return f"{n / 2**20:.3g} MB"


def checked_file(path: str | PathLike[str], kind: str, file: str | PathLike[str] | None = None, key: str = "",
                 relative_to: str | PathLike[str] = "") -> Path:
    """path, if it names a regular file of at most the kind's size limit; else a TaskError naming
    `file` and `key` where the path was given (default: the path itself, no key)."""
    path = Path(path)
    what = KINDS[kind][0]
    where, named = (path, "") if file is None else (file, f"'{path}', ")
    try:
        info = path.stat()
    except OSError as err:
        raise TaskError(where, key, f"{named}an unreadable file ({(err.strerror or str(err)).lower()})",
                        f"an existing, readable {what} file"
                        + (f", relative to {relative_to}" if relative_to else "")) from None
    mode = info.st_mode
    if not stat.S_ISREG(mode):
        found = ("a folder" if stat.S_ISDIR(mode) else "a named pipe (FIFO)" if stat.S_ISFIFO(mode) else
                 "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
        raise TaskError(where, key, named + found, f"a regular {what} file")
    limit = limit_bytes(kind)
    if info.st_size > limit:
        raise TaskError(where, key, f"{named}{_size(info.st_size)}",
                        f"a {what} file of at most {_size(limit)} (CELL_MAX_{kind.upper()}_MB sets the limit)")
    return path


def read_text(path: str | PathLike[str], kind: str, file: str | PathLike[str] | None = None, key: str = "") -> str:
    """The UTF-8 text (a byte order mark allowed) of a checked_file, read to at most its limit
    however the file changes meanwhile."""
    path = checked_file(path, kind, file, key)
    what, limit = KINDS[kind][0], limit_bytes(kind)
    where = path if file is None else file
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as err:
        raise TaskError(where, key, f"an unreadable file ({(err.strerror or str(err)).lower()})",
                        f"a readable {what} file") from None
    if len(data) > limit:
        raise TaskError(where, key, f"a file growing past {_size(limit)} while read",
                        f"a {what} file of at most {_size(limit)}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        raise TaskError(where, key or f"line {line}", f"bytes that are not UTF-8 text (0x{data[err.start]:02x})",
                        f"a {what} file in UTF-8") from None
