"""Planning a task with several features: each feature's own shot by the one-shot planner (its
camera by the task's camera rule around its centre), every shot judged on every feature (the
coverage matrix, cell.planning.coverage), and the fewest shots covering every coverable feature by
integer programming (cell.planning.set_cover), ties broken by travel. A feature no shot covers is named
with the requirement that binds in its own plan: the plan is partial (not feasible), never
silently short of a feature."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from cell.collision.scene import CollisionScene, reaching_joints
from cell.core.progress import Progress, Stage
from cell.planning import coverage, joint, one_shot, prefilter, regions
from cell.planning.set_cover import fewest_shots
from cell.planning.parallel import SERIAL
from cell.planning.plan import FeatureVerdict, Plan, PlannerSettings, Search
from cell.planning.scene import build_scene
from cell.planning.parallel import Pool

if TYPE_CHECKING:
    from concurrent.futures import Future

    from cell.physics.costs import RequirementValue
    from cell.planning.coverage import Lent
    from cell.planning.joint import Joint
    from cell.planning.plan import Coverage, Shot
    from cell.planning.scene import Scene
    from cell.planning.viewpoints import Viewpoints
    from cell.task.types import Task


# a candidate shot judged on every feature (None at its own), the judging's time [s] and the shot
# with drives re-solved over the features it may cover where that covers more (cell.planning.joint)
Column = tuple[list["Coverage | None"], float, "Joint | None"]

def travel(shots: Sequence[Shot]) -> np.ndarray:
    """(S,) travel of each candidate shot [m]: its camera's distance from the candidates' mean
    camera position plus its lamp's from their mean lamp position. A linear stand-in for the
    arm's and the lamp's travel between the chosen shots (a tour's length is not linear in the
    choice): of equally few shots, those nearer the middle lie nearer each other."""
    cameras = np.array([s.camera_position for s in shots])
    lamps = np.array([s.lamp_position for s in shots])
    return (np.linalg.norm(cameras - cameras.mean(axis=0), axis=1)
            + np.linalg.norm(lamps - lamps.mean(axis=0), axis=1))


def own_plan(task: Task, settings: PlannerSettings, T_cell_cam: np.ndarray | None, arm_joints: np.ndarray | None,
             header: str, say: Callable[[str], None], visible: np.ndarray | None = None) -> Plan:
    """A job: the one-shot plan of a one-feature task, its camera at T_cell_cam (a planned
    viewpoint's, reached by `arm_joints`, and `visible` its samples' visibility map, found by
    the viewpoints) or by the task's rule (None); with settings.collisions its lamp searched
    among the poses clear of the cell's bodies (one_shot.plan) and its shot's clearance judged
    (cleared)."""
    if header:
        say(header)
    p = one_shot.plan(task, settings, progress=say, T_cell_cam=T_cell_cam, visible=visible, arm_joints=arm_joints)
    return cleared(task, p) if settings.collisions else p


def cleared(task: Task, p: Plan) -> Plan:
    """A one-shot plan with its shot's Clearance (cell.collision): the arm at the shot's joints
    (the fixed camera rule's: the inverse kinematics nearest the home joints (ur5e.HOME_JOINTS); none where the arm does
    not reach, which the run refuses anyway), the camera body and the lamp. A shot closer than
    the padding makes the plan infeasible, the two bodies named: `collision` binding where the
    optics held (so a `collision` binding says the lighting and the camera met every requirement
    and the bodies alone refuse the shot); where the optics failed first, their binding stays the
    cause and the collision follows in the hint."""
    shot = p.shot
    joints = reaching_joints(task.frames, shot.T_cell_cam, shot.arm_joints)
    clearance = CollisionScene.of(task).clearance(shot.T_cell_cam, joints, shot.lamp_position)
    p = replace(p, shots=(replace(shot, clearance=clearance),))
    if clearance.ok:
        return p
    if not p.feasible:
        return replace(p, hint=f"{p.hint}; the shot also collides: {clearance.reason()}")
    return replace(p, feasible=False, binding="collision", miss=float("inf"), hint=clearance.reason())


def uncovered_verdict(name: str, candidates: Sequence[Plan], judged: Sequence[Coverage], own: Sequence[bool],
                      lent: Plan) -> FeatureVerdict:
    """The FeatureVerdict of a feature no shot covers, its true cause first: where candidate shots
    light and see it as required (their coverage of it, or its own plan's `collision` binding:
    cleared()) and each of them collides, `collision` with the first such shot's bodies (its own
    first); else the requirement that binds in its own first plan (`lent`) and its hint."""
    optical = [(not mine, p.shot.clearance) for p, c, mine in zip(candidates, judged, own)
               if c.covered or mine and p.binding == "collision"]
    refused = [clearance for _, clearance in sorted(optical, key=lambda o: o[0])      # its own shot first
               if clearance is not None and not clearance.ok]
    if not refused:
        return FeatureVerdict(name, None, lent.binding, lent.hint)
    every = ("the one candidate shot that lights and sees it as required collides" if len(refused) == 1 else
             f"each of the {len(refused)} candidate shots that light and see it as required collides")
    return FeatureVerdict(name, None, "collision", f"{refused[0].reason()}; {every}")


def viewpoints_of(task: Task, settings: PlannerSettings, say: Callable[[str], None]) -> Viewpoints:
    """The Viewpoints of a one-feature task (cell.planning.viewpoints), with their own time."""
    from cell.planning.viewpoints import plan_viewpoints
    start = time.perf_counter()
    grid = regions.SphereGrid(np.radians(settings.grid_step_deg))
    scene = build_scene(task, settings.samples)
    v = plan_viewpoints(task, scene, one_shot.visibility_map(scene, grid), grid, settings.collisions)
    return replace(v, time_s=time.perf_counter() - start)


def kept_line(name: str, views: Viewpoints) -> str:
    """What a feature's viewpoint stage kept and why it pruned the rest, in one line."""
    return (f"feature {name}: {len(views.kept)} of {views.poses} camera poses kept (pruned: "
            + ", ".join(f"{n} {s.replace('_', ' ')}" for s, n in views.pruned.items() if n) + ")")


