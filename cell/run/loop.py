"""The closed loop of `cell run`: plan, drive the cell, capture, measure the
feature's gray, correct (cell.run.control), until every feature pixel is in the gray band or N
iterations have run. It composes the stages: acquisition (plan, connect, move, expose, capture),
measurement, the control law, the device session's safe stop and the recorder's run folder."""
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from cell.physics.sensor import saturation_level
from cell.run import acquisition, control, measurement, refit, registration

from cell.planning import evaluate
from cell.run.acquisition import acquire, move_to, plan_and_connect, plan_recorded
from cell.devices.interfaces import speaking_for
from cell.core.errors import GoalNotReached, PlanInfeasible
from cell.planning.plan import gray_stats
from cell.report.recorder import Ending, Recorder, file_name
from cell.report.result import Result


CAUSES = {          # report.json's `cause` of a run that ends without the goal (exit 1): the README's table
    "registration": "the feature appears beyond loop.registration_limit_m from where the model puts it "
                    "(hand-eye or fixture)",
    "black pixels": "part of the region reads the black level (off the part or shadowed: hand-eye or fixture)",
    "albedo": "the level implies an albedo outside loop.albedo_scale_range",
    "spread": "the shape still disagrees after a refit",
    "lamp aim": "the refitted material does not explain the captures (the lamp's aim, shadows)",
    "material shape": "the shape disagrees and the captures cannot tell the material's",
    "infeasible": "the band is infeasible for the model as measured (the plan or a re-plan)",
    "iterations": "the iterations ran out",
    "features": "a shot's features each fit the band alone but not together under one exposure",
    "bands": "a shot's features have gray bands with nothing in common",
    "replan": "a shot of several features needs more than an exposure (it is not re-planned)",
}


REGISTRATION_FLOOR_M = 0.001   # the least registration_limit: a plan without lamp tolerance still
                               # measures through a sub-millimetre hand-eye error


@dataclass(frozen=True)
class Iteration:
    """One capture of the loop: its settings, the model's and the measured gray, the model's
    error, the verdict and the correction taken after it (a stop too; None when in band or the last)."""

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
    registration: dict | None = None     # registration.Registration.to_json
    correction: dict | None = None
    feature: str | None = None           # its feature's name, in a shot of several (cell.run.inspection)

    def to_json(self):
        document = {k: getattr(self, k) for k in self.__dataclass_fields__
                    if k not in ("correction", "feature")}
        return ({"feature": self.feature} if self.feature else {}) | document | (
            {"correction": self.correction} if self.correction else {})


@dataclass(frozen=True)
class Corrected:
    """The correction taken after iteration `iteration` (its document in report.json)."""

    iteration: int
    correction: dict


@dataclass(frozen=True)
class BlackLevelFound:
    """The sensor's black level the run works with (measurement.BlackLevel)."""

    black: measurement.BlackLevel


@dataclass(frozen=True)
class Refitted:
    """The material refitted after iteration `iteration` (refit.Refit) and its file's name."""

    iteration: int
    refit: object
    material_file: str

    def to_json(self):
        return {"iteration": self.iteration, "material_file": self.material_file} | self.refit.to_json()


@dataclass(frozen=True)
class Replan:
    """A re-plan after iteration `iteration` for an albedo scale (its document in report.json)."""

    iteration: int
    albedo_scale: float
    plan: dict                   # its plan.json

    def to_json(self):
        return {"iteration": self.iteration, "albedo_scale": self.albedo_scale, "plan": self.plan}


