"""`cell bench`: what accuracy costs in time, and how fast the kernels are.

Each planner setting (PlannerSettings: map grid step, lamp candidates, feature samples,
refinement) is timed warm (one plan first, then the median of repeats) and compared with a
reference plan of the same task at fine resolution (REFERENCE):
- gray error: a plan predicts mean/min/max gray over the feature from its own samples. The truth
  is what its chosen lamp pose and exposure give on the reference's fine samples with the same
  physics (G = u t / kappa^2, u from cell.planning.evaluate on the reference scene). `gray_error` is
  predicted - true for each of mean, min, max [gray levels]; `gray_error_max` the largest
  magnitude e: every fine sample's true gray then lies within e of the predicted [min, max].
- lamp error: distance to the reference plan's lamp [mm] and angle between the two lamp
  directions seen from the feature centre [deg].
- feasible_agrees: the plan's verdict equals the reference's. A flip or any NaN/inf is flagged.
Pareto front, per task: settings no other setting beats on both time_s and gray_error_max.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, replace
from importlib.resources import files
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.planning import evaluate, one_shot
from cell.core import geometry
from cell.devices import rig
from cell.planning.plan import PlannerSettings, gray_stats
from cell.planning.regions import SphereGrid
from cell.planning.scene import build_scene
from cell.report import words
from cell.bench.throughput import benchmark_gray, benchmark_visibility, wall_times

if TYPE_CHECKING:
    from cell.core.progress import Progress
    from cell.planning.plan import Plan
    from cell.task.types import Task

EXAMPLES = files("lightplan_tasks")     # tasks/, installed with the package (pyproject.toml)
DEFAULT_TASKS = (EXAMPLES / "hinge.yaml", EXAMPLES / "conrod.yaml")
DEFAULT = PlannerSettings()
SWEEP = {
    "coarse": PlannerSettings(grid_step_deg=4.0, pan_step_deg=20.0, tilt_step_deg=10.0, radius_steps=3,
                              samples=16),
    "default": DEFAULT,
    "fine": PlannerSettings(grid_step_deg=1.0, pan_step_deg=5.0, tilt_step_deg=2.5, radius_steps=10,
                            samples=128),
    "grid 4 deg": replace(DEFAULT, grid_step_deg=4.0),
    "grid 1 deg": replace(DEFAULT, grid_step_deg=1.0),
    "candidates /8": replace(DEFAULT, pan_step_deg=20.0, tilt_step_deg=10.0, radius_steps=3),
    "candidates x8": replace(DEFAULT, pan_step_deg=5.0, tilt_step_deg=2.5, radius_steps=12),
    "samples 16": replace(DEFAULT, samples=16),
    "samples 32": replace(DEFAULT, samples=32),
    "samples 128": replace(DEFAULT, samples=128),
    "no refinement": replace(DEFAULT, refine=False),
}
QUICK_SWEEP = ("coarse", "default", "fine")
REFERENCE = PlannerSettings(grid_step_deg=0.5, pan_step_deg=2.0, tilt_step_deg=1.0, radius_steps=20,
                            samples=256)
QUICK_REFERENCE = PlannerSettings(grid_step_deg=1.0, pan_step_deg=4.0, tilt_step_deg=2.0, radius_steps=12,
                                  samples=192)
GRAY_SIZES = (10_000, 100_000, 1_000_000, 10_000_000)     # candidate x sample evaluations
QUICK_GRAY_SIZES = (10_000, 1_000_000)
GRID_STEPS_DEG = (4.0, 2.0, 1.0)                          # visibility map sizes
QUICK_GRID_STEPS_DEG = (4.0,)


def timed_plan(task: Task, settings: PlannerSettings, repeats: int) -> tuple[Plan, float, list[float]]:
    """(plan, median wall time [s], every time): one warm-up plan (the planner is deterministic:
    its result is the plan), then `repeats` timed ones."""
    result = one_shot.plan(task, settings)
    times = wall_times(lambda: one_shot.plan(task, settings), repeats)
    return result, float(np.median(times)), times


def accuracy(task: Task, result: Plan, reference: Plan, truth: evaluate.Problem) -> dict[str, Any]:
    """Errors of a plan against the reference plan (module docstring); `truth` is the
    evaluate.Problem of the reference's scene."""
    shot, ref_shot = result.shot, reference.shot
    pos = shot.lamp_position
    u = evaluate.unit_gray(truth, pos[None], rig.lamp_aim(task.lamp.rig.pivot_m, pos)[None])[0]
    true_gray = truth.black_level + u[0] * shot.exposure.shutter_s / shot.exposure.f_number**2
    predicted, true = gray_stats(shot.gray), gray_stats(true_gray)
    error = {k: predicted[k] - true[k] for k in predicted}
    center = reference.planned_scene.center
    cos = geometry.unit(pos - center) @ geometry.unit(ref_shot.lamp_position - center)
    numbers = np.concatenate([shot.gray, true_gray, pos, shot.joints, list(asdict(shot.exposure).values()),
                              [r.value for r in result.requirements]])
    return {
        "predicted_gray": predicted, "true_gray": true, "gray_error": error,
        "gray_error_max": max(abs(e) for e in error.values()),
        "lamp_error_mm": 1e3 * float(np.linalg.norm(pos - ref_shot.lamp_position)),
        "lamp_error_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))),
        "feasible_agrees": result.feasible == reference.feasible,
        "finite": bool(np.all(np.isfinite(numbers))),
    }