def at_viewpoint(task: Task, settings: PlannerSettings, views: Viewpoints, k: int,
                 say: Callable[[str], None]) -> Plan:
    """A job: the one-shot plan of a one-feature task at its k-th kept viewpoint."""
    vp = views.kept[k]
    return own_plan(task, settings, vp.T_cell_cam, vp.arm_joints, f"feature {task.feature.name}, viewpoint {k}: "
                    f"camera at {np.round(vp.T_cell_cam[:3, 3], 3).tolist()} m", say, views.visible)


def views_and_first_plan(task: Task, settings: PlannerSettings,
                         say: Callable[[str], None]) -> tuple[Viewpoints, Plan]:
    """A job: (the Viewpoints of a one-feature task, its plan at the first kept one, or by the
    fixed rule when none is kept: the plan that only lends). One job, not two: a job costs the
    cluster's scheduler some 10 ms of the cores the plans need."""
    views = viewpoints_of(task, settings, say)
    if not views.kept:
        return views, own_plan(task, settings, None, None, "", say)
    return views, at_viewpoint(task, settings, views, 0, say)


@dataclass(frozen=True)
class ColumnStart:
    """What of a column's judging (judge_column) is begun before the rest: the requirements the
    shot misses for sure on each feature (cell.planning.prefilter.missed: empty where the full
    judge decides), the features left to judge in full, their dense patches being laid
    (coverage.laid; None on one thread) and the time [s] it took the caller."""

    missed: list[tuple[RequirementValue, ...]]
    left: list[int]
    dense: list[Future[Scene]] | None
    spent_s: float


def begin_column(tasks: Sequence[Task], f: int, shot: Shot, lent: Sequence[Lent]) -> ColumnStart:
    """judge_column's beginning (ColumnStart): the prefilter, and the dense patches of the
    features it leaves laid on the thread beside (coverage.laid). A serial pool begins the next
    column with it while it judges this one (parallel.SerialJobs' `ahead`): that column's
    patches are laid while this one's samples are judged, not waited for at its certificates."""
    start = time.perf_counter()
    missed = prefilter.missed(tasks, lent, shot, f)
    left = [g for g in range(len(tasks)) if g != f and not missed[g]]
    dense = coverage.laid([tasks[g] for g in left], [lent[g] for g in left], shot)
    return ColumnStart(missed, left, dense, time.perf_counter() - start)


