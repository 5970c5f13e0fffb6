"""`cell bench`'s many-feature rows (issue 28): the generated long bracket
(lightplan_tasks.many_features: the bracket's five faces repeated every 14 mm) at SIZES features,
each planned warm serially (ROUNDS times, the sizes in turn: the medians) and on 2 worker
processes of a LocalCluster, each plan alone in a fresh process of its own (cell.bench.alone: it
warms up with a one-feature plan, then plans the size): the times, the judge's share of the serial plan (timing_s: judge / total), the peak memory of that
plan's processes (the plan's process and, with workers, its cluster's nannies and workers; not
this one, which holds no plan: proportional and resident, as alone.PeakMemory counts them),
whether the two plans are the same (the digests of their plan.json content without timing_s),
and the machine's load (1-minute average) as the plan starts and ends. Then the growth exponent
of the serial time between GROWTH[0] and GROWTH[1] features (the log-log slope: 1 is linear, 2 the
square) and, at SIDE_BY_SIDE features, 1 worker against 2 in rounds side by side on a LocalCluster
of this process (cell.bench.multi_feature's)."""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cell.bench import alone, multi_feature
from cell.planning import parallel
from cell.planning.whole_part import plan_features
from cell.task.loader import load_task

SIZES = (10, 20, 40, 100)           # features of the generated part (--quick: QUICK_SIZES)
QUICK_SIZES = (5, 10)
GROWTH = (10, 40)                   # the growth exponent's two sizes (--quick: the first and last)
SIDE_BY_SIDE = 40                   # the size of the rounds of 1 and 2 workers (--quick: the last)
ROUNDS = 3                          # serial plans of each size, and of 1 and 2 workers each (--quick: 1)
SERIAL_TARGET_S = 20.0              # the done-when, at 40 features
GROWTH_TARGET = 1.1
JUDGE_SHARE_TARGET = 0.20
SPEEDUP_TARGET = 1.6
MEMORY_TARGET_B = 1e9


def growth_exponent(features: Sequence[int], times: Sequence[float], between: tuple[int, int]) -> float:
    """The exponent k of time ~ features^k between the two sizes `between`: the log-log slope
    ln(t2 / t1) / ln(n2 / n1); NaN where they are one size (a bench of one size has no growth)."""
    (n1, n2), by = between, dict(zip(features, times))
    if n1 == n2:
        return math.nan
    return math.log(by[n2] / by[n1]) / math.log(n2 / n1)


def serial_row(measured: Sequence[dict[str, Any]], say: Callable[[str], None]) -> dict[str, Any]:
    """One size's serial row from its rounds (alone.measure's of the task, each alone in a
    process of its own): the median of their wall, CPU and judge times and of their judge
    shares (one plan's share moves with the machine by more than a change to the judge), each
    round's wall and share beside, the largest peak memory, the load from the first round's
    start to the last round's end, and the digest where every round's plan is the same (else
    None: a plan that changes with the run is a fault)."""
    m = measured[0]
    digests = {r["digest"] for r in measured}
    row = {"task": "many", "features": m["features"], "candidates": m["candidates"], "shots": m["shots"],
           "feasible": all(r["feasible"] for r in measured),
           "serial_s": float(np.median([r["wall_s"] for r in measured])),
           "serial_cpu_s": float(np.median([r["cpu_s"] for r in measured])),
           "judge_s": float(np.median([r["timing_s"]["judge"] for r in measured])),
           "judge_share": float(np.median([r["judge_share"] for r in measured])),
           "serial_rounds_s": [r["wall_s"] for r in measured], "judge_shares": [r["judge_share"] for r in measured],
           "peak_memory_serial_b": max(r["peak_rss_b"] for r in measured),
           "peak_pss_serial_b": max(r["peak_pss_b"] for r in measured),
           "load": [measured[0]["load"][0], measured[-1]["load"][1]],
           "digest": m["digest"] if len(digests) == 1 else None}
    shares = row["judge_shares"]
    say(f"many {row['features']} features: {row['candidates']} candidate shots, {row['shots']} shots; serial "
        f"{row['serial_s']:.1f} s (judge {row['judge_share']:.0%}; {len(measured)} rounds, judge {min(shares):.0%}-"
        f"{max(shares):.0%}), peak memory {row['peak_pss_serial_b'] / 1e6:.0f} MB proportional "
        f"({row['peak_memory_serial_b'] / 1e6:.0f} MB resident); load {row['load'][0]:.1f} -> {row['load'][1]:.1f}"
        + ("" if row["digest"] else "; the rounds' plans DIFFER"))
    return row


def workers_row(row: dict[str, Any], path: Path, say: Callable[[str], None]) -> dict[str, Any]:
    """`row` with the same size planned alone on 2 workers (alone.measure: a process of its own
    and its LocalCluster's nannies and workers): time, speedup over serial, the peak memory of
    those processes, the load, whether the plan is the serial one (their digests equal)."""
    m = alone.measure(path, 2)
    out = {**row, "workers_2_s": m["wall_s"], "workers_2_cpu_s": m["cpu_s"], "speedup": row["serial_s"] / m["wall_s"],
           "peak_memory_2_workers_b": m["peak_rss_b"], "peak_pss_2_workers_b": m["peak_pss_b"],
           "load_2_workers": m["load"], "identical": row["digest"] is not None and m["digest"] == row["digest"]}
    say(f"many {row['features']} features on 2 workers: {m['wall_s']:.1f} s ({out['speedup']:.2f}x serial), peak "
        f"memory {m['peak_pss_b'] / 1e6:.0f} MB proportional ({m['peak_rss_b'] / 1e6:.0f} MB resident) in all "
        f"processes; load {m['load'][0]:.1f} -> {m['load'][1]:.1f}; plan identical to the serial one: "
        + ("yes" if out["identical"] else "NO"))
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
    first, `rounds` times, then on 2 workers, each plan alone in a process of its own (cell.bench.alone); then the
    rounds of 1 and 2 workers of one LocalCluster of this process's."""
    from lightplan_tasks import many_features
    sizes = tuple(sizes or (QUICK_SIZES if quick else SIZES))
    growth = GROWTH if set(GROWTH) <= set(sizes) else (sizes[0], sizes[-1])
    side = SIDE_BY_SIDE if SIDE_BY_SIDE in sizes else sizes[-1]
    rounds = rounds or (1 if quick else ROUNDS)
    with tempfile.TemporaryDirectory() as folder:
        paths = {n: many_features.write(folder, n) for n in sizes}
        measured: dict[int, list[dict[str, Any]]] = {n: [] for n in sizes}
        for _ in range(rounds):         # the sizes in turn, round after round: a drift of the machine's speed
            for n in sizes:             # falls on every size alike
                measured[n].append(alone.measure(paths[n], 0))
        serial = {n: serial_row(measured[n], say) for n in sizes}
        rows = [workers_row(serial[n], paths[n], say) for n in sizes]
        task = load_task(paths[side])
        with parallel.local_cluster(2) as two:
            plan_features(replace(task, features=task.features[:1]), pool=two)    # the workers' first plan
            one = two.restricted(sorted(two.client.nthreads())[:1])
            _, (one_times, two_times), ratios = multi_feature.side_by_side(task, one, two, rounds)
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
