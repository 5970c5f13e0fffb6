"""`cell run` of a task with several features, or with planned viewpoints: plan its shots
(cell.planning.whole_part), refuse a partial plan before anything moves, connect, visit the chosen shots in
the shortest order (cell.run.route) and run the closed loop at each, each in its own folder
shot-<s>/ (s: the shot's index in plan.json). Every shot runs loop.iterate on the features it is
the shot of: one, as `cell run` of a one-feature task does, or several: one capture, each
feature located and measured in its own image region, one exposure for all of them. The run's
report.json holds every feature's result.
A shot that does not converge leaves the devices fine: the other shots still run, and the run
exits 1 at the end naming each feature not in band; a device fault stops everything (exit 3)."""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.run import localization, loop, measurement, motion
from cell.run import moves as cell_moves
from cell.run.acquisition import require_feasible
from cell.planning.whole_part import assigned, candidate_features, feature_plan
from cell.run.context import RunContext
from cell.run.defects import unseen
from cell.devices.interfaces import speaking_for
from cell.core.errors import GoalNotReached, PlanInfeasible
from cell.core.geometry import apply, rotation_angle
from cell.report import words
from cell.report.cell_view import write_cell_view
from cell.report.recorder import Ending, Recorder
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.planning.plan import Plan
    from cell.planning.scene import Scene
    from cell.task.types import Task


@dataclass(frozen=True)
class ShotRun(Result):
    """One shot's closed loop (cell.report.result's verdict: `success`, every feature in its
    band; `message`, why not): the plan's shot index, its features' names, its Iterations (each
    named by its feature), re-plans, refits, the black level found in it, and how far the camera
    read back from the shot's pose (None: not read). Its report.json is to_json(), with
    `converged` and `reason` (success and message) as well; a device fault is the run's."""

    shot: int
    features: tuple[str, ...]
    success: bool
    message: str
    iterations: tuple[loop.Iteration, ...] = ()
    replans: tuple[loop.Replan, ...] = ()
    refits: tuple[loop.Refitted, ...] = ()
    black: measurement.BlackLevel | None = None     # found in this shot, if any
    camera_error: dict[str, float] | None = None    # position_m, angle_deg
    cause: str | None = None
    fault: dict[str, Any] | None = None
    located: loop.Located | None = None             # the pose error localized in this shot, if any

    @property
    def pose_error(self) -> localization.PoseError | None:
        """The pose error the model followed in this shot (None: none, or within what the plan
        tolerates)."""
        return self.located.error if self.located and self.located.followed else None

    def of(self, name: str) -> list[loop.Iteration]:
        """The Iterations of feature `name`."""
        return [it for it in self.iterations if it.feature == name]

    def summary(self) -> str:
        """`converged after N iterations; leaf_a gray 104-119, ...`, one line."""
        n = len({it.iteration for it in self.iterations})
        grays = ", ".join(f"{name} gray {its[-1].measured_gray['min']:.0f}-{its[-1].measured_gray['max']:.0f}"
                          for name in self.features if (its := self.of(name)))
        verdict = f"converged after {words.count(n, 'iteration')}" if self.success else \
            f"not converged: {self.message}"
        return verdict + (f"; {grays}" if grays else "")

    def details(self) -> dict[str, Any]:
        return {"shot": self.shot, "features": list(self.features), "converged": self.success,
                "iterations": [it.to_json() for it in self.iterations],
                "captures": self.captures, "replans": [r.to_json() for r in self.replans],
                "refits": [r.to_json() for r in self.refits], "camera_error": self.camera_error,
                "localization": self.located.to_json() if self.located else None}

    @property
    def counters(self) -> dict[str, int]:
        return {"iterations": len({it.iteration for it in self.iterations}), "captures": len(self.captures),
                "replans": len(self.replans), "refits": len(self.refits)}

    @property
    def captures(self) -> list[str]:
        """The shot's capture files, each once (a capture of several features is each one's), in
        the order taken (capture-N: by N)."""
        return sorted({it.capture for it in self.iterations}, key=lambda c: int(c.split("-")[1].split(".")[0]))