@dataclass(frozen=True)
class RunResult(Result):
    """What a run achieved (cell.report.result's verdict: `success`, every feature pixel in the
    band; `message`, why not; `cause`, CAUSES' key; the device fault), the plan, every iteration,
    re-plan and refit, and the black level. report.json is to_json(), with `converged` and
    `reason` (success and message) as well."""

    task: str
    success: bool
    message: str
    plan: dict[str, Any] | None
    iterations: tuple[Iteration, ...] = ()
    replans: tuple[Replan, ...] = ()
    fault: dict[str, Any] | None = None
    black_level: dict[str, Any] | None = None
    refits: tuple[Refitted, ...] = ()
    cause: str | None = None     # CAUSES' key of a run that ended without the goal

    @property
    def captures(self) -> list[str]:
        return [it.capture for it in self.iterations]

    @property
    def counters(self) -> dict[str, int]:
        return {"iterations": len(self.iterations), "captures": len(self.captures), "replans": len(self.replans),
                "refits": len(self.refits)}

    def details(self) -> dict[str, Any]:
        return {"task": self.task, "plan": self.plan, "iterations": [it.to_json() for it in self.iterations],
                "converged": self.success, "captures": self.captures, "reason": self.message,
                "replans": [r.to_json() for r in self.replans], "black_level": self.black_level,
                "refits": [r.to_json() for r in self.refits]}


@dataclass(frozen=True)
class Model:
    """The plan the loop works with and the task (its black level) it was planned for."""

    plan: object
    task: object

    def predicted(self, black_level, shutter_s, f_number):
        """The plan's gray per sample at these settings with black level b, G = b + c P t: the
        plan's signal (its gray less the black level it was planned with) ~ t / kappa^2."""
        e = self.plan.shot.exposure
        signal = self.plan.shot.gray - evaluate.black_level(self.task)
        return black_level + signal * (shutter_s / e.shutter_s) * (e.f_number / f_number) ** 2

    def exposure(self, black_level, lens_range):
        """(shutter, f-number) the planner's closed form sets for the plan's lamp pose with black
        level b (evaluate.centring_exposure on the plan's signal per unit exposure)."""
        e, camera = self.plan.shot.exposure, self.task.camera
        unit = (self.plan.shot.gray - evaluate.black_level(self.task)) * e.f_number**2 / e.shutter_s
        shutter, kappa, _ = evaluate.centring_exposure(unit[None], evaluate.planning_band(self.task), black_level,
                                                       lens_range[0], camera.shutter_range_s, lens_range)
        return float(shutter[0]), float(kappa[0])


def find_black_level(task, plan, devices, recorder):
    """acquisition.find_black_level at the planned f-number and focus (a manual lens is not turned
    twice more), with the most light the plan's model lets reach the feature in the dark frame."""
    e = plan.shot.exposure
    return acquisition.find_black_level(task, devices, recorder, e.f_number, e.focus_m, lambda shutter_s: float(
        np.max(Model(plan, task).predicted(0.0, shutter_s, e.f_number))))


def registration_limit(task, shot):
    """How far from where the model puts it the feature may be found [m]: loop.registration_limit_m,
    else what the plan tolerates. A fixture error d turns the lamp's direction to the feature by
    d / r (r the lamp's distance), and the plan holds the band under lamp errors up to
    lamp_tolerance: d = r tan(lamp_tolerance), at least REGISTRATION_FLOOR_M (3.9-4.0 mm on the
    examples: 1 deg at 0.22-0.23 m)."""
    if task.loop.registration_limit_m is not None:
        return task.loop.registration_limit_m
    return max(shot.distance_m * np.tan(task.requirements.lamp_tolerance_rad), REGISTRATION_FLOOR_M)


def locate(task, scene, devices, recorder, k, capture, saturation, limit, feature=None):
    """Registration (cell.run.registration) of a capture at the read-back camera and lamp poses, logged
    (as `feature`'s, when named); returns (Registration, the shift the measurement takes: the found
    one when trusted and within the limit [m], else none, the model's region)."""
    with speaking_for(devices.lamp):
        lamp_pose = devices.lamp.lamp_pose()
    row, col, inside = measurement.sample_pixels(task, capture.T_cell_cam, scene.points)
    found = registration.locate(capture.image, task, scene, capture.T_cell_cam, lamp_pose, row[inside], col[inside],
                            saturation)
    recorder.step("register", f"{feature}: " * bool(feature) + found.describe(), iteration=k,
                  **({"feature": feature} if feature else {}), **found.to_json())
    within = found.trusted and registration.beyond_limit(found.to_json(), limit) is None
    return found, found.shift_px if within else (0.0, 0.0)


