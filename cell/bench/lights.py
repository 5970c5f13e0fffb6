"""`cell bench`'s rows for the lights besides the spot (issue 24, item 7), on a task with `lights:`
(default: tasks/ring.yaml):

- `kernels`, one row per light type (spot, ring, bar, area, dome, coaxial): the contribution
  kernel (cell.planning.lights.contribution at a fixed count of emitter points, the sum over them
  included) in emitter points x samples per second on the certificate's dense patch, against the
  NumPy reference (cell.physics.reference.gray_per_exposure summed over the same points) timed on
  the first samples in the same run; `agreement` is their largest difference there, relative to
  the largest contribution.
- `channels`, planning the task's feature with N fixed lights, each on its own channel
  (channel_lights: bars, areas and rings on a sphere about the feature, aimed at it), the task's own
  lights replaced: the wall time of one_shot.plan warm (a plan of the same task first, then the
  median of the repeats; cpu_s its process time, what it costs on a machine other jobs load),
  the certificate included, and where it goes (stage_clock): every light's
  contribution at the search's samples and on the certificate's dense patch, the drive program
  (cell.planning.drives.solve_drives, all its calls) and the certificate (its contributions included).

Layer 9: imports the layers below."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from importlib.resources import files
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.bench.throughput import median_time
from cell.core import geometry
from cell.physics import reference
from cell.planning import certificate, drives, evaluate, lights, one_shot
from cell.planning.scene import build_scene
from cell.task.types import Channel, Light

if TYPE_CHECKING:
    from cell.planning.plan import Plan
    from cell.task.types import Task

LIGHT_TASKS = (files("lightplan_tasks") / "ring.yaml",)    # a task with lights, installed with the package
CHANNELS = (1, 5, 10, 20, 40)          # fixed channels planned (40: OMRON's scale)
QUICK_CHANNELS = (1, 5)
TARGET_CHANNELS, TARGET_S = 40, 2.0    # the issue's: 40 fixed channels, one feature, warm, certified
EMITTER_POINTS = 64                    # per light in the kernel rows (a spot is one, an area 8 x 8)
QUICK_SAMPLES = 2000                   # the kernel rows' samples with --quick (else the dense patch's)
REFERENCE_EVALUATIONS = 20_000         # emitter points x samples the NumPy reference is timed on
SPHERE_M = 0.25                        # channel_lights' distance from the feature centre
ELEVATION_DEG = (20.0, 70.0)           # their elevations above the feature's tangent plane
CHANNEL_POWER_W = 3.0                  # each one's radiant power
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
SHAPES: dict[str, dict[str, Any]] = {"bar": {"length_m": 0.10}, "area": {"size_m": (0.05, 0.05)},
                                     "ring": {"radius_m": 0.03, "tilt_rad": np.radians(20.0)}}


def channel_lights(task: Task, n: int) -> tuple[Light, ...]:
    """n fixed lights about the task's (first) feature, on channels 1..n: a bar, an area, a ring in
    turn, on a sphere of SPHERE_M about the feature centre at elevations evenly over ELEVATION_DEG
    and azimuths by the golden angle (no two alike), each aimed at the centre."""
    scene = build_scene(task)
    out = []
    for k in range(n):
        elevation = np.radians(ELEVATION_DEG[0] + (ELEVATION_DEG[1] - ELEVATION_DEG[0]) * (k + 0.5) / n)
        azimuth = k * GOLDEN_ANGLE
        d = scene.frame @ geometry.direction_from_angles(azimuth, elevation)
        kind = ("bar", "area", "ring")[k % 3]
        shape: dict[str, Any] = SHAPES[kind]
        out.append(Light(f"{kind}_{k + 1}", kind, "fixed", CHANNEL_POWER_W, Channel(k + 1),
                         scene.center + SPHERE_M * d, -d, geometry.frame_from_normal(-d)[:, 0],
                         key=f"lights[{k}]", **shape))
    return tuple(out)


def type_lights(task: Task) -> tuple[Light, ...]:
    """One light of each type about the task's feature (the kernel rows): a spot like the task's
    lamp at 45 deg, a ring 8 cm above, a bar and an area 15 cm off at 45 deg, a dome over the
    feature and a coaxial source on the camera's axis."""
    scene = build_scene(task)
    up, side = scene.frame[:, 2], scene.frame[:, 0]
    slant = geometry.unit(up + side)

    def fixed(kind, distance, axis=None, **keys):
        axis = -slant if axis is None else axis
        return Light(kind, kind, "fixed", 1.0, Channel(1), scene.center - distance * axis, axis,
                     geometry.frame_from_normal(axis)[:, 0], **keys)
    return (fixed("spot", 0.2, cone_angle_rad=task.lamp.cone_angle_rad, profile=task.lamp.profile),
            fixed("ring", 0.08, -up, radius_m=0.05, tilt_rad=np.radians(30.0)),
            fixed("bar", 0.15, length_m=0.12),
            fixed("area", 0.15, size_m=(0.06, 0.06)),
            fixed("dome", 0.12, -up, radius_m=0.12, hole_radius_m=0.02),
            Light("coaxial", "coaxial", "flange", 1.0, Channel(1), np.array([0.0, 0.0, 0.05]),
                  np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), radius_m=0.01))


