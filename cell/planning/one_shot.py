"""Illumination and sensor planning (sec. 5): lamp pose on the rig, shutter, f-number and focus.

Global search over the rig's reachable candidates with the bulk Warp kernels, then Nelder-Mead
refinement from several starts (the problem is not convex, physics notes sec. 5). Shutter and
f-number follow the near closed form G ~ t / kappa^2 for every lamp pose (sec. 5.4, in
cell.planning.evaluate). Feasibility is max_i f_i <= 1 over the requirement values (erratum eq. 25,
cell.planning.requirements). The result is a cell.planning.plan.Plan of plain values: it pickles.
"""

from __future__ import annotations

import pickle
import time
from collections.abc import Callable, Generator, Iterator
from itertools import accumulate
from dataclasses import replace
from typing import TYPE_CHECKING, NamedTuple, cast

import numpy as np
from numpy.typing import ArrayLike

from cell.planning import (certificate, defects, drives, evaluate, lights, lockstep, nelder_mead, regions,
                           requirements, viewpoints)
from cell.core import geometry
from cell.devices import rig
from cell.physics import brdf, depth_of_field as dof
from cell.physics.costs import RequirementValue
from cell.planning.plan import (Exposure, LightSetting, Maps, Plan, PlannerSettings, Refinement, Search, Shot,
                                Verification)

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.types import LampRig, Task

Allowed = Callable[[np.ndarray], np.ndarray]     # (K, 3) lamp joints -> (K,) where the lamp may stand (ClearOfCell)


def visibility_map(scene: Scene, grid: regions.SphereGrid, first: np.ndarray | None = None,
                   count: int = 0) -> np.ndarray:
    """(E, A) directions of the feature frame every sample sees (Warp ray casting, sec. 2.2).
    `first`: the map of the scene's first `count` samples, found before (a feature's own samples,
    the certificate's worst points added after them): only the rest are cast and the two maps
    combined, the same map (a direction every sample sees; each sample's rays its own)."""
    from kernels.visibility import visible_from_all
    if first is None:
        count = 0
    elif count == len(scene.points):
        return first
    found = visible_from_all(scene.shadow_mesh, scene.points[count:], scene.normals[count:], scene.frame,
                             grid.azimuth, grid.elevation)
    return found if first is None else first & found


def build_maps(task: Task, scene: Scene, settings: PlannerSettings, visible: np.ndarray | None = None) -> Maps:
    """Visibility (all samples), dominant-term (where visible) and region distance maps (sec. 2.2, 5.2).
    The visibility map (given: a plan's own, judging another camera pose on its samples) does not
    depend on the camera; the others do (the view direction is in the BRDF). The region distance
    is found where it is read (regions.RegionDistance); the BRDF map only a picture reads
    (cell.report.pictures draws it)."""
    grid = regions.SphereGrid(np.radians(settings.grid_step_deg))
    if visible is None:
        visible = visibility_map(scene, grid)
    view = geometry.unit(scene.camera_position - scene.center)
    dominant = regions.dominant_term_map(grid, scene.frame, scene.normal, view, task.part.material, where=visible)
    wanted = regions.wanted_region(dominant, visible, task.requirements.reflection)
    empty = np.zeros(0)
    return Maps(grid, visible, dominant, wanted, regions.RegionDistance(grid, wanted), empty, empty, empty)


