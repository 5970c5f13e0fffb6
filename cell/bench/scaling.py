"""`cell bench`'s many-feature rows (issue 28): the generated long bracket
(lightplan_tasks.many_features: the bracket's five faces repeated every 14 mm) at SIZES features,
each planned warm serially and on 2 worker processes of one LocalCluster: the times, the judge's
share of the serial plan (timing_s: judge / total), the peak memory of all the processes (this one
and its children: the cluster's nanny and workers; proportional and resident, below), whether the two plans are the same, and the
machine's load (1-minute average) before and after. Then the growth exponent of the serial time
between GROWTH[0] and GROWTH[1] features (the log-log slope: 1 is linear, 2 the square) and, at
SIDE_BY_SIDE features, 1 worker against 2 in rounds side by side (cell.bench.multi_feature's).

Peak memory: the sum over this process and its children of the resident set sizes, sampled every
MEMORY_PERIOD_S while a plan runs (psutil, which Dask's distributed depends on): pages that
processes share (libraries) count in each, so that sum is an upper bound; and of the
proportional set sizes (Linux's /proc/PID/smaps_rollup `Pss`: a shared page split among the
processes mapping it, so the sum is what the processes take together), every PSS_EVERY-th sample
(reading it costs some milliseconds a process). The issue's 1 GB is judged on the proportional sum."""

from __future__ import annotations

import math
import os
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import psutil

from cell.bench import multi_feature
from cell.planning import parallel
from cell.planning.whole_part import plan_features
from cell.task.loader import load_task

if TYPE_CHECKING:
    from cell.planning.plan import Plan
    from cell.task.types import Task

SIZES = (10, 20, 40, 100)           # features of the generated part (--quick: QUICK_SIZES)
QUICK_SIZES = (5, 10)
GROWTH = (10, 40)                   # the growth exponent's two sizes (--quick: the first and last)
SIDE_BY_SIDE = 40                   # the size of the rounds of 1 and 2 workers (--quick: the last)
ROUNDS = 3                          # of 1 and 2 workers each (--quick: 1)
MEMORY_PERIOD_S = 0.05
PSS_EVERY = 10                      # samples: the proportional sizes every 0.5 s
SERIAL_TARGET_S = 20.0              # the done-when, at 40 features
GROWTH_TARGET = 1.1
JUDGE_SHARE_TARGET = 0.20
SPEEDUP_TARGET = 1.6
MEMORY_TARGET_B = 1e9


class PeakMemory:
    """The largest sums [bytes] of this process's and its children's (recursive) memory, sampled by
    a thread while the `with` block runs: `peak` of the resident set sizes (every `period` s),
    `peak_proportional` of the proportional set sizes (every PSS_EVERY-th sample)."""

    def __init__(self, period: float = MEMORY_PERIOD_S) -> None:
        self.period, self.peak, self.peak_proportional = period, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    @staticmethod
    def _processes() -> list[psutil.Process]:
        me = psutil.Process()
        return [me, *me.children(recursive=True)]

    def resident(self) -> int:
        """The sum of resident set sizes now [bytes]; a child that ends while being read counts 0."""
        total = 0
        for process in self._processes():
            try:
                total += process.memory_info().rss
            except psutil.NoSuchProcess:
                pass
        return total

    def proportional(self) -> int:
        """The sum of proportional set sizes now [bytes] (smaps_rollup's Pss; a process whose
        rollup cannot be read, off Linux or ended, counts its resident set, or 0)."""
        total = 0
        for process in self._processes():
            total += proportional_size(process)
        return total

    def _sample(self) -> None:
        count = 0
        while True:
            self.peak = max(self.peak, self.resident())
            if count % PSS_EVERY == 0:
                self.peak_proportional = max(self.peak_proportional, self.proportional())
            count += 1
            if self._stop.wait(self.period):
                return

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.resident())
        self.peak_proportional = max(self.peak_proportional, self.proportional())


