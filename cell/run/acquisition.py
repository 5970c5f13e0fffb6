"""Acquisition, shared by the closed loop and the calibration routines: plan, refuse an
infeasible plan before anything moves and connect the devices; set the light channels' drives
and an exposure and take a frame, find the sensor's black level (the task's, or a dark
frame's), each step logged as the devices read it back. The moves are cell.run.motion's."""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from cell.physics.sensor import levels
from cell.devices.interfaces import speaking_for
from cell.core.errors import DeviceFault, PlanInfeasible
from cell.planning.plan import gray_stats
from cell.run import measurement
from cell.report import words

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.devices.session import Session
    from cell.planning.plan import Plan, Shot
    from cell.planning.scene import Scene
    from cell.report.recorder import Recorder
    from cell.task.types import Task


@dataclass(frozen=True)
class Capture:
    """One frame as the camera delivered it and what the devices read back when it was taken."""

    image: np.ndarray            # (H, W) gray, uint8/uint16 (a real sensor) or float (the sim)
    T_cell_cam: np.ndarray       # the arm's read-back camera pose
    shutter_s: float             # the shutter time the camera reports
    f_number: float
    focus_m: float
    name: str                    # its file in the run folder
    drives: dict[int, float] = field(default_factory=dict)   # each light channel's level read back (0..1)


def plan_recorded(task: Task, recorder: Recorder, albedo_scale: float = 1.0, iteration: int | None = None,
                  subfolder: str = "", T_cell_cam: np.ndarray | None = None, clear: bool = False) -> Plan:
    """Plan (the function `cell plan` uses, its lamp among the poses clear of the cell's bodies:
    one_shot.plan; the camera at T_cell_cam, else by the task's rule), with `clear` the shot's
    clearance checked as `cell plan` checks it (whole_part.cleared: a shot closer than the
    padding is infeasible, its bodies named, before any move is planned: where only poses under
    the padding meet every requirement, `collision`), write plan.json (its pictures when the run
    has ended: Recorder.write_plan), log it."""
    from cell.planning.one_shot import plan
    from cell.planning.whole_part import cleared
    planned = plan(task, albedo_scale=albedo_scale, progress=recorder.progress, T_cell_cam=T_cell_cam)
    if clear:
        planned = cleared(task, planned)
    folder = recorder.write_plan(planned, task, subfolder)
    shot = planned.shot
    g, exposure = gray_stats(shot.gray), shot.exposure
    verdict = "feasible" if planned.feasible else f"infeasible: {words.reason(planned)}"
    recorder.step("plan", f"{verdict}; lamp {shot.distance_m:.3f} m, phase "
                          f"{np.degrees(shot.phase_angle_rad):.1f} deg; {1e3 * exposure.shutter_s:.3f} ms, "
                          f"f/{exposure.f_number:.1f}; predicted gray {g['min']:.1f}-{g['max']:.1f}"
                          + (f" (albedo x{albedo_scale:.3g})" if albedo_scale != 1.0 else ""),
                  iteration=iteration, albedo_scale=albedo_scale, feasible=planned.feasible,
                  binding=planned.binding, hint=planned.hint, joints=shot.joints,
                  shutter_s=exposure.shutter_s, f_number=exposure.f_number, predicted_gray=g,
                  folder=str(folder))
    return planned


def require_feasible(plan: Plan) -> None:
    """Refuse an infeasible plan before anything moves (PlanInfeasible, exit 1)."""
    if not plan.feasible:
        raise PlanInfeasible(f"infeasible: {plan.message}", f"infeasible: {words.reason(plan)}")


def plan_and_connect(task: Task, recorder: Recorder, session: Session,
                     connect: Callable[[Scene], Devices]) -> tuple[Plan, Devices]:
    """Plan (plan_recorded, the shot's clearance checked as `cell plan` checks it: a shot whose
    bodies collide is refused with them named, the true cause, not the first contact on the move
    there), refuse an infeasible plan before anything moves, then connect(scene) the cell's
    devices into the session. Returns the plan and the devices."""
    planned = plan_recorded(task, recorder, clear=True)
    require_feasible(planned)
    devices = session.devices = connect(planned.planned_scene)
    return planned, devices


