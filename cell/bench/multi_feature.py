"""`cell bench`'s multi-feature rows: planning time against the number of features (and the
candidate shots they bring), and planning on Dask workers (cell.planning.parallel): one LocalCluster of 2
processes, timed with its jobs on 1 of them and on both, the speedup, and whether each plan equals
the serial one in every key but timing_s.

Evaluations: the lamp candidates x samples of every candidate shot's global search (its last
search's), summed; serial and parallel count the same, so their rates' ratio is the times'.
The worker rows are warm (the cluster's start and the workers' first plan, which loads Warp's
kernels, are reported apart: startup_s, first_s), 1 and 2 workers timed in turn, ROUNDS rounds.
A virtual machine's speed drifts from second to second (here one worker's plan of the bracket
took 4.2-6.1 s within an hour, nothing else running), so the speedup is the median of the
rounds' ratios, each of two runs side by side, and the rounds' spread is kept. Beside it the
machine's own speedup (machine_speedup): the rate at which a core counts while the other core
counts too, against alone. Two virtual cores of a shared host lose 5-15 % of it to each other,
so that ceiling is what the plan's speedup is to be read against. On a machine other jobs load,
2 processes take a larger share of its cores than 1: the speedup is a quiet machine's only when
nothing else runs.

The collision row (issue 26): the task planned as `cell plan` plans it, with its collision checks
(every shot's clearance, the viewpoints' collision pruning, the route's moves checked:
cell.run.moves.with_moves) and without (PlannerSettings(collisions=False), no moves), side by side
in ABBA rounds, the ratio of the median times with the machine's load (/proc/loadavg) beside it."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from importlib.resources import files
from typing import TYPE_CHECKING, Any

import os

import numpy as np

from cell.planning import parallel
from cell.planning.plan import PlannerSettings
from cell.planning.whole_part import plan_features
from cell.run.moves import with_moves

if TYPE_CHECKING:
    from cell.planning.plan import Plan
    from cell.task.types import Task

FEATURE_TASKS = (files("lightplan_tasks") / "bracket.yaml",)    # the multi-feature example, installed with the package
SPEEDUP_TARGET = 1.8            # 2 workers over 1 (the done-when)
ROUNDS = 7                      # of 1 and 2 workers each (--quick: 1)
SPIN_S = 0.5                    # a spin job's time (machine_speedup)
COLLISION_TARGET = 1.3          # planning with collision checks / without (issue 26's done-when)


def evaluations(plan: Plan) -> int:
    """Lamp candidates x samples of the global searches of a multi-feature plan's candidate shots."""
    return sum(p.search.candidates * len(p.planned_scene.points) for p in plan.plans)


def without_timing(document: Any) -> Any:
    """A plan.json without its timing_s keys (at any depth): what must equal between runs."""
    if isinstance(document, dict):
        return {k: without_timing(v) for k, v in document.items() if k != "timing_s"}
    if isinstance(document, list):
        return [without_timing(v) for v in document]
    return document


def same_plan(a: Plan, b: Plan) -> bool:
    """The two multi-feature plans and each candidate's own plan equal but for timing_s."""
    return (without_timing(a.to_json()) == without_timing(b.to_json()) and len(a.plans) == len(b.plans)
            and all(without_timing(p.to_json()) == without_timing(q.to_json()) for p, q in zip(a.plans, b.plans)))


