"""The closed loop of `cell run`: plan, drive the cell, capture, measure the
feature's gray, correct (cell.run.control), until every feature pixel is in the gray band or N
iterations have run. It composes the stages: acquisition (plan, connect, move, expose, capture),
measurement, the control law, the device session's safe stop and the recorder's run folder.

One step (`step`) serves a shot of one feature and a shot of several (cell.run.inspection): each
capture measures every LoopFeature of the Aim in its own region; one feature is corrected alone
(and may be refitted and re-planned), several are joined for one exposure. What the steps share
and never change is the RunContext."""
from __future__ import annotations

from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from cell.physics.sensor import saturation_level
from cell.run import acquisition, channels, control, localization, measurement, motion, refit, registration

from cell.planning import evaluate
from cell.run.acquisition import Capture, acquire, plan_and_connect, plan_recorded, planned_drives
from cell.run.context import RunContext
from cell.run.defects import MeasuredDefect, measure as measure_defects, on_defects, unseen
from cell.run.measurement import BlackLevel, Measurement
from cell.run.refit import Refit
from cell.collision.scene import CollisionScene, reaching_joints
from cell.devices.rig import lamp_aim, lamp_joints, lamp_position
from cell.devices.interfaces import speaking_for
from cell.core.errors import GoalNotReached
from cell.planning.plan import gray_stats
from cell.report.recorder import Ending, Recorder, file_name
from cell.report import words
from cell.report.words import count
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.collision.paths import Move, Stop
    from cell.devices.interfaces import Devices
    from cell.planning.plan import Plan, Shot
    from cell.planning.scene import Scene
    from cell.run.registration import Registration
    from cell.task.types import Task


