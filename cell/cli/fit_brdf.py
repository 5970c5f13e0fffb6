"""`cell fit-brdf DATA.csv [--out material.yaml] [--name NAME] [--json]`: the fit's table, the
material file, notes on absent and unresolved terms; the fit and its rule for an unresolved term
are `cell measure-brdf`'s (cell.physics.brdf_fit.fit_goniometer)."""

from __future__ import annotations

import argparse
import datetime
import os
import stat
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any


from cell.core import jsonio
from cell.core.files import write_yaml
from cell.core.errors import TaskError
from cell.physics.brdf_fit import (SIGNIFICANCE, TERMS, absent_notes, fit_goniometer, read_goniometer,
                                   shown_estimate, unresolved_notes)
from cell.physics.material import PARAMETERS

if TYPE_CHECKING:
    from cell.physics.brdf_fit import PhaseFit


def summary(fits: Sequence[PhaseFit], material: dict[str, Any]) -> str:
    """A table a person reads: the material written, per parameter and phase angle as
    cell measure-brdf says it (shown_estimate), and the terms the data hold there."""
    unresolved = (material.get("unresolved") or {}).get("terms", {})

    def gone(f, term):
        return term in f.absent or f.phase_deg in unresolved.get(term, [])

    width = max(18, *(len(shown_estimate(material, p, k)) for p in PARAMETERS for k in range(len(fits))))
    lines = [f"{'phase':>6} {'rows':>5} " + " ".join(f"{p:>{width}}" for p in PARAMETERS) + f" {'rms':>9}  terms"]
    for k, f in enumerate(fits):
        terms = ", ".join(("diffuse",) + tuple(t for t in TERMS if not gone(f, t)))
        lines.append(f"{f.phase_deg:6g} {f.rows:5d} " + " ".join(f"{shown_estimate(material, p, k):>{width}}"
                                                                  for p in PARAMETERS)
                     + f" {f.rms_residual:9.2g}  {terms}")
    return "\n".join(lines)


def output_file(out: str, data: str | os.PathLike[str]) -> Path:
    """The material file --out names, checked before the fit: a regular file or a new one, in a
    folder where files can be created, and not the data (YAML over the CSV)."""
    def refuse(found, expected="a material file to write, in a folder that exists and is writable"):
        raise TaskError("command line", "--out", f"{out} ({found})", expected)

    if not out.strip():
        raise TaskError("command line", "--out", "an empty path", "a material file to write")
    path = Path(out)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as err:
        refuse(err.strerror)
    if mode is not None and stat.S_ISDIR(mode):
        refuse("a folder")
    if mode is not None and not stat.S_ISREG(mode):
        refuse("not a regular file")
    try:
        same = os.path.samefile(path, data)          # also through a symlink or a hard link
    except OSError:
        same = path.resolve() == Path(data).resolve()
    if same:
        refuse("the goniometer CSV itself", "a material file other than the data")
    if mode is None and not path.parent.is_dir():
        refuse(f"no folder {path.parent}")
    try:
        if mode is None:
            tempfile.TemporaryFile(dir=path.parent).close()
        else:
            open(path, "ab").close()                 # neither truncates nor touches it
    except OSError as err:
        refuse(f"no file can be created in {path.parent}: {err.strerror}" if mode is None else
               f"not writable: {err.strerror}")
    return path


def command(args: argparse.Namespace) -> int:
    path = Path(args.data)
    out = output_file(args.out, path) if args.out is not None else None
    source = (f"fit of {path} by cell fit-brdf on {datetime.date.today().isoformat()}: eq. (6)-(7) "
              f"per phase angle, relative residuals, a specular term kept if its F-test p < {SIGNIFICANCE:g}")
    fitted = fit_goniometer(read_goniometer(path), args.name or path.stem, source)
    fits, doc = fitted.fits, fitted.material
    if out:
        try:
            write_yaml(out, doc, inline_lists=True)
        except OSError as err:
            raise TaskError("command line", "--out", f"{out} ({err.strerror})", "a writable file") from None
    for note in [*absent_notes(fits), *unresolved_notes(doc)]:
        print(note, file=sys.stderr)
    if args.json:
        print(jsonio.dumps(doc, indent=2))
    else:
        print(summary(fits, doc))
        if args.out:
            print(f"wrote {args.out}")
    return 0