def judge_column(tasks: Sequence[Task], f: int, shot: Shot, lent: Sequence[Lent],
                 say: Callable[[str], None], begun: ColumnStart | None = None) -> Column:
    """A job: (the Coverage of feature f's candidate `shot` on every other feature, whose own
    first plan lent its samples and maps (`lent`, coverage.Lent; None at f: its plan's verdict
    stands), its own time [s] (its beginning's included, `begun` where begun before:
    begin_column), the shot's Joint: its drives re-solved over every feature it may cover where
    that covers more, else None, cell.planning.joint). Only the features the prefilter
    (cell.planning.prefilter) leaves are judged in full, their samples' gray kernel launched once
    for all (coverage.judge_all): a part's many features are mostly out of one shot's view."""
    start = time.perf_counter()
    if begun is None:
        begun = begin_column(tasks, f, shot, lent)
    else:
        start -= begun.spent_s
    left = begun.left
    judged = dict(zip(left, coverage.judge_all([tasks[g] for g in left], [lent[g] for g in left], shot,
                                               begun.dense)))
    column = [None if g == f else judged[g] if g in judged else coverage.rejected(t, begun.missed[g])
              for g, t in enumerate(tasks)]
    return column, time.perf_counter() - start, joint.resolve(tasks, lent, f, shot, column)


def candidate_plans(tasks: Sequence[Task], settings: PlannerSettings, progress: Progress, pool: Pool = SERIAL
                    ) -> tuple[list[tuple[int, Plan]], list[Viewpoints] | None, list[Plan], list[Column]]:
    """[(feature index, its Plan)] of every candidate shot, the Viewpoints of each feature (None:
    the fixed camera rule, one candidate per feature), each feature's plan that lends its samples
    and maps to the judge (its first), and the coverage of each candidate on every other feature
    (judge_column). A planned feature gets a plan per kept viewpoint (cell.planning.viewpoints); one with
    none gets its fixed-rule plan, which only lends (not a candidate).
    Every step is a job of `pool` (cell.planning.parallel), handed on as the results it needs complete:
    each feature's viewpoints and first plan ahead of the rest (the judge needs every first
    plan), its other lamp searches once its viewpoints are known, a shot's judging once its plan
    and every first plan are. Progress: a stage each for the viewpoints (when planned), the lamp
    searches (each with its certificate) and the judging, their totals growing as jobs are handed
    on; a feature's kept viewpoints a line, a job's own lines only the live bars' detail."""
    fixed = tasks[0].camera.viewpoint.mode == "fixed"
    views: list[Viewpoints | None] = [None] * len(tasks)
    plans: dict[tuple[int, int], Plan] = {}
    columns: dict[tuple[int, int], Column | None] = {}
    with ExitStack() as stages:
        viewing = None if fixed else stages.enter_context(progress.stage("viewpoints", len(tasks)))
        searching = stages.enter_context(progress.stage("lamp searches", len(tasks)))
        judging = stages.enter_context(progress.stage("judging", 0))
        jobs = pool.jobs(searching.note)

        def settled():
            """Close each stage whose jobs are all done and whose total can grow no more."""
            if fixed or all(v is not None for v in views):
                if viewing is not None:
                    viewing.close()
                if searching.done == searching.total:
                    searching.close()
                    if judging.done == judging.total:
                        judging.close()

        def planned(f, k, plan):
            """Keep a plan; once every feature's first is in, judge each candidate not yet judged."""
            plans[f, k] = plan
            searching.advance()
            firsts = [plans.get((g, 0)) for g in range(len(tasks))]
            if any(p is None for p in firsts):
                return
            lent = [coverage.Lent.of(p) for p in firsts]
            for (g, j), p in plans.items():
                if (g, j) not in columns and (views[g] is None or j < len(views[g].kept)):
                    columns[g, j] = None
                    judging.grow(1)
                    jobs.submit(("judge", g, j), judge_column, tasks, g, p.shot, lent, ahead=begin_column)

        for f, t in enumerate(tasks):
            if fixed:
                jobs.submit(("plan", f, 0), own_plan, t, settings, None, None, f"feature {t.feature.name}:",
                            first=True)
            else:
                jobs.submit(("views", f, 0), views_and_first_plan, t, settings, first=True)
        for (kind, f, k), result in jobs:
            if kind == "views":
                views[f], first = view, _ = result
                progress.say(kept_line(tasks[f].feature.name, view))
                cast("Stage", viewing).advance()
                searching.grow(len(view.kept) - 1)
                for j in range(1, len(view.kept)):
                    jobs.submit(("plan", f, j), at_viewpoint, tasks[f], settings, view, j)
                planned(f, 0, first)
            elif kind == "plan":
                planned(f, k, result)
            else:
                judging.advance()
                columns[f, k] = result
            settled()
    whose = sorted(columns)             # (feature, k) of each candidate, in the serial order
    # every job is done: each feature's viewpoints and each candidate's column are in
    done_views, done_columns = cast("list[Viewpoints]", views), cast(dict[tuple[int, int], Column], columns)
    return ([(f, plans[f, k]) for f, k in whose], None if fixed else done_views,
            [plans[f, 0] for f in range(len(tasks))], [done_columns[c] for c in whose])