def timed(task: Task, repeats: int) -> tuple[Plan, float]:
    """(the serial plan, its median wall time [s] over `repeats` runs)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        plan = plan_features(task)
        times.append(time.perf_counter() - t0)
    return plan, float(np.median(times))


def feature_rows(task: Task, quick: bool, repeats: int,
                 say: Callable[[str], None]) -> tuple[list[dict[str, Any]], Plan, float]:
    """Serial planning time of the task's first k features, k = 1 .. all (quick: 1 and all); the
    last row's plan is the serial reference of the worker rows."""
    label, n = task.path.stem, len(task.features)
    if not quick:                       # warm: this process's first plan loads Warp's kernels
        plan_features(replace(task, features=task.features[:1]))
    rows, plans = [], []
    for k in sorted({1, n}) if quick else range(1, n + 1):
        plan, time_s = timed(replace(task, features=task.features[:k]), repeats)
        assert plan.cover is not None                  # a multi-feature plan's
        rows.append({"task": label, "features": k, "candidates": plan.cover["candidate_shots"],
                     "evaluations": evaluations(plan), "time_s": time_s,
                     "evaluations_per_s": evaluations(plan) / time_s, "stages_s": plan.timing_s})
        plans.append(plan)
        say(f"{label} {k} of {n} features: {rows[-1]['candidates']} candidate shots, {time_s:.2f} s serial")
    return rows, plans[-1], rows[-1]["time_s"]


def spin(seconds: float, say: Callable[[str], None]) -> int:
    """A job: plain integer steps for `seconds`; how many (the rate its core gives it)."""
    end, steps = time.perf_counter() + seconds, 0
    while time.perf_counter() < end:
        steps += 1
    return steps


def machine_speedup(one: parallel.Pool, two: parallel.Pool, rounds: int) -> list[float]:
    """Each round's 2 x (a spin job's steps while another runs beside it on the other worker) /
    (a spin job's steps alone): what two processes on the machine's cores make of them with
    nothing to share and no job to wait for, the ceiling of the plan's speedup. ABBA rounds."""
    ratios = []
    for r in range(rounds):
        steps = {}
        for k in (0, 1) if r % 2 == 0 else (1, 0):
            steps[k] = np.mean((one, two)[k].map(spin, [(SPIN_S,)] * (2 + 2 * k), lambda line: None))
        ratios.append(2.0 * steps[1] / steps[0])
    return ratios


def side_by_side(task: Task, one: parallel.Pool, two: parallel.Pool,
                 rounds: int) -> tuple[list[Plan], tuple[list[float], list[float]], list[float]]:
    """(the plans on pools `one` and `two`, their times [s], each round's ratio one / two) of
    plan_features, `rounds` rounds of a run on each, which first in turn (ABBA: a machine that
    slows or speeds up as the rounds go weighs on both alike)."""
    plans: dict[int, Plan] = {}
    times: tuple[list[float], list[float]] = ([], [])
    for r in range(rounds):
        for k in (0, 1) if r % 2 == 0 else (1, 0):
            t0 = time.perf_counter()
            plans[k] = plan_features(task, pool=(one, two)[k])
            times[k].append(time.perf_counter() - t0)
    return [plans[0], plans[1]], times, [a / b for a, b in zip(*times)]


def worker_row(task: Task, serial: Plan, serial_s: float, rounds: int,
               say: Callable[[str], None]) -> dict[str, Any]:
    """1 and 2 workers of one LocalCluster against the serial plan `serial` (serial_s [s]): each
    worker count's median time, the speedup as the median of the rounds' ratios (with every
    round's: the spread), and the machine's own speedup in as many rounds (machine_speedup)."""
    label = task.path.stem
    t0 = time.perf_counter()
    with parallel.local_cluster(2) as both:
        startup_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        first = plan_features(task, pool=both)          # the workers' first plan: Warp's kernels load
        first_s = time.perf_counter() - t0
        one = both.restricted(sorted(both.client.nthreads())[:1])
        plans, (one_times, two_times), ratios = side_by_side(task, one, both, rounds)
        ceiling = machine_speedup(one, both, rounds)
    one_s, two_s, count = float(np.median(one_times)), float(np.median(two_times)), evaluations(serial)
    assert serial.cover is not None                    # a multi-feature plan's
    row = {"task": label, "features": len(task.features), "candidates": serial.cover["candidate_shots"],
           "evaluations": count, "serial_s": serial_s, "startup_s": startup_s, "first_s": first_s,
           "workers": [{"workers": 1, "time_s": one_s, "evaluations_per_s": count / one_s},
                       {"workers": 2, "time_s": two_s, "evaluations_per_s": count / two_s}],
           "speedup": float(np.median(ratios)), "speedups": ratios,
           "machine_speedup": float(np.median(ceiling)), "machine_speedups": ceiling,
           "speedup_with_startup": serial_s / (startup_s + first_s),
           "identical": all(same_plan(serial, p) for p in (first, *plans))}
    say(f"{label} on workers: 1 worker {one_s:.2f} s, 2 workers {two_s:.2f} s: {row['speedup']:.2f}x (median of "
        f"{rounds} rounds: " + ", ".join(f"{r:.2f}" for r in ratios) + f"; the machine's own "
        f"{row['machine_speedup']:.2f}x; cluster start {startup_s:.1f} s, first plan {first_s:.2f} s); plans "
        "identical to the serial one: " + ("yes" if row["identical"] else "NO"))
    return row


