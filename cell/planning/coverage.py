"""Whether a given shot covers a feature: every requirement (cell.planning.requirements) on the feature's
samples at the shot's fixed camera pose, lamp pose and exposure, the lamp moved by its tolerance
at that exposure too, the maps for that camera position (the wanted reflection region depends on
the view), and the dense certificate (cell.planning.certificate.verify). The search (cell.planning.one_shot) chooses
a shot for a feature; this judges one it is given, on any feature, so its own module; the set
cover (cell.planning.set_cover) reads its verdicts.

For a feature's own planned shot it repeats the plan's judgement exactly (same samples, maps,
focus and exposure), so it agrees with plan()'s verdict.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from cell.planning import certificate, defects, evaluate, requirements
from cell.planning.one_shot import build_maps, light_settings
from cell.planning.plan import Coverage

if TYPE_CHECKING:
    from collections.abc import Sequence

    from cell.planning.evaluate import Rows
    from cell.physics.costs import RequirementValue
    from cell.planning.plan import Plan, PlannerSettings, Shot
    from cell.planning.scene import Scene
    from cell.task.types import Task


def of_plan(task: Task, plan: Plan) -> Coverage:
    """The Coverage of a one-feature task's own plan (its verdict, nothing judged again)."""
    shot = plan.shot
    return Coverage(task.feature.name, plan.feasible, shot.gray, shot.requirements, plan.verification,
                    shot.lights, shot.defects)


@dataclass(frozen=True)
class Lent:
    """What a feature's own plan lends to judging other shots on it, what does not depend on the
    camera: its samples (the Scene, with the certificate's worst points), its settings and its
    visibility map; a few kB where the plan with its maps is half a MB."""

    scene: Scene
    settings: PlannerSettings
    visible: np.ndarray

    @classmethod
    def of(cls, plan: Plan) -> Lent:
        if plan.scene is None or plan.maps is None:
            raise ValueError("a multi-feature plan lends nothing: its features' own plans do")
        return cls(plan.scene, plan.settings, plan.maps.visible)


def stacked(lent: Sequence[Lent], T_cell_cam: np.ndarray) -> tuple[Scene, list[tuple[int, int]]]:
    """The samples of several features of one part (their own plans' `lent`) in one scene, seen
    by a camera at T_cell_cam, and each feature's rows [start, end) in it."""
    counts = np.array([len(x.scene.points) for x in lent])
    ends = np.cumsum(counts)
    scene = replace(lent[0].scene, T_cell_cam=T_cell_cam, points=np.vstack([x.scene.points for x in lent]),
                    normals=np.vstack([x.scene.normals for x in lent]))
    return scene, list(zip((ends - counts).tolist(), ends.tolist()))


def rejected(task: Task, missed: tuple[RequirementValue, ...]) -> Coverage:
    """The Coverage of a shot on the one-feature `task` that the prefilter (cell.planning.prefilter)
    found to miss the requirements `missed`: not covered, nothing predicted (no gray)."""
    return Coverage(task.feature.name, False, np.zeros(0), missed)


def judge_all(tasks: Sequence[Task], lent: Sequence[Lent], shot: Shot) -> list[Coverage]:
    """judge of `shot` on each one-feature task of one part (with its Lent), the gray kernel on
    the samples launched once for all of them (evaluate.SharedLaunches), not once per feature."""
    if not tasks:
        return []
    task = tasks[0]
    scene, bounds = stacked(lent, shot.T_cell_cam)
    shared = evaluate.SharedLaunches(evaluate.gray_inputs(task, scene, task.part.material.scaled(1.0)),
                                     [end - start for start, end in bounds])
    return [judge(t, x, shot, shared.rows(k)) for k, (t, x) in enumerate(zip(tasks, lent))]


def judge(task: Task, lent: Lent, shot: Shot, shared: Rows | None = None) -> Coverage:
    """Coverage of `shot` (cell.planning.plan.Shot) on the one-feature `task`, whose own plan lent what
    does not depend on the camera (Lent); the samples' gray kernel its own or `shared`, its rows of
    a launch shared with other features (judge_all)."""
    scene = replace(lent.scene, T_cell_cam=shot.T_cell_cam)
    maps = build_maps(task, scene, lent.settings, visible=lent.visible, lamps=shot.lamp_position[None],
                      reflectance=False)
    problem = evaluate.build_problem(task, scene, maps, focus_m=shot.exposure.focus_m, gray=shared)
    e = shot.exposure
    c = evaluate.at_exposure(problem, shot.lamp_position, e.shutter_s, e.f_number, joints=shot.joints,
                             drive=shot.drive)
    if task.lights:         # the drive program's shutter, as one_shot.lighting judges it: not one centring this feature
        c = replace(c, t_need=np.array([e.shutter_s * (problem.kappa_open / e.f_number) ** 2]))
    values = requirements.judged(problem, c, requirements.ln_values(problem, c))
    gray = np.minimum(c.gray[0], 2.0 ** task.camera.sensor.bit_depth - 1)
    shares = light_settings(problem, c)
    found = defects.judge(problem, c) if task.feature.defects else ()
    if not all(r.met for r in values):
        return Coverage(task.feature.name, False, gray, values, lights=shares, defects=found)
    verification, _ = certificate.verify(problem, shot)
    return Coverage(task.feature.name, verification.holds, gray, certificate.worse_of(values, verification),
                    verification, shares, defects.worse_of(found, verification.defects))