def run_shot(ctx: RunContext, plan: Plan, s: int, done: list[ShotRun]) -> ShotRun:
    """The closed loop (loop.iterate) at plan.shots[s] on the features it is the shot of, in its
    folder shot-<s>/ (its own log.jsonl, every step also in the run's, and report.json, written
    however it ends; re-plans keep the shot's camera pose); a pose error an earlier shot found
    (ctx.pose_error) is applied before it moves: the features' tasks and plans carried along with
    the part (localization.located_task, moved_plan), the arm's hand-eye corrected; the move to
    that carried shot refused (out of reach, no path clear), its viewpoint re-planned for where the
    part is, as a shot localized in itself is (loop.carried_viewpoint; no viewpoint serves: cause
    `pose`, the refusal and the re-plan named; a move refused later: cause `pose`, the pose named
    first, not `collision`); features the loop re-planned into several shots for where the part is
    (loop.Split) visited in turn (split_views), the shot's captures shared by them; its ShotRun
    is appended to `done` however it ends. A goal not reached ends the shot (its ShotRun says
    why); a device fault is raised on."""
    from cell.report.pictures import write_convergence
    shot = plan.shots[s]
    names = assigned(plan, s)
    index = [f.name for f in plan.features]
    tasks = [ctx.task.with_feature(index.index(n)) for n in names]
    plans = [feature_plan(plan, s, index.index(n)) for n in names]
    T_cell_cam, pose = shot.T_cell_cam, ctx.pose_error
    if pose is not None:                # found in an earlier shot: applied before this one moves
        tasks = [localization.located_task(t, pose) for t in tasks]
        plans = [localization.moved_plan(p, pose.T_part) for p in plans]
        T_cell_cam = pose.T_part @ T_cell_cam
    features = [loop.LoopFeature.planned(t, p) for t, p in zip(tasks, plans)]
    events, message, error, cause = loop.Events(), "", None, None
    planned = [shot.T_cell_cam if pose is None else T_cell_cam]     # the pose of the shot (or view) visited last

    def camera_now() -> dict[str, float]:
        """camera_error against the pose visited last, both as the pose error the model follows puts them."""
        followed = pose or (events.located.error if events.located and events.located.followed else None)
        T = planned[-1] if followed is None or len(planned) > 1 else followed.T_part @ shot.T_cell_cam
        return camera_error(localization.corrected(ctx.devices, followed), T)

    with ctx.recorder.sub(f"shot-{s}", shot=s) as rec:
        try:
            try:
                if pose is not None:        # its carried move refused: its viewpoint re-planned there
                    located, replanned = loop.carried_viewpoint(replace(ctx, recorder=rec), features, pose)
                    if replanned:
                        features, T_cell_cam = list(located), located[0].model.plan.shot.T_cell_cam
                        planned.append(T_cell_cam)
                        rec.step("correct", f"{localization.describe(pose, pose.views)}: {replanned}",
                                 action="locate", viewpoint=True)
                for event in loop.iterate(replace(ctx, recorder=rec, T_cell_cam=T_cell_cam), features):
                    events.add(event)
            except loop.Split as split:     # its features re-planned for where the part is: several views
                for event in split_views(replace(ctx, recorder=rec, black=ctx.black or events.black), split, events,
                                         planned):
                    events.add(event)
            error = camera_now()
            n = len({it.iteration for it in events.iterations})
            rec.step("done", f"converged after {words.count(n, 'iteration')}", converged=True, iterations=n)
        except GoalNotReached as err:               # the devices are fine: the next shot runs
            message, cause = str(err), err.cause
            if pose is not None and cause == motion.CAUSE:  # the true cause: the part is not where planned
                message, cause = f"{localization.describe(pose, pose.views)}; carried there, {message}", "pose"
            rec.step("done", f"not converged: {err}", converged=False, reason=message)
            error = camera_now()
        except BaseException as err:                # a fault, Ctrl-C, SIGTERM: the session stops all
            message = str(err) or type(err).__name__
            raise
        finally:
            iterations = [it if it.feature else replace(it, feature=names[0]) for it in events.iterations]
            result = ShotRun(s, names, not message, message, tuple(iterations), tuple(events.replans),
                             tuple(events.refits), events.black, error, cause, located=stated(events.located, ctx.task))
            done.append(result)
            rec.write_json("report.json", result.to_json())
            if iterations:
                write_convergence(rec.folder / "convergence.png", [it.to_json() for it in iterations],
                                  tasks[0].requirements.gray_band, [r.to_json() for r in events.refits])
    return result