def plan_features(task: Task, settings: PlannerSettings = PlannerSettings(),
                  progress: Progress | None = None, pool: Pool = SERIAL) -> Plan:
    """The Plan of a task's features (one or more): the chosen shots, each with the features it
    covers (Shot.covers), and per feature the shot covering it (Plan.features). Candidate shots:
    each feature's own by the task's camera rule, or (camera.viewpoint: planned) one per kept
    viewpoint of each feature. The plans and the coverage matrix's columns are jobs of `pool`
    (cell.planning.parallel: here, or on a Dask cluster), each result placed by its job's key: the same
    plan either way. progress: its stages' bars or lines and the cover's line (none when None)."""
    progress = progress or Progress.silent()
    t0 = time.perf_counter()
    tasks = [task.with_feature(i) for i in range(len(task.features))]
    cands, views, lend, columns = candidate_plans(tasks, settings, progress, pool)
    t_jobs = time.perf_counter()
    # a candidate whose drives solved over several features cover more: that shot, its column
    cands = [(g, p if j is None else p.as_chosen(j.shot, j.own, j.features)) for (g, p), (_, _, j) in zip(cands, columns)]
    columns = [(c if j is None else j.column, t, j) for c, t, j in columns]
    shots = [p.shot for _, p in cands]
    # a column is None only at its own feature, whose coverage is its plan's
    judged = [[coverage.of_plan(t, p) if g == f else cast("Coverage", column[f])
               for (g, p), (column, _, _) in zip(cands, columns)] for f, t in enumerate(tasks)]
    covers = np.array([[c.covered for c in row] for row in judged]).reshape(len(tasks), len(shots))
    colliding = np.array([s.clearance is not None and not s.clearance.ok for s in shots], bool)
    covers[:, colliding] = False                # a shot too close to collide covers nothing
    t_judge = time.perf_counter()
    distance = travel(shots) if shots else np.zeros(0)
    cover = fewest_shots(covers, distance)
    index = {s: k for k, s in enumerate(cover.chosen)}
    verdicts = []
    for f, t in enumerate(tasks):
        by = [s for s in cover.chosen if covers[f, s]]
        if not by:
            if views is not None and not views[f].kept:
                verdicts.append(FeatureVerdict(t.feature.name, None, "viewpoint", views[f].why_none()))
            else:
                verdicts.append(uncovered_verdict(t.feature.name, [p for _, p in cands], [c[f] for c in judged],
                                                  [g == f for g, _ in cands], lend[f]))
            continue
        own = [s for s in by if cands[s][0] == f]                           # its own shot if chosen
        best = own[0] if own else min(by, key=lambda s: judged[f][s].worst)
        verdicts.append(FeatureVerdict(t.feature.name, index[best]))
    chosen = tuple(replace(shots[s], covers=tuple(judged[f][s] for f in range(len(tasks)) if covers[f, s]))
                   for s in cover.chosen)
    progress.say(f"cover: {len(chosen)} of {len(shots)} shots cover {len(cover.coverable)} of {len(tasks)} features")
    uncovered = [v for v in verdicts if v.covered_by is None]
    if uncovered:
        v = uncovered[0]
        f = [t.feature.name for t in tasks].index(v.name)
        miss = lend[f].miss if v.binding != "viewpoint" else float("inf")
        binding, hint = v.binding, f"feature '{v.name}' is covered by no shot: {v.hint}"
    else:
        worst = max((r for shot in chosen for c in shot.covers for r in c.requirements), key=lambda r: r.value)
        binding, miss, hint = worst.name, worst.value - 1.0, ""
    timing = {"candidates": t_jobs - t0, "judge": sum(t for _, t, _ in columns), "cover": time.perf_counter() - t_judge,
              "total": time.perf_counter() - t0}
    if views is not None:                  # of "candidates" (as "judge"): the view spheres, before any lamp
        timing["viewpoints"] = sum(v.time_s for v in views)
    plans = tuple(p for _, p in cands)
    search = Search(candidates=sum(p.search.candidates for p in plans), starts=sum(p.search.starts for p in plans),
                    refinements=tuple(r for p in plans for r in p.search.refinements))
    notes = tuple(f"{tasks[f].feature.name}: {n}" for f, p in cands for n in p.notes)
    record = {"candidate_shots": len(shots), "covers": covers.tolist(), "travel_m": distance.tolist(),
              "chosen": list(cover.chosen), "rejected": {"collision": int(colliding.sum())}}
    if views is not None:
        record |= {"candidate_features": [f for f, _ in cands],
                   "viewpoints": [{"feature": t.feature.name, **v.to_json()} for t, v in zip(tasks, views)]}
    return Plan(task_name=task.name, feasible=not uncovered, binding=binding, miss=miss, objective=cover.objective,
                hint=hint, shots=chosen, maps=None, settings=settings, scene=None, search=search,
                timing_s=timing, notes=notes, features=tuple(verdicts), plans=plans, cover=record)


