"""Files written whole: the text goes to a temporary file beside the target, which is then renamed
into place (or linked, when an existing file must not be replaced), so that a reader or a crash
never sees half a file and a file that appears meanwhile is never overwritten. The YAML writer
beside `inputs`' reader."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import yaml


def _creation_mode() -> int:
    """The mode a new file gets by open(): 0o666 less the process's umask (mkstemp's own 0o600
    would hide the file from the group and others)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def write_text(path: str | os.PathLike[str], text: str, replace: bool = True) -> Path:
    """text as the whole file at path; an existing file is replaced only when `replace` (else
    FileExistsError, also for one that appeared while writing). Returns the path."""
    path = Path(path)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(temporary, _creation_mode())
        if replace:
            os.replace(temporary, path)
        else:
            os.link(temporary, path)            # fails if the path exists: never overwritten
    finally:
        if os.path.lexists(temporary):
            os.unlink(temporary)
    return path


def write_yaml(path: str | os.PathLike[str], document: Any, replace: bool = True, header: str = "",
               inline_lists: bool = False) -> Path:
    """The document as a YAML file (write_text), keys in their order, below `header`'s lines as
    comments; `inline_lists` writes a list of scalars on one line ([a, b]), as material tables are."""
    comments = "".join(f"# {line}\n" for line in header.splitlines())
    text = yaml.safe_dump(document, sort_keys=False, width=100, default_flow_style=None if inline_lists else False)
    return write_text(path, comments + text, replace)
