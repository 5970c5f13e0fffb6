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
from typing import TYPE_CHECKING, NamedTuple, cast

import numpy as np

from cell.planning import certificate, defects, evaluate, requirements
from cell.planning.one_shot import build_maps, light_settings
from cell.planning.plan import Coverage
from kernels.runtime import in_background, threads

if TYPE_CHECKING:
    from collections.abc import Sequence
    from concurrent.futures import Future

    from cell.planning.evaluate import Rows
    from cell.physics.costs import RequirementValue
    from cell.planning.plan import DefectCnr, LightSetting, Plan, PlannerSettings, Shot, Verification
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


def laid(tasks: Sequence[Task], lent: Sequence[Lent], shot: Shot) -> list[Future[Scene]] | None:
    """Each one-feature task's dense patch (certificate.dense_scene) seen by `shot`'s camera,
    being laid on the thread beside the caller's (kernels.runtime.in_background), where the
    process has one (else None: judge_all makes the patches of the features met, each when
    verified)."""
    if threads() == 1:
        return None
    return [in_background(certificate.dense_scene, t, replace(x.scene, T_cell_cam=shot.T_cell_cam))
            for t, x in zip(tasks, lent)]


def judge_all(tasks: Sequence[Task], lent: Sequence[Lent], shot: Shot,
              dense: Sequence[Future[Scene]] | None = None) -> list[Coverage]:
    """judge of `shot` on each one-feature task of one part (with its Lent), the gray kernel on
    the samples launched once for all of them (evaluate.SharedLaunches), not once per feature,
    what one Problem over all their samples finds given to each feature's (what_whole_gives), and
    the certificates of those whose samples meet every requirement verified together
    (certificate.lit and verdicts: their dense patches' launches shared too). `dense`: each
    feature's dense patch being laid (laid's, begun before: cell.planning.whole_part lays a
    column's while it judges the column before), else laid here (laid). Where they are laid
    beside (a process of two threads or more), the certificates' specular points are found
    first and their launches begun on another thread beside (certificate.lit) while the samples
    are judged: nearly every pair the prefilter (cell.planning.prefilter) leaves meets them, and
    a launch asked for last would be waited for whole. On one thread only the patches of the
    features met are made, each when verified."""
    if not tasks:
        return []
    task = tasks[0]
    scenes = [replace(x.scene, T_cell_cam=shot.T_cell_cam) for x in lent]
    laying = laid(tasks, lent, shot) if dense is None else dense
    if laying is not None:
        patches, launches = certificate.lit(task, task.part.material.scaled(1.0), shot, [d.result() for d in laying],
                                            beside=True)
    scene, bounds = stacked(lent, shot.T_cell_cam)
    shared = evaluate.SharedLaunches(evaluate.gray_inputs(task, scene, task.part.material.scaled(1.0)),
                                     [end - start for start, end in bounds])
    whole = evaluate.build_problem(task, scene, None, focus_m=shot.exposure.focus_m,
                                   gray=evaluate.Rows(shared, 0, len(scene.points)))
    sampled = [on_samples(t, x, s, shot, shared.rows(k), whole) for k, (t, x, s) in enumerate(zip(tasks, lent, scenes))]
    met = [k for k, s in enumerate(sampled) if all(r.met for r in s.values)]
    problems = [sampled[k].problem for k in met]
    if laying is not None:
        found = certificate.verdicts(problems, shot, patches, launches, met)
    else:
        found = certificate.verify_all(problems, shot, [in_background(certificate.dense_scene, tasks[k], scenes[k])
                                                        for k in met])
    verified = dict(zip(met, found))
    return [covered(t, s, verified[k][0] if k in verified else None) for k, (t, s) in enumerate(zip(tasks, sampled))]


def judge(task: Task, lent: Lent, shot: Shot) -> Coverage:
    """Coverage of `shot` (cell.planning.plan.Shot) on the one-feature `task`, whose own plan lent what
    does not depend on the camera (Lent): every requirement on its samples, then, where they
    all hold, the certificate on its dense patch."""
    return judge_all([task], [lent], shot)[0]


