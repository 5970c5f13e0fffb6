"""Input files are read only when they are regular files under a size limit, so that a device
(`/dev/zero`), a named pipe with no writer or a huge file given by mistake is refused in one line
at once instead of hanging or filling memory.

The limits are settings: environment variables CELL_MAX_<KIND>_MB override the defaults below
(a task or material file is a few kB; a CAD mesh may be large).
"""
import os
import stat
from pathlib import Path

from cell.errors import TaskError

LIMIT_MB = {"yaml": 1.0, "mesh": 256.0, "csv": 50.0}


def limit_bytes(kind):
    """The size limit of a kind of input file [bytes]: CELL_MAX_<KIND>_MB or the default."""
    name = f"CELL_MAX_{kind.upper()}_MB"
    raw = os.environ.get(name)
    try:
        mb = float(raw) if raw is not None else LIMIT_MB[kind]
    except ValueError:
        raise TaskError("environment", name, repr(raw), "a size in MB") from None
    if not mb > 0:
        raise TaskError("environment", name, repr(raw), "a positive size in MB")
    return mb * 2**20


def checked_file(path, kind, file=None, key="", relative_to=""):
    """path, if it names a regular file of at most the kind's size limit; else a TaskError naming
    `file` and `key` (where the path was given; default: the path itself)."""
    path = Path(path)
    where = file if file is not None else path
    try:
        info = path.stat()
    except OSError as err:
        raise TaskError(where, key, f"'{path}' ({err.strerror.lower()})",
                        "an existing, readable file" + (f", relative to {relative_to}" if relative_to else "")) from None
    if stat.S_ISDIR(info.st_mode):
        raise TaskError(where, key, f"'{path}', a folder", "a file")
    if not stat.S_ISREG(info.st_mode):
        raise TaskError(where, key, f"'{path}', not a regular file (a device, pipe or socket)",
                        "a regular file")
    limit = limit_bytes(kind)
    if info.st_size > limit:
        raise TaskError(where, key, f"'{path}' of {info.st_size / 2**20:.1f} MB",
                        f"at most {limit / 2**20:g} MB for a {kind} file (CELL_MAX_{kind.upper()}_MB "
                        f"sets the limit)")
    return path


def read_text(path, kind, file=None, key=""):
    """The text of a checked_file (UTF-8), read to at most its limit however the file changes."""
    path = checked_file(path, kind, file, key)
    limit = int(limit_bytes(kind))
    where = file if file is not None else path
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as err:
        raise TaskError(where, key, f"'{path}' ({err.strerror.lower()})", "a readable file") from None
    if len(data) > limit:
        raise TaskError(where, key, f"'{path}' growing past {limit / 2**20:g} MB while read",
                        f"at most {limit / 2**20:g} MB for a {kind} file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise TaskError(where, key, f"'{path}' with bytes that are not UTF-8 text", f"a {kind} text file") from None
