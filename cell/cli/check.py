"""`cell check TASK`: load a task and everything it references, lay the feature patch onto the
surface as the planner does (so a patch over an edge is refused here too), print a summary in the
units people read, each coordinate with the frame it is in, and warn of triangles wound against
their neighbours (cell.task.winding), with where they are. A task whose cell.backend is hw is
refused here as `cell run` would refuse it (cell.task.device_config.for_hw)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import numpy as np

from cell.cli import backend_of
from cell.task.loader import load_task
from cell.task.winding import flipped_faces

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.types import Task


def _span(pair, scale=1.0, unit=""):
    """'low..high unit' of an SI range shown in another unit (scale: that unit per SI unit)."""
    return f"{pair[0] * scale:g}..{pair[1] * scale:g}" + (f" {unit}" if unit else "")


def _vector(v, scale=1.0, decimals=3):
    return str((np.round(np.asarray(v) * scale, decimals) + 0.0).tolist())   # + 0.0: no "-0.0"


def _camera_constant(sensor):
    """c with its standard error, and where it comes from: the datasheet keys, the camera file."""
    c = f"c = {sensor.camera_constant:.5g}" + (
        f" +- {sensor.camera_constant_stderr:.2g}" if sensor.camera_constant_stderr is not None else "") + " 1/(W s)"
    if sensor.quantum_efficiency is not None:
        c += (f" (EMVA 1288: eta {sensor.quantum_efficiency:g} at {sensor.wavelength_m * 1e9:g} nm, "
              f"K {sensor.system_gain_dn_per_e:g} DN/e-)")
    source = (sensor.source or "").splitlines()[0:1]
    where = [f"from {sensor.file}"] if sensor.file else []
    where += [_clip(source[0], 70)] if source else []
    return c + (f"; {': '.join(where)}" if where else "")


def _clip(text, length):
    return text if len(text) <= length else text[:length - 3] + "..."


def _feature_lines(f, label):
    """The feature's and its requirements' lines."""
    deg, req, radius_mm = 180.0 / np.pi, f.requirements, f.radius_m * 1e3
    return [f"{label:<12} center {_vector(f.center_m, 1e3, 2)} mm, normal {_vector(f.normal)} (part frame), "
            f"radius {radius_mm:g} mm (area {np.pi * radius_mm**2:.1f} mm^2), {f.samples} samples",
            f"requirements gray {'any (' + _span(req.gray_band) + ', the sensor range)' if req.gray_any else _span(req.gray_band)}, "
            f"{req.reflection}, "
            f"margin {req.region_margin_rad * deg:g} deg, lamp tolerance {req.lamp_tolerance_rad * deg:g} deg, "
            f"depth of field {req.depth_of_field_m * 1e3:g} mm"]


def summarize(task: Task) -> str:
    """A short human summary of a loaded task, in the units people read."""
    mesh, cam, lamp = task.part.mesh, task.camera, task.lamp
    sensor, lens, rig, material = cam.sensor, cam.lens, lamp.rig, task.part.material
    deg = 180.0 / np.pi
    source = material.source.splitlines()[0]
    size = " x ".join(f"{e:.1f}" for e in mesh.extents * 1e3)
    devices = "".join(f", {name} settings" for name in task.cell.devices.given)
    hand_eye = task.cell.devices.arm.hand_eye_file
    devices += f", hand-eye from {hand_eye}" if hand_eye else ""
    (first, *more) = [_feature_lines(f, "feature" if len(task.features) == 1 else f"feature {f.name}")
                      for f in task.features]
    return "\n".join([
        f"task         {task.name} ({task.path})",
        f"part         {task.part.mesh_path}: {size} mm, {len(mesh.faces)} triangles",
        first[0],
        f"material     {material.name}: {_clip(source, 70)}",
        first[1],
        *(line for lines in more for line in lines),
        (f"camera       {cam.distance_m:g} m along {_vector(cam.view_direction)} (part frame), " if cam.viewpoint.mode == "fixed"
         else f"camera       planned on view spheres {_span(cam.viewpoint.standoff_range_m, 1, 'm')} from each "
              f"feature, {np.degrees(cam.viewpoint.step_rad):g} deg apart, ")
        + f"shutter {_span(cam.shutter_range_s, 1e3, 'ms')}",
        f"sensor       {sensor.width_px} x {sensor.height_px} px, pitch {sensor.pixel_pitch_m * 1e6:g} um, "
        f"{sensor.bit_depth} bit, {_camera_constant(sensor)}",
        f"lens         f = {lens.focal_length_m * 1e3:g} mm, f-number {_span(lens.f_number_range)}, "
        f"circle of confusion {lens.circle_of_confusion_m * 1e6:g} um",
        f"lamp         {lamp.power_w * 1e3:g} mW, cone {lamp.cone_angle_rad * deg:g} deg, " + (
            "ideal cone (eq. 11)" if lamp.profile is None else
            f"profile of {len(lamp.profile)} angles to {lamp.profile[-1, 0] * deg:g} deg"),
        f"rig          pan {_span(rig.pan_range_rad, deg, 'deg')}, "
        f"tilt {_span(rig.tilt_range_rad, deg, 'deg')}, "
        f"radius {_span(rig.radius_range_m, unit='m')} ({rig.radius_axis})",
        f"cell         backend {task.cell.backend}{devices}",
        f"sim          seed {task.sim.seed}, effects {', '.join(task.sim.effects) or 'none'}",
    ])


def patch_line(task: Task, scene: Scene, label: str = "patch") -> str:
    """The feature's samples as laid onto the surface: how far the patch bends away from the
    feature's tangent plane (its sag)."""
    sag = np.abs((scene.points - scene.center) @ scene.normal).max()
    return (f"{label:<12} {len(scene.points)} samples on the surface, within {sag * 1e3:.2f} mm of its "
            f"tangent plane")


def command(args: argparse.Namespace) -> int:
    from cell.planning.scene import build_scene          # Warp's BVH: the planner's own patch, no copy

    task = load_task(args.task)
    backend_of(task, args.backend)              # a task for the real cell names what it connects to
    print(summarize(task))
    flipped = flipped_faces(task.part.mesh)
    if len(flipped):
        print(f"warning      the mesh has {len(flipped)} triangles wound against their neighbours (flipped): "
              f"{flipped.where()}; the planner sees them from behind: fix the mesh's winding")
    for i, f in enumerate(task.features):
        label = "patch" if len(task.features) == 1 else f"patch {f.name}"
        print(patch_line(task, build_scene(task.with_feature(i)), label))
    return 0
