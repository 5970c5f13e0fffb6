"""`cell calibrate TASK [--backend sim|hw] [--out DIR] [--shots N] [--yes]`: exit 0 with c
fitted, 1 infeasible plan or nothing usable measured, 2 bad input, 3 device fault."""
import sys
from pathlib import Path

from cell import backends
from cell.calibrate import MIN_SHOTS, run
from cell.cli import create_folder, one_feature, output_folder
from cell.errors import TaskError
from cell.loader import load_task
from cell.operator import Operator


def command(args):
    if args.shots < MIN_SHOTS:
        raise TaskError("command line", "--shots", args.shots, f"an integer >= {MIN_SHOTS}")
    out = output_folder(args.out, f"{Path(args.task).stem}-calibration")
    task = one_feature(load_task(args.task), "calibrate")
    backend = args.backend or task.cell.backend
    c_model = task.camera.sensor.camera_constant
    # the simulated cell holds the task's part already: it confirms for itself, as for the lamp radius
    Operator(yes=args.yes or backend == "sim", stdout=sys.stderr).confirm(
        "calibration", "place the reference part (the task's part, of the task's material) in the cell; "
                       "the camera constant is measured against its material table")
    create_folder(out)
    result = run(task, out, lambda scene: backends.open_devices(task, scene, backend, yes=args.yes), args.shots)
    fit = result.fit
    print(f"camera constant c = {fit.camera_constant:.5g} +- {fit.stderr:.2g} 1/(W s) "
          f"({result.camera_constant_ratio:.3f} x the task's {c_model:.5g}); black level "
          f"{fit.black_level:.2f}, linearity r2 {fit.r2:.5f}, {fit.used} pairs "
          f"({fit.saturated} saturated, {fit.dark} at 0 left out)")
    print(f"  set camera.sensor.camera_constant: {fit.camera_constant:.5g} in the tasks that use "
          f"this camera (e.g. {args.task})")
    print(f"  wrote {out}/calibration.json, calibration.png, log.jsonl, {len(result.shots)} captures and the "
          f"plan's pictures")
    return 0