def pareto(points: Sequence[tuple[float, float]]) -> list[bool]:
    """Flags of the (time, error) points that no other point dominates (<= in both, < in one);
    a point with a NaN/inf is off the front and dominates nothing."""
    pts = np.asarray(points, dtype=float)
    ok = np.all(np.isfinite(pts), axis=1)
    return [bool(ok[i] and not any(ok[j] and np.all(q <= p) and np.any(q < p) for j, q in enumerate(pts)))
            for i, p in enumerate(pts)]


def sweep_task(task: Task, names: Iterable[str], reference_settings: PlannerSettings, repeats: int,
               say: Callable[[str], None]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """(rows of the settings `names`, the reference's summary) for one task."""
    label = task.path.stem
    t0 = time.perf_counter()
    reference = one_shot.plan(task, reference_settings)
    ref_time = time.perf_counter() - t0
    say(f"{label} reference: {ref_time:.1f} s, {len(reference.planned_scene.points)} samples, "
        f"{'feasible' if reference.feasible else 'infeasible: ' + words.reason(reference)}")
    truth = evaluate.build_problem(task, reference.planned_scene, reference.maps)
    rows = []
    for name in names:
        settings = SWEEP[name]
        result, time_s, times = timed_plan(task, settings, repeats)
        row = {"name": name, "task": label, "settings": asdict(settings),
               "candidates": len(one_shot.candidate_grid(task.lamp.rig, settings)[0]),
               "samples": len(result.planned_scene.points), "time_s": time_s, "times_s": times,
               "stages_s": result.timing_s,
               "feasible": result.feasible, "binding": result.binding, "miss": result.miss,
               **accuracy(task, result, reference, truth), "default": settings == DEFAULT}
        rows.append(row)
        say(f"{label} {name}: {time_s:.3f} s, gray error {row['gray_error_max']:.3f}, lamp "
            f"{row['lamp_error_mm']:.1f} mm / {row['lamp_error_deg']:.2f} deg{flags(row)}")
    for row, on_front in zip(rows, pareto([(r["time_s"], r["gray_error_max"]) for r in rows])):
        row["pareto"] = on_front
    ref = {"task": label, "settings": asdict(reference_settings), "time_s": ref_time,
           "candidates": len(one_shot.candidate_grid(task.lamp.rig, reference_settings)[0]),
           "samples": len(reference.planned_scene.points), "feasible": reference.feasible,
           "binding": reference.binding,
           "miss": reference.miss,
           "predicted_gray": gray_stats(reference.shot.gray),
           "lamp_position_m": reference.shot.lamp_position.tolist()}
    return rows, ref


def flags(row: dict[str, Any]) -> str:
    """What the progress line shouts about: a feasibility flip, a NaN/inf."""
    return ("" if row["feasible_agrees"] else "  FLIP: feasibility differs from the reference") + \
        ("" if row["finite"] else "  NaN/inf in the plan")


def kernel_rows(task: Task, quick: bool, repeats: int, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """Kernel throughput rows on the task's scene (cell.bench.throughput), tagged with the task."""
    label = task.path.stem
    scene = build_scene(task)
    sensor = task.camera.sensor
    rows = []
    for size in QUICK_GRAY_SIZES if quick else GRAY_SIZES:
        for shadows in (True, False):
            rows.extend(benchmark_gray(scene.warp_mesh, scene.points, scene.normals, scene.camera_position,
                                       task.part.material.table(), task.lamp.power_w, task.lamp.cone_angle_rad,
                                       sensor.camera_constant, sensor.pixel_area_m2, evaluations=size,
                                       shadows=shadows, repeat=repeats))
    for step in QUICK_GRID_STEPS_DEG if quick else GRID_STEPS_DEG:
        grid = SphereGrid(np.radians(step))
        rows += benchmark_visibility(scene.warp_mesh, scene.points, scene.normals, scene.frame,
                                     grid.azimuth, grid.elevation, repeat=repeats)
    for row in rows:
        row["task"] = label
        say(f"{label} kernel {row['name']} at {row['size']:.3g}: {row['warp_per_s']:.3g}/s"
            + (f", {row['ratio']:.3g} x {row['reference']}" if row["ratio"] is not None
               else f" ({row['unavailable']})"))
    return rows


def targets(settings: Iterable[dict[str, Any]], kernels: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """The issue's done-when: default within 1 gray level and well under 1 s; gray kernel >= 5x
    NumPy at 1e6 evaluations."""
    out = []
    for row in (r for r in settings if r["default"]):
        out.append({"name": f"{row['task']}: default gray error <= 1 gray level",
                    "value": row["gray_error_max"], "limit": 1.0, "met": row["gray_error_max"] <= 1.0})
        out.append({"name": f"{row['task']}: default warm plan < 1 s",
                    "value": row["time_s"], "limit": 1.0, "met": row["time_s"] < 1.0})
    for row in (r for r in kernels if r["name"] == "gray" and abs(r["size"] / 1e6 - 1.0) < 0.01):
        out.append({"name": f"{row['task']}: gray kernel Warp / NumPy at 1e6 >= 5",
                    "value": row["ratio"], "limit": 5.0, "met": row["ratio"] >= 5.0})
    return out


def run(tasks: Iterable[Task], quick: bool, progress: Progress,
        feature_tasks: Iterable[Task] = (), light_tasks: Iterable[Task] = (), many: bool = False,
        defect_tasks: Iterable[Task] = ()) -> dict[str, Any]:
    """The benchmark of the loaded one-feature `tasks`: every setting's row against the task's
    reference, the references, the kernel rows; of the multi-feature `feature_tasks` the
    cell.bench.multi_feature rows; of the `light_tasks` (with lights besides the spot) the
    cell.bench.lights rows; of the `defect_tasks` the cell.bench.contrast rows; the big launches on
    1 and 2 threads (cell.bench.threads); with `many`, the generated many-feature part's
    (cell.bench.scaling); and the targets (bench.json). Each part is a stage of `progress` (a step
    per task), its rows' lines said as they come."""
    from cell.bench import contrast, lights, multi_feature, scaling, threads
    tasks, feature_tasks, light_tasks = list(tasks), list(feature_tasks), list(light_tasks)
    defect_tasks = list(defect_tasks)
    say = progress.say
    repeats = 1 if quick else 3
    result: dict[str, Any] = {"quick": quick, "repeats": repeats, "settings": [], "references": [], "kernels": [],
                              "threads": [], "features": [], "workers": [], "collisions": [], "channels": [],
                              "contrast": [], "scaling": [], "scaling_summary": None}

    def stage(name: str, items: list[Any]) -> Iterator[Any]:
        """The items, each a step of the stage `name` (none: no stage)."""
        if items:
            with progress.stage(name, len(items)) as bar:
                for item in bar.each(items):
                    bar.note(getattr(getattr(item, "path", None), "stem", ""))
                    yield item

    for task in stage("settings sweep", tasks):
        rows, ref = sweep_task(task, QUICK_SWEEP if quick else SWEEP,
                               QUICK_REFERENCE if quick else REFERENCE, repeats, say)
        result["settings"] += rows
        result["references"].append(ref)
    for task in stage("kernel rates", tasks):
        result["kernels"] += kernel_rows(task, quick, repeats, say)
    for _ in stage("threads", [tasks] if tasks else []):
        result["threads"] = threads.run(tasks, quick, say)
    for task in stage("multi-feature plans", feature_tasks):
        for key, rows in multi_feature.run([task], quick, say).items():
            result[key] += rows
    for task in stage("lights and channels", light_tasks):
        for key, rows in lights.run([task], quick, say).items():
            result[key] += rows
    for task in stage("defects' contrast", defect_tasks):
        result["contrast"] += contrast.run([task], quick, say)["contrast"]
    for _ in stage("many-feature scaling", [many] if many else []):
        result |= scaling.run(quick, say)
    result["targets"] = (targets(result["settings"], result["kernels"])
                         + multi_feature.targets(result["workers"], result["collisions"])
                         + lights.targets(result["channels"]) + scaling.targets(result["scaling"], result["scaling_summary"]))
    return result