def shoot(task, model, devices, recorder, k, shutter_s, f_number, albedo_scale, black):
    """Expose, capture and measure the feature in it (measure_capture). Returns (Iteration,
    Measurement, predicted gray per sample)."""
    capture = acquire(devices, recorder, k, shutter_s, f_number, model.plan.shot.exposure.focus_m)
    return measure_capture(task, model, devices, recorder, k, capture, albedo_scale, black)


def measure_capture(task, model, devices, recorder, k, capture, albedo_scale, black, feature=None):
    """Locate the task's feature in capture k (locate), measure it where found, in its own image
    region, and compare with the plan's model at the capture's settings (G = b + c P t, the signal
    ~ t / kappa^2); `feature` names it in a capture of several (its picture
    capture-k-<feature>.png, else capture-k-feature.png). Returns (Iteration, Measurement,
    predicted gray per sample)."""
    from cell.report.pictures import annotate_capture
    f_number = capture.f_number
    bit_depth = devices.camera.bit_depth
    saturation = saturation_level(bit_depth)
    found, shift = locate(task, model.plan.scene, devices, recorder, k, capture, saturation,
                          registration_limit(task, model.plan.shot), feature)
    m = measurement.measure_feature(capture.image, task, capture.T_cell_cam, model.plan.scene.points, saturation, shift)
    predicted = model.predicted(black.value, capture.shutter_s, f_number)
    error, relation = control.model_error(m.sample_gray, predicted, saturation, black.value)
    band = task.requirements.gray_band
    in_band = m.in_band(band)
    stats, expected = m.stats(), gray_stats(predicted)
    verdict = f"{'in' if in_band else 'out of'} band {band[0]:g}-{band[1]:g}"
    named = f"{feature}: " if feature else ""
    caption = f"{k}: {named}gray {m.min:.0f}-{m.max:.0f}, {stats['saturated']} saturated: {verdict}"
    annotated = recorder.write_image(f"capture-{k}-{file_name(feature) if feature else 'feature'}.png",
                                     annotate_capture(capture.image, m, bit_depth, caption))
    it = Iteration(k, capture.shutter_s, float(f_number), expected, stats, error, relation, in_band,
                   capture.name, annotated, albedo_scale, found.to_json(), feature=feature)
    recorder.step("measure", f"{named}gray mean {stats['mean']:.1f}, {m.min:.1f}-{m.max:.1f} over "
                             f"{stats['pixels']} px "
                             f"(pixels {stats['pixel_min']:.0f}-{stats['pixel_max']:.0f}, noise "
                             f"{stats['noise_rms']:.1f} rms, {stats['saturated']} saturated); the model predicts "
                             f"{expected['mean']:.1f}, {expected['min']:.1f}-{expected['max']:.1f}; "
                             f"{control.describe_error(error, relation)}; {verdict}",
                  **{key: v for key, v in it.to_json().items() if key not in ("albedo_scale", "registration")})
    return it, m, predicted


def limits_of(task, plan):
    """The control.Limits of a one-feature task's plan: its band, the shutter range, the f-numbers
    from the widest the depth of field allows to the lens's narrowest, the plausible albedos."""
    lens_range = (evaluate.depth_of_field_limits(task, plan.scene)[2], task.camera.lens.f_number_range[1])
    return control.Limits(tuple(map(float, task.requirements.gray_band)), task.camera.shutter_range_s,
                          lens_range, task.loop.albedo_scale_range)


