"""`cell run TASK [--backend sim|hw] [--out DIR] [--max-iterations N] [--yes]`: exit 0 when every
feature pixel ends in the gray band, 1 when not (with the reason), 3 on a device fault. A task
with several features, or planned viewpoints, runs its shots (cell.run.inspection)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from cell.run import backends, loop
from cell.cli import backend_of, create_folder, output_folder
from cell.core.errors import TaskError
from cell.task.loader import load_task

if TYPE_CHECKING:
    from cell.task.types import Task


def command(args: argparse.Namespace) -> int:
    if args.max_iterations < 1:
        raise TaskError("command line", "--max-iterations", args.max_iterations, "an integer >= 1")
    out = output_folder(args.out, Path(args.task).stem)
    task = load_task(args.task)
    backend = backend_of(task, args.backend)
    create_folder(out)
    if task.whole_part:
        return shots(task, out, backend, args)
    result = loop.run(task, out, lambda scene: backends.open_devices(task, scene, backend, args.yes),
                      args.max_iterations)
    last, n = result.iterations[-1], len(result.iterations)
    g, (low, high) = last.measured_gray, task.requirements.gray_band
    print(f"{task.name}: converged after {loop.count(n, 'iteration')}: feature gray {g['min']:.0f}-{g['max']:.0f} "
          f"(mean {g['mean']:.1f}, band {low:g}-{high:g}) at {1e3 * last.shutter_s:.3f} ms, "
          f"f/{last.f_number:.2f}")
    print(f"  wrote {out}/report.json, log.jsonl, {loop.count(n, 'capture')} with the feature drawn, plan pictures")
    return 0


def shots(task: Task, out: Path, backend: str, args: argparse.Namespace) -> int:
    """The shots of a task with several features or planned viewpoints, and a line per feature."""
    from cell.run import inspection
    first = task.with_feature(0)            # the simulated cell renders the first feature's scene
    result = inspection.run(task, out, lambda scene: backends.open_devices(first, scene, backend, args.yes),
                            args.max_iterations)
    features = result.feature_results()
    print(f"{task.name}: converged: {len(features)} of {len(features)} features in band, "
          f"{loop.count(len(result.shots), 'shot')} in the order {list(result.order)} "
          f"({result.travel_m:.3f} m of travel)")
    for f in features:
        print(f"  feature {inspection.gray_line(f)}")
    print(f"  wrote {out}/report.json, log.jsonl, plan.json and a folder per shot "
          + ", ".join(f"shot-{s}/" for s in result.order))
    return 0