def kernel_rows(task: Task, quick: bool, repeats: int, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """The contribution kernel per light type against the NumPy reference (module docstring)."""
    label = task.path.stem
    dense = build_scene(task)
    scene = build_scene(task, certificate.dense_samples(task, dense), T_cell_cam=dense.T_cell_cam)
    points, normals = scene.points, scene.normals
    if quick:
        points, normals = points[:QUICK_SAMPLES], normals[:QUICK_SAMPLES]
    material, sensor, top = task.part.material, task.camera.sensor, evaluate.planning_band(task)[1]
    rows = []
    for light in type_lights(task):
        e = lights.emitters(light, scene.T_cell_cam, EMITTER_POINTS)
        n_points = len(e.position)

        def warp(p=points, q=normals, made=light):
            return lights.contribution(scene.warp_mesh, p, q, scene.T_cell_cam, made, material, sensor, top,
                                       count=EMITTER_POINTS)
        n_ref = max(1, min(len(points), REFERENCE_EVALUATIONS // n_points))

        def numpy(e=e):
            return reference.gray_per_exposure(scene.warp_mesh, points[:n_ref], normals[:n_ref],
                                               scene.camera_position, e.position, e.axis, e.power_w,
                                               e.cone_angle_rad, material.table(), sensor.camera_constant,
                                               sensor.pixel_area_m2, profile=e.profile).value.sum(axis=0)
        warp()
        t_warp = median_time(warp, repeats)
        t_ref = median_time(numpy, 1)
        want, got = numpy(), warp(points[:n_ref], normals[:n_ref]).unit_gray
        size, ref_size = n_points * len(points), n_points * n_ref
        row = {"task": label, "name": f"contribution, {light.type}", "light_type": light.type,
               "emitter_points": n_points, "samples": len(points), "size": size, "warp_per_s": size / t_warp,
               "reference": "numpy", "reference_size": ref_size, "reference_per_s": ref_size / t_ref,
               "ratio": (size / t_warp) / (ref_size / t_ref), "unavailable": None,
               "agreement": float(np.max(np.abs(got - want)) / max(float(np.max(want)), 1e-300))}
        rows.append(row)
        say(f"{label} kernel {row['name']}: {n_points} points x {len(points)} samples, {row['warp_per_s']:.3g}/s, "
            f"{row['ratio']:.3g} x numpy (agree to {row['agreement']:.1e})")
    return rows


@contextlib.contextmanager
def stage_clock() -> Iterator[dict[str, float]]:
    """Seconds spent in the planner's light contributions (at the search's samples, and within the
    certificate on its dense patch), its drive program and its certificate while the block runs:
    each of those functions wrapped in a timer for the block, the planner itself unchanged."""
    spent = {"contributions": 0.0, "certificate_contributions": 0.0, "drives": 0.0, "certificate": 0.0}
    inside: list[str] = []
    wrapped = [(lights, "contributions", "contributions"), (drives, "solve_drives", "drives"),
               (certificate, "verify", "certificate")]

    def timer(fn, key):
        def timed(*args, **kwargs):
            name = "certificate_contributions" if key == "contributions" and "certificate" in inside else key
            inside.append(key)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - t0
                inside.pop()
        return timed
    originals = [(module, attr, getattr(module, attr)) for module, attr, _ in wrapped]
    try:
        for (module, attr, key), (_, _, fn) in zip(wrapped, originals):
            setattr(module, attr, timer(fn, key))
        yield spent
    finally:
        for module, attr, fn in originals:
            setattr(module, attr, fn)


def channel_row(task: Task, n: int, repeats: int) -> tuple[dict[str, Any], Plan]:
    """Planning the task with channel_lights(task, n) instead of its lights: warm (one plan
    first), the median of `repeats` timed plans and the shares of the median one."""
    planned = replace(task, lights=channel_lights(task, n))
    one_shot.plan(planned)
    runs = []
    for _ in range(max(1, repeats)):
        with stage_clock() as spent:
            t0, cpu0 = time.perf_counter(), time.process_time()
            plan = one_shot.plan(planned)
            total, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        runs.append((total, spent, plan, cpu))
    total, spent, plan, cpu = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
    assert plan.verification is not None or not plan.feasible
    shot = plan.shot
    row: dict[str, Any] = {"task": task.path.stem, "channels": n, "time_s": total, "times_s": [r[0] for r in runs], "cpu_s": cpu,
           "contributions_s": spent["contributions"], "certificate_contributions_s": spent["certificate_contributions"],
           "drives_s": spent["drives"], "certificate_s": spent["certificate"],
           "samples": len(plan.planned_scene.points),
           "dense_points": plan.verification.points if plan.verification is not None else 0,
           "on": int(sum(light.drive > 0 for light in shot.lights[1:])),
           "feasible": plan.feasible, "binding": plan.binding}
    row["other_s"] = total - row["contributions_s"] - row["drives_s"] - row["certificate_s"]
    return row, plan


def run(tasks: Iterable[Task], quick: bool, say: Callable[[str], None]) -> dict[str, list[dict[str, Any]]]:
    """{"kernels": the contribution rows per light type, "channels": planning against the number of
    channels} of the tasks with lights."""
    repeats = 1 if quick else 3
    out: dict[str, list[dict[str, Any]]] = {"kernels": [], "channels": []}
    for task in tasks:
        out["kernels"] += kernel_rows(task, quick, repeats, say)
        for n in QUICK_CHANNELS if quick else CHANNELS:
            row, _ = channel_row(task, n, repeats)
            out["channels"].append(row)
            say(f"{row['task']} with {n} channels: {row['time_s']:.2f} s warm (contributions "
                f"{row['contributions_s'] + row['certificate_contributions_s']:.2f} s, drives {row['drives_s']:.3f} s, "
                f"certificate {row['certificate_s']:.2f} s), {row['on']} channels on, "
                + ("feasible" if row["feasible"] else f"infeasible: {row['binding']}"))
    return out


def targets(channels: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """The issue's: TARGET_CHANNELS fixed channels on one feature planned within TARGET_S warm,
    certificate included (where that many were planned)."""
    return [{"name": f"{row['task']}: {TARGET_CHANNELS} channels warm plan <= {TARGET_S:g} s",
             "value": row["time_s"], "limit": TARGET_S, "met": row["time_s"] <= TARGET_S}
            for row in channels if row["channels"] == TARGET_CHANNELS]