def split_views(ctx: RunContext, split: loop.Split, events: loop.Events,
                planned: list[np.ndarray]) -> Iterator[loop.Event]:
    """The closed loop (loop.iterate) at each shot of split.plan in turn, on the features it is
    the shot of (assigned, whole_part.feature_plan; their tasks where split.error puts the part,
    the arm's hand-eye corrected by it), its captures numbered on from the shot's last; the
    split logged with the carried shot's refusal, each view's pose appended to `planned`, logged.
    Every view's move is checked before the first moves (moves.view_moves: reach, collisions,
    the arm's time, logged as `views`): one not clear stops the shot (GoalNotReached, cause
    `collision`, motion.refusal), nothing moved. A goal not reached in one ends the shot."""
    index = [f.name for f in split.plan.features]
    ctx = replace(ctx, pose_error=split.error)
    ctx.recorder.step("correct", f"{localization.describe(split.error, split.error.views)}: {split.refused}; {split}",
                      action="locate", viewpoint=True)
    moves = cell_moves.view_moves(split.task, split.plan, localization.corrected(ctx.devices, split.error))
    blocked = next((m for m in moves if not m.clear), None)
    if blocked is not None:
        raise motion.refusal(blocked)
    took = sum(m.duration_s for m in moves)
    ctx.recorder.step("views", f"the {len(moves)} views' moves checked before the first moves: {took:.1f} s of the "
                               f"arm's moves, every one collision-checked ({'; '.join(map(motion.how_apart, moves))})",
                      moves=[m.to_json() for m in moves])
    for j, view in enumerate(split.plan.shots):
        names = assigned(split.plan, j)
        features = [loop.LoopFeature.planned(split.task.with_feature(index.index(n)),
                                             feature_plan(split.plan, j, index.index(n))) for n in names]
        ctx.recorder.step("correct", f"{split}: view {j + 1} of {len(split.plan.shots)}, {', '.join(names)}, camera at "
                                     f"{np.round(view.T_cell_cam[:3, 3], 4).tolist()} m", action="locate",
                          view=j + 1, features=list(names))
        planned.append(view.T_cell_cam)
        first = 1 + max((it.iteration for it in events.iterations), default=0)
        yield from loop.iterate(replace(ctx, T_cell_cam=view.T_cell_cam), features, first)


def stated(located: loop.Located | None, task: Task) -> loop.Located | None:
    """The pose error localized at a shot's feature stated about the task's first feature's centre,
    as the simulator's truth keys turn the part (the same E_part: a turn about the shot's feature
    moves the first feature's centre by (R - 1) times the arm between them; the bracket's bevel,
    3 deg about y, 1.7 mm in x and z)."""
    if located is None:
        return None
    first = apply(task.frames.T_cell_part, task.features[0].center_m)
    return replace(located, error=located.error.about(first))


def camera_error(devices: Devices, T_cell_cam: np.ndarray) -> dict[str, float]:
    """How far the arm's read-back camera pose is from T_cell_cam: position [m] and the angle
    between their orientations [deg]."""
    with speaking_for(devices.arm):
        T = devices.arm.camera_pose()
    return {"position_m": float(np.linalg.norm(T[:3, 3] - np.asarray(T_cell_cam)[:3, 3])),
            "angle_deg": float(np.degrees(rotation_angle(T, T_cell_cam)))}


def visit_order(task: Task, plan: Plan, devices: Devices,
                recorder: Recorder) -> tuple[tuple[int, ...], float, list[cell_moves.Move]]:
    """The shots' order (plan.shots indices) of the plan's checked route (cell.run.moves), its
    moves as the run makes them from the devices' read-back start pose (run_moves), logged with
    their travel. A move that cannot be made clear: PlanInfeasible (exit 1) before anything moves."""
    order = cell_moves.order(plan)
    moves = cell_moves.run_moves(task, plan, devices)
    blocked = next((m for m in moves if not m.clear), None)
    if blocked is not None:
        raise PlanInfeasible(f"infeasible: collision binds: {blocked.reason()}",
                             f"infeasible: {blocked.reason()}")
    travel = float(sum(m.travel_m for m in moves))
    via = sum(len(m.via) for m in moves)
    with speaking_for(devices.arm):
        camera = devices.arm.camera_pose()[:3, 3]
    with speaking_for(devices.lamp):
        lamp = devices.lamp.lamp_pose()[0]
    recorder.step("route", f"shots in the order {list(order)}: {travel:.3f} m of camera and lamp travel from "
                           f"the start, every move collision-checked ({words.count(via, 'via point')})",
                  order=list(order), travel_m=travel, start={"camera_m": camera, "lamp_m": lamp},
                  moves=[m.to_json() for m in moves])
    return order, travel, moves