class Sampled(NamedTuple):
    """A shot judged on a feature's samples (on_samples): its Problem, requirement values, the
    samples' gray, each light's share and the defects found."""

    problem: evaluate.Problem
    values: tuple[RequirementValue, ...]
    gray: np.ndarray
    shares: tuple[LightSetting, ...]
    found: tuple[DefectCnr, ...]


def on_samples(task: Task, lent: Lent, scene: Scene, shot: Shot, shared: Rows, whole: evaluate.Problem) -> Sampled:
    """`shot` judged on the samples of the one-feature `task` (with its Lent), seen from the shot's
    camera (`scene`: the Lent's samples, its T_cell_cam the shot's), their gray kernel `shared`,
    its rows of a launch shared with other features, whose samples `whole` holds (judge_all:
    what_whole_gives)."""
    maps = build_maps(task, scene, lent.settings, visible=lent.visible)
    problem = evaluate.build_problem(task, scene, maps, focus_m=shot.exposure.focus_m, gray=shared,
                                     seen=cast(np.ndarray, whole.camera_seen)[shared.start:shared.end])
    what_whole_gives(problem, whole, shared, shot)
    e = shot.exposure
    c = evaluate.at_exposure(problem, shot.lamp_position, e.shutter_s, e.f_number, joints=shot.joints,
                             drive=shot.drive)
    if task.lights:         # the drive program's shutter, as one_shot.lighting judges it: not one centring this feature
        c = replace(c, t_need=np.array([e.shutter_s * (problem.kappa_open / e.f_number) ** 2]))
    values = requirements.judged(problem, c, requirements.ln_values(problem, c))
    gray = np.minimum(c.gray[0], 2.0 ** task.camera.sensor.bit_depth - 1)
    found = defects.judge(problem, c) if task.feature.defects else ()
    return Sampled(problem, values, gray, light_settings(problem, c), found)


def what_whole_gives(problem: evaluate.Problem, whole: evaluate.Problem, rows: Rows, shot: Shot) -> None:
    """Give `problem` (a feature's samples, their `rows` of `whole`'s: a Problem of the samples
    of every feature the shot is judged on, in one array) its rows of what `whole` finds for all
    at once, each sample's row its own: the view angles and pixel footprints
    (requirements.problem_view_angles, footprints), the camera body's and the arm's shadows of
    the shot's lamp and the poses its tolerance moves it to (evaluate.spot_blocked: at_exposure's
    lamps) and the samples the lamp's housing and links hide from the camera
    (requirements.lamp_hides: camera_view's); their prefilters only skip bodies and lamps that
    can meet none of the rays (the samples' sphere, here of every feature's), so each row is the
    one the feature's own Problem finds (whose camera_seen is its rows of whole's as well:
    evaluate.build_problem's `seen`). One call each for the shot, not one per feature."""
    a, b = rows.start, rows.end
    problem.given("view_angles", requirements.problem_view_angles(whole)[a:b])
    problem.given("footprints", requirements.footprints(whole)[a:b])
    lamp = np.asarray(shot.lamp_position, float).reshape(1, 3)
    lamps = lamp if shot.joints is None else np.vstack([lamp, evaluate.moved_positions(problem, shot.joints)])
    problem.keep_at_lamps("blocked", lamps, evaluate.spot_blocked(whole, lamps)[:, a:b])
    problem.keep_at_lamps("hides", lamp, requirements.lamp_hides(whole, lamp)[:, a:b])


def covered(task: Task, s: Sampled, verification: Verification | None) -> Coverage:
    """The Coverage of a shot judged on the samples (`s`) and, where they meet every requirement,
    on the dense patch (`verification`)."""
    if verification is None:
        return Coverage(task.feature.name, False, s.gray, s.values, lights=s.shares, defects=s.found)
    return Coverage(task.feature.name, verification.holds, s.gray, certificate.worse_of(s.values, verification),
                    verification, s.shares, defects.worse_of(s.found, verification.defects))
