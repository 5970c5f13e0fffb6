"""`cell fit-brdf DATA.csv [--out material.yaml] [--name NAME] [--json]`: the fit's table, the
material file, notes on absent terms."""
import datetime
import sys
from pathlib import Path

import yaml

from cell import jsonio
from cell.errors import TaskError
from cell.fit import SIGNIFICANCE, TERMS, absent_notes, fit_material, material_document, read_goniometer
from cell.material import PARAMETERS


def summary(fits):
    """A table a person reads: value +- standard error per parameter and phase angle."""
    def cell(f, i):
        if i in (2, 4) and TERMS[i // 2 - 1] in f.absent:
            return "-"
        return f"{f.params[i]:.4g} +- {f.stderr[i]:.2g}"

    lines = [f"{'phase':>6} {'rows':>5} " + " ".join(f"{p:>18}" for p in PARAMETERS) + f" {'rms':>9}  terms"]
    for f in fits:
        terms = ", ".join(("diffuse",) + tuple(t for t in TERMS if t not in f.absent))
        lines.append(f"{f.phase_deg:6g} {f.rows:5d} " + " ".join(f"{cell(f, i):>18}" for i in range(5))
                     + f" {f.rms_residual:9.2g}  {terms}")
    return "\n".join(lines)


def command(args):
    path = Path(args.data)
    fits = fit_material(read_goniometer(path))
    source = (f"fit of {path} by cell fit-brdf on {datetime.date.today().isoformat()}: eq. (6)-(7) "
              f"per phase angle, relative residuals, a specular term kept if its F-test p < {SIGNIFICANCE:g}")
    doc = material_document(fits, args.name or path.stem, source)
    if args.out:
        try:
            text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
            Path(args.out).write_text(text)
        except OSError as err:
            raise TaskError(args.out, "", f"an unwritable path ({err.strerror})", "a writable file") from None
    for note in absent_notes(fits):
        print(note, file=sys.stderr)
    if args.json:
        print(jsonio.dumps(doc, indent=2))
    else:
        print(summary(fits))
        if args.out:
            print(f"wrote {args.out}")
    return 0
