"""`cell measure-brdf TASK --out DIR [--backend sim|hw] [--yes] [--json]`: the cell as a
goniometer (cell.calibration.goniometer); writes the material file with standard errors. Exit 0 measured,
1 a phase angle without enough readings, 2 bad input, 3 device fault."""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from cell.run import backends
from cell.core import jsonio
from cell.cli import backend_of, create_folder, output_folder
from cell.task.loader import load_task
from cell.devices.operator import Operator
from cell.physics.brdf_fit import shown_estimate, unresolved_notes
from cell.physics.material import PARAMETERS


def command(args: argparse.Namespace) -> int:
    from cell.calibration import goniometer

    out = output_folder(args.out, f"{Path(args.task).stem}-brdf")
    task = load_task(args.task)
    backend = backend_of(task, args.backend)
    # the simulated cell holds the sample already: it confirms for itself
    operator = Operator(yes=args.yes, simulated=backend == "sim", stdout=sys.stderr)
    operator.require("sample", "placing the sample")
    staged = goniometer.sample_task(task)
    create_folder(out)
    with contextlib.redirect_stdout(sys.stderr):         # the devices' prompts too: stdout is --json's
        result = goniometer.run(task, out, lambda scene: backends.open_devices(staged, scene, backend, yes=args.yes),
                                operator)
    if args.json:
        print(jsonio.dumps(result.summary(), indent=2))
        return 0
    doc = result.measured_material          # goniometer.run returns only once it is measured
    for i, phase in enumerate(doc["phase_deg"]):
        print(f"phase {phase:g} deg: " + ", ".join(
            f"{k} {shown_estimate(doc, k, i)}" for k in PARAMETERS))      # as cell fit-brdf shows them
    for note in unresolved_notes(doc):                  # as cell fit-brdf says them of the same CSV
        print(f"  {note}")
    print(f"  {len(result.readings)} of {result.poses} poses measured ({len(result.refused)} refused, "
          f"{len(result.failed)} without a reading)")
    print(f"  wrote {result.material_file}: a task uses it as part.material; goniometer.csv, fit.png, "
          f"measurement.json, log.jsonl and the captures in {out}")
    return 0