def proportional_size(process: psutil.Process) -> int:
    """A process's proportional set size [bytes] from /proc/PID/smaps_rollup (one line to read,
    where psutil's memory_full_info parses every mapping's smaps); its resident set where the
    rollup is missing (not Linux, or older than 4.14), 0 once it has ended."""
    try:
        with open(f"/proc/{process.pid}/smaps_rollup") as rollup:
            for line in rollup:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except FileNotFoundError:
        pass
    except (ProcessLookupError, PermissionError):
        return 0
    try:
        return process.memory_info().rss
    except psutil.NoSuchProcess:
        return 0


def growth_exponent(features: Sequence[int], times: Sequence[float], between: tuple[int, int]) -> float:
    """The exponent k of time ~ features^k between the two sizes `between`: the log-log slope
    ln(t2 / t1) / ln(n2 / n1)."""
    (n1, n2), by = between, dict(zip(features, times))
    return math.log(by[n2] / by[n1]) / math.log(n2 / n1)


def timed(task: Task, pool: parallel.Pool) -> tuple[Plan, float, PeakMemory]:
    """(plan_features of the task on `pool`, its wall time [s], the peak memory of all processes)."""
    with PeakMemory() as memory:
        t0 = time.perf_counter()
        plan = plan_features(task, pool=pool)
        time_s = time.perf_counter() - t0
    return plan, time_s, memory


def serial_row(task: Task, say: Callable[[str], None]) -> tuple[dict[str, Any], Plan]:
    """One size's serial row (no worker process alive: the memory is this process's) and its plan."""
    load_before = os.getloadavg()[0]
    plan, time_s, peak = timed(task, parallel.SERIAL)
    assert plan.cover is not None                      # a multi-feature plan's
    row = {"task": "many", "features": len(task.features), "candidates": plan.cover["candidate_shots"],
           "shots": len(plan.shots), "feasible": plan.feasible, "serial_s": time_s, "judge_s": plan.timing_s["judge"],
           "judge_share": plan.timing_s["judge"] / plan.timing_s["total"], "peak_memory_serial_b": peak.peak,
           "peak_pss_serial_b": peak.peak_proportional, "load": [load_before, os.getloadavg()[0]]}
    say(f"many {row['features']} features: {row['candidates']} candidate shots, {row['shots']} shots; serial "
        f"{time_s:.1f} s (judge {row['judge_share']:.0%}), peak memory {peak.peak_proportional / 1e6:.0f} MB "
        f"proportional ({peak.peak / 1e6:.0f} MB resident); load "
        f"{load_before:.1f} -> {row['load'][1]:.1f}")
    return row, plan


def workers_row(row: dict[str, Any], task: Task, serial: Plan, two: parallel.Pool,
                say: Callable[[str], None]) -> dict[str, Any]:
    """`row` with the same size planned on the 2 workers of `two`: time, speedup over serial, the
    peak memory of all processes, the load, whether the plan is the serial one."""
    load_before = os.getloadavg()[0]
    plan, time_s, peak = timed(task, two)
    out = {**row, "workers_2_s": time_s, "speedup": row["serial_s"] / time_s, "peak_memory_2_workers_b": peak.peak,
           "peak_pss_2_workers_b": peak.peak_proportional, "load_2_workers": [load_before, os.getloadavg()[0]],
           "identical": multi_feature.same_plan(serial, plan)}
    say(f"many {row['features']} features on 2 workers: {time_s:.1f} s ({out['speedup']:.2f}x serial), peak memory "
        f"{peak.peak_proportional / 1e6:.0f} MB proportional ({peak.peak / 1e6:.0f} MB resident) in all processes; "
        f"load {load_before:.1f} -> {out['load_2_workers'][1]:.1f}; plan "
        "identical to the serial one: " + ("yes" if out["identical"] else "NO"))
    return out


def summary_line(s: dict[str, Any]) -> str:
    """The growth exponent and the rounds of 1 and 2 workers, in a line."""
    return (f"many: serial time grows as features^{s['growth_exponent']:.2f} from {s['growth_between'][0]} to "
            f"{s['growth_between'][1]} features; at {s['workers_features']} features 1 worker {s['worker_1_s']:.1f} s, "
            f"2 workers {s['workers_2_s']:.1f} s: {s['speedup']:.2f}x (median of {len(s['speedups'])} rounds; the "
            f"machine's own {s['machine_speedup']:.2f}x on {s['cpus']} cores)")