def collision_row(task: Task, rounds: int, say: Callable[[str], None]) -> dict[str, Any]:
    """The task's serial plan timed with the collision checks (and its route's moves checked)
    and without (PlannerSettings.collisions, no moves), `rounds` ABBA rounds; ratio = median with
    / median without."""
    times: tuple[list[float], list[float]] = ([], [])
    settings = (PlannerSettings(), PlannerSettings(collisions=False))
    for r in range(rounds):
        for k in (0, 1) if r % 2 == 0 else (1, 0):
            t0 = time.perf_counter()
            plan = plan_features(task, settings[k])
            if settings[k].collisions:
                with_moves(task, plan)
            times[k].append(time.perf_counter() - t0)
    with_s, without_s = float(np.median(times[0])), float(np.median(times[1]))
    load = os.getloadavg()[0]
    row = {"task": task.path.stem, "features": len(task.features), "with_collisions_s": with_s,
           "without_collisions_s": without_s, "times_with_s": times[0], "times_without_s": times[1],
           "ratio": with_s / without_s, "load": load}
    say(f"{row['task']} collision checks: {with_s:.2f} s with, {without_s:.2f} s without: "
        f"{row['ratio']:.2f}x (median of {rounds} rounds, load {load:.2f})")
    return row


def run(tasks: Iterable[Task], quick: bool, say: Callable[[str], None]) -> dict[str, list[dict[str, Any]]]:
    """{"features": rows, "workers": rows, "collisions": rows} of the multi-feature `tasks`."""
    repeats = 1 if quick else 3
    out: dict[str, list[dict[str, Any]]] = {"features": [], "workers": [], "collisions": []}
    for task in tasks:
        rows, serial, serial_s = feature_rows(task, quick, repeats, say)
        out["features"] += rows
        out["workers"].append(worker_row(task, serial, serial_s, 1 if quick else ROUNDS, say))
        out["collisions"].append(collision_row(task, 1 if quick else 3, say))
    return out


def targets(workers: Iterable[dict[str, Any]], collisions: Iterable[dict[str, Any]] = ()) -> list[dict[str, Any]]:
    """The issues' done-when: 2 workers at least SPEEDUP_TARGET x 1 worker; the plans identical;
    planning with collision checks at most COLLISION_TARGET x without."""
    out = [{"name": f"{row['task']} planning with collision checks / without <= {COLLISION_TARGET:g}",
            "value": row["ratio"], "limit": COLLISION_TARGET, "met": row["ratio"] <= COLLISION_TARGET}
           for row in collisions]
    for row in workers:
        out.append({"name": f"{row['task']}: 2 workers / 1 worker >= {SPEEDUP_TARGET:g}",
                    "value": row["speedup"], "limit": SPEEDUP_TARGET, "met": row["speedup"] >= SPEEDUP_TARGET})
        out.append({"name": f"{row['task']}: serial and parallel plans identical",
                    "value": float(row["identical"]), "limit": 1.0, "met": row["identical"]})
    return out