def iterate(task, plan, devices, recorder, max_iterations, black=None, T_cell_cam=None):
    """Drive, find the black level (BlackLevelFound; a `black` given, found in an earlier shot,
    is taken as it is), shoot, correct until every feature pixel is in the band, yielding each
    Iteration as soon as it is measured, then its Corrected and a Replan as they happen; raises
    GoalNotReached saying why when no correction is possible or the iterations run out. A black
    level the plan did not know re-sets its exposure (the lamp pose stays: b only shifts the band
    the signal must meet) and is the re-plans' from then on. Re-plans put the camera at
    T_cell_cam (a shot's of several, cell.run.inspection), else by the task's camera rule."""
    limits = limits_of(task, plan)
    band, lens_range = limits.band, limits.f_number_range
    model, albedo, moved, given, refitted = Model(plan, task), 1.0, False, black, False
    black = None
    shutter, f_number = plan.shot.exposure.shutter_s, plan.shot.exposure.f_number
    for k in range(1, max_iterations + 1):
        if not moved:
            move_to(devices, model.plan.shot, recorder, k)
            moved = True
        if black is None:
            black = given or find_black_level(task, plan, devices, recorder)
            if not given:
                yield BlackLevelFound(black)
            if black.value != evaluate.black_level(task):
                shutter, f_number = model.exposure(black.value, lens_range)
                sensor = replace(task.camera.sensor, black_level=black.value)
                task = replace(task, camera=replace(task.camera, sensor=sensor))
        it, m, predicted = shoot(task, model, devices, recorder, k, shutter, f_number, albedo, black)
        yield it
        shutter = it.shutter_s
        far = registration.beyond_limit(it.registration, registration_limit(task, model.plan.shot))
        if far:                                 # the plan's poses do not hold: nothing to correct
            yield Corrected(k, {"action": "stop", "albedo_scale": albedo, "reason": far, "cause": "registration"})
            raise GoalNotReached(far, "registration")
        if it.in_band:
            return
        if k == max_iterations:
            raise GoalNotReached(f"not in band {band[0]:g}-{band[1]:g} after {count(k, 'iteration')}: "
                                 f"feature gray {m.min:.1f}-{m.max:.1f} ({it.measured_gray['saturated']} pixels "
                                 f"saturated) at {1e3 * shutter:.3g} ms, f/{f_number:.1f}; "
                                 f"{control.describe_error(it.model_error, it.model_error_relation)}", "iterations")
        c = control.correct(m, predicted, shutter, f_number, limits, black, albedo)
        if c.action == "stop" and c.cause == "spread" and not refitted:     # the shape is wrong: refit
            refitted = True
            task, replanned = yield from refit_and_replan(task, model, devices, recorder, k, m, c, black, albedo,
                                                         shutter, f_number, it.registration["shift_px"],
                                                         T_cell_cam)
            model, albedo, moved = Model(replanned, task), 1.0, False
            shutter, f_number = replanned.shot.exposure.shutter_s, replanned.shot.exposure.f_number
            continue
        if c.action == "stop":                  # its cause in report.json; the done step says why
            yield Corrected(k, c.document(albedo))
            raise GoalNotReached(c.reason, c.cause)
        if c.action == "replan":
            albedo *= c.model_error
        recorder.step("correct", c.message(shutter, f_number, albedo), iteration=k, **c.document(albedo))
        yield Corrected(k, c.document(albedo))
        if c.action == "exposure":
            shutter, f_number = c.shutter_s, c.f_number
            continue
        replanned = plan_recorded(task, recorder, albedo, iteration=k, subfolder=f"replan-{k}",
                                  T_cell_cam=T_cell_cam)
        yield Replan(k, albedo, replanned.to_json())
        if not replanned.feasible:
            raise GoalNotReached(f"{control.describe_error(c.model_error, c.relation)}; {c.reason}; "
                                 f"re-planned for an albedo x{albedo:.3g}: infeasible, {replanned.binding}: "
                                 f"{replanned.hint}", "infeasible")
        model = Model(replanned, task)
        shutter, f_number, moved = replanned.shot.exposure.shutter_s, replanned.shot.exposure.f_number, False


