"""The closed loop of `cell run` (design.md, steps 3-4): plan, drive the cell, capture, measure the
feature's gray, correct (cell.control), until every feature pixel is in the gray band or N
iterations have run. It composes the stages: acquisition (plan, connect, move, expose, capture),
measurement, the control law, the device session's safe stop and the recorder's run folder."""
from dataclasses import dataclass, replace
from pathlib import Path

from cell import control, measure
from cell.acquisition import acquire, move_to, plan_and_connect, plan_recorded
from cell.errors import GoalNotReached
from cell.evaluate import depth_of_field_limits
from cell.plan import gray_stats
from cell.recorder import Recorder
from cell.session import Session


@dataclass(frozen=True)
class Iteration:
    """One capture of the loop: its settings, the model's and the measured gray, the model's
    error, the verdict and the correction taken after it (None when in band or the last)."""

    iteration: int
    shutter_s: float
    f_number: float
    predicted_gray: dict
    measured_gray: dict
    model_error: float
    model_error_relation: str
    in_band: bool
    capture: str
    annotated: str
    albedo_scale: float
    correction: dict | None = None

    def to_json(self):
        document = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "correction"}
        return document | ({"correction": self.correction} if self.correction else {})


@dataclass(frozen=True)
class Corrected:
    """The correction taken after iteration `iteration` (its document in report.json)."""

    iteration: int
    correction: dict


@dataclass(frozen=True)
class Replan:
    iteration: int
    albedo_scale: float
    plan: dict                   # its plan.json


@dataclass(frozen=True)
class RunResult:
    """What a run achieved, like scipy's OptimizeResult: `success` (every feature pixel in the
    band), `message` (why not: the error's line), the plan, every iteration and re-plan, and the
    device fault with its safe stop's outcome when there was one. report.json is to_json()."""

    task: str
    success: bool
    message: str
    plan: dict | None
    iterations: tuple = ()
    replans: tuple = ()
    fault: dict | None = None

    @property
    def captures(self):
        return [it.capture for it in self.iterations]

    def to_json(self):
        return {"task": self.task, "plan": self.plan, "iterations": [it.to_json() for it in self.iterations],
                "converged": self.success, "captures": self.captures, "reason": self.message,
                "replans": [{"iteration": r.iteration, "albedo_scale": r.albedo_scale, "plan": r.plan}
                            for r in self.replans]} | ({"fault": self.fault} if self.fault else {})


def shoot(task, plan, devices, recorder, k, shutter_s, f_number, albedo_scale):
    """Expose, capture, measure and compare with the plan's model at these settings
    (G ~ t / kappa^2). Returns (Iteration, Measurement, predicted gray per sample)."""
    from cell.pictures import annotate_capture
    shot = plan.shot
    capture = acquire(devices, recorder, k, shutter_s, f_number, shot.exposure.focus_m)
    bit_depth = devices.camera.bit_depth
    saturation = measure.saturation_level(bit_depth)
    m = measure.measure_feature(capture.image, task, capture.T_cell_cam, plan.scene.points, saturation)
    predicted = shot.gray * (capture.shutter_s / shot.exposure.shutter_s) * (shot.exposure.f_number / f_number) ** 2
    error, relation = control.model_error(m.sample_gray, predicted, saturation)
    band = task.requirements.gray_band
    in_band = m.in_band(band)
    stats, expected = m.stats(), gray_stats(predicted)
    verdict = f"{'in' if in_band else 'out of'} band {band[0]:g}-{band[1]:g}"
    caption = f"{k}: gray {m.min:.0f}-{m.max:.0f}, {stats['saturated']} saturated: {verdict}"
    annotated = recorder.write_image(f"capture-{k}-feature.png",
                                     annotate_capture(capture.image, m, bit_depth, caption))
    it = Iteration(k, capture.shutter_s, float(f_number), expected, stats, error, relation, in_band,
                   capture.name, annotated, albedo_scale)
    recorder.step("measure", f"gray mean {stats['mean']:.1f}, {m.min:.1f}-{m.max:.1f} over {stats['pixels']} px "
                             f"(pixels {stats['pixel_min']:.0f}-{stats['pixel_max']:.0f}, noise "
                             f"{stats['noise_rms']:.1f} rms, {stats['saturated']} saturated); the model predicts "
                             f"{expected['mean']:.1f}, {expected['min']:.1f}-{expected['max']:.1f}; "
                             f"{control.describe_error(error, relation)}; {verdict}",
                  **{key: v for key, v in it.to_json().items() if key != "albedo_scale"})
    return it, m, predicted


