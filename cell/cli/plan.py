"""`cell plan TASK [--out DIR] [--json]`: exit 0 feasible (every feature covered), 1 infeasible
(with the reason: the first uncovered feature and its cause)."""
import sys
from pathlib import Path

import numpy as np

from cell import jsonio
from cell.acquisition import require_feasible
from cell.cli import create_folder, output_folder
from cell.loader import load_task
from cell.multiplan import plan_features
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


def features_summary(plan):
    """One line per shot and one per feature (the shot covering it, or why none does)."""
    n, covered = len(plan.features), sum(f.covered_by is not None for f in plan.features)
    verdict = "feasible" if plan.feasible else "PARTIAL"
    lines = [f"{plan.task_name}: {verdict}: {len(plan.shots)} shot{'s' * (len(plan.shots) != 1)} cover "
             f"{covered} of {n} features (of {plan.cover['candidate_shots']} candidate shots"
             + (", planned viewpoints" if "viewpoints" in plan.cover else "") + "); "
             f"time {plan.timing_s['total']:.2f} s"]
    for k, shot in enumerate(plan.shots):
        pan, tilt, radius = shot.joints
        lines.append(f"  shot {k}: camera at {np.round(shot.camera_position, 3).tolist()} m, lamp pan "
                     f"{np.degrees(pan):.1f} deg, tilt {np.degrees(tilt):.1f} deg, radius {radius:.3f} m, "
                     f"{1e3 * shot.exposure.shutter_s:.2f} ms, f/{shot.exposure.f_number:.1f}, focus "
                     f"{shot.exposure.focus_m:.3f} m; covers " + ", ".join(c.feature for c in shot.covers))
        if shot.arm_joints is not None:
            lines.append(f"          planned camera looking along {np.round(shot.T_cell_cam[:3, 2], 3).tolist()}, "
                         f"UR5e joints {np.round(np.degrees(shot.arm_joints), 1).tolist()} deg")
    for f in plan.features:
        if f.covered_by is None:
            lines.append(f"  feature {f.name}: covered by no shot: {f.binding} binds: {f.hint}")
            continue
        c = next(c for c in plan.shots[f.covered_by].covers if c.feature == f.name)
        g = gray_stats(c.gray)
        lines.append(f"  feature {f.name}: shot {f.covered_by}, gray {g['min']:.1f}-{g['max']:.1f}, "
                     f"max f_i {c.worst:.3g}")
    return "\n".join(lines)


def command(args):
    out = output_folder(args.out, f"{Path(args.task).stem}-plan")
    task = load_task(args.task)
    create_folder(out)
    planner = plan if len(task.features) == 1 and task.camera.viewpoint.mode == "fixed" else plan_features
    result = planner(task, progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    write_plan(result, task, out)
    if args.json:
        print(jsonio.dumps(result.to_json(), indent=2))
    else:
        print(summary(result) if not result.features else features_summary(result))
        print(f"  wrote {out}/plan.json and pictures")
    require_feasible(result)
    return 0