def cover_of(plan: Plan) -> dict[str, Any]:
    """The set cover's numbers of a multi-feature plan (cell.planning.whole_part; a one-feature
    plan has none)."""
    if plan.cover is None:
        raise ValueError("a one-feature plan has no cover: it is its own shot")
    return plan.cover


def candidate_features(plan: Plan) -> list[int]:
    """The feature whose own candidate each of plan.plans is (cell.planning.whole_part: one per feature
    with the fixed camera rule, one per kept viewpoint of each feature when planned)."""
    return cover_of(plan).get("candidate_features") or list(range(len(plan.plans)))


def assigned(plan: Plan, s: int) -> tuple[str, ...]:
    """The names of the features plan.shots[s] is the shot of (Plan.features' covered_by), in the
    task's order: each feature is measured once, in its own shot, though another may cover it too.
    A fewest-shots cover gives every chosen shot at least one (else it would not be needed)."""
    return tuple(f.name for f in plan.features if f.covered_by == s)


def feature_plan(plan: Plan, s: int, f: int) -> Plan:
    """The one-shot Plan of feature f at plan.shots[s], as the one-feature loop works on it: the
    shot's own candidate plan when it was planned for f; else the plan whose samples coverage
    judged f on (f's first candidate), its camera moved to the shot's, with the gray coverage
    predicts there (cell.planning.coverage.judge), each light's share of it (where the task has
    lights: the basis captures' prediction on f's samples, cell.run.channels) and its verdict."""
    shot, k = plan.shots[s], cover_of(plan)["chosen"][s]
    owners, name = candidate_features(plan), plan.features[f].name
    if owners[k] == f:
        return plan.plans[k]
    covered = next(c for c in shot.covers if c.feature == name)
    lend = plan.plans[owners.index(f)]
    scene = replace(lend.planned_scene, T_cell_cam=shot.T_cell_cam)
    if len(covered.gray) != len(scene.points):
        raise ValueError(f"feature {name}: {len(covered.gray)} predicted grays for {len(scene.points)} samples")
    own = replace(shot, gray=covered.gray, requirements=covered.requirements, covers=(),
                  lights=covered.lights or shot.lights)
    return replace(lend, feasible=covered.covered, shots=(own,), scene=scene, verification=covered.verification)