def run(quick: bool, say: Callable[[str], None], sizes: Sequence[int] | None = None,
        rounds: int | None = None) -> dict[str, Any]:
    """{"scaling": a row per size, "scaling_summary": the growth exponent and the rounds of 1 and 2
    workers} of the generated part at `sizes` features (default SIZES, --quick QUICK_SIZES) and
    `rounds` (default ROUNDS, --quick 1), written into a temporary folder: every size serially
    first, then on 2 workers."""
    from lightplan_tasks import many_features
    sizes = tuple(sizes or (QUICK_SIZES if quick else SIZES))
    growth = GROWTH if set(GROWTH) <= set(sizes) else (sizes[0], sizes[-1])
    side = SIDE_BY_SIDE if SIDE_BY_SIDE in sizes else sizes[-1]
    rounds = rounds or (1 if quick else ROUNDS)
    with tempfile.TemporaryDirectory() as folder:
        tasks = {n: load_task(many_features.write(folder, n)) for n in sizes}
        one_feature = replace(tasks[sizes[0]], features=tasks[sizes[0]].features[:1])
        plan_features(one_feature)                         # warm: this process's first plan loads Warp's kernels
        serial = {n: serial_row(tasks[n], say) for n in sizes}
        with parallel.local_cluster(2) as two:
            plan_features(one_feature, pool=two)           # and the workers' first
            rows = [workers_row(serial[n][0], tasks[n], serial[n][1], two, say) for n in sizes]
            one = two.restricted(sorted(two.client.nthreads())[:1])
            _, (one_times, two_times), ratios = multi_feature.side_by_side(tasks[side], one, two, rounds)
            machine = multi_feature.machine_speedup(one, two, rounds)
    summary = {"growth_between": list(growth),
               "growth_exponent": growth_exponent([r["features"] for r in rows], [r["serial_s"] for r in rows], growth),
               "workers_features": side, "worker_1_s": float(np.median(one_times)),
               "workers_2_s": float(np.median(two_times)), "speedup": float(np.median(ratios)), "speedups": ratios,
               "machine_speedup": float(np.median(machine)), "machine_speedups": machine, "cpus": os.cpu_count()}
    say(summary_line(summary))
    return {"scaling": rows, "scaling_summary": summary}


def targets(rows: Sequence[dict[str, Any]], summary: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's done-when at 40 features (none when 40 was not planned, as with --quick)."""
    row = next((r for r in rows if r["features"] == 40), None)
    if row is None:
        return []
    out = [("many-40: warm serial plan <= 20 s", row["serial_s"], SERIAL_TARGET_S, row["serial_s"] <= SERIAL_TARGET_S),
           ("many-40: judge <= 20 % of planning", row["judge_share"], JUDGE_SHARE_TARGET,
            row["judge_share"] <= JUDGE_SHARE_TARGET),
           ("many-40: peak memory with 2 workers <= 1 GB", row["peak_pss_2_workers_b"] / 1e9, MEMORY_TARGET_B / 1e9,
            row["peak_pss_2_workers_b"] <= MEMORY_TARGET_B)]
    if tuple(summary["growth_between"]) == GROWTH:
        out.append((f"many: growth exponent {GROWTH[0]} -> {GROWTH[1]} features <= {GROWTH_TARGET:g}",
                    summary["growth_exponent"], GROWTH_TARGET, summary["growth_exponent"] <= GROWTH_TARGET))
    if summary["workers_features"] == 40:
        out.append((f"many-40: 2 workers / 1 worker >= {SPEEDUP_TARGET:g}", summary["speedup"], SPEEDUP_TARGET,
                    summary["speedup"] >= SPEEDUP_TARGET))
    return [{"name": name, "value": value, "limit": limit, "met": met} for name, value, limit, met in out]
