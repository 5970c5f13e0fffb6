"""`cell bench [TASK...] [--quick] [--out DIR] [--json]`: tables on stdout (stderr with --json),
bench.json and bench.png in DIR, progress on stderr (a bar per stage on a terminal: cell.core.progress)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from cell.bench import scaling, suite
from cell.core import jsonio
from cell.core.progress import Progress
from cell.cli import create_folder, output_folder
from cell.report import words
from cell.task.loader import load_task

if TYPE_CHECKING:
    from cell.task.types import Task


def text_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Columns aligned: left for the first two, right for the rest."""
    cells = [header] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    return "\n".join("  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
                     for r in cells)


def report(result: dict[str, Any]) -> str:
    """The terminal tables: settings, kernels, features, workers, channels, contrast, threads, targets."""
    settings = text_table(
        ["task", "setting", "cands", "samples", "time s", "certify s", "err mean", "err min", "err max", "worst",
         "lamp mm", "lamp deg", "feasible", "tightest", "agrees", "finite", "pareto", "default"],
        [[r["task"], r["name"], r["candidates"], r["samples"], f"{r['time_s']:.3f}",
          f"{r['stages_s'].get('verify', 0.0):.3f}",
          *(f"{r['gray_error'][k]:+.3f}" for k in ("mean", "min", "max")), f"{r['gray_error_max']:.3f}",
          f"{r['lamp_error_mm']:.1f}", f"{r['lamp_error_deg']:.2f}", "yes" if r["feasible"] else "NO",
          words.label(r["binding"]), "yes" if r["feasible_agrees"] else "FLIP", "yes" if r["finite"] else "NaN/inf",
          "*" if r["pareto"] else "", "*" if r["default"] else ""] for r in result["settings"]])
    refs = "\n".join(f"reference {r['task']}: {r['time_s']:.1f} s, {r['candidates']} candidates, "
                     f"{r['samples']} samples, grid {r['settings']['grid_step_deg']} deg, "
                     + (f"feasible, tightest requirement: {words.label(r['binding'])}" if r["feasible"] else
                        f"infeasible: {words.label(r['binding'])} fails")
                     for r in result["references"])
    kernels = text_table(
        ["task", "kernel", "size", "Warp /s", "reference", "ref size", "ref /s", "ratio"],
        [[r["task"], r["name"], f"{r['size']:.3g}", f"{r['warp_per_s']:.3g}", r["reference"],
          *((f"{r['reference_size']:.3g}", f"{r['reference_per_s']:.3g}", f"{r['ratio']:.1f}")
            if r["ratio"] is not None else ("-", "-", r["unavailable"]))] for r in result["kernels"]])
    features = text_table(
        ["task", "features", "candidates", "evaluations", "time s", "evals/s", "judge s"],
        [[r["task"], r["features"], r["candidates"], r["evaluations"], f"{r['time_s']:.2f}",
          f"{r['evaluations_per_s']:.3g}", f"{r['stages_s']['judge']:.3f}"] for r in result["features"]])
    workers = text_table(
        ["task", "features", "candidates", "serial s", "1 worker s", "2 workers s", "1 worker evals/s",
         "2 workers evals/s", "speedup", "rounds", "machine", "start s", "first s", "identical"],
        [[r["task"], r["features"], r["candidates"], f"{r['serial_s']:.2f}",
          *(f"{w['time_s']:.2f}" for w in r["workers"]), *(f"{w['evaluations_per_s']:.3g}" for w in r["workers"]),
          f"{r['speedup']:.2f}x", f"{min(r['speedups']):.2f}-{max(r['speedups']):.2f} ({len(r['speedups'])})",
          f"{r['machine_speedup']:.2f}x",
          f"{r['startup_s']:.1f}", f"{r['first_s']:.2f}", "yes" if r["identical"] else "NO"]
         for r in result["workers"]])
    collisions = text_table(
        ["task", "features", "with collisions s", "without s", "ratio", "rounds", "load"],
        [[r["task"], r["features"], f"{r['with_collisions_s']:.2f}", f"{r['without_collisions_s']:.2f}",
          f"{r['ratio']:.2f}x", str(len(r["times_with_s"])), f"{r['load']:.2f}"] for r in result.get("collisions", [])])
    channels = text_table(
        ["task", "channels", "on", "samples", "dense", "time s", "cpu s", "contributions s", "dense contributions s",
         "drives s", "certificate s", "other s", "feasible"],
        [[r["task"], r["channels"], r["on"], r["samples"], r["dense_points"], f"{r['time_s']:.2f}", f"{r['cpu_s']:.2f}",
          *(f"{r[k]:.2f} ({r[k] / r['time_s']:.0%})" for k in ("contributions_s", "certificate_contributions_s")),
          f"{r['drives_s']:.3f} ({r['drives_s'] / r['time_s']:.0%})",
          *(f"{r[k]:.2f} ({r[k] / r['time_s']:.0%})" for k in ("certificate_s", "other_s")),
          "yes" if r["feasible"] else f"NO: {words.label(r['binding'])}"] for r in result["channels"]])
    threads = text_table(
        ["task", "launch", "evaluations", "1 thread /s", "2 threads /s", "speedup", "rounds", "machine", "load"],
        [[r["task"], r["launch"], f"{r['evaluations']:.3g}",
          *(f"{t['evaluations_per_s']:.3g}" for t in r["threads"]), f"{r['speedup']:.2f}x",
          f"{min(r['speedups']):.2f}-{max(r['speedups']):.2f} ({len(r['speedups'])})", f"{r['machine_speedup']:.2f}x",
          "{:.1f}-{:.1f}".format(*r["load"])] for r in result["threads"]])
    many = text_table(
        ["task", "features", "candidates", "shots", "serial s", "judge s", "judge share", "2 workers s", "speedup",
         "PSS MB serial", "PSS MB 2 workers", "RSS MB 2 workers", "load serial", "load 2 workers", "identical"],
        [[r["task"], r["features"], r["candidates"], r["shots"], f"{r['serial_s']:.1f}", f"{r['judge_s']:.1f}",
          f"{r['judge_share']:.0%}", f"{r['workers_2_s']:.1f}", f"{r['speedup']:.2f}x",
          f"{r['peak_pss_serial_b'] / 1e6:.0f}", f"{r['peak_pss_2_workers_b'] / 1e6:.0f}",
          f"{r['peak_memory_2_workers_b'] / 1e6:.0f}",
          "{:.1f}-{:.1f}".format(*r["load"]), "{:.1f}-{:.1f}".format(*r["load_2_workers"]),
          "yes" if r["identical"] else "NO"] for r in result["scaling"]])
    goals = "\n".join(f"{'met    ' if t['met'] else 'NOT MET'}  {t['name']}: {t['value']:.3g}"
                      for t in result["targets"])
    parts = [settings, refs, "\n".join(summary(result["settings"])), kernels] if result["settings"] else []
    if not result["settings"] and result["kernels"]:         # the light rows' kernels alone
        parts.append(kernels)
    parts += [threads] if result["threads"] else []
    parts += [features, workers] if result["workers"] else []
    parts += [collisions] if result.get("collisions") else []
    parts += [channels] if result["channels"] else []
    parts += [contrast_table(result["contrast"])] if result.get("contrast") else []
    parts += [many, scaling.summary_line(result["scaling_summary"])] if result["scaling"] else []
    return "\n\n".join(parts + [goals])


