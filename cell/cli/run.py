"""`cell run TASK [--backend sim|hw] [--out DIR] [--max-iterations N] [--yes]`: exit 0 when every
feature pixel ends in the gray band, 1 when not (with the reason), 3 on a device fault."""
from pathlib import Path

from cell import backends, loop
from cell.cli import create_folder, one_feature, output_folder
from cell.errors import TaskError
from cell.loader import load_task


def command(args):
    if args.max_iterations < 1:
        raise TaskError("command line", "--max-iterations", args.max_iterations, "an integer >= 1")
    out = output_folder(args.out, Path(args.task).stem)
    task = one_feature(load_task(args.task), "run")
    backend = args.backend or task.cell.backend
    create_folder(out)
    result = loop.run(task, out, lambda scene: backends.open_devices(task, scene, backend, args.yes),
                      args.max_iterations)
    last, n = result.iterations[-1], len(result.iterations)
    g, (low, high) = last.measured_gray, task.requirements.gray_band
    print(f"{task.name}: converged after {loop.count(n, 'iteration')}: feature gray {g['min']:.0f}-{g['max']:.0f} "
          f"(mean {g['mean']:.1f}, band {low:g}-{high:g}) at {1e3 * last.shutter_s:.3f} ms, "
          f"f/{last.f_number:.2f}")
    print(f"  wrote {out}/report.json, log.jsonl, {loop.count(n, 'capture')} with the feature drawn, plan pictures")
    return 0