def planned_drives(shot: Shot) -> dict[int, float]:
    """{channel: drive level 0..1} of the shot's lights on the lighting controller (Shot.lights;
    a light on no channel is always on and has none)."""
    return {light.channel: light.drive for light in shot.lights if light.channel is not None}


def set_drives(devices: Devices, drives: Mapping[int, float], recorder: Recorder,
               iteration: int | None = None) -> dict[int, float]:
    """Each light channel to its drive level (0..1) on the lighting controller, logged as read
    back; returns the read-back {channel: level}. Nothing to set, nothing done; channels to set
    and no controller is a DeviceFault (the loader and cell.task.device_config see to it that a
    task's channels have one)."""
    if not drives:
        return {}
    lights = devices.lights
    if lights is None:
        raise DeviceFault("lighting", f"channels {sorted(drives)} to drive and the cell has no lighting controller")
    with speaking_for(lights):
        read = {channel: lights.set_drive(channel, level) for channel, level in sorted(drives.items())}
    recorder.step("set_drives", ", ".join(f"channel {c} at {100 * level:.1f} %" for c, level in read.items()),
                  iteration=iteration, drives={str(c): level for c, level in read.items()})
    return read


def acquire(devices: Devices, recorder: Recorder, iteration: int, shutter_s: float, f_number: float,
            focus_m: float, name: str | None = None, drives: Mapping[int, float] | None = None) -> Capture:
    """Set the light channels' drives (set_drives; none given: as they are), f-number, focus and
    shutter, take a frame and save it at once (capture-N.png, or name.png, the sim's float gray
    rounded to the sensor's levels). Returns the Capture. The shutter comes last: a camera drops
    the frames exposed before it changed (OpenCVCamera), and an operator turning the lens by hand
    would otherwise be in them."""
    camera = devices.camera
    read = set_drives(devices, drives or {}, recorder, iteration)
    with speaking_for(camera):
        camera.set_aperture(f_number)
        camera.set_focus(focus_m)
        shutter_s = camera.set_exposure(shutter_s)
    recorder.step("set_exposure", f"shutter {1e3 * shutter_s:.3f} ms, f/{f_number:.2f}, focus "
                                  f"{focus_m:.3f} m", iteration=iteration,
                  shutter_s=shutter_s, f_number=f_number, focus_m=focus_m)
    with speaking_for(camera):
        image = np.asarray(camera.capture())
    name = recorder.write_image(f"{name or f'capture-{iteration}'}.png", levels(image, camera.bit_depth))
    recorder.step("capture", name, iteration=iteration, capture=name, shape=image.shape, dtype=str(image.dtype))
    with speaking_for(devices.arm):
        pose = devices.arm.camera_pose()
    return Capture(image, pose, shutter_s, float(f_number), float(focus_m), name, read)


DARK_FRAME = "dark"       # the dark frame's file in the run folder (dark.png), named as what it is


def find_black_level(task: Task, devices: Devices, recorder: Recorder, f_number: float, focus_m: float,
                     feature_light: Callable[[float], float] | None = None,
                     drives: Mapping[int, float] | None = None) -> measurement.BlackLevel:
    """The task's camera.sensor.black_level, else a dark frame's (measurement.black_level_of):
    dark.png at the shortest shutter (a light on no channel cannot be switched off) and f_number,
    the light channels at `drives` (the loop's: all off), logged with feature_light(shutter) when
    given: the most light the model lets reach the feature in that frame [gray]. Returns the
    measurement.BlackLevel."""
    b = task.camera.sensor.black_level
    if b is not None:
        black = measurement.BlackLevel(float(b), 0.0, "task")
        recorder.step("black_level", f"black level {b:.2f} gray (camera.sensor.black_level)", **black.to_json())
        return black
    capture = acquire(devices, recorder, 0, task.camera.shutter_range_s[0], f_number, focus_m, DARK_FRAME, drives)
    black = measurement.black_level_of(capture.image)
    light = {} if feature_light is None else {"feature_light": feature_light(capture.shutter_s)}
    note = f": the feature's light at most {light['feature_light']:.2g} gray by the model" if light else ""
    recorder.step("black_level", f"black level {black.value:.2f} gray, noise {black.noise_rms:.2f} rms (dark frame "
                                 f"at {1e3 * capture.shutter_s:.3g} ms, f/{f_number:.1f}{note})", iteration=0,
                  **black.to_json(), **light)
    return black