def candidate_grid(lamp_rig: LampRig, settings: PlannerSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pan x tilt x radius grid over the rig's ranges (pan wraps: no duplicate at +-180)."""
    p0, p1 = lamp_rig.pan_range_rad
    full_turn = p1 - p0 >= 2 * np.pi - 1e-9
    n_pan = max(1, int(round((p1 - p0) / np.radians(settings.pan_step_deg)))) + (0 if full_turn else 1)
    pan = np.linspace(p0, p1, n_pan, endpoint=not full_turn)
    t0, t1 = lamp_rig.tilt_range_rad
    tilt = np.linspace(t0, t1, max(2, int(round((t1 - t0) / np.radians(settings.tilt_step_deg))) + 1))
    radius = np.linspace(*lamp_rig.radius_range_m, max(1, settings.radius_steps))
    P, T, R = np.meshgrid(pan, tilt, radius, indexing="ij")
    return P.ravel(), T.ravel(), R.ravel()


def pick_starts(pan: np.ndarray, tilt: np.ndarray, objective_values: np.ndarray, count: int,
                min_separation: float, clear: Callable[[np.ndarray], np.ndarray] | None = None) -> list[int]:
    """Best candidates that are at least `min_separation` apart on the sphere (diverse starts);
    with `clear` (grid indices -> whether the lamp there keeps clear of the cell's bodies) those
    it passes first (clear_first)."""
    order = np.argsort(objective_values)
    chosen: list[int] = []
    dirs = geometry.direction_from_angles(pan, tilt)
    for k in order if clear is None else clear_first(order, clear):
        if all(np.arccos(np.clip(dirs[k] @ dirs[j], -1, 1)) >= min_separation for j in chosen):
            chosen.append(k)
        if len(chosen) == count:
            break
    return chosen


CLEAR_BATCH = 32            # clear_first's first batch of candidates asked at once (then twice as many)


def clear_first(order: np.ndarray, clear: Callable[[np.ndarray], np.ndarray]) -> Iterator[int]:
    """The candidates of `order` that `clear` passes, in that order, then the others in it: each
    asked as the iteration reaches it, in batches growing twofold (the starts are a few of the
    best, so mostly only the first batch is asked)."""
    refused: list[int] = []
    start, size = 0, CLEAR_BATCH
    while start < len(order):
        batch = order[start:start + size]
        for k, ok in zip(batch.tolist(), clear(batch).tolist()):
            if ok:
                yield k
            else:
                refused.append(k)
        start, size = start + size, 2 * size
    yield from refused


CERTIFY_ROUNDS = 3          # searches again with the certificate's worst points added
UNLIT_OBJECTIVE = 1e300     # the objective of a pose no exposure can make work (it is inf), finite


def score(problem: evaluate.Problem, values: dict[str, np.ndarray]) -> np.ndarray:
    """The search's objective (lower is better): requirements.objective, eq. (22)'s smooth max of
    the ln f_i; with `gray_band: any`, where every requirement is met (each ln f_i <= 0), the worst
    defect's ln(min_cnr / CNR) instead (<= 0, below every pose that misses one, whose smooth max
    exceeds its largest ln f_i > 0): among the poses that meet every requirement the plan takes
    the largest worst CNR."""
    objective = requirements.objective(values)
    if not problem.task.requirements.gray_any:
        return objective
    return np.where(requirements.missed(values), objective, values["defect_cnr"])


REFINE_EVALUATIONS = 90
# scipy's words for the solver's verdict (its Nelder-Mead's messages), which plan.json's refinements keep
CONVERGED = "Optimization terminated successfully."
OUT_OF_EVALUATIONS = "Maximum number of function evaluations has been exceeded."


def refinement(start: ArrayLike, lamp_rig: LampRig) -> Generator[np.ndarray, np.ndarray,
                                                                  tuple[np.ndarray, Refinement]]:
    """Nelder-Mead (cell.planning.nelder_mead: scipy's, step for step) over (pan, tilt, radius)
    in grid-step units from `start`, clipped to the rig's ranges, as a generator: yields (K, 3)
    joints whose objectives (pose_objectives') it needs and is sent their K values, each clipped
    pose once (steps beyond a range's end land on one pose); each step's points are asked
    together, those it may need ahead of its choice (nelder_mead.batches), so a step costs one
    round of the lockstep, not one or two. Returns (joints, Refinement with the solver's verdict
    and evaluation count)."""
    lo = np.array([lamp_rig.pan_range_rad[0], lamp_rig.tilt_range_rad[0], lamp_rig.radius_range_m[0]])
    hi = np.array([lamp_rig.pan_range_rad[1], lamp_rig.tilt_range_rad[1], lamp_rig.radius_range_m[1]])
    scale = np.array([np.radians(5.0), np.radians(5.0), 0.05])

    origin = np.asarray(start, float)

    def clipped(z):         # np.clip's values, without its checks; (K, 3) steps at once, row by row the same
        return np.minimum(np.maximum(origin + z * scale, lo), hi)

    seen: dict[bytes, float] = {}       # clipped joints -> objective
    search = nelder_mead.batches(np.vstack([np.zeros(3), np.eye(3)]), 0.02, 1e-4, REFINE_EVALUATIONS)
    try:
        steps = next(search)
        while True:
            poses = clipped(steps)
            keys = [x.tobytes() for x in poses]
            new = {key: x for key, x in zip(keys, poses) if key not in seen}
            if new:
                values = yield np.array(list(new.values()))
                seen.update(zip(new, (float(v) for v in values)))
            steps = search.send([seen[key] for key in keys])
    except StopIteration as stop:
        z, fun, nfev = stop.value
    converged = nfev < REFINE_EVALUATIONS
    return clipped(z), Refinement(converged, nfev, CONVERGED if converged else OUT_OF_EVALUATIONS, float(fun))


def evaluated(problem: evaluate.Problem, joints: list[np.ndarray]
              ) -> tuple[np.ndarray, evaluate.Candidates, dict[str, np.ndarray], list[tuple[evaluate.Candidates, drives.Drives]]]:
    """The search's final candidates: (joints stacked (K, 3), their Candidates with the lamp moved
    by its tolerance, their requirement values, and with the task's other lights each one's
    lighting: the drives solved for it)."""
    stack = np.array(joints)
    lit = [lighting(problem, x) for x in stack] if problem.task.lights else []
    if lit:
        final = evaluate.stacked([c for c, _ in lit])
    else:
        final = evaluate.candidates(problem, stack[:, 0], stack[:, 1], stack[:, 2])
    return stack, final, requirements.ln_values(problem, final), lit


def pose_objectives(problem: evaluate.Problem, joints: ArrayLike) -> np.ndarray:
    """(K,) the search's objective (score: eq. 22, or the worst CNR with `gray_band: any`) of K
    lamp poses (K, 3) (pan, tilt, radius), the lamp moved by its tolerance; an unlit pose's (inf) capped at UNLIT_OBJECTIVE: Nelder-Mead compares
    differences, and inf - inf is NaN. A pose's value reads its own row alone (the kernel's thread
    per lamp and sample, NumPy's reductions per row): the same however many are evaluated at once."""
    x = np.asarray(joints, float).reshape(-1, 3)
    c = evaluate.candidates(problem, x[:, 0], x[:, 1], x[:, 2])
    return np.minimum(score(problem, requirements.ln_values(problem, c)), UNLIT_OBJECTIVE)


def refine_all(problem: evaluate.Problem, starts: list[np.ndarray], lamp_rig: LampRig,
               allowed: Allowed | None = None) -> list[tuple[np.ndarray, Refinement]]:
    """The refinement from every start, the starts in lockstep (cell.planning.lockstep.drive):
    each round's objective evaluations of all starts in one evaluate.candidates call (one kernel
    launch, one pass of the requirements), the same results as one start at a time. A pose not
    `allowed` (ClearOfCell) counts as unlit (UNLIT_OBJECTIVE): the simplex moves away from it."""
    def batch(asked: list[tuple[int, np.ndarray]]) -> list[np.ndarray]:
        joints = np.concatenate([x for _, x in asked])
        values = pose_objectives(problem, joints)
        if allowed is not None:
            values = np.where(allowed(joints), values, UNLIT_OBJECTIVE)
        ends = list(accumulate(len(x) for _, x in asked))
        return [values[a:b] for a, b in zip([0] + ends, ends)]     # np.split's pieces, without its checks

    return lockstep.drive([refinement(x, lamp_rig) for x in starts], batch)


def plan(task: Task, settings: PlannerSettings = PlannerSettings(), albedo_scale: float = 1.0,
         progress: Callable[[str], None] | None = None, T_cell_cam: np.ndarray | None = None,
         visible: np.ndarray | None = None, arm_joints: ArrayLike | None = None) -> Plan:
    """Plan a task (the CLI, the closed loop and the benchmark all call this), its camera at
    T_cell_cam (a planned viewpoint's, the arm's joints reaching it `arm_joints`, the shot's) or
    by the task's camera rule, `visible` the visibility map of the feature's own samples
    (settings' count, on its grid) where it was found before (it does not depend on the camera:
    a feature's viewpoints share it): search, then certify the chosen shot (certified). With
    settings.collisions (the default) the search takes the best lamp pose clear of the cell's
    bodies (search, ClearOfCell), a note counting the poses it refused; where that plan is
    infeasible and a pose was refused, the search without the bodies gives the verdict: its
    shot, where it meets every requirement, is then refused by the shot's clearance check
    (whole_part.cleared: `collision`, the bodies alone refuse it), else its requirement is the
    cause."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    clear = ClearOfCell(task, arm_joints) if settings.collisions else None
    known = Searched() if clear is not None else None
    result = certified(task, settings, albedo_scale, say, T_cell_cam, visible, clear, known)
    if clear is not None and clear.refused:
        if result.feasible:
            result = replace(result, notes=result.notes + (clear.note(),))
        else:
            say("no lamp pose clear of the cell's bodies meets every requirement: the search without them")
            result = certified(task, settings, albedo_scale, say, T_cell_cam, visible, None, known)
    if arm_joints is not None:
        result = replace(result, shots=(replace(result.shot, arm_joints=tuple(float(q) for q in np.asarray(arm_joints))),))
    return replace(result, timing_s={**result.timing_s, "total": time.perf_counter() - t0})


def certified(task: Task, settings: PlannerSettings, albedo_scale: float, say: Callable[[str], None],
              T_cell_cam: np.ndarray | None, visible: np.ndarray | None, clear: ClearOfCell | None,
              known: Searched | None = None) -> Plan:
    """The search (its lamp among the poses `clear` passes; `known`: what the plan's searches found
    before, Searched), then the chosen shot certified on the
    dense patch (cell.planning.certificate); where the certificate fails, its worst points join
    the samples and the search runs again, at most CERTIFY_ROUNDS times. The plan is feasible
    when its samples and its certificate say so."""
    extra = np.zeros((0, 3))
    for rounds in range(CERTIFY_ROUNDS + 1):
        result, problem = search(task, settings, albedo_scale, extra, say, T_cell_cam, visible, clear, known)
        if not result.feasible:
            return result
        t = time.perf_counter()
        verification, worst = verified(problem, result.shot, extra, known)
        timing = {**result.timing_s, "verify": time.perf_counter() - t}
        say(f"certificate: {verification.points} points, gray {verification.gray_min:.1f}-"
            f"{verification.gray_max:.1f}: " + ("holds" if verification.holds else
                                                 ", ".join(r.name for r in verification.failing) + " missed"))
        if verification.holds or rounds == CERTIFY_ROUNDS:
            break
        extra = np.vstack([extra, worst])
    verification = replace(verification, rounds=rounds)
    judged = certificate.worse_of(result.shot.requirements, verification)
    shot = replace(result.shot, requirements=judged, defects=defects.worse_of(result.shot.defects, verification.defects))
    result = replace(result, shots=(shot,), verification=verification,
                     timing_s=timing)
    if verification.holds:
        return result
    cause = min(verification.failing, key=lambda r: requirements.CAUSES.index(r.name))
    return replace(result, feasible=False, binding=cause.name, miss=cause.value - 1.0, hint=cause.detail)


def search(task: Task, settings: PlannerSettings, albedo_scale: float, extra: np.ndarray,
           say: Callable[[str], None], T_cell_cam: np.ndarray | None = None,
           visible: np.ndarray | None = None, clear: ClearOfCell | None = None,
           known: Searched | None = None) -> tuple[Plan, evaluate.Problem]:
    """(Plan of the search over the rig on the task's samples plus `extra` points, its Problem;
    `visible`: the own samples' visibility map, found before, only the extra points' cast).
    With `clear` (ClearOfCell), the starts are the best grid poses it passes (pick_starts, asked
    only as far as the starts need); each refinement runs free (the lamp stands only at the pose
    chosen, never on a refinement's way) and the pose chosen is the best of the starts and the
    refinements' ends meeting every requirement that is clear, so where a refinement ends on a
    refused pose the next best clear one is taken. Where no clear one meets every requirement,
    the refinements that ended on a refused pose run again from their starts with the refused
    poses counted as unlit (refine_all's `allowed`: the simplex moves away from them); then the
    best clear pose meeting them, else the best meeting them (which whole_part.cleared refuses,
    its bodies named: the bodies alone refuse it), else the best clear one. Where it refuses no
    pose asked, the search is the one without the bodies, bit for bit. `known` (Searched): what
    the plan's searches found before with these extra points, taken, not found again."""
    timing: dict[str, float] = {}
    key = np.ascontiguousarray(extra, dtype=float).tobytes()
    found = None if known is None else known.grids.get(key)
    if found is None:
        found = global_search(task, settings, albedo_scale, extra, T_cell_cam, visible, timing)
        if known is not None:
            known.grids[key] = found
    scene, problem, (pan, tilt, radius), global_values = found
    maps = cast(Maps, problem.maps)
    obj = maps.candidate_objective
    say(f"maps: {maps.visible.mean():.0%} of directions visible, {maps.wanted.mean():.1%} give "
        f"{task.requirements.reflection} reflection")
    say(f"global search: {len(pan)} lamp poses x {len(scene.points)} samples")
    allowed = None if clear is None else clear.at(scene)
    lamp_rig = task.lamp.rig

    t = time.perf_counter()
    grid_clear = None if allowed is None else (lambda k: allowed(np.column_stack([pan[k], tilt[k], radius[k]])))
    starts = pick_starts(pan, tilt, obj, settings.starts, np.radians(2 * settings.pan_step_deg), grid_clear)
    poses = [np.array([pan[k], tilt[k], radius[k]]) for k in starts]
    refined = refined_from(problem, poses, lamp_rig, None if known is None else (known.refined, key)) \
        if settings.refine else []
    stack, final, final_values, lit = evaluated(problem, poses + [x for x, _ in refined])
    missed = requirements.missed(final_values)
    blocked = np.zeros(len(stack), bool) if allowed is None else ~allowed(stack)
    again = [poses[i] for i, ended in enumerate(blocked[len(poses):]) if ended]
    if allowed is not None and again and np.all(missed | blocked):      # no clear pose meets every requirement
        refined += refine_all(problem, again, lamp_rig, allowed)
        stack, final, final_values, lit = evaluated(problem, poses + [x for x, _ in refined])
        missed, blocked = requirements.missed(final_values), ~allowed(stack)
    rank = np.lexsort((score(problem, final_values), blocked, missed))
    best = int(rank[0])
    timing["refine"] = time.perf_counter() - t
    search = Search(candidates=len(pan), starts=len(poses), refinements=tuple(r for _, r in refined))
    shot = make_shot(problem, stack[best], final.pick(best), {k: v[best:best + 1] for k, v in final_values.items()})
    if task.feature.defects:
        maps = replace(maps, defect_cnr=defect_map(problem, final.pick(best), maps))
    verdict = requirements.verdict(shot.requirements, requirements.failing_everywhere(global_values))
    binding = next(r for r in shot.requirements if r.name == verdict.binding)
    return Plan(task_name=task.name, feasible=verdict.feasible, binding=verdict.binding, miss=verdict.miss,
                objective=verdict.objective, hint="" if verdict.feasible else hint(binding, lit[best][1] if lit else None),
                shots=(shot,),
                maps=maps, settings=settings, scene=scene, search=search, timing_s=timing,
                notes=notes(problem, shot),
                gray_any=task.requirements.gray_any), problem


class GlobalSearch(NamedTuple):
    """A search's samples and maps, its Problem (the maps with the global candidates and their
    objective), the candidates (pan, tilt, radius) and their requirement values (global_search)."""

    scene: Scene
    problem: evaluate.Problem
    candidates: tuple[np.ndarray, np.ndarray, np.ndarray]
    values: dict[str, np.ndarray]


def global_search(task: Task, settings: PlannerSettings, albedo_scale: float, extra: np.ndarray,
                  T_cell_cam: np.ndarray | None, visible: np.ndarray | None, timing: dict[str, float]) -> GlobalSearch:
    """search's first stages, which the cell's bodies do not enter: the scene of the task's samples
    plus `extra` points (the camera at T_cell_cam or by the task's rule), the maps (`visible`: the
    own samples' visibility map, found before, only the extra points' cast), the Problem and
    every grid candidate's requirement values and objective (the global search, sec. 5.3); each
    stage's time in `timing`."""
    from cell.planning.scene import build_scene
    t0 = time.perf_counter()
    scene = build_scene(task, settings.samples, extra, T_cell_cam)
    if T_cell_cam is None and task.camera.viewpoint.mode == "fixed":
        viewpoints.require_reach(task, scene)                       # the arm takes the camera there, or exit 1
    timing["scene"] = time.perf_counter() - t0

    t = time.perf_counter()
    if visible is not None:
        grid = regions.SphereGrid(np.radians(settings.grid_step_deg))
        visible = visibility_map(scene, grid, visible, len(scene.points) - len(extra))
    maps = build_maps(task, scene, settings, visible=visible)
    timing["maps"] = time.perf_counter() - t

    t = time.perf_counter()
    problem = evaluate.build_problem(task, scene, maps, albedo_scale)
    pan, tilt, radius = candidate_grid(task.lamp.rig, settings)
    values = requirements.ln_values(problem, evaluate.candidates(problem, pan, tilt, radius, tolerance=False))
    maps = replace(maps, candidate_pan=pan, candidate_tilt=tilt, candidate_objective=score(problem, values))
    problem = replace(problem, maps=maps)
    timing["global_search"] = time.perf_counter() - t
    return GlobalSearch(scene, problem, (pan, tilt, radius), values)


Refined = dict[tuple[bytes, bytes], tuple[np.ndarray, Refinement]]


def refined_from(problem: evaluate.Problem, starts: list[np.ndarray], lamp_rig: LampRig,
                 known: tuple[Refined, bytes] | None) -> list[tuple[np.ndarray, Refinement]]:
    """refine_all from every start (free: no pose refused), those refined before on the same
    search's Problem taken from `known` ((the refinements by search and start, that search's
    key)): a start's refinement is its own alone (refine_all: the same as one start at a
    time), so the others run in lockstep without them."""
    if known is None:
        return refine_all(problem, starts, lamp_rig)
    refined, key = known
    keys = [(key, np.ascontiguousarray(x, dtype=float).tobytes()) for x in starts]
    new = [k for k, x in enumerate(starts) if keys[k] not in refined]
    if new:
        refined.update(zip([keys[k] for k in new], refine_all(problem, [starts[k] for k in new], lamp_rig)))
    return [refined[k] for k in keys]


def verified(problem: evaluate.Problem, shot: Shot, extra: np.ndarray,
             known: Searched | None) -> tuple[Verification, np.ndarray]:
    """certificate.verify of `shot` on the Problem of the search with these `extra` points, taken
    from `known` (Searched) where the same shot (its pickle's bytes) was verified on it before."""
    if known is None:
        return certificate.verify(problem, shot)
    key = (np.ascontiguousarray(extra, dtype=float).tobytes(), pickle.dumps(shot))
    if key not in known.verified:
        known.verified[key] = certificate.verify(problem, shot)
    return known.verified[key]


class Searched:
    """What a plan's searches found that the cell's bodies do not change, kept for its search
    without them (plan: where no clear lamp pose meets every requirement): each global search
    (global_search) by the extra points it searched with, each free refinement by that and its
    start, and each certificate (verified) by that and the shot. The search without the bodies
    starts at mostly the same grid poses, often ends at the same shot and so adds the same points
    in its certificate rounds: what it would find again is taken instead, the same numbers (the
    same functions on the same inputs), found once."""

    def __init__(self) -> None:
        self.grids: dict[bytes, GlobalSearch] = {}
        self.refined: Refined = {}
        self.verified: dict[tuple[bytes, bytes], tuple[Verification, np.ndarray]] = {}


class ClearOfCell:
    """Where the lamp may stand in a task's cell: whether the lamp at (K, 3) joints (pan, tilt,
    radius) keeps the padding from the cell's other bodies (collision.scene.CollisionScene.
    lamp_check) with the camera at a search's scene's pose and the arm at `arm_joints` (a planned
    viewpoint's) or at the inverse kinematics nearest home (collision.scene.reaching_joints), as
    whole_part.cleared judges the shot. The bodies are placed once per camera pose (a plan's
    certificate rounds share it), each pose is asked once, and the poses refused are counted
    (`refused`: the plan's note, and whether its search without the bodies is asked)."""

    def __init__(self, task: Task, arm_joints: ArrayLike | None = None) -> None:
        self.task, self.arm_joints = task, arm_joints
        self.camera: bytes | None = None                              # the pose the bodies are placed at
        self.check: Callable[[ArrayLike], np.ndarray] | None = None   # CollisionScene.lamp_check there
        self.known: dict[bytes, bool] = {}                            # each joints asked: clear

    @property
    def refused(self) -> int:
        return sum(not ok for ok in self.known.values())

    def at(self, scene: Scene) -> Allowed:
        """The Allowed of the lamp's joints with the camera at scene.T_cell_cam."""
        from cell.collision.scene import CollisionScene, reaching_joints
        key = scene.T_cell_cam.tobytes()
        if self.check is None or key != self.camera:
            arm = reaching_joints(self.task.frames, scene.T_cell_cam, self.arm_joints)
            self.camera, self.known = key, {}
            self.check = CollisionScene.of(self.task).lamp_check(scene.T_cell_cam, arm)
        pivot, check = self.task.lamp.rig.pivot_m, self.check

        def allowed(joints: np.ndarray) -> np.ndarray:
            x = np.asarray(joints, float).reshape(-1, 3)
            keys = [row.tobytes() for row in x]
            new = {key: row for key, row in zip(keys, x) if key not in self.known}
            if new:
                rows = np.array(list(new.values()))
                self.known.update(zip(new, check(rig.lamp_position(pivot, rows[:, 0], rows[:, 1],
                                                                         rows[:, 2])).tolist()))
            return np.array([self.known[key] for key in keys], bool)
        return allowed

    def note(self) -> str:
        """The plan's note of the lamp poses its search refused."""
        return (f"{self.refused} lamp poses the search tried refused: the lamp there closer than the padding "
                f"{1e3 * self.task.cell.collision.padding_m:g} mm to another body of the cell")


def defect_map(problem: evaluate.Problem, candidate: evaluate.Candidates, maps: Maps) -> np.ndarray:
    """(D, E, A) Maps.defect_cnr: defects.direction_map over the map's visible cells (NaN elsewhere)."""
    out = np.full((len(problem.task.feature.defects),) + maps.visible.shape, np.nan)
    out[:, maps.visible] = defects.direction_map(problem, candidate,
                                                 maps.grid.directions(problem.scene.frame)[maps.visible])
    return out


BAND = ("gray_min", "gray_max", "lamp_tolerance")     # what the drive program's verdict explains


def hint(binding: RequirementValue, chosen: drives.Drives | None) -> str:
    """What would fix an infeasible plan: the binding requirement's sentence, and where the band
    binds and drive levels were chosen, the program's own verdict (how far the darkest sample
    stays below the band with every channel at full drive, or the brightest above it at the
    lowest, or which samples pull the band both ways)."""
    if chosen is None or binding.name not in BAND or chosen.feasible:
        return binding.detail
    return f"{binding.detail}; {chosen.message}"


def lighting(problem: evaluate.Problem, joints: ArrayLike) -> tuple[evaluate.Candidates, drives.Drives]:
    """The spot at `joints` (pan, tilt, radius) with the task's other lights: their drive levels,
    shutter and f-number by the linear program over every light's gray (cell.planning.drives: the
    band's margin, robust to the drive tolerance; with `gray_band: any` raised to the sensor's top,
    drives.raised), as Candidates of one judged at that exposure,
    the spot moved by its tolerance and the drives off by theirs; the shutter the band needs is the
    program's at the widest f-number the depth of field allows."""
    task = problem.task
    x = np.asarray(joints, float)
    pivot = task.lamp.rig.pivot_m
    position = rig.lamp_position(pivot, x[0], x[1], x[2]).reshape(1, 3)
    spot, _, _, spot_term = evaluate.unit_gray(problem, position, rig.lamp_aim(pivot, position))
    channels = [task.lamp.channel] + [light.channel for light in task.lights]
    ranges = np.array([c.drive_range for c in channels])
    on_controller = np.array([c.number is not None for c in channels])
    ranges[on_controller & evaluate.wrong_reflection(problem, np.vstack([spot, problem.lights.unit_gray]),
                                                     np.vstack([spot_term, problem.lights.dominant]))] = (0.0, 0.0)
    unit_gray = np.vstack([spot, problem.lights.unit_gray])
    rows = defects.contrast_rows(problem, position[0], unit_gray) if task.feature.defects else None
    chosen = drives.solve_drives(unit_gray, problem.band, problem.black_level,
                                 problem.kappa_open, task.camera.shutter_range_s, task.camera.lens.f_number_range,
                                 ranges, [c.switched for c in channels], task.requirements.drive_tolerance, rows)
    c = evaluate.at_exposure(problem, position[0], chosen.shutter_s, chosen.f_number, joints=tuple(x),
                             drive=chosen.drive)
    if task.requirements.gray_any:
        chosen = drives.raised(chosen, unit_gray, problem.black_level, problem.kappa_open,
                               task.camera.shutter_range_s, task.camera.lens.f_number_range, ranges,
                               _top_signal(problem, c))
        c = evaluate.at_exposure(problem, position[0], chosen.shutter_s, chosen.f_number, joints=tuple(x),
                                 drive=chosen.drive)
    need = chosen.shutter_s * (problem.kappa_open / chosen.f_number) ** 2
    return replace(c, t_need=np.array([need])), chosen


def _top_signal(problem: evaluate.Problem, c: evaluate.Candidates) -> float:
    """The brightest sample's signal (gray less b) at the nominal drives that `gray_band: any`'s
    exposure may reach: the band's top less b (the sensor's range, cell.task.loader.any_band),
    shrunk by how much brighter the lamp's tolerance moves and the drive and light errors make
    the brightest sample (c's moved grays), so that none of them saturates."""
    b = problem.black_level
    nominal = float(np.max(c.gray[0]) - b)
    worst = float(np.max(c.moved_gray - b, initial=nominal))
    return (problem.band[1] - b) * nominal / worst if worst > 0 else 0.0


def light_settings(problem: evaluate.Problem, candidate: evaluate.Candidates) -> tuple[LightSetting, ...]:
    """The LightSetting of the spot and of each of the task's other lights for one candidate
    (Candidates of one): drive, cell-frame pose, and the gray it adds at the candidate's exposure."""
    task, scene = problem.task, problem.scene
    gain = float(candidate.shutter[0] / candidate.kappa[0] ** 2)
    drive = candidate.drive[0]
    pivot = task.lamp.rig.pivot_m
    aim = rig.lamp_aim(pivot, candidate.position)
    spot = evaluate.unit_gray(problem, candidate.position, aim)[0][0]
    out = [LightSetting(task.lamp.name, "spot", "pan_tilt", task.lamp.channel.number, float(drive[0]),
                        candidate.position[0], aim[0], gain * drive[0] * spot)]
    for k, light in enumerate(task.lights):
        centre, axis, _ = lights.pose(light, scene.T_cell_cam)
        out.append(LightSetting(light.name, light.type, light.mount, light.channel.number, float(drive[1 + k]),
                                centre, axis, gain * drive[1 + k] * problem.lights.unit_gray[k]))
    return tuple(out)


def notes(problem: evaluate.Problem, shot: Shot) -> tuple[str, ...]:
    """Facts about the chosen shot that no requirement judges: phase angles beyond the material
    table (planned with its end values, which the table's interpolation clamps to)."""
    scene, table = problem.scene, problem.material.phase_rad
    s = geometry.unit(shot.lamp_position - scene.points)
    v = geometry.unit(scene.camera_position - scene.points)
    phase = np.degrees(brdf.phase_angle(s, v))
    lo, hi = np.degrees(table[0]), np.degrees(table[-1])
    out = []
    if phase.max() > hi + 1e-9 or phase.min() < lo - 1e-9:
        out.append(f"phase angles {phase.min():.1f}-{phase.max():.1f} deg reach beyond the material table's "
                   f"{lo:g}-{hi:g} deg: planned with the table's end values there")
    return tuple(out)


def make_shot(problem: evaluate.Problem, joints: np.ndarray, candidate: evaluate.Candidates,
              values: dict[str, np.ndarray]) -> Shot:
    """The Shot of the chosen lamp pose (Candidates of one and its requirement values)."""
    scene, lens = problem.scene, problem.task.camera.lens
    pos = candidate.position[0]
    s = geometry.unit(pos - scene.center)
    v = geometry.unit(scene.camera_position - scene.center)
    kappa = float(candidate.kappa[0])
    exposure = Exposure(float(candidate.shutter[0]), kappa, problem.focus_m,
                        float(dof.depth_of_field(problem.focus_m, lens.focal_length_m, kappa,
                                                 lens.circle_of_confusion_m)))
    full_scale = 2.0 ** problem.task.camera.sensor.bit_depth - 1
    return Shot(T_cell_cam=scene.T_cell_cam, joints=tuple(float(x) for x in joints), lamp_position=pos,
                exposure=exposure, gray=np.minimum(candidate.gray[0], full_scale), distance_m=float(np.linalg.norm(pos - scene.center)),
                phase_angle_rad=float(brdf.phase_angle(s, v)),
                requirements=requirements.judged(problem, candidate, values),
                lights=light_settings(problem, candidate),
                defects=defects.judge(problem, candidate) if problem.task.feature.defects else ())
