"""`cell plan TASK [--out DIR] [--json]`: exit 0 feasible, 1 infeasible (with the reason)."""
import sys
from pathlib import Path

import numpy as np

from cell import jsonio
from cell.acquisition import require_feasible
from cell.cli import create_folder, output_folder
from cell.loader import load_task
from cell.plan import gray_stats
from cell.planner import plan
from cell.recorder import write_plan


def summary(plan):
    """A few lines for the terminal."""
    shot = plan.shot
    pan, tilt, radius = shot.joints
    g = gray_stats(shot.gray)
    verdict = "feasible" if plan.feasible else f"INFEASIBLE ({plan.binding} misses by {plan.miss:.3g})"
    return "\n".join([
        f"{plan.task_name}: {verdict}",
        f"  lamp   {shot.distance_m:.3f} m from the feature, phase angle {np.degrees(shot.phase_angle_rad):.1f} deg"
        f" (pan {np.degrees(pan):.1f} deg, tilt {np.degrees(tilt):.1f} deg, radius {radius:.3f} m)",
        f"  camera shutter {1e3 * shot.exposure.shutter_s:.2f} ms, f/{shot.exposure.f_number:.1f},"
        f" focus {shot.exposure.focus_m:.3f} m (depth of field {1e3 * shot.exposure.depth_of_field_m:.1f} mm)",
        f"  gray   mean {g['mean']:.1f}, min {g['min']:.1f}, max {g['max']:.1f}",
        f"  binding {plan.binding} = {max(r.value for r in plan.requirements):.4g};"
        f" time {plan.timing_s['total']:.2f} s",
    ])


def command(args):
    out = output_folder(args.out, f"{Path(args.task).stem}-plan")
    task = load_task(args.task)
    create_folder(out)
    result = plan(task, progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    write_plan(result, task, out)
    if args.json:
        print(jsonio.dumps(result.to_json(), indent=2))
    else:
        print(summary(result))
        print(f"  wrote {out}/plan.json and pictures")
    require_feasible(result)
    return 0