@dataclass(frozen=True)
class InspectionResult(Result):
    """A run of several shots (cell.report.result's verdict: `success`, every feature in its
    band; `message`, why not; the device fault), the plan, the visiting order and its travel and
    each shot's ShotRun. report.json is to_json(), with `converged` and `reason` as well."""

    task: str
    success: bool
    message: str
    plan: dict[str, Any] | None
    features: tuple[str, ...]               # the plan's feature names, in the task's order
    covered_by: tuple[int | None, ...]      # the plan's shot index of each (None: uncovered)
    order: tuple[int, ...] = ()
    travel_m: float | None = None
    shots: tuple[ShotRun, ...] = ()
    fault: dict[str, Any] | None = None
    cause: str | None = None

    @property
    def counters(self) -> dict[str, int]:
        return {"features": len(self.features), "shots": len(self.shots),
                "iterations": sum(r.counters["iterations"] for r in self.shots),
                "captures": sum(len(r.captures) for r in self.shots)}

    def feature_results(self) -> list[dict[str, Any]]:
        """Per feature: name, shot, converged (its shot converged: it ended in band, and each of
        its declared defects measured at least its min_cnr, cell.run.defects.unseen), the last
        capture's measured_gray, iterations, reason when not converged, and with declared defects
        their CNR in the last capture (`defects`, as a one-feature run's report.json; `cause`
        `contrast` where one was unseen)."""
        runs: dict[int | None, ShotRun] = {r.shot: r for r in self.shots}
        out = []
        for name, s in zip(self.features, self.covered_by):
            run = runs.get(s)
            its = run.of(name) if run else []
            in_band = bool(run and run.success and its and its[-1].in_band)
            missed = unseen(its[-1].defects) if in_band else None
            converged = in_band and not missed
            reason = "" if converged else missed or (run.message if run else "not run: " + (
                f"the run stopped at a device fault ({self.fault['error']})" if self.fault else
                self.message or "covered by no shot"))
            out.append({"name": name, "shot": s, "converged": converged,
                        "measured_gray": its[-1].measured_gray if its else None,
                        "in_band": bool(its and its[-1].in_band), "iterations": len(its),
                        "capture": f"shot-{s}/{its[-1].capture}" if its else None, "reason": reason,
                        **({"defects": [d.to_json() for d in its[-1].defects]} if its and its[-1].defects else {}),
                        **({"cause": "contrast"} if missed else {})})
        return out

    def details(self) -> dict[str, Any]:
        black = next((r.black.to_json() for r in self.shots if r.black), None)
        located = next((r.located.to_json() for r in self.shots if r.located and r.located.followed),
                       next((r.located.to_json() for r in self.shots if r.located), None))
        return {"task": self.task, "plan": self.plan, "converged": self.success,
                "features": self.feature_results(), "order": list(self.order), "travel_m": self.travel_m,
                "shots": [{"shot": r.shot, "folder": f"shot-{r.shot}", "features": list(r.features),
                           "converged": r.success, "reason": r.message,
                           "iterations": len({it.iteration for it in r.iterations}),
                           "camera_error": r.camera_error} for r in self.shots],
                "iterations": [{"shot": r.shot, **it.to_json()} for r in self.shots for it in r.iterations],
                "captures": [f"shot-{r.shot}/{c}" for r in self.shots for c in r.captures],
                "black_level": black, "localization": located}


def plan_logged(task: Task, recorder: Recorder) -> Plan:
    """plan_features (the function `cell plan` uses for several features), plan.json in the run
    folder (its pictures when the run has ended), logged."""
    from cell.planning.whole_part import plan_features
    plan = cell_moves.with_moves(task, plan_features(task, progress=recorder.out.labelled(" " * 16)))
    recorder.write_plan(plan, task)
    covered = sum(f.covered_by is not None for f in plan.features)
    verdict = "feasible" if plan.feasible else "PARTIAL"
    recorder.step("plan", f"{verdict}: {words.covering(len(plan.shots), covered, len(plan.features))}"
                          + ("" if plan.feasible else f"; {words.reason(plan)}"),
                  feasible=plan.feasible, binding=plan.binding, hint=plan.hint, shots=len(plan.shots),
                  features={f.name: f.covered_by for f in plan.features})
    return plan