def contrast_table(rows: Sequence[dict[str, Any]]) -> str:
    """cell.bench.contrast's rows: what judging each defect's worst CNR costs a lamp pose, against
    its gray's cost, and how close it comes to the reference."""
    return text_table(["task", "defect", "samples", "resolution", "orientations", "time s", "x gray", "CNR error %"],
                      [[r["task"], r["defect"], r["samples"], r["resolution"], r["orientations"], f"{r['time_s']:.4f}",
                        f"{r['ratio']:.1f}", f"{100 * r['cnr_error']:.2f}"] for r in rows])


def summary(settings: Sequence[dict[str, Any]]) -> list[str]:
    """Per task: the default setting's time and error, and the fastest setting within 1 gray
    level of the reference."""
    lines = []
    for label in dict.fromkeys(r["task"] for r in settings):
        rows = [r for r in settings if r["task"] == label]
        default = next(r for r in rows if r["default"])
        close = [r for r in rows if r["gray_error_max"] <= 1.0]
        fastest = min(close, key=lambda r: r["time_s"]) if close else None
        lines.append(f"{label}: default {default['time_s']:.3f} s, gray within {default['gray_error_max']:.2f} of "
                     f"the reference; fastest within 1 gray level: "
                     + (f"{fastest['name']}, {fastest['time_s']:.3f} s ({fastest['gray_error_max']:.2f})"
                        if fastest else "none"))
    return lines


def with_lights(task: Task) -> bool:
    """Whether a one-feature task gets cell.bench.lights' rows (it has lights besides the spot)
    rather than the settings sweep."""
    return bool(task.lights) and not task.whole_part


def with_defects(task: Task) -> bool:
    """Whether a one-feature task gets cell.bench.contrast's rows (its feature declares defects)
    rather than the settings sweep (a plan of each setting would take minutes)."""
    return not task.whole_part and not with_lights(task) and bool(task.feature.defects)


def command(args: argparse.Namespace) -> int:
    from cell.bench.contrast import DEFECT_TASKS
    from cell.bench.lights import LIGHT_TASKS
    from cell.bench.multi_feature import FEATURE_TASKS
    from cell.report.pictures import write_bench
    out = output_folder(args.out, "bench")
    if args.tasks:
        paths = args.tasks
    else:
        paths = list(suite.DEFAULT_TASKS) + list(FEATURE_TASKS) + list(LIGHT_TASKS) + list(DEFECT_TASKS)
    loaded = [load_task(path) for path in paths]          # all first
    tasks = [t for t in loaded if not t.whole_part and not with_lights(t) and not with_defects(t)]
    feature_tasks = [t for t in loaded if t.whole_part]
    light_tasks = [t for t in loaded if with_lights(t)]
    create_folder(out)
    result = suite.run(tasks, args.quick, Progress(sys.stderr), feature_tasks, light_tasks, many=not args.tasks,
                       defect_tasks=[t for t in loaded if with_defects(t)])
    text = jsonio.dumps(result, indent=2)
    (out / "bench.json").write_text(text + "\n")
    if result["settings"]:              # bench.png: the one-feature settings sweep
        write_bench(out / "bench.png", result["settings"])
    tables = sys.stderr if args.json else sys.stdout
    print(report(result), file=tables)
    print(f"wrote {out}/bench.json" + (" and bench.png" if result["settings"] else ""), file=tables, flush=True)
    if args.json:
        print(text)
    return 0
