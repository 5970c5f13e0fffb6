"""`cell bench`'s thread rows: the planner's and the simulator's big kernel launches on 1 and 2
threads side by side (kernels.runtime splits a launch over threads, one slice each), on a
one-feature task's own scene: its visibility maps, its global search (every lamp of the rig's
candidate grid on the samples), its certificate (9 lamps, a shot and its tolerance ring's count,
on the dense patch) and the simulated camera's image of it (a primary ray per pixel).

Beside them the machine's own speedup in the same rounds: the same NumPy arithmetic (np.sin
over an array, which lets go of the GIL) on one thread and cut in two on two. What two threads
make of two cores depends on what else runs: a virtual machine's two cores lose some of it to
each other, and on a shared host that schedules by session (Linux's autogroup) a busy session's
threads share one session's part of the cores however many they are. So the kernels' speedup is
to be read against the machine's, measured alongside, and with the load average beside both
(before and after). Rounds alternate which thread count goes first (ABBA); a speedup is the
median of the rounds' ratios.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.devices import rig
from cell.physics.projection import intrinsics, pixel_rays
from cell.planning import certificate, evaluate, one_shot
from cell.planning.plan import PlannerSettings
from cell.planning.regions import SphereGrid
from cell.planning.scene import build_scene
from kernels import runtime
from kernels.gray import gray_per_exposure
from kernels.render import render
from kernels.visibility import visibility_maps

if TYPE_CHECKING:
    from cell.task.types import Task

THREADS = (1, 2)
ROUNDS = 5                      # of each thread count (--quick: 1)
ARITHMETIC_VALUES = 4_000_000   # the machine's own speedup: np.sin over this many float64s


def launches(task: Task) -> dict[str, tuple[int, Callable[[], object]]]:
    """{name: (evaluations, one call)} of the task's big launches, built once (the scenes, rays and
    lamps are not timed)."""
    settings = PlannerSettings()
    scene = build_scene(task)
    mesh, material, sensor, lamp = scene.warp_mesh, task.part.material.table(), task.camera.sensor, task.lamp
    grid = SphereGrid(np.radians(settings.grid_step_deg))
    pivot = lamp.rig.pivot_m
    pan, tilt, radius = one_shot.candidate_grid(lamp.rig, settings)
    lamps = rig.lamp_position(pivot, pan, tilt, radius)
    dense = build_scene(task, certificate.dense_samples(task, scene))
    ring = lamps[np.linspace(0, len(lamps) - 1, 1 + evaluate.TOLERANCE_RING).astype(int)]    # a shot's count
    rays = pixel_rays(intrinsics(sensor, task.camera.lens), scene.T_cell_cam, sensor.width_px, sensor.height_px)
    shading = (lamp.power_w, lamp.cone_angle_rad, material, sensor.camera_constant, sensor.pixel_area_m2)

    def gray(on, at):
        return lambda: gray_per_exposure(mesh, on.points, on.normals, on.camera_position, at, rig.lamp_aim(pivot, at),
                                         *shading, profile=lamp.profile)
    return {
        "visibility maps": (len(scene.points) * grid.azimuth.size * grid.elevation.size,
                            lambda: visibility_maps(mesh, scene.points, scene.normals, scene.frame, grid.azimuth,
                                                    grid.elevation)),
        "global search": (len(lamps) * len(scene.points), gray(scene, lamps)),
        "certificate": (len(ring) * len(dense.points), gray(dense, ring)),
        "renderer": (len(rays), lambda: render(mesh, scene.camera_position, rays, ring[0],
                                               rig.lamp_aim(pivot, ring[0]), *shading, profile=lamp.profile)),
    }


def arithmetic(threads: int, pool: ThreadPoolExecutor, values: np.ndarray, out: np.ndarray) -> Callable[[], object]:
    """np.sin of `values` into `out`, cut into `threads` contiguous parts, each on a thread of `pool`."""
    edges = np.linspace(0, len(values), threads + 1).astype(int)

    def run():
        parts = [pool.submit(np.sin, values[a:b], out[a:b]) for a, b in zip(edges[:-1], edges[1:])]
        for part in parts:
            part.result()
    return run


def run(tasks: list[Task], quick: bool, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """A row per task and launch (--quick: of the first task only): evaluations, the median time
    and rate on each of THREADS, the speedup (median of the rounds' ratios, every round's kept),
    the machine's own speedup and the load average (1 min) before and after."""
    tasks = tasks[:1] if quick else tasks
    rounds = 1 if quick else ROUNDS
    values = np.linspace(0.0, 1.0, ARITHMETIC_VALUES)
    out = np.empty_like(values)
    with ThreadPoolExecutor(max_workers=max(THREADS)) as pool:
        machine = {n: arithmetic(n, pool, values, out) for n in THREADS}
        return [row for task in tasks for row in task_rows(task, rounds, machine, say)]


def task_rows(task: Task, rounds: int, machine: dict[int, Callable[[], object]],
              say: Callable[[str], None]) -> list[dict[str, Any]]:
    """run's rows of one task, `machine` the arithmetic on each thread count."""
    rows = []
    label = task.path.stem
    calls = launches(task)
    times: dict[str, dict[int, list[float]]] = {name: {n: [] for n in THREADS} for name in [*calls, "machine"]}
    load_before = os.getloadavg()[0]
    for _, call in [*calls.values(), *((0, m) for m in machine.values())]:
        call()                                  # warm: Warp's first load of a kernel, the threads' start
    for r in range(rounds):
        for n in THREADS if r % 2 == 0 else THREADS[::-1]:
            runtime.set_threads(n)
            try:
                for name, call in [*((k, c) for k, (_, c) in calls.items()), ("machine", machine[n])]:
                    t0 = time.perf_counter()
                    call()
                    times[name][n].append(time.perf_counter() - t0)
            finally:
                runtime.set_threads(None)
    load_after = os.getloadavg()[0]
    one, two = THREADS
    machine_ratios = [a / b for a, b in zip(times["machine"][one], times["machine"][two])]
    for name, (count, _) in calls.items():
        ratios = [a / b for a, b in zip(times[name][one], times[name][two])]
        median = {n: float(np.median(times[name][n])) for n in THREADS}
        row = {"task": label, "launch": name, "evaluations": count,
               "threads": [{"threads": n, "time_s": median[n], "evaluations_per_s": count / median[n]}
                           for n in THREADS],
               "speedup": float(np.median(ratios)), "speedups": ratios,
               "machine_speedup": float(np.median(machine_ratios)), "machine_speedups": machine_ratios,
               "load": [load_before, load_after]}
        rows.append(row)
        say(f"{label} {name}: {count:.3g} evaluations, {count / median[one]:.3g}/s on 1 thread, "
            f"{count / median[two]:.3g}/s on 2: {row['speedup']:.2f}x (the machine's own "
            f"{row['machine_speedup']:.2f}x; load {load_before:.1f} -> {load_after:.1f})")
    return rows