CAUSES = {          # report.json's `cause` of a run that ends without the goal (exit 1): the README's table
    "registration": "the feature appears beyond loop.registration_limit_m from where the model puts it "
                    "(hand-eye or fixture), or could not be registered while its gray was otherwise in band",
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
    "channel": "a light channel gives far less light than the model and the other channels do (its LEDs, "
               "their wiring or the controller's output)",
    "pose": "the part (or the camera) is so far from where the model puts it that the cell cannot work there "
            "(no plan for where it is, the feature leaves the view, the move to the shot planned there collides, "
            "or the views cannot tell the part's position along some direction to within the registration limit)",
    motion.CAUSE: "a move the run must make has no path clear of collisions (both bodies named; nothing moved)",
    "contrast": "the gray is in band but a declared defect measures below its min_cnr in the last capture",
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
    predicted_gray: dict[str, float]
    measured_gray: dict[str, float]
    model_error: float
    model_error_relation: str
    in_band: bool
    capture: str
    annotated: str
    albedo_scale: float
    registration: dict[str, Any]         # registration.Registration.to_json
    correction: dict[str, Any] | None = None
    feature: str | None = None           # its feature's name, in a shot of several (cell.run.inspection)
    drives: dict[str, float] = field(default_factory=dict)   # {channel: level 0..1} read back at the capture
    defects: tuple[MeasuredDefect, ...] = ()     # the feature's declared defects' CNR in this capture

    def to_json(self) -> dict[str, Any]:
        document = {k: getattr(self, k) for k in self.__dataclass_fields__
                    if k not in ("correction", "feature", "drives", "defects")}
        return ({"feature": self.feature} if self.feature else {}) | document | (
            {"drives": self.drives} if self.drives else {}) | (
            {"defects": [d.to_json() for d in self.defects]} if self.defects else {}) | (
            {"correction": self.correction} if self.correction else {})


@dataclass(frozen=True)
class Corrected:
    """The correction taken after iteration `iteration` (its document in report.json)."""

    iteration: int
    correction: dict[str, Any]


@dataclass(frozen=True)
class BlackLevelFound:
    """The sensor's black level the run works with (measurement.BlackLevel)."""

    black: BlackLevel


@dataclass(frozen=True)
class Refitted:
    """The material refitted after iteration `iteration` (refit.Refit) and its file's name."""

    iteration: int
    refit: Refit
    material_file: str

    def to_json(self) -> dict[str, Any]:
        return {"iteration": self.iteration, "material_file": self.material_file} | self.refit.to_json()


@dataclass(frozen=True)
class Replan:
    """A re-plan after iteration `iteration` for an albedo scale (its document in report.json)."""

    iteration: int
    albedo_scale: float
    plan: dict[str, Any]         # its plan.json

    def to_json(self) -> dict[str, Any]:
        return {"iteration": self.iteration, "albedo_scale": self.albedo_scale, "plan": self.plan}


@dataclass(frozen=True)
class Located:
    """The part's and the camera's pose error found at capture `iteration` (cell.run.localization)
    from `views` views, whether the model followed it (re-planned for where the part is), how
    well the views tell the part's position there (None: not judged, the error within what the plan
    tolerates or implausible) and the lamp's aim error the part was located under (None: within
    the lamp tolerance, or not searched)."""

    iteration: int
    error: localization.PoseError
    followed: bool
    resolution: localization.Resolution | None = None
    lamp: localization.LampTurn | None = None

    def to_json(self) -> dict[str, Any]:
        """report.json's `localization`: the estimate (PoseError.to_json), the capture it was
        found at, whether the model followed it, its weakest direction (Resolution.to_json) and
        the lamp's aim error (LampTurn.to_json)."""
        return self.error.to_json() | {"iteration": self.iteration, "followed": self.followed} | (
            self.resolution.to_json() if self.resolution else {}) | (self.lamp.to_json() if self.lamp else {})


Event = Iteration | Corrected | BlackLevelFound | Refitted | Replan | Located     # what iterate yields


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
    localization: dict[str, Any] | None = None     # Located.to_json of the pose error found

    @property
    def captures(self) -> list[str]:
        return [it.capture for it in self.iterations]

    @property
    def counters(self) -> dict[str, int]:
        return {"iterations": len(self.iterations), "captures": len(self.captures), "replans": len(self.replans),
                "refits": len(self.refits)}

    def details(self) -> dict[str, Any]:
        last = self.iterations[-1] if self.iterations else None
        return {"task": self.task, "plan": self.plan, "iterations": [it.to_json() for it in self.iterations],
                "converged": self.success, "captures": self.captures,
                "replans": [r.to_json() for r in self.replans], "black_level": self.black_level,
                "refits": [r.to_json() for r in self.refits], "localization": self.localization,
                **({"gray_band": "any"} if (self.plan or {}).get("gray_band") == "any" else {}),
                **({"defects": [d.to_json() for d in last.defects]} if last is not None and last.defects else {})}


@dataclass(frozen=True)
class Model:
    """The plan the loop works with and the task (its black level) it was planned for."""

    plan: Plan
    task: Task

    def predicted(self, black_level: float, shutter_s: float, f_number: float) -> np.ndarray:
        """The plan's gray per sample at these settings with black level b, G = b + c P t: the
        plan's signal (its gray less the black level it was planned with) ~ t / kappa^2."""
        e = self.plan.shot.exposure
        signal = self.plan.shot.gray - evaluate.black_level(self.task)
        return black_level + signal * (shutter_s / e.shutter_s) * (e.f_number / f_number) ** 2

    def exposure(self, black_level: float, lens_range: tuple[float, float]) -> tuple[float, float]:
        """(shutter, f-number) the planner's closed form sets for the plan's lamp pose with black
        level b (evaluate.centring_exposure on the plan's signal per unit exposure); with
        `gray_band: any`, the plan's exposure gain x = t / kappa^2 by (high - b) / (high - b0) (b0
        the black level planned with): its brightest signal shrinks with the room left below the
        band's top, its headroom for the tolerances kept."""
        e, camera = self.plan.shot.exposure, self.task.camera
        if self.task.requirements.gray_any:
            high, planned = evaluate.planning_band(self.task)[1], evaluate.black_level(self.task)
            gain = e.shutter_s / e.f_number**2 * (high - black_level) / (high - planned)
            shutter, kappa = evaluate.exposure_for_gain(gain, lens_range[0], camera.shutter_range_s, lens_range)
            return float(shutter), float(kappa)
        unit = (self.plan.shot.gray - evaluate.black_level(self.task)) * e.f_number**2 / e.shutter_s
        shutter, kappa, _ = evaluate.centring_exposure(unit[None], evaluate.planning_band(self.task), black_level,
                                                       lens_range[0], camera.shutter_range_s, lens_range)
        return float(shutter[0]), float(kappa[0])


def find_black_level(task: Task, plan: Plan, devices: Devices, recorder: Recorder) -> BlackLevel:
    """acquisition.find_black_level at the planned f-number and focus (a manual lens is not turned
    twice more) with every light channel off, logged with the most light the plan's model lets
    reach the feature in the dark frame: the lights on no channel (all of it without channels),
    their planned gray scaled by the shutter."""
    shot = plan.shot
    e, channels = shot.exposure, planned_drives(shot)
    signal = (sum((light.gray for light in shot.lights if light.channel is None), np.zeros(len(shot.gray)))
              if channels else Model(plan, task).predicted(0.0, e.shutter_s, e.f_number))
    return acquisition.find_black_level(task, devices, recorder, e.f_number, e.focus_m,
                                        lambda shutter_s: float(np.max(signal) * shutter_s / e.shutter_s),
                                        dict.fromkeys(channels, 0.0))


def registration_limit(task: Task, shot: Shot) -> float:
    """How far from where the model puts it the feature may be found [m]: loop.registration_limit_m,
    else what the plan tolerates. A fixture error d turns the lamp's direction to the feature by
    d / r (r the lamp's distance), and the plan holds the band under lamp errors up to
    lamp_tolerance: d = r tan(lamp_tolerance), at least REGISTRATION_FLOOR_M (3.9-4.0 mm on the
    examples: 1 deg at 0.22-0.23 m)."""
    if task.loop.registration_limit_m is not None:
        return task.loop.registration_limit_m
    return max(shot.distance_m * np.tan(task.requirements.lamp_tolerance_rad), REGISTRATION_FLOOR_M)


def limits_of(task: Task, plan: Plan) -> control.Limits:
    """The control.Limits of a one-feature task's plan: its band, the shutter range, the f-numbers
    from the widest the depth of field allows to the lens's narrowest, the plausible albedos."""
    lens_range = (evaluate.depth_of_field_limits(task, plan.planned_scene)[2], task.camera.lens.f_number_range[1])
    low, high = task.requirements.gray_band
    return control.Limits((float(low), float(high)), task.camera.shutter_range_s,
                          lens_range, task.loop.albedo_scale_range)


@dataclass(frozen=True)
class LoopFeature:
    """A feature as the loop drives it: its one-feature task as the loop knows it now (the black
    level measured, the material refitted), the Model of the plan it works with, and the Limits
    of its correction (limits_of its first plan)."""

    task: Task
    model: Model
    limits: control.Limits

    @staticmethod
    def planned(task: Task, plan: Plan) -> LoopFeature:
        """The LoopFeature of a one-feature task and its one-shot plan."""
        return LoopFeature(task, Model(plan, task), limits_of(task, plan))

    @property
    def name(self) -> str:
        """The feature's name in the task."""
        return self.task.feature.name


@dataclass(frozen=True)
class Aim:
    """What the next capture is taken with and judged against: the features it measures (one, or
    a shot's several), the black level, the exposure, the light channels' drives ({channel: level
    0..1}, the plan's: set before every capture), the albedo scale of the plan, whether the cell
    stands at the plan's poses (not after a re-plan), whether the material was refitted and the
    drives re-solved on basis captures (each once in a loop), whether the part was localized
    (once in a loop) and the pose error the model follows (the arm's hand-eye corrected by it),
    and each channel's light measured over the model's by the basis captures (channel_scale)."""

    features: tuple[LoopFeature, ...]
    black: BlackLevel
    shutter_s: float
    f_number: float
    albedo_scale: float = 1.0
    moved: bool = True
    refitted: bool = False
    drives: dict[int, float] = field(default_factory=dict)
    balanced: bool = False
    located: bool = False
    pose_error: localization.PoseError | None = None
    channel_scale: dict[int, float] = field(default_factory=dict)

    @property
    def shot(self) -> Shot:
        """The shot the features' plans share."""
        return self.features[0].model.plan.shot

    def rendered(self, drives: dict[int, float]) -> dict[int, float] | None:
        """The drive levels the model's images are rendered at (registration) for a capture at
        read-back `drives`: each channel's times its measured channel_scale, the light that
        channel really gives (a channel 30 % weaker than modelled changes the feature's shading,
        not only its level); None without channels (every light on)."""
        return {c: level * self.channel_scale.get(c, 1.0) for c, level in drives.items()} or None

    def label(self, feature: LoopFeature) -> str | None:
        """The feature's name in a capture of several (its log lines and picture named by it);
        None in a capture of one."""
        return feature.name if len(self.features) > 1 else None


class Measured(NamedTuple):
    """A feature in one capture: its Iteration, its Measurement and the model's gray per sample."""

    iteration: Iteration
    measurement: Measurement
    predicted: np.ndarray


def locate(ctx: RunContext, feature: LoopFeature, k: int, capture: Capture, name: str | None,
           drives: dict[int, float] | None) -> tuple[Registration, tuple[float, float]]:
    """Registration (cell.run.registration) of the feature in capture k at the read-back camera
    and lamp poses and the light drives the model renders (Aim.rendered), logged (as `name`'s,
    when given); returns (Registration, the shift the measurement takes: the found one when
    trusted and within registration_limit [px], else none)."""
    devices, task, scene = ctx.devices, feature.task, feature.model.plan.planned_scene
    with speaking_for(devices.lamp):
        lamp_pose = devices.lamp.lamp_pose()
    row, col, inside = measurement.sample_pixels(task, capture.T_cell_cam, scene.points)
    found = registration.locate(capture.image, task, scene, capture.T_cell_cam, lamp_pose, row[inside], col[inside],
                                saturation_level(devices.camera.bit_depth), drives)
    ctx.recorder.step("register", f"{name}: " * bool(name) + found.describe(), iteration=k,
                      **({"feature": name} if name else {}), **found.to_json())
    limit = registration_limit(task, feature.model.plan.shot)
    within = found.trusted and registration.beyond_limit(found.to_json(), limit) is None
    return found, found.shift_px if within else (0.0, 0.0)


def measure_capture(ctx: RunContext, aim: Aim, feature: LoopFeature, k: int, capture: Capture) -> Measured:
    """Locate the feature in capture k (locate), measure it where found, in its own image region,
    and compare with its plan's model at the capture's settings (G = b + c P t, the signal ~
    t / kappa^2); in a capture of several its picture is capture-k-<name>.png, else
    capture-k-feature.png."""
    from cell.report.pictures import annotate_capture
    task, model, name = feature.task, feature.model, aim.label(feature)
    f_number = capture.f_number
    bit_depth = ctx.devices.camera.bit_depth
    saturation = saturation_level(bit_depth)
    found, shift = locate(ctx, feature, k, capture, name, aim.rendered(capture.drives))
    seen = measure_defects(capture.image, task, model.plan.planned_scene, capture.T_cell_cam, shift, aim.black.value,
                           {d.name: d.predicted_cnr for d in model.plan.shot.defects})
    marked = on_defects(capture.image, task, model.plan.planned_scene, capture.T_cell_cam, shift, seen)
    m = measurement.measure_feature(capture.image, task, capture.T_cell_cam, model.plan.planned_scene.points,
                                    saturation, shift, marked)
    predicted = model.predicted(aim.black.value, capture.shutter_s, f_number)
    error, relation = control.model_error(m.sample_gray, predicted, saturation, aim.black.value)
    band = task.requirements.gray_band
    in_band = m.in_band(band) and found.trusted        # measured where the feature may not be: never in band
    stats, expected = m.stats(), gray_stats(predicted)
    verdict = (f"{'in' if in_band else 'out of'} band {band[0]:g}-{band[1]:g}" if found.trusted else
               f"not registered: not judged in band {band[0]:g}-{band[1]:g}")
    named = f"{name}: " if name else ""
    caption = f"{k}: {named}gray {m.min:.0f}-{m.max:.0f}, {stats['saturated']} saturated: {verdict}"
    annotated = ctx.recorder.write_image(f"capture-{k}-{file_name(name) if name else 'feature'}.png",
                                         annotate_capture(capture.image, m, bit_depth, caption, marked))
    it = Iteration(k, capture.shutter_s, float(f_number), expected, stats, error, relation, in_band,
                   capture.name, annotated, aim.albedo_scale, found.to_json(), feature=name,
                   drives={str(c): level for c, level in capture.drives.items()}, defects=seen)
    ctx.recorder.step("measure", f"{named}gray mean {stats['mean']:.1f}, {m.min:.1f}-{m.max:.1f} over "
                                 f"{stats['pixels']} px "
                                 f"(pixels {stats['pixel_min']:.0f}-{stats['pixel_max']:.0f}, noise "
                                 f"{stats['noise_rms']:.1f} rms, {stats['saturated']} saturated); the model "
                                 f"predicts {expected['mean']:.1f}, {expected['min']:.1f}-{expected['max']:.1f}; "
                                 f"{control.describe_error(error, relation)}; {verdict}"
                                 + "".join(f"; {d.kind} '{d.name}' CNR {d.describe()}" for d in seen),
                      **{key: v for key, v in it.to_json().items() if key not in ("albedo_scale", "registration")})
    return Measured(it, m, predicted)


def iterate(ctx: RunContext, features: Sequence[LoopFeature], first_capture: int = 1) -> Iterator[Event]:
    """The closed loop of one shot, of one feature or of several measured in each capture
    (captures numbered from first_capture up to ctx.max_iterations: the views a shot is split
    into share its captures, inspection.split_views; none left, GoalNotReached cause `iterations`
    before anything moves): move to the shot's poses, take ctx.black or find the black level (find_black_level,
    BlackLevelFound), then step until every feature is in its band, yielding each Iteration as soon
    as it is measured, then its Corrected and a Replan or Refitted as they happen; raises
    GoalNotReached saying why when no correction is possible or the iterations run out. A black
    level the plan did not know: one feature's task takes it (the re-plans' from then on) and its
    plan's exposure is re-set (Model.exposure; the lamp pose stays: b only shifts the band the
    signal must meet); a shot of several puts it into every prediction and the first capture's
    correction absorbs it."""
    first = features[0]
    if first_capture > ctx.max_iterations:
        raise GoalNotReached(f"{', '.join(f.name for f in features)} not captured: none of the shot's "
                             f"{count(ctx.max_iterations, 'capture')} is left for their view", "iterations")
    devices = localization.corrected(ctx.devices, ctx.pose_error)
    motion.move_to(first.task, devices, first.model.plan.shot, ctx.recorder, first_capture)
    black = ctx.black or find_black_level(first.task, first.model.plan, devices, ctx.recorder)
    if not ctx.black:
        yield BlackLevelFound(black)
    exposure = first.model.plan.shot.exposure
    aim = Aim(tuple(features), black, exposure.shutter_s, exposure.f_number,
              drives=planned_drives(first.model.plan.shot), located=ctx.pose_error is not None,
              pose_error=ctx.pose_error)
    if len(features) == 1 and black.value != evaluate.black_level(first.task):
        aim = knowing_black_level(aim)
    for k in range(first_capture, ctx.max_iterations + 1):
        after = yield from step(ctx, aim, k)
        if after is None:
            return
        aim = after


def knowing_black_level(aim: Aim) -> Aim:
    """The Aim of one feature with a black level its plan did not know: its task's sensor takes
    it, and the plan's lamp pose gets the exposure the planner's closed form sets for it."""
    (feature,) = aim.features
    shutter, f_number = feature.model.exposure(aim.black.value, feature.limits.f_number_range)
    return replace(aim, features=(replace(feature, task=with_black_level(feature.task, aim.black.value)),),
                   shutter_s=shutter, f_number=f_number)


def with_black_level(task: Task, black_level: float) -> Task:
    """The task with its camera's sensor at the black level measured (camera.sensor.black_level)."""
    return replace(task, camera=replace(task.camera, sensor=replace(task.camera.sensor, black_level=black_level)))


def step(ctx: RunContext, aim: Aim, k: int) -> Generator[Event, None, Aim | None]:
    """Capture k, the closed loop's one step: to the plan's poses when not there (after a
    re-plan), expose and capture (acquire; the arm's hand-eye corrected by the pose error the
    model follows), each feature located and measured (measure_capture: its Iteration yielded);
    then the first that applies: a feature found beyond its registration limit, or not registered
    while its gray on the model's region is in band, is localized, once (locate_part), and when the
    model follows it the loop captures again where it is; else one beyond its registration_limit
    stops (the plan's poses do not hold: nothing to correct), as does one not registered whose
    gray on the model's region is in band (no correction changes that, and it is never reported in
    band: registration.not_registered); every feature in its band ends the loop (returns None); a
    correction that would stop at black pixels (the region off the part), or stop with a feature not
    registered (its shading judged on a region that may not be the feature: the hinge turned 3 deg,
    its camera 1 deg, its lamp 2 deg off its aim, read a spread of 1.80 there against the 1.20 the
    feature has), localizes first, once; one
    that stops where the model follows a pose error and a feature is not registered stops with
    cause `pose` (the estimate does not hold: the part is not where it puts it, whatever the gray
    then says); the last iteration stops; else the correction after it (correct_after: the next Aim)."""
    ctx = replace(ctx, devices=localization.corrected(ctx.devices, aim.pose_error))
    if not aim.moved:
        motion.move_to(aim.features[0].task, ctx.devices, aim.shot, ctx.recorder, k)
    capture = acquire(ctx.devices, ctx.recorder, k, aim.shutter_s, aim.f_number, aim.shot.exposure.focus_m,
                      drives=aim.drives)
    measured = [measure_capture(ctx, aim, feature, k, capture) for feature in aim.features]
    yield from (m.iteration for m in measured)
    aim = replace(aim, shutter_s=capture.shutter_s, moved=True)
    for feature, m in zip(aim.features, measured):
        found = m.iteration.registration
        far = registration.beyond_limit(found, registration_limit(feature.task, feature.model.plan.shot))
        unregistered = not found["trusted"] and m.measurement.in_band(feature.task.requirements.gray_band)
        if (far or unregistered) and not aim.located:
            aim = yield from locate_part(ctx, aim, k, capture)
            if not aim.moved:               # the model followed the part: capture again there
                return aim
        why = far or (registration.not_registered(found) if unregistered else None)
        if why:
            name = aim.label(feature)
            reason = f"{name}: {why}" if name else why
            yield Corrected(k, {"action": "stop", "albedo_scale": aim.albedo_scale, "reason": reason,
                                "cause": "registration"})
            raise GoalNotReached(reason, "registration")
    if all(m.iteration.in_band for m in measured):
        return None
    # the control law's verdict, once (locate_part below changes no input of it: it returns where
    # the model follows the part); None where the channels are re-balanced first
    c = None if rebalancing(aim) else correction(aim, measured)
    registered = all(m.iteration.registration["trusted"] for m in measured)
    if c is not None and not aim.located and (c.cause == "black pixels" or (c.action == "stop" and not registered)):
        aim = yield from locate_part(ctx, aim, k, capture)      # off the part, or judged on a region that
        if not aim.moved:                                       # may not be the feature: where is it?
            return aim
    error = aim.pose_error
    if c is not None and c.action == "stop" and error is not None and not registered:
        # the model followed an estimate that does not hold
        why = (f"where the localization puts the part ({localization.describe(error, error.views)}) the "
               f"feature is not found: {c.reason}")
        yield Corrected(k, {"action": "stop", "cause": "pose", "reason": why})
        raise GoalNotReached(why, "pose")
    if k == ctx.max_iterations:
        raise GoalNotReached(not_in_band(aim, measured, k), "iterations")
    return (yield from correct_after(ctx, aim, k, measured, c))


def locate_part(ctx: RunContext, aim: Aim, k: int, capture: Capture) -> Generator[Event, None, Aim]:
    """Localize the part and the camera from capture k (cell.run.localization, against the first
    feature's model and its signal above the black level measured; a saturated capture, whose edges
    are clipped, waits for the next): a pose error
    within what the plan tolerates (localization.significant) is reported (Located) and the loop
    goes on; a larger one is told apart by a second view (second_view), the lamp's aim error
    searched at that estimate (aim_error) and, beyond the lamp tolerance, the part located again
    in the views modelled under the turned lamp (the lamp's fade along the part moves with its aim,
    which the edge fit reads as the part moved: the conrod 2 deg off, 12.7 mm along its shank),
    and, where the part's position stays open by more than the registration limit, by further
    views (resolve: the weakest-direction guard), reported, and the model follows it (follow); a fit beyond any fixture
    or hand-eye error (localization.implausible), or a position still open, stops (GoalNotReached,
    cause `pose`, the open direction named). Returns the Aim."""
    feature = aim.features[0]
    task, scene, shot = with_black_level(feature.task, aim.black.value), feature.model.plan.planned_scene, aim.shot
    saturation = saturation_level(ctx.devices.camera.bit_depth)
    lit = capture.image >= 0.5 * saturation
    if lit.any() and np.mean(capture.image[lit] >= saturation) > registration.SATURATED_FRACTION:
        ctx.recorder.step("localize", "the capture is saturated: the part is localized in a capture the "
                                      "exposure has corrected", iteration=k)
        return aim
    with speaking_for(ctx.devices.lamp):
        lamp_pose = ctx.devices.lamp.lamp_pose()
    first = localization.View(capture.image, capture.T_cell_cam, lamp_pose, capture.drives or None)
    error = localization.localize(task, scene, [first])
    if error is None:
        ctx.recorder.step("localize", "the view shows too little of the part's edges to localize it: the model's "
                                      "pose is kept", iteration=k)
        return replace(aim, located=True)
    limit = registration_limit(task, shot)
    if not localization.significant(error, capture.T_cell_cam, limit, task.requirements.lamp_tolerance_rad):
        ctx.recorder.step("localize", localization.describe(error, 1) + ": within what the plan tolerates",
                          iteration=k, followed=False, **error.to_json())
        yield Located(k, error, False)
        return replace(aim, located=True)
    candidates = clear_views(ctx, task, scene, lamp_pose, capture)
    found_at = motion.standing(task, ctx.devices)
    views = [first]
    second = second_view(ctx, aim, k, scene, lamp_pose, capture, candidates)
    if second is not None:
        views.append(second)
        error = localization.localize(task, scene, views) or error
    turn = None if localization.implausible(error, capture.T_cell_cam) else aim_error(ctx, task, k, scene, views, error)
    if turn is not None:
        views = [turn.applied(v) for v in views]
        error = localization.localize(task, scene, views) or error
    error, resolved, back = resolve(ctx, task, k, scene, capture, views, error, limit, candidates, found_at, turn)
    wrong = localization.implausible(error, capture.T_cell_cam) or (resolved.unresolved(limit) if resolved else None)
    ctx.recorder.step("localize", localization.describe(error, error.views)
                      + (f"; its position {resolved.along} is told to within {1e3 * resolved.uncertainty_m:.1f} mm"
                         if resolved else "")
                      + (f"; under the lamp {np.degrees(turn.angle_rad):.2f} deg off its aim" if turn else ""),
                      iteration=k, followed=not wrong, **error.to_json(),
                      **(resolved.to_json() if resolved else {}), **(turn.to_json() if turn else {}))
    yield Located(k, error, not wrong, resolved, turn)
    if wrong:
        yield Corrected(k, {"action": "stop", "cause": "pose", "reason": wrong})
        raise GoalNotReached(wrong, "pose")
    return (yield from follow(ctx, aim, k, error, back))


def aim_error(ctx: RunContext, task: Task, k: int, scene: Scene, views: Sequence[localization.View],
              error: localization.PoseError) -> localization.LampTurn | None:
    """The lamp's aim error at the estimate (localization.lamp_turn over the views that share the
    first view's lamp pose), logged; None where it is within the task's lamp tolerance: the plan
    holds the band under such a turn, and the search finds sub-degree turns where the lamp is on
    its aim (the model's shading differs from the world's by more than a small turn does). Beyond
    it the loop locates the part again with the lamp so turned (locate_part)."""
    turn = localization.lamp_turn(task, scene, views, error)
    degrees = np.degrees(turn.angle_rad)
    tolerance = np.degrees(task.requirements.lamp_tolerance_rad)
    if turn.angle_rad <= task.requirements.lamp_tolerance_rad:
        ctx.recorder.step("localize", f"the lamp's aim found {degrees:.2f} deg off, within the {tolerance:g} deg "
                                      "the plan tolerates: the model's aim kept", iteration=k, **turn.to_json())
        return None
    ctx.recorder.step("localize", f"the lamp's aim found {degrees:.2f} deg off (its axis "
                                  f"{np.round(turn.axis, 4).tolist()} in the cell; the edges' cost {turn.cost:.3f} "
                                  f"per sample, {turn.unturned_cost:.3f} on its aim), beyond the {tolerance:g} deg "
                                  "the plan tolerates: the part located again under the turned lamp",
                      iteration=k, **turn.to_json())
    return turn


def clear_views(ctx: RunContext, task: Task, scene: Scene, lamp_pose: registration.LampPose,
                capture: Capture) -> list[np.ndarray]:
    """The camera poses of the further views (localization.second_views about capture's) that the
    arm reaches and the collision check clears at the pose with the lamp where it is."""
    return [T for T in localization.second_views(capture.T_cell_cam, scene.center) if clear(ctx, task, T, lamp_pose[0])]


def clear(ctx: RunContext, task: Task, T_cell_cam: np.ndarray, lamp_position_m: np.ndarray) -> bool:
    """Whether the arm reaches the camera pose and the collision check clears the cell there with
    the lamp at that position."""
    return (ctx.devices.arm.refusal(T_cell_cam) is None and CollisionScene.of(task).clearance(
        T_cell_cam, reaching_joints(task.frames, T_cell_cam), lamp_position_m).ok)


def second_view(ctx: RunContext, aim: Aim, k: int, scene: Scene, lamp_pose: registration.LampPose,
                capture: Capture, candidates: Sequence[np.ndarray]) -> localization.View | None:
    """The second view of the part: of the candidates (clear_views), the one whose information with
    the first view's is best conditioned (localization.by_information) and whose path there is
    clear (take_view), captured as locate-k.png; None when no pose serves (the one view's
    estimate stands, and the log says so)."""
    task = aim.features[0].task
    first = localization.View(capture.image, capture.T_cell_cam, lamp_pose, capture.drives or None)
    ordered = localization.by_information(task, scene, first, candidates) if candidates else []
    view = take_view(ctx, task, k, scene, capture, [(T, None) for T in ordered], f"locate-{k}", "the second view",
                     "a second view of the part, to tell a part offset from a camera turn")
    if view is None:
        ctx.recorder.step("localize", "no second view of the part is reachable and clear of collisions: one view "
                                      "cannot tell a part offset from a camera turn", iteration=k)
    return view


def take_view(ctx: RunContext, task: Task, k: int, scene: Scene, capture: Capture,
              ordered: Sequence[tuple[np.ndarray, tuple[float, float, float] | None]], name: str, to: str,
              why: str, back: Stop | None = None) -> localization.View | None:
    """The first of the ordered (camera pose, lamp joints or None: the lamp where it is) whose
    path there is clear (motion.check; `to` names it) and, given `back` (a Stop read before), the
    path from there back to it too (motion.check_back), moved to (motion.move_camera; logged with
    `why`), exposed for the model's brightest part there (localization.view_exposure) at capture's
    f-number, focus and drives and captured as `name`.png, with the lamp's read-back pose; None
    when no path is clear."""
    drives = capture.drives or None
    for T, joints in ordered:
        move = motion.check(task, ctx.devices, T, joints, to=to)
        if not move.clear or (back is not None and not motion.check_back(
                task, ctx.devices, move, T, joints, back, to, "the pose the part was found at").clear):
            continue
        read = motion.move_camera(task, ctx.devices, T, ctx.recorder, to, k, move, joints)
        ctx.recorder.step("move_camera", f"camera at {np.round(read[:3, 3], 4).tolist()} m in the cell frame: {why}",
                          iteration=k, position_m=read[:3, 3])
        with speaking_for(ctx.devices.lamp):
            lamp_pose = ctx.devices.lamp.lamp_pose()
        model = localization.model_view(task, scene, read, lamp_pose, drives)
        shutter = localization.view_exposure(model, saturation_level(ctx.devices.camera.bit_depth), capture.f_number,
                                             task.camera.shutter_range_s)
        view = acquire(ctx.devices, ctx.recorder, k, shutter, capture.f_number, capture.focus_m, name=name,
                       drives=drives)
        return localization.View(view.image, view.T_cell_cam, lamp_pose, view.drives or None)
    return None


def resolve(ctx: RunContext, task: Task, k: int, scene: Scene, capture: Capture, views: list[localization.View],
            error: localization.PoseError, limit_m: float, candidates: Sequence[np.ndarray], found_at: Stop,
            turn: localization.LampTurn | None = None
            ) -> tuple[localization.PoseError, localization.Resolution | None, Stop | None]:
    """The weakest-direction guard: how well the views (capture's first; appended to) tell the
    part's position where the estimate puts it (localization.resolution of their
    rendered_information); where it stays open beyond limit_m along some direction
    (Resolution.unresolved), a further view, the candidate not yet tried that tells it best
    (localization.by_resolution; take_view): the camera poses (candidates) with the lamp where it
    is, and the first two views' camera poses with the lamp low along that direction
    (localization.lamps_along: what stands up along it casts shadows across the part), each
    cleared at its pose as clear_views does; the part localized in every view again from the
    estimate moved along that direction as the rendered images fit best (localization.localize's
    `along`); at most localization.MAX_EXTRA_VIEWS. A further view with which the fit is
    implausible (localization.implausible: it matched the wrong edges there) is logged and left
    out, the estimate before it kept. The lamp goes back to the plan's pose with the next shot's
    move. Where the guard took a further view, one more from the side of the direction it found
    open (localization.sideways), every view fitted again from the model's pose and along that
    direction, the better (localization.better) refined at the fine scales (localization.side_refit:
    against the model rendered where that fit put the part, the position the views told kept);
    where it took none but the fit's own tilt across the first view is told worse than the plan
    tolerates (localization.untold_tilt; side_direction), one from the side of the direction that tilt moves the
    part's points along the first view's axis, the first views' estimate refined at the fine
    scales (side_refit: they told the position). The side view: the lamp back at the first view's pose, among the
    candidates whose move there and whose way back to `found_at` (where the devices stood at
    capture k, motion.check_back) are clear: the move on to where the loop goes next is known only
    after the fit (follow goes back first where it is refused); none clear, the side view is
    skipped and the log says so. Returns the estimate, its covariance widened by what the views tell over
    their residual (PoseError.widened by Resolution.covariance: the edge fit's own covers its
    noise, not a tilt the views leave open that the fit holds where the model's image was
    rendered), its Resolution (None where the first estimate is implausible: nothing to resolve)
    and `found_at` where the arm stands at the side view (None: it does not). Given the lamp's aim
    error found (`turn`: aim_error), every view taken with the lamp at the pose it was found at
    is modelled under the turned lamp (LampTurn.applied), the lamp-low views under their own aim,
    and the view from the side is taken whatever the fit's own tilt says (a tilt along the part and
    the lamp turned along it both move the light along it, traded in two views: the conrod tilted
    3 deg, its lamp 2 deg off, fitted 3.3 deg short with a standard error of 0.15 deg), every view
    fitted again from the model's pose (side_refit held that tilt)."""
    if localization.implausible(error, capture.T_cell_cam):
        return error, None, None
    lamp_pose, pivot = views[0].lamp_pose, task.lamp.rig.pivot_m
    radius = float(np.linalg.norm(np.asarray(lamp_pose[0]) - pivot))
    tried = [(v.T_cell_cam[:3, 3], np.asarray(v.lamp_pose[0])) for v in views]

    def judged(error: localization.PoseError) -> tuple[list[localization.Told], localization.Resolution]:
        told = localization.rendered_information(task, scene, error, [(v.T_cell_cam, v.lamp_pose, v.drives)
                                                                      for v in views], [v.image for v in views])
        return told, localization.resolution(task, scene, told, len(told))

    def lit(joints: tuple[float, float, float] | None) -> registration.LampPose:
        if joints is None:
            return lamp_pose
        position = lamp_position(pivot, *joints)
        return position, lamp_aim(pivot, position)

    def aimed(view: localization.View | None) -> localization.View | None:
        return view if view is None or turn is None else turn.applied(view)

    def new(T: np.ndarray, joints: tuple[float, float, float] | None) -> bool:
        return bool(min(np.linalg.norm(T[:3, 3] - c) + np.linalg.norm(lit(joints)[0] - l) for c, l in tried) > 0.005)

    told, resolved = judged(error)
    opened = None                       # the direction the guard found open, if it took a further view
    for _ in range(localization.MAX_EXTRA_VIEWS):
        open_by = resolved.unresolved(limit_m)
        lamps = [(v.T_cell_cam, joints) for v in views[:2]
                 for joints in localization.lamps_along(task, resolved.direction, radius)
                 if clear(ctx, task, v.T_cell_cam, lit(joints)[0])]
        left = [(T, joints) for T, joints in [*((T, None) for T in candidates), *lamps] if new(T, joints)]
        if open_by is None or not left:
            break
        opened = resolved
        ctx.recorder.step("localize", f"{localization.describe(error, error.views)}: {open_by}: a further view",
                          iteration=k, **error.to_json(), **resolved.to_json())
        infos = localization.rendered_information(task, scene, error, [(T, lit(joints), views[0].drives)
                                                                       for T, joints in left])
        ordered = [left[i] for i in localization.by_resolution(task, scene, told, infos)]
        view = aimed(take_view(ctx, task, k, scene, capture, ordered, f"locate-{k}-{len(tried) + 1}",
                               "a further view", f"a further view of the part, to tell its position {resolved.along}"))
        if view is None:
            break
        tried.append((view.T_cell_cam[:3, 3], np.asarray(view.lamp_pose[0])))
        further = localization.localize(task, scene, [*views, view], (error, resolved.direction)) or error
        wrong = localization.implausible(further, capture.T_cell_cam)
        if wrong:
            ctx.recorder.step("localize", f"with the further view {wrong}: that view is left out, the estimate of "
                                          f"{count(len(views), 'view')} kept", iteration=k, **further.to_json())
            continue
        views.append(view)
        error = further
        told, resolved = judged(error)
    side_of = side_direction(ctx, task, scene, k, error, views[0], opened, turn)
    if side_of is not None:            # a view from the side, the lamp back where the first view had it
        direction, named = side_of
        pan, tilt, length = (float(j) for j in lamp_joints(pivot, lamp_pose[0]))
        home = (pan, tilt, length)
        side = [(T, home) for T in (candidates[i] for i in localization.sideways(
            candidates, views[0].T_cell_cam, scene.center, direction, lamp_pose[0])) if new(T, home)]
        seen = aimed(take_view(ctx, task, k, scene, capture, side, f"locate-{k}-{len(tried) + 1}",
                               "a view from the side", f"a view of the part from the side, to tell its tilt {named}",
                               found_at))
        if seen is None:
            ctx.recorder.step("localize", f"no view from the side of the part {named} is reachable with "
                                          "its move there and its way back to the pose the part was found at clear: "
                                          "the side view is skipped, the estimate's standard errors widened by what "
                                          "the views tell", iteration=k)
        fitted = (None if seen is None else localization.localize(task, scene, [*views, seen])
                  if opened is not None or turn is not None
                  else localization.side_refit(task, scene, [*views, seen], error))
        if seen is not None and fitted is not None and not localization.implausible(fitted, capture.T_cell_cam):
            along = None if opened is None else localization.localize(task, scene, [*views, seen],
                                                                       (error, opened.direction))
            views.append(seen)
            error = fitted if along is None else localization.side_refit(task, scene, views,
                                                                         localization.better(fitted, along))
            told, resolved = judged(error)
        return error.widened(resolved.covariance), resolved, None if seen is None else found_at
    return error.widened(resolved.covariance), resolved, None


def side_direction(ctx: RunContext, task: Task, scene: Scene, k: int, error: localization.PoseError,
                   first: localization.View, opened: localization.Resolution | None,
                   turn: localization.LampTurn | None) -> tuple[np.ndarray, str] | None:
    """Whether resolve takes a view from the side of the part, and along which direction (with
    its words): along the direction the guard found open where it took a further view (`opened`);
    otherwise along the direction the fit's own tilt across the first view moves the part's points
    along its axis (localization.untold_tilt), where that tilt is told worse than
    TILT_TOLD x the plan's lamp tolerance, or whatever it is told under a lamp's turn found (`turn`:
    a tilt along the part and the lamp turned along it both move the light along it, traded in
    two views), the reason logged; None: no side view."""
    if opened is not None:
        return opened.direction, opened.along
    tolerance = 0.0 if turn is not None else task.requirements.lamp_tolerance_rad
    untold = localization.untold_tilt(error, first.T_cell_cam, tolerance)
    if untold is None:
        return None
    named = localization.along(task, scene, untold[0])
    tolerated = np.degrees(localization.TILT_TOLD * tolerance)
    why = (f"its tilt {named} and the lamp's turn both move the light along the part" if turn is not None
           else f"its tilt {named} is told to within {np.degrees(untold[1]):.2f} deg, more than the "
                f"{tolerated:.2f} deg the plan tolerates")
    ctx.recorder.step("localize", f"{localization.describe(error, error.views)}: {why}: a view from the side",
                      iteration=k, **error.to_json())
    return untold[0], named


def follow(ctx: RunContext, aim: Aim, k: int, error: localization.PoseError, back: Stop | None = None
           ) -> Generator[Event, None, Aim]:
    """The model follows the pose error found at capture k: the arm's hand-eye corrected, each
    feature's task with the part where it is (localization.located_task); one feature re-planned
    there (the camera kept on the part: a planned shot's pose moved with it), several carried
    along with the part (localization.moved_plan; that shot's move refused, its viewpoint
    re-planned for where the part is: carried_viewpoint, which raises Split where the features
    need several shots). A re-plan that is infeasible or a feature that
    leaves the view stops (GoalNotReached, cause `pose`). The re-plan searches the lamp among the
    poses clear of the cell's bodies where the corrected hand-eye puts the camera
    (one_shot.plan's). As a last resort, where none of them meets every requirement
    (the re-plan's `collision` binding: the best pose that meets them is under the padding) or
    the move to the re-planned shot is refused (no path clear), the loop's plan carried along with
    the part serves (lamp_kept); its move refused too, the run stops (cause `pose`). Where the arm
    stands at the side view (`back`: where it stood at capture k, the way there checked before
    it left), every move on is checked from there and, refused, from `back` (went_back)."""
    features = tuple(replace(f, task=localization.located_task(f.task, error)) for f in aim.features)
    reason = f"the model follows the part: {localization.describe(error, error.views)}"
    document = {"action": "locate", "reason": reason, "localization": error.to_json()}
    if len(features) > 1:
        features = tuple(replace(f, model=Model(localization.moved_plan(f.model.plan, error.T_part), f.task))
                         for f in features)
        ctx.recorder.step("correct", reason, iteration=k, **document)
        yield Corrected(k, document)
        went_back(ctx, features[0].task, features[0].model.plan.shot, error, back, k)
        features, viewpoint = carried_viewpoint(ctx, features, error)
        if viewpoint:
            why = f"{reason}; {viewpoint}"
            ctx.recorder.step("correct", why, iteration=k, action="locate", viewpoint=True)
            yield Corrected(k, document | {"viewpoint": why})
        return replace(aim, features=features, moved=False, located=True, pose_error=error)
    (feature,) = features
    T_cell_cam = None if ctx.T_cell_cam is None else error.T_part @ ctx.T_cell_cam
    ctx.recorder.step("correct", reason, iteration=k, **document)
    yield Corrected(k, document)
    replanned = plan_recorded(feature.task, ctx.recorder, aim.albedo_scale, iteration=k, subfolder=f"located-{k}",
                              T_cell_cam=T_cell_cam, clear=True)
    yield Replan(k, aim.albedo_scale, replanned.to_json())
    if not replanned.feasible and replanned.binding != "collision":
        why = f"{localization.describe(error, error.views)}; re-planned for where the part is"
        raise GoalNotReached(f"{why}: infeasible, {replanned.binding}: {replanned.hint}", "pose",
                             f"{why}: infeasible: {words.reason(replanned)}")
    row, col, inside = measurement.sample_pixels(feature.task, replanned.shot.T_cell_cam,
                                                 replanned.planned_scene.points)
    if not np.all(inside):
        raise GoalNotReached(f"{localization.describe(error, error.views)}: {int(np.sum(~inside))} of the "
                             f"feature's {len(inside)} samples leave the view where the part is", "pose")
    went_back(ctx, feature.task, (replanned if replanned.feasible else
                                  localization.moved_plan(feature.model.plan, error.T_part)).shot, error, back, k)
    if replanned.feasible:
        move = where_located(ctx, feature.task, replanned.shot, error)
        if move.clear:
            located = replace(feature, model=Model(replanned, feature.task))
            return replace(replan_aim(aim, located, aim.albedo_scale), located=True, pose_error=error)
        refused = f"the move there is refused: {motion.refusal(move)}"
    else:
        refused = ("no lamp pose clear of the cell's bodies meets every requirement (the best that does: "
                   f"{replanned.hint})")
    kept = lamp_kept(ctx, feature, error, refused)
    ctx.recorder.step("correct", kept.why, iteration=k, action="locate", lamp_kept=kept.why)
    yield Corrected(k, document | {"lamp_kept": kept.why})
    located = replace(feature, model=Model(kept.plan, feature.task))
    return replace(replan_aim(aim, located, aim.albedo_scale), shutter_s=aim.shutter_s, f_number=aim.f_number,
                   located=True, pose_error=error)


def went_back(ctx: RunContext, task: Task, shot: Shot, error: localization.PoseError, back: Stop | None,
              k: int) -> None:
    """Where the arm stands at the view from the side (`back` given: where it stood at capture k,
    the way back there checked before the side view was taken) and the move from there to the
    shot planned for where the part is (where_located) is refused, the arm goes back first
    (motion.go_back, checked again from where it reads back; the lamp stays, at the first
    view's pose), logged with the refusal; the loop's checks then start there. Otherwise nothing
    moves."""
    if back is None:
        return
    move = where_located(ctx, task, shot, error)
    if move.clear:
        return
    read = motion.go_back(task, ctx.devices, back, ctx.recorder, "the pose the part was found at", k)
    ctx.recorder.step("move_camera", f"camera at {np.round(read[:3, 3], 4).tolist()} m in the cell frame: back where "
                                     f"the part was found, the move on from the side view refused "
                                     f"({motion.refusal(move)})", iteration=k, position_m=read[:3, 3])


class Kept(NamedTuple):
    """The plan carried along with the part (lamp_kept) and why the re-plan's was not taken."""

    plan: Plan
    why: str


def lamp_kept(ctx: RunContext, feature: LoopFeature, error: localization.PoseError, refused: str) -> Kept:
    """Where the shot re-planned for where the part is cannot be taken (`refused`, in words: no
    lamp pose clear of the cell's bodies meets every requirement, or the move there is refused):
    the plan the loop works with carried along with the part (localization.moved_plan: the
    camera's view of the part kept, the lamp at its planned joints, turned about its fixed pivot,
    so it lights the part from nearly where it did; capture k's exposure, which the loop corrects
    for the light it then gives), its move checked (where_located). Refused too: GoalNotReached,
    cause `pose`, naming the pose found and both refusals; nothing moved."""
    carried = localization.moved_plan(feature.model.plan, error.T_part)
    move = where_located(ctx, feature.task, carried.shot, error)
    if not move.clear:
        raise GoalNotReached(f"{there(error, refused)}; with the lamp kept at the plan's pose: "
                             f"{motion.refusal(move)}", "pose")
    return Kept(carried, f"re-planned for where the part is, {refused}: the plan's lamp pose kept as the last "
                         f"resort, the camera moved with the part (its move clear: {motion.how_apart(move)})")


def where_located(ctx: RunContext, task: Task, shot: Shot, error: localization.PoseError) -> Move:
    """The move to the shot planned for where the localization puts the part (the task's part
    there, the arm's hand-eye corrected), checked from where the devices stand (motion.check:
    either order of the camera and the lamp, via points); moves nothing."""
    return motion.check(task, localization.corrected(ctx.devices, error), shot.T_cell_cam, shot.joints,
                        "the shot's poses")


def carried_viewpoint(ctx: RunContext, features: Sequence[LoopFeature], error: localization.PoseError
                      ) -> tuple[tuple[LoopFeature, ...], str | None]:
    """A shot's features, their tasks and plans carried along with the part where `error` puts it
    (localization.located_task, moved_plan), as the loop takes them there: as they are where the
    move to their shot is clear (where_located; None), else re-planned at a viewpoint for the
    located part (viewpoint_replanned: Split where they need several shots, GoalNotReached
    cause `pose` where no viewpoint serves) with why, in words."""
    move = where_located(ctx, features[0].task, features[0].model.plan.shot, error)
    if move.clear:
        return tuple(features), None
    refused = f"the carried shot's move is refused: {motion.refusal(move)}"
    located = viewpoint_replanned(ctx, features, error, refused)
    return located, f"{refused}; {count(len(located), 'feature')} re-planned at a new viewpoint"


def viewpoint_replanned(ctx: RunContext, features: Sequence[LoopFeature], error: localization.PoseError,
                        refused: str) -> tuple[LoopFeature, ...]:
    """A shot's features (one or several, their tasks already where the part is: a shot localized
    in itself, or a later one, inspection.run_shot) re-planned for the
    located part where the shot carried along with it cannot be taken (`refused`: its camera
    pose out of the arm's reach or its move not clear): the whole-part planner
    (whole_part.plan_features: viewpoints over the sphere, reach and collisions pruned, the
    fewest shots) on the task of those features alone, its one shot if one covers them all, each
    feature's plan there (whole_part.feature_plan), its move checked (where_located); several
    shots: Split (the caller runs each). Infeasible there or the one shot's move refused:
    GoalNotReached, cause `pose`, the carried shot's refusal named first; nothing moved."""
    from cell.planning.whole_part import feature_plan, plan_features
    task = replace(features[0].task, features=tuple(f.task.feature for f in features))
    plan = plan_features(task)
    if not plan.feasible:
        raise GoalNotReached(there(error, f"{refused}; the shot's viewpoint re-planned: {words.reason(plan)}"), "pose")
    if len(plan.shots) > 1:
        raise Split(task, plan, error, refused)
    located = tuple(replace(f, model=Model(feature_plan(plan, 0, i), f.task)) for i, f in enumerate(features))
    move = where_located(ctx, located[0].task, located[0].model.plan.shot, error)
    if not move.clear:
        raise GoalNotReached(there(error, f"{refused}; at the re-planned viewpoint: {motion.refusal(move)}"), "pose")
    return located


class Split(Exception):
    """A shot of several features that, re-planned for where the part is (viewpoint_replanned)
    since the shot carried there was `refused` (in words), needs several shots: `plan`
    (whole_part.plan_features') of `task` (those features, the part where `error` puts it);
    whoever runs the shot (inspection.run_shot) visits each of them."""

    def __init__(self, task: Task, plan: Plan, error: localization.PoseError, refused: str) -> None:
        super().__init__(f"the shot's features re-planned for where the part is need {len(plan.shots)} shots")
        self.task, self.plan, self.error, self.refused = task, plan, error, refused


def there(error: localization.PoseError, refused: str) -> str:
    """A stop where the shot planned for the part's pose cannot be taken: the pose found, then
    what was `refused` there."""
    return f"{localization.describe(error, error.views)}; re-planned for where the part is, {refused}"


def not_in_band(aim: Aim, measured: Sequence[Measured], k: int) -> str:
    """Why the loop stops after its last iteration k: the gray of each feature against its band."""
    at = f"{1e3 * aim.shutter_s:.3g} ms, f/{aim.f_number:.1f}"
    if len(measured) == 1:
        (it, m, _), band = measured[0], aim.features[0].limits.band
        return (f"not in band {band[0]:g}-{band[1]:g} after {count(k, 'iteration')}: feature gray "
                f"{m.min:.1f}-{m.max:.1f} ({it.measured_gray['saturated']} pixels saturated) at {at}; "
                f"{control.describe_error(it.model_error, it.model_error_relation)}")
    return f"not every feature in band after {count(k, 'iteration')} at {at}: " + "; ".join(
        f"{f.name} {m.min:.1f}-{m.max:.1f} (band {f.limits.band[0]:g}-{f.limits.band[1]:g}, "
        f"{it.measured_gray['saturated']} saturated)" for f, (it, m, _) in zip(aim.features, measured))


def correction(aim: Aim, measured: Sequence[Measured]) -> control.Correction:
    """The control law on a capture's measurements: one feature's Correction (control.correct), or
    the one exposure of several features, their measurements joined (control.shared_correction)."""
    if len(measured) == 1:
        (feature,), (_, m, predicted) = aim.features, measured[0]
        return control.correct(m, predicted, aim.shutter_s, aim.f_number, feature.limits, aim.black,
                               aim.albedo_scale)
    return control.shared_correction([f.name for f in aim.features], measured, [f.limits for f in aim.features],
                                     aim.shutter_s, aim.f_number, aim.black)


def correct_after(ctx: RunContext, aim: Aim, k: int, measured: Sequence[Measured],
                  c: control.Correction | None) -> Generator[Event, None, Aim]:
    """Act on capture k's correction `c` (correction(aim, measured); None where the channels are
    re-balanced first: rebalance) (Corrected, logged but for a stop): a shape that disagrees
    with one feature's model refits the material and re-plans, once (refit_and_replan); a stop
    raises GoalNotReached with its cause; an exposure sets the next one; a re-plan plans one
    feature again with the albedo scale times the measured model error, its lamp among the poses
    clear of the cell's bodies (one_shot.plan's; Replan; infeasible, a collision the
    cause where only colliding poses meet every requirement: GoalNotReached). A shot of several
    features is not refitted or re-planned (control.shared_correction stops instead)."""
    if c is None:
        return (yield from rebalance(ctx, aim, k, measured))
    if c.action == "stop" and c.cause == "spread" and len(aim.features) == 1 and not aim.refitted:
        return (yield from refit_and_replan(ctx, aim, k, measured[0], c))
    if c.action == "stop":                  # its cause in report.json; the done step says why
        yield Corrected(k, c.document(aim.albedo_scale))
        raise GoalNotReached(c.reason, c.cause)
    albedo = aim.albedo_scale * c.model_error if c.action == "replan" else aim.albedo_scale
    ctx.recorder.step("correct", c.message(aim.shutter_s, aim.f_number, albedo), iteration=k, **c.document(albedo))
    yield Corrected(k, c.document(albedo))
    if c.action == "exposure":
        return replace(aim, shutter_s=c.shutter_s, f_number=c.f_number)
    (feature,) = aim.features
    replanned = plan_recorded(feature.task, ctx.recorder, albedo, iteration=k, subfolder=f"replan-{k}",
                              T_cell_cam=ctx.T_cell_cam, clear=True)
    yield Replan(k, albedo, replanned.to_json())
    if not replanned.feasible:
        why = (f"{control.describe_error(c.model_error, c.relation)}; {c.reason}; "
               f"re-planned for an albedo x{albedo:.3g}")
        raise GoalNotReached(f"{why}: infeasible, {replanned.binding}: {replanned.hint}", "infeasible",
                             f"{why}: infeasible: {words.reason(replanned)}")
    return replan_aim(aim, replace(feature, model=Model(replanned, feature.task)), albedo)


def rebalancing(aim: Aim) -> bool:
    """Whether the correction after a capture out of band re-solves the light channels' drives
    first (rebalance): a shot lit by several lights on the controller, of one feature or of
    several, not yet balanced."""
    return bool(aim.features[0].task.lights) and bool(aim.drives) and not aim.balanced


def rebalance(ctx: RunContext, aim: Aim, k: int, measured: Sequence[Measured]) -> Generator[Event, None, Aim]:
    """After capture k of a shot lit by several lights, out of band: one basis capture per
    channel on (cell.run.channels: each at its drive, the others off, at capture k's exposure),
    read where capture k found each feature, and the drives, shutter and f-number re-solved on the
    measured shares over every feature's samples, each sample against its own feature's band (as
    the planner's joint program, cell.planning.joint: bands with nothing in common are no
    obstacle) and f-numbers no wider than every feature's depth of field allows (Corrected,
    action `drives`; each feature's Model predicts the measured shares at the new drives from then
    on, and the model's images for registration are rendered with each channel's measured scale,
    Aim.channel_scale). A channel far below the others against the model is named; when no drives put every
    feature in band, a channel fault is the cause (`channel`), else the band is infeasible as
    measured (`infeasible`)."""
    task, e = aim.features[0].task, aim.shot.exposure
    gain = aim.shutter_s / aim.f_number**2
    counts = [len(m.predicted) for m in measured]

    def capture_with(levels: dict[int, float], name: str) -> np.ndarray:
        capture = acquire(ctx.devices, ctx.recorder, k, aim.shutter_s, aim.f_number, e.focus_m,
                          name=f"basis-{k}-{name}", drives=levels)
        return np.concatenate([measurement.surface_at_samples(capture.image, m.measurement) for m in measured])

    lights = channels.joined([f.model.plan.shot.lights for f in aim.features])
    shares = channels.measure(lights, aim.drives, gain / (e.shutter_s / e.f_number**2), aim.black.value,
                              capture_with)
    bands = [evaluate.planning_band(f.task) for f in aim.features]
    low, high = (np.repeat([b[end] for b in bands], counts) for end in (0, 1))     # each sample its feature's
    settings = {c.number: c for c in [task.lamp.channel, *(light.channel for light in task.lights)]
                if c.number is not None}
    basis = channels.resolve(shares, gain, (low, high), aim.black.value,
                             max(f.limits.f_number_range[0] for f in aim.features), task.camera.shutter_range_s,
                             task.camera.lens.f_number_range, {n: c.drive_range for n, c in settings.items()},
                             {n: c.switched for n, c in settings.items()},
                             max(f.task.requirements.drive_tolerance for f in aim.features))
    ctx.recorder.step("basis", basis.describe(), iteration=k, **basis.to_json())
    fault = basis.fault()
    if not basis.solved.feasible:
        cause, reason = (("channel", fault) if fault else
                         ("infeasible", f"re-solved on the measured light of each channel: {basis.solved.message}"))
        yield Corrected(k, {"action": "stop", "cause": cause, "reason": reason} | basis.to_json())
        raise GoalNotReached(reason, cause)
    solved = basis.solved
    drives = {c: 0.0 for c in aim.drives} | {s.channel: float(w) for s, w in zip(shares, solved.drive)
                                             if s.channel is not None}
    doc = ({"action": "drives", "reason": basis.describe() + (f"; {fault}" if fault else "")} | basis.to_json()
           | {"drives": {str(c): w for c, w in sorted(drives.items())}})
    ctx.recorder.step("correct", "drives re-solved on the basis captures: " + ", ".join(
        f"channel {c} at {100 * w:.1f} %" for c, w in sorted(drives.items())) +
        f", {1e3 * solved.shutter_s:.3g} ms, f/{solved.f_number:.1f}", iteration=k, **doc)
    yield Corrected(k, doc)
    ends = np.cumsum([0, *counts])
    features = tuple(replace(f, model=measured_model(f, shares, gain, drives, solved.shutter_s, solved.f_number,
                                                     slice(a, b)))
                     for f, a, b in zip(aim.features, ends[:-1], ends[1:]))
    scale = {s.channel: s.scale for s in shares if s.channel is not None and np.isfinite(s.scale)}
    return replace(aim, features=features, drives=drives, shutter_s=solved.shutter_s, f_number=solved.f_number,
                   balanced=True, channel_scale=scale)


def measured_model(feature: LoopFeature, shares: Sequence[channels.Share], gain: float, drives: dict[int, float],
                   shutter_s: float, f_number: float, samples: slice = slice(None)) -> Model:
    """The Model of the measured shares at new drives and exposure: its plan's shot predicts each
    light's share (measured at capture gain t / kappa^2 on the feature's `samples` of the shares'
    samples, scaled to its new drive and exposure) and their sum over the task's black level, so
    that Model.predicted scales it as the plan's."""
    plan, task = feature.model.plan, feature.task
    shot = plan.shot
    new_gain = shutter_s / f_number**2
    by_channel = {s.channel: s for s in shares}
    lights = []
    for light in shot.lights:
        share = by_channel.get(light.channel)
        if light.channel is None or share is None:       # off, or always on (the no-channel capture's)
            drive = 0.0 if light.channel is not None else light.drive
            fixed = by_channel.get(None)
            gray = (np.zeros_like(light.gray) if light.channel is not None or fixed is None
                    else fixed.unit(gain)[samples] * new_gain / max(len(fixed.names), 1))
            lights.append(replace(light, drive=drive, gray=gray))
        else:
            lights.append(replace(light, drive=drives[light.channel],
                                  gray=share.unit(gain)[samples] * drives[light.channel] * new_gain))
    signal = sum((light.gray for light in lights), np.zeros(len(shot.gray)))
    exposure = replace(shot.exposure, shutter_s=shutter_s, f_number=f_number)
    new_shot = replace(shot, exposure=exposure, lights=tuple(lights), gray=evaluate.black_level(task) + signal)
    return Model(replace(plan, shots=(new_shot,)), task)


def replan_aim(aim: Aim, feature: LoopFeature, albedo_scale: float) -> Aim:
    """The Aim at a re-plan of the one feature (its Model the new plan): the plan's exposure and
    drives, the cell still to move to its poses."""
    shot = feature.model.plan.shot
    return replace(aim, features=(feature,), shutter_s=shot.exposure.shutter_s, f_number=shot.exposure.f_number,
                   albedo_scale=albedo_scale, moved=False, drives=planned_drives(shot))


def refit_and_replan(ctx: RunContext, aim: Aim, k: int, measured: Measured,
                     c: control.Correction) -> Generator[Event, None, Aim]:
    """After capture k whose shape disagreed with the feature's model (Correction c, cause
    spread): probe, refit the material (cell.run.refit; Corrected, Refitted) and re-plan with it
    (Replan; the camera at ctx.T_cell_cam, else by the task's rule; the lamp among the poses clear
    of the cell's bodies, one_shot.plan's). Returns the Aim of the
    refitted material's plan; GoalNotReached when the refit cannot be used or its plan is
    infeasible."""
    (feature,), recorder = aim.features, ctx.recorder
    it, m, _ = measured
    recorder.step("correct", f"refit the material: {c.reason}", iteration=k, action="refit")
    yield Corrected(k, {"action": "refit", "cause": "spread", "reason": c.reason})
    disagreement = refit.Disagreement(k, m, (aim.shutter_s, aim.f_number, aim.shot.exposure.focus_m), aim.black,
                                      aim.albedo_scale, it.registration["shift_px"], aim.drives or None)
    fitted = refit.probe_and_refit(ctx, feature.task, feature.model.plan.planned_scene, disagreement)
    yield Refitted(k, fitted, refit.keep(fitted, feature.task, recorder, k))
    refit.require_usable(fitted, c.reason)
    task = refit.task_with(feature.task, fitted)
    replanned = plan_recorded(task, recorder, 1.0, iteration=k, subfolder=f"refit-{k}", T_cell_cam=ctx.T_cell_cam,
                              clear=True)
    yield Replan(k, 1.0, replanned.to_json())
    if not replanned.feasible:
        why = f"the material is not the task's ({fitted.summary()}); re-planned for the refitted material"
        raise GoalNotReached(f"{why}: infeasible, {replanned.binding}: {replanned.hint}", "infeasible",
                             f"{why}: infeasible: {words.reason(replanned)}")
    return replace(replan_aim(aim, replace(feature, task=task, model=Model(replanned, task)), 1.0), refitted=True)


def run(task: Task, out: str | Path, connect: Callable[[Scene], Devices], max_iterations: int = 6) -> RunResult:
    """Plan, connect(scene) -> Devices, then iterate; out/report.json (RunResult.to_json) is
    written however the run ends. Raises PlanInfeasible or GoalNotReached (exit 1), or DeviceFault
    (exit 3) after the safe stop of every device (session.Session). Returns the RunResult."""
    from cell.report.pictures import write_convergence
    out, events = Path(out), Events()

    def result(reason: str, fault: dict[str, Any] | None) -> RunResult:     # its cause: the Ending's
        return RunResult(str(task.path), not reason, reason, recorder.plan, tuple(events.iterations),
                         tuple(events.replans), fault, events.black_json, tuple(events.refits),
                         localization=events.localization_json)

    try:
        with Recorder(out) as recorder, Ending(recorder, "not converged", "report.json", result,
                                               converged=False) as ending:
            with ending.session:
                planned, devices = plan_and_connect(task, recorder, ending.session, connect)
                context = RunContext(task, devices, recorder, max_iterations)
                for event in iterate(context, [LoopFeature.planned(task, planned)]):
                    events.add(event)
                missed = unseen(events.iterations[-1].defects) if events.iterations else None
                if missed:
                    raise GoalNotReached(missed, "contrast")
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

    def __init__(self) -> None:
        self.iterations: list[Iteration] = []
        self.replans: list[Replan] = []
        self.refits: list[Refitted] = []
        self.black: BlackLevel | None = None
        self.located: Located | None = None

    def add(self, event: Event) -> None:
        if isinstance(event, Located):
            self.located = event
        elif isinstance(event, Corrected):
            self.iterations = [replace(it, correction=event.correction) if it.iteration == event.iteration else it
                               for it in self.iterations]
        elif isinstance(event, BlackLevelFound):
            self.black = event.black
        elif isinstance(event, Refitted):
            self.refits.append(event)
        elif isinstance(event, Iteration):
            self.iterations.append(event)
        else:
            self.replans.append(event)

    @property
    def black_json(self) -> dict[str, Any] | None:
        return self.black.to_json() if self.black else None

    @property
    def localization_json(self) -> dict[str, Any] | None:
        """report.json's `localization` (Located.to_json), None when the part was not localized."""
        return self.located.to_json() if self.located else None
