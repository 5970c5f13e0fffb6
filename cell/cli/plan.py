"""`cell plan TASK... [--out DIR] [--json] [--pictures chosen|all] [--workers N | --scheduler ADDRESS]`:
exit 0 feasible (every feature of every task covered), 1 infeasible (with the reason: the first
uncovered feature and its cause), 2 bad input. Of several tasks, one refused before its search (a
fixed camera the arm cannot take) is named with its cause and the others are planned all the same
(exit 1). With --workers or --scheduler the plans' jobs run on Dask (cell.planning.parallel); the
plans are the serial ones. Every plan.json is written before any picture is drawn; of a
multi-feature plan's candidate shots only the chosen get pictures, unless --pictures all. Progress
on stderr (cell.core.progress): bars on a terminal, a few lines elsewhere."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cell.core import jsonio
from cell.core.progress import Progress
from cell.planning import parallel
from cell.cli import create_folder, output_folder
from cell.core.errors import PlanInfeasible, TaskError
from cell.task.loader import load_task
from cell.planning.whole_part import own_plan, plan_features
from cell.planning.plan import PlannerSettings, gray_stats
from cell.report import words
from cell.report.recorder import draw_plan, write_plan
from cell.run.moves import with_moves

if TYPE_CHECKING:
    from cell.planning.plan import Plan
    from cell.task.types import Task


def summary(plan: Plan) -> str:
    """A few lines for the terminal."""
    shot = plan.shot
    pan, tilt, radius = shot.joints
    g = gray_stats(shot.gray)
    verdict = "feasible" if plan.feasible else f"INFEASIBLE: {words.reason(plan)}"
    return "\n".join([
        f"{plan.task_name}: {verdict}",
        f"  lamp   {shot.distance_m:.3f} m from the feature, phase angle {np.degrees(shot.phase_angle_rad):.1f} deg"
        f" (pan {np.degrees(pan):.1f} deg, tilt {np.degrees(tilt):.1f} deg, radius {radius:.3f} m)",
        f"  camera shutter {1e3 * shot.exposure.shutter_s:.2f} ms, f/{shot.exposure.f_number:.1f},"
        f" focus {shot.exposure.focus_m:.3f} m (depth of field {1e3 * shot.exposure.depth_of_field_m:.1f} mm)",
        f"  gray   mean {g['mean']:.1f}, min {g['min']:.1f}, max {g['max']:.1f}",
        *([f"  {words.tightest(shot.requirements, plan.binding)}"] if plan.feasible else []),
        f"  planned in {plan.timing_s['total']:.2f} s",
    ])


def features_summary(plan: Plan) -> str:
    """A headline (the verdict, the count covered and, of a plan not feasible, its true cause:
    words.reason), then one line per shot and one per feature (the shot covering it, or why none
    does). PARTIAL: a feature no shot covers; INFEASIBLE: every feature covered, a move refused."""
    n, covered = len(plan.features), sum(f.covered_by is not None for f in plan.features)
    verdict = "feasible" if plan.feasible else "PARTIAL" if covered < n else "INFEASIBLE"
    assert plan.cover is not None                      # a multi-feature plan's
    lines = [f"{plan.task_name}: {verdict}: {words.covering(len(plan.shots), covered, n)} (chosen from "
             f"{words.count(plan.cover['candidate_shots'], 'candidate shot')}"
             + (", planned viewpoints" if "viewpoints" in plan.cover else "") + "); "
             + ("" if plan.feasible else f"{words.reason(plan)}; ")
             + f"planned in {plan.timing_s['total']:.2f} s"]
    for k, shot in enumerate(plan.shots):
        pan, tilt, radius = shot.joints
        lines.append(f"  shot {k}: camera at {np.round(shot.camera_position, 3).tolist()} m (cell frame), lamp pan "
                     f"{np.degrees(pan):.1f} deg, tilt {np.degrees(tilt):.1f} deg, radius {radius:.3f} m, "
                     f"{1e3 * shot.exposure.shutter_s:.2f} ms, f/{shot.exposure.f_number:.1f}, focus "
                     f"{shot.exposure.focus_m:.3f} m; covers " + ", ".join(c.feature for c in shot.covers))
        if shot.arm_joints is not None:
            lines.append(f"          planned camera looking along {np.round(shot.T_cell_cam[:3, 2], 3).tolist()}, "
                         f"UR5e joints {np.round(np.degrees(shot.arm_joints), 1).tolist()} deg")
    for f in plan.features:
        if f.covered_by is None:
            lines.append(f"  {words.uncovered(f.name, f.binding, f.hint)}")
            continue
        c = next(c for c in plan.shots[f.covered_by].covers if c.feature == f.name)
        g = gray_stats(c.gray)
        lines.append(f"  feature {f.name}: shot {f.covered_by}, gray {g['min']:.1f}-{g['max']:.1f}, "
                     f"{words.tightest(c.requirements)}")
    return "\n".join(lines)


def command(args: argparse.Namespace) -> int:
    workers = worker_count(args)
    several = len(args.tasks) > 1
    out = None                          # the folders' places checked before any work
    if several and args.out is not None:
        out = output_folder(args.out, "plan")
    else:
        for path in args.tasks:
            output_folder(args.out, f"{Path(path).stem}-plan")
    tasks = [load_task(path) for path in args.tasks]
    names = distinct([Path(path).stem for path in args.tasks])
    with parallel.pool(workers, args.scheduler) as pool:
        folders = task_folders(args, out, names)
        stderr = Progress(sys.stderr)
        progress = [stderr.labelled(f"{name}: " if several else "") for name in names]
        if pool is parallel.SERIAL or not several:
            results = [plan_one(task, p, pool) for task, p in zip(tasks, progress)]
        else:                           # the tasks' jobs side by side on the cluster
            with ThreadPoolExecutor(len(tasks)) as threads:
                results = [f.result() for f in [threads.submit(plan_one, t, p, pool) for t, p in zip(tasks, progress)]]
    for result, task, folder in zip(results, tasks, folders):
        if isinstance(result, PlanInfeasible):
            if several or args.out is None:
                folder.rmdir()          # made by this command, left empty: refused before any search
        else:
            write_plan(result, task, folder)
    if not several and isinstance(results[0], PlanInfeasible):
        raise results[0]
    for result, task, folder in zip(results, tasks, folders):      # every plan.json first, then pictures
        if not isinstance(result, PlanInfeasible):
            draw_plan(result, task, folder, args.pictures)
    if args.json:
        documents = [refused_json(task, result) if isinstance(result, PlanInfeasible) else result.to_json()
                     for task, result in zip(tasks, results)]
        print(jsonio.dumps(documents if several else documents[0], indent=2))
    else:
        for result, task, folder in zip(results, tasks, folders):
            if isinstance(result, PlanInfeasible):
                print(f"{task.name}: INFEASIBLE, not planned: {result.said.removeprefix(task.name + ': ')}")
                continue
            print(summary(result) if not result.features else features_summary(result))
            print(f"  wrote {folder}/plan.json and pictures")
    failed = [(f"{path}: " if several else "", result) for result, path in zip(results, args.tasks)
              if isinstance(result, PlanInfeasible) or not result.feasible]
    if failed:                          # every task that failed, each with its true cause
        raise PlanInfeasible("infeasible: " + "; ".join(f"{where}{why(result)[0]}" for where, result in failed),
                             "infeasible: " + "; ".join(f"{where}{why(result)[1]}" for where, result in failed))
    return 0


def why(result: Plan | PlanInfeasible) -> tuple[str, str]:
    """(the message as plan.json gives it, the same in words) of an infeasible plan or a refusal."""
    if isinstance(result, PlanInfeasible):
        return str(result), result.said
    return result.message, words.reason(result)


def plan_one(task: Task, progress: Progress, pool: parallel.Pool) -> Plan | PlanInfeasible:
    """`cell plan`'s Plan of a task: planner.plan's of one feature at the task's camera rule (one
    job of `pool`), plan_features' of several or of planned viewpoints with its route's checked
    moves (cell.run.moves); the PlanInfeasible of a task refused before its search (a fixed camera
    the arm cannot take), so that the other tasks are planned all the same."""
    try:
        if len(task.features) == 1 and task.camera.viewpoint.mode == "fixed":
            return pool.map(own_plan, [(task, PlannerSettings(), None, None, "")], progress.say)[0]
        return with_moves(task, plan_features(task, progress=progress, pool=pool))
    except PlanInfeasible as refused:
        return refused


def refused_json(task: Task, refused: PlanInfeasible) -> dict[str, object]:
    """--json's entry of a task refused before its search: plan.json's verdict keys, no shot."""
    binding, _, _ = str(refused).partition(":")
    return {"task": task.name, "feasible": False, "binding": binding, "hint": refused.said, "message": str(refused)}


def worker_count(args: argparse.Namespace) -> int | None:
    """--workers as a whole number >= 1 (None: not given); --workers and --scheduler exclude each
    other. Bad input otherwise (exit 2)."""
    if args.workers is not None and args.scheduler is not None:
        raise TaskError("command line", "--scheduler", f"--scheduler {args.scheduler} with --workers {args.workers}",
                        "one of them: --workers N starts a cluster on this machine, --scheduler ADDRESS "
                        "uses a running one")
    if args.workers is None:
        return None
    try:
        n = int(args.workers)
    except ValueError:
        n = 0
    if n < 1:
        raise TaskError("command line", "--workers", args.workers, "a whole number of worker processes, at least 1")
    return n


def distinct(names: Iterable[str]) -> list[str]:
    """The names, a repeat of an earlier one numbered -2, -3, ..."""
    out = []
    for name in names:
        unique, n = name, 1
        while unique in out:
            n += 1
            unique = f"{name}-{n}"
        out.append(unique)
    return out


def task_folders(args: argparse.Namespace, out: Path | None, names: Iterable[str]) -> list[Path]:
    """Each task's output folder, created now that every task loaded: --out itself (one task),
    a folder of each task's name in --out (several), or runs/<task>-plan-<time> (-2, -3, ... when
    taken, also by an earlier task of the same name)."""
    if out is None and args.out is not None:
        return [create_folder(output_folder(args.out, ""))]
    if out is None:
        return [create_folder(output_folder(None, f"{Path(path).stem}-plan")) for path in args.tasks]
    create_folder(out)
    return [create_folder(out / name) for name in names]
