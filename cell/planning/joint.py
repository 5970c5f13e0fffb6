"""One shot's drive levels re-solved over every feature it can cover, while the shots are judged.

A candidate shot's drives, shutter and f-number are its own feature's (cell.planning.one_shot's
program, cell.planning.drives): another feature in its view is judged at them, and is often too
dark or too bright there although some drive levels would put both in band. Below saturation a
pixel's gray is linear in each channel's drive, G_p = b + x sum_k w_k v_kp (eq. 10, 17 summed over
the channels), so the same program over the samples of every feature the shot may cover (the
prefilter's, cell.planning.prefilter; each sample against its own feature's band) finds them, or
says there are none:

1. the samples of the shot's own feature and of every feature the prefilter left, each with its
   channels' gray per exposure v_kp at the shot's camera, spot pose and focus (evaluate.unit_gray,
   Problem.lights); a light that gives another reflection than one of them asks is off (as in
   one_shot.lighting); the f-number at least the widest each feature's depth of field allows;
2. the program's drives judged on each feature in full (coverage.judge: every requirement, the
   lamp and drive tolerances, the dense certificate); a feature the program's optimum misses the
   band on, or the judge does not cover, is dropped and the program solved again without it
   (the own feature never: without it the shot is not this candidate; one the shot covered at
   its own drives only when no other is left to drop);
3. the joint drives are kept only where the shot still covers every feature it covered at its
   own drives (coverage not lost): then it covers as many or more, and the narrowest margin over
   them is at least that of its own drives, which are one point of the program (the other
   features were covered at the shot's f-number, so it is no wider than their depth of field
   allows). The set cover (cell.planning.set_cover) chooses over each candidate's best coverage.

A task without lights besides the spot has nothing to re-solve (its one lamp's drive is fixed):
its candidates and plans are as before.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from cell.devices import rig
from cell.physics import depth_of_field as dof
from cell.planning import coverage, drives, evaluate
from cell.planning.plan import Exposure

if TYPE_CHECKING:
    from cell.planning.coverage import Lent
    from cell.planning.plan import Coverage, Shot
    from cell.task.types import Task


@dataclass(frozen=True)
class Joint:
    """A candidate shot with drives solved over several features: the shot (its own feature's
    gray, requirements and lights at the joint drives), its own feature's Coverage there, and its
    column (each feature's Coverage, None at its own, as whole_part's judge_column), the features
    whose samples the program held (names) and its margin [gray]."""

    shot: Shot
    own: Coverage
    column: list[Coverage | None]
    features: tuple[str, ...]
    margin_gray: float


def covered(column: Sequence[Coverage | None]) -> set[int]:
    """The features a column covers (its own, None, counted as covered)."""
    return {g for g, c in enumerate(column) if c is None or c.covered}


def resolve(tasks: Sequence[Task], lent: Sequence[Lent], f: int, shot: Shot,
            column: list[Coverage | None]) -> Joint | None:
    """The Joint of feature f's candidate `shot`, whose column at its own drives is `column`,
    over the features the prefilter left (a Coverage with a gray), or None: no lights to drive,
    no other feature in question, no drives in band for the own feature with another, or none
    without losing a feature it covered (the module's steps)."""
    if not tasks[f].lights:
        return None
    asked = [g for g, c in enumerate(column) if c is not None and len(c.gray)]
    if not asked:
        return None
    before = covered(column)
    held_data = {g: _Feature.of(tasks[g], lent[g], shot) for g in [f, *asked]}
    while asked:
        held = [f, *asked]
        chosen = _solve(tasks[f], [held_data[g] for g in held])
        if not chosen.feasible:
            # drop a feature the shot did not cover first: those it covered it must keep
            droppable = [g for g in asked if g not in before] or asked
            asked = [g for g in asked if g != _worst(held, [held_data[g] for g in held], chosen, droppable)]
            continue
        joint = _at_drives(shot, held_data[f].problem, chosen)
        own = coverage.judge(tasks[f], lent[f], joint)
        if not own.covered:
            return None
        judged = dict(zip(asked, coverage.judge_all([tasks[g] for g in asked], [lent[g] for g in asked], joint)))
        lost = [g for g in asked if not judged[g].covered]
        if lost:
            asked = [g for g in asked if g not in lost]
            continue
        after = [None if g == f else judged.get(g, c) for g, c in enumerate(column)]
        if not before <= covered(after):
            return None
        joint = replace(joint, gray=own.gray, requirements=own.requirements, lights=own.lights, defects=own.defects)
        return Joint(joint, own, after, tuple(tasks[g].feature.name for g in held), chosen.margin_gray)
    return None


@dataclass(frozen=True)
class _Feature:
    """One feature at the shot: its Problem (samples, band, focus, widest f-number), each light's
    gray per exposure (1 + K, P) (the spot at the shot's pose first, the others at full drive)
    and the lights that give another reflection than it asks (1 + K,)."""

    problem: evaluate.Problem
    unit_gray: np.ndarray
    wrong: np.ndarray

    @classmethod
    def of(cls, task: Task, lent: Lent, shot: Shot) -> _Feature:
        scene = replace(lent.scene, T_cell_cam=shot.T_cell_cam)
        problem = evaluate.build_problem(task, scene, None, focus_m=shot.exposure.focus_m)
        pivot = task.lamp.rig.pivot_m
        position = shot.lamp_position.reshape(1, 3)
        spot, _, _, spot_term = evaluate.unit_gray(problem, position, rig.lamp_aim(pivot, position))
        v = np.vstack([spot, problem.lights.unit_gray])
        return cls(problem, v, evaluate.wrong_reflection(problem, v, np.vstack([spot_term, problem.lights.dominant])))


def _solve(task: Task, held: Sequence[_Feature]) -> drives.Drives:
    """The drive program (cell.planning.drives) over the samples of the features `held`, each
    sample against its own feature's band: a light wrong for one of them off (one on the
    controller; one on its own supply stays on), the widest f-number the one that holds every
    depth of field, the largest drive tolerance any of them asks."""
    channels = [task.lamp.channel] + [light.channel for light in task.lights]
    ranges = np.array([c.drive_range for c in channels], float)
    on_controller = np.array([c.number is not None for c in channels])
    ranges[on_controller & np.any([x.wrong for x in held], axis=0)] = (0.0, 0.0)
    unit_gray, low, high = _stacked(held)
    camera = task.camera
    return drives.solve_drives(unit_gray, (low, high), held[0].problem.black_level,
                               max(x.problem.kappa_open for x in held), camera.shutter_range_s,
                               camera.lens.f_number_range, ranges, [c.switched for c in channels],
                               max(x.problem.task.requirements.drive_tolerance for x in held))


def _worst(features: Sequence[int], held: Sequence[_Feature], chosen: drives.Drives, droppable: Sequence[int]) -> int:
    """The feature of `droppable` (of `features`, held in that order) whose sample misses the
    band the most at the program's best drives: the one to drop."""
    owner = np.repeat(np.arange(len(held)), [x.unit_gray.shape[1] for x in held])
    gain = chosen.shutter_s / chosen.f_number**2
    delta = max(x.problem.task.requirements.drive_tolerance for x in held)
    unit_gray, low, high = _stacked(held)
    signal = gain * (chosen.drive @ unit_gray)
    b = held[0].problem.black_level
    miss = np.maximum(low - (b + (1 - delta) * signal), b + (1 + delta) * signal - high)
    worst = owner[np.argsort(-miss)]
    return int(next(features[k] for k in worst if features[k] in droppable))


def _stacked(held: Sequence[_Feature]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The held features' samples side by side: each light's gray per exposure (1 + K, P) and
    each sample's own feature's band, low and high (P,)."""
    low = np.concatenate([np.full(x.unit_gray.shape[1], x.problem.band[0]) for x in held])
    high = np.concatenate([np.full(x.unit_gray.shape[1], x.problem.band[1]) for x in held])
    return np.hstack([x.unit_gray for x in held]), low, high


def _at_drives(shot: Shot, problem: evaluate.Problem, chosen: drives.Drives) -> Shot:
    """The shot at the program's drives, shutter and f-number (its focus kept), its lights'
    drives set (their gray and requirements the own feature's judge gives)."""
    lens = problem.task.camera.lens
    exposure = Exposure(chosen.shutter_s, chosen.f_number, shot.exposure.focus_m,
                        float(dof.depth_of_field(shot.exposure.focus_m, lens.focal_length_m, chosen.f_number,
                                                 lens.circle_of_confusion_m)))
    lights = tuple(replace(light, drive=float(w)) for light, w in zip(shot.lights, chosen.drive))
    return replace(shot, exposure=exposure, lights=lights)