def iterate(task, plan, devices, recorder, max_iterations):
    """Drive, shoot, correct until every feature pixel is in the band, yielding each Iteration as
    soon as it is measured, then its Corrected and a Replan as they happen; raises GoalNotReached
    saying why when no correction is possible or the iterations run out."""
    band = tuple(map(float, task.requirements.gray_band))
    lens_range = (depth_of_field_limits(task, plan.scene)[2], task.camera.lens.f_number_range[1])
    albedo, moved = 1.0, False
    shutter, f_number = plan.shot.exposure.shutter_s, plan.shot.exposure.f_number
    for k in range(1, max_iterations + 1):
        if not moved:
            move_to(devices, plan.shot, recorder, k)
            moved = True
        it, m, predicted = shoot(task, plan, devices, recorder, k, shutter, f_number, albedo)
        yield it
        shutter = it.shutter_s
        if it.in_band:
            return
        if k == max_iterations:
            raise GoalNotReached(f"not in band {band[0]:g}-{band[1]:g} after {count(k, 'iteration')}: "
                                 f"feature gray {m.min:.1f}-{m.max:.1f} ({it.measured_gray['saturated']} pixels "
                                 f"saturated) at {1e3 * shutter:.3g} ms, f/{f_number:.1f}; "
                                 f"{control.describe_error(it.model_error, it.model_error_relation)}")
        c = control.correct(m, predicted, shutter, f_number, band, task.camera.shutter_range_s, lens_range)
        if c.action == "stop":
            raise GoalNotReached(c.reason)
        if c.action == "replan":
            albedo *= c.model_error
        recorder.step("correct", c.message(shutter, f_number, albedo), iteration=k, **c.document(albedo))
        yield Corrected(k, c.document(albedo))
        if c.action == "exposure":
            shutter, f_number = c.shutter_s, c.f_number
            continue
        plan = plan_recorded(task, recorder, albedo, iteration=k, subfolder=f"replan-{k}")
        yield Replan(k, albedo, plan.to_json())
        if not plan.feasible:
            raise GoalNotReached(f"{control.describe_error(c.model_error, c.relation)}; {c.reason}; "
                                 f"re-planned for an albedo x{albedo:.3g}: infeasible, {plan.binding}: "
                                 f"{plan.hint}")
        shutter, f_number, moved = plan.shot.exposure.shutter_s, plan.shot.exposure.f_number, False


def run(task, out, connect, max_iterations=6):
    """Plan, connect(scene) -> Devices, then iterate; out/report.json (RunResult.to_json) is
    written however the run ends. Raises PlanInfeasible or GoalNotReached (exit 1), or DeviceFault
    (exit 3) after the safe stop of every device (session.Session). Returns the RunResult."""
    from cell.pictures import write_convergence
    out = Path(out)
    iterations, replans, reason = [], [], ""
    with Recorder(out) as recorder:
        session = Session(on_fault=recorder.fault, log=recorder.log.name)
        try:
            with session:
                planned = plan_and_connect(task, recorder, session, connect)
                for event in iterate(task, planned, session.devices, recorder, max_iterations):
                    if isinstance(event, Corrected):
                        iterations[-1] = replace(iterations[-1], correction=event.correction)
                    else:
                        (iterations if isinstance(event, Iteration) else replans).append(event)
            n = len(iterations)
            recorder.step("done", f"converged after {count(n, 'iteration')}", converged=True, iterations=n)
        except BaseException as err:
            reason = str(err) or type(err).__name__
            if not session.fault:                   # the goal was not reached: the devices are fine
                recorder.step("done", f"not converged: {err}", converged=False, reason=str(err))
            raise
        finally:
            result = RunResult(str(task.path), not reason, reason, recorder.plan, tuple(iterations),
                               tuple(replans), session.fault)
            recorder.write_json("report.json", result.to_json())
            if iterations:
                write_convergence(out / "convergence.png", [it.to_json() for it in iterations],
                                  task.requirements.gray_band)
    return result


def count(n, noun):
    return f"{n} {noun}{'s' * (n != 1)}"