def run(task: Task, out: str | Path, connect: Callable[[Scene], Devices],
        max_iterations: int = 6) -> InspectionResult:
    """Plan the task's shots (plan_logged), refuse a partial or infeasible plan before anything
    moves (PlanInfeasible naming the first feature no shot covers, exit 1), connect(scene) ->
    Devices (scene: the first feature's, whose mesh the simulated cell renders), order the shots
    (visit_order) and run each (run_shot). out/report.json (InspectionResult.to_json) is written
    however the run ends. Raises GoalNotReached naming every feature not in band (exit 1; its
    cause, report.json's, the first such feature's: `contrast` for a defect unseen, else its
    shot's), or DeviceFault (exit 3) after the safe stop. Returns the InspectionResult."""
    out = Path(out)
    runs: list[ShotRun] = []
    order: tuple[int, ...] = ()
    travel: float | None = None
    black: measurement.BlackLevel | None = None
    pose: localization.PoseError | None = None
    names = tuple(f.name for f in task.features)
    covered_by: tuple[int | None, ...] = (None,) * len(names)

    def result(reason, fault):
        return InspectionResult(str(task.path), not reason, reason, recorder.plan, names, covered_by, order,
                                travel, tuple(runs), fault)

    with Recorder(out) as recorder, Ending(recorder, "not converged", "report.json", result,
                                           converged=False) as ending:
        session = ending.session
        with session:
            plan = plan_logged(task, recorder)
            covered_by = tuple(f.covered_by for f in plan.features)
            require_feasible(plan)
            devices = session.devices = connect(plan.plans[candidate_features(plan).index(0)].planned_scene)
            order, travel, moves = visit_order(task, plan, devices, recorder)
            # the route drawn in its order, over the plan's own cell.html, once the run has ended
            recorder.later(lambda: write_cell_view(recorder.folder / "cell.html", plan, task, order))
            context = RunContext(task, devices, recorder, max_iterations)
            for n, (s, move) in enumerate(zip(order, moves)):
                recorder.step("shot", f"shot {n + 1} of {len(order)} (plan's shot {s}): "
                                      f"{describe(plan, s)}", shot=s, visit=n + 1, features=assigned(plan, s))
                cell_moves.follow(task, devices, move, recorder, plan.shots[s].joints)
                done = run_shot(replace(context, black=black, pose_error=pose), plan, s, runs)
                black, pose = black or done.black, pose or done.pose_error
                recorder.step("shot_done", f"shot {n + 1} of {len(order)} (plan's shot {s}): {done.summary()}",
                              shot=s, converged=done.success, reason=done.message)
        failed = [f for f in result("", None).feature_results() if not f["converged"]]
        if failed:
            what = "not in band" + (" or a defect unseen" if any(f.get("cause") == "contrast" for f in failed) else "")
            causes = {r.shot: r.cause for r in runs}
            raise GoalNotReached(f"{len(failed)} of {len(names)} features {what}: " + "; ".join(
                f"{f['name']} (shot {f['shot']}): {f['reason']}" for f in failed),
                next((c for f in failed if (c := f.get("cause") or causes.get(f["shot"]))), None))
        recorder.step("done", f"converged: every feature in band ({len(names)} features, "
                              f"{words.count(len(runs), 'shot')})", converged=True)
    return ending.result


def describe(plan: Plan, s: int) -> str:
    """`leaf_a, leaf_b; camera at [...] m (cell frame), lamp pan ..., 2.265 ms, f/1.4`: plan.shots[s]'s line."""
    shot = plan.shots[s]
    pan, tilt, radius = shot.joints
    camera = np.round(shot.camera_position, 3).tolist()
    return (", ".join(assigned(plan, s)) + f"; camera at {camera} m (cell frame), lamp pan {np.degrees(pan):.1f} "
            f"deg, tilt {np.degrees(tilt):.1f} deg, radius {radius:.3f} m; {1e3 * shot.exposure.shutter_s:.3f} ms, "
            f"f/{shot.exposure.f_number:.1f}")


def gray_line(feature: dict[str, Any]) -> str:
    """`leaf_a: shot 0, gray 104-119 (mean 112.3), 1 iteration`, of a feature_results() entry."""
    g = feature["measured_gray"] or {}
    gray = f"gray {g['min']:.0f}-{g['max']:.0f} (mean {g['mean']:.1f})" if g else "not measured"
    return f"{feature['name']}: shot {feature['shot']}, {gray}, {words.count(feature['iterations'], 'iteration')}"