def refit_and_replan(task, model, devices, recorder, k, m, c, black, albedo, shutter_s, f_number, shift_px,
                     T_cell_cam=None):
    """After capture k (at shutter_s, f_number) whose shape disagreed with the model (Correction
    c, cause spread; the feature found shift_px away): probe, refit the material (cell.run.refit;
    Corrected, Refitted) and re-plan with it (Replan; the camera at T_cell_cam, else by the task's
    rule). Returns (the task with the refitted material, its plan); GoalNotReached when the refit
    cannot be used or its plan is infeasible."""
    recorder.step("correct", f"refit the material: {c.reason}", iteration=k, action="refit")
    yield Corrected(k, {"action": "refit", "cause": "spread", "reason": c.reason})
    fitted = refit.probe_and_refit(task, model.plan.scene, devices, recorder, k, m,
                                   (shutter_s, f_number, model.plan.shot.exposure.focus_m), black, albedo, shift_px)
    yield Refitted(k, fitted, refit.keep(fitted, task, recorder, k))
    refit.require_usable(fitted, c.reason)
    task = refit.task_with(task, fitted)
    replanned = plan_recorded(task, recorder, 1.0, iteration=k, subfolder=f"refit-{k}", T_cell_cam=T_cell_cam)
    yield Replan(k, 1.0, replanned.to_json())
    if not replanned.feasible:
        raise GoalNotReached(f"the material is not the task's ({fitted.summary()}); re-planned for the refitted "
                             f"material: infeasible, {replanned.binding}: {replanned.hint}", "infeasible")
    return task, replanned


def run(task, out, connect, max_iterations=6):
    """Plan, connect(scene) -> Devices, then iterate; out/report.json (RunResult.to_json) is
    written however the run ends. Raises PlanInfeasible or GoalNotReached (exit 1), or DeviceFault
    (exit 3) after the safe stop of every device (session.Session). Returns the RunResult."""
    from cell.report.pictures import write_convergence
    out, events = Path(out), Events()

    def result(reason, fault):
        err = ending.error
        cause = None if err is None else "infeasible" if isinstance(err, PlanInfeasible) else getattr(err, "cause", None)
        return RunResult(str(task.path), not reason, reason, recorder.plan, tuple(events.iterations),
                         tuple(events.replans), fault, events.black_json, tuple(events.refits), cause)

    try:
        with Recorder(out) as recorder, Ending(recorder, "not converged", "report.json", result,
                                               converged=False) as ending:
            with ending.session:
                planned = plan_and_connect(task, recorder, ending.session, connect)
                for event in iterate(task, planned, ending.session.devices, recorder, max_iterations):
                    events.add(event)
            n = len(events.iterations)
            recorder.step("done", f"converged after {count(n, 'iteration')}", converged=True, iterations=n)
    finally:                                    # after report.json: a failing picture loses no report
        if events.iterations:
            write_convergence(out / "convergence.png", [it.to_json() for it in events.iterations],
                              task.requirements.gray_band, [r.to_json() for r in events.refits])
    return ending.result


class Events:
    """iterate's events gathered as RunResult holds them: every Iteration, the Corrected taken
    after capture k written into capture k's iterations (one per feature in a capture of
    several), Replans, Refitted, and the black level found."""

    def __init__(self):
        self.iterations, self.replans, self.refits, self.black = [], [], [], None

    def add(self, event):
        if isinstance(event, Corrected):
            self.iterations = [replace(it, correction=event.correction) if it.iteration == event.iteration else it
                               for it in self.iterations]
        elif isinstance(event, BlackLevelFound):
            self.black = event.black
        elif isinstance(event, Refitted):
            self.refits.append(event)
        else:
            (self.iterations if isinstance(event, Iteration) else self.replans).append(event)

    @property
    def black_json(self):
        return self.black.to_json() if self.black else None


def count(n, noun):
    return f"{n} {noun}{'s' * (n != 1)}"
