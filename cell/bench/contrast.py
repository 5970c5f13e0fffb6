"""`cell bench`'s rows for what the contrast requirement costs (issue 25, item 6), on a task
with `defects:` (default: tasks/hinge-scratch.yaml and tasks/conrod-defects.yaml, whose dent
gives a dent's rows beside the scratches'):

- `contrast`, per defect, feature samples and resolution: the time to judge every defect's
  worst CNR (cell.planning.defects) at POSES lamp poses around the feature (a ring at 45 deg
  tilt, mid radius, each exposed for its brightest sample at the band's top), warm (the kernel
  inputs kept, the judgements not), against the time the same poses' gray takes
  (cell.planning.evaluate.at_exposure: the band's own cost), and the largest relative error of
  its worst CNR against the reference's (the finest resolution on the most samples). The
  resolutions: `ranked` (a scratch every 15 deg, a dent 2 rings x 8 azimuths: the global
  search's), `grid` (5 deg, 4 x 24), `judged` (the grid refined where the worst may lie between
  grid orientations, as a chosen shot is judged), the reference every 0.25 deg (quick: 1 deg)
  and 100 times finer about each sample's worst, a dent's 16 x 96.

Layer 9: imports the layers below."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from importlib.resources import files
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.devices import rig
from cell.planning import defects, evaluate
from cell.planning.scene import build_scene

if TYPE_CHECKING:
    from cell.task.types import Task

# tasks with defects, installed: the hinge's scratch; the conrod's scratch and dent (a dent's rows)
DEFECT_TASKS = (files("lightplan_tasks") / "hinge-scratch.yaml", files("lightplan_tasks") / "conrod-defects.yaml")
POSES = 8
QUICK_POSES = 2
SAMPLES = (16, 64, 256)
QUICK_SAMPLES = (16, 64)
REFERENCE = defects.Resolution(float(np.radians(0.25)), 16, 96)
QUICK_REFERENCE = defects.Resolution(float(np.radians(1.0)), 16, 96)
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
RESOLUTIONS = {"ranked": defects.RANKED, "grid": defects.JUDGED, "judged": defects.JUDGED}


def poses(problem: evaluate.Problem, count: int) -> list[evaluate.Candidates]:
    """count lamp poses about the rig's pivot at 45 deg tilt and mid radius, a golden angle apart
    in pan (none in the feature frame's x-z plane, on every orientation grid), each exposed
    at f/5.6 for its brightest sample at the band's top (cell.planning.evaluate.at_exposure)."""
    task = problem.task
    pivot, r = task.lamp.rig.pivot_m, float(np.mean(task.lamp.rig.radius_range_m))
    out = []
    for pan in GOLDEN_ANGLE * (np.arange(count) + 0.5):        # no pan on an orientation grid
        position = rig.lamp_position(pivot, pan, np.radians(45.0), r).reshape(1, 3)
        u = evaluate.unit_gray(problem, position, rig.lamp_aim(pivot, position))[0][0]
        shutter = (problem.band[1] - problem.black_level) / max(float(u.max()), 1e-300) * 5.6**2
        out.append(evaluate.at_exposure(problem, position, shutter, 5.6))
    return out


def worst(problem: evaluate.Problem, c: evaluate.Candidates, d: Any, name: str,
          resolution: defects.Resolution) -> float:
    """The defect's worst CNR at one pose by the row's method."""
    if name == "judged":
        problem.kernels.defects.pop("judged", None)
        return next(j.predicted_cnr for j in defects.judge(problem, c) if j.name == d.name)
    ratio, _, _, thetas = defects.cnr_field(problem, c, d, resolution=resolution)
    if name != "reference" or d.kind != "scratch":
        return float(ratio.min())
    at = thetas[np.argmin(ratio[0], axis=-1)]         # then 100 times finer about each sample's minimum
    closer = at[:, None] + resolution.step_rad * np.arange(-100, 101) / 100
    every = np.arange(len(at))
    return min(float(ratio.min()), float(defects.cnr_field(problem, c, d, every, thetas=closer)[0].min()))


def _problem(task: Task, samples: int) -> evaluate.Problem:
    one = replace(task, features=(replace(task.feature, samples=samples),))
    return evaluate.build_problem(one, build_scene(one), None)


def rows_of(task: Task, quick: bool, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """The task's contrast rows (see the module's docstring)."""
    samples = QUICK_SAMPLES if quick else SAMPLES
    reference = QUICK_REFERENCE if quick else REFERENCE
    count = QUICK_POSES if quick else POSES
    best = _problem(task, samples[-1])
    ref_poses = poses(best, count)
    truth = {d.name: [worst(best, c, d, "reference", reference) for c in ref_poses] for d in task.feature.defects}
    out = []
    for n in samples:
        problem = _problem(task, n)
        chosen = poses(problem, count)
        start = time.perf_counter()
        for c in chosen:
            evaluate.at_exposure(problem, c.position[0], float(c.shutter[0]), float(c.kappa[0]))
        gray_s = (time.perf_counter() - start) / count
        for d in task.feature.defects:
            for name, resolution in RESOLUTIONS.items():
                if name == "judged" and d.kind != "scratch":
                    continue                        # a dent's or coating's judgement is its grid's
                worst(problem, chosen[0], d, name, resolution)        # warm: its kernel inputs kept
                start = time.perf_counter()
                found = [worst(problem, c, d, name, resolution) for c in chosen]
                spent = (time.perf_counter() - start) / count
                error = max(abs(f - t) / max(t, 1e-300) for f, t in zip(found, truth[d.name]))
                out.append({"task": task.name, "defect": d.name, "kind": d.kind, "samples": n, "resolution": name,
                            "orientations": len(defects.orientations(d, resolution.step_rad)),
                            "time_s": spent, "gray_s": gray_s, "ratio": spent / max(gray_s, 1e-12),
                            "cnr_error": error})
                say(f"contrast {task.name}: {d.name} {name} at {n} samples: {spent:.3f} s a pose "
                    f"({out[-1]['ratio']:.1f}x the gray's), worst CNR within {100 * error:.1f} %")
    return out


def run(tasks: Iterable[Task], quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """{"contrast": rows} of the tasks with defects (none: no rows)."""
    rows: list[dict[str, Any]] = []
    for task in tasks:
        rows += rows_of(task, quick, say)
    return {"contrast": rows}
