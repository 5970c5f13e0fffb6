"""The `cell` command line. Every CellError becomes one line on stderr and its exit code:
0 done, 1 goal not reached, 2 bad input, 3 device fault."""
import argparse
import importlib
import signal
import sys

from cell.errors import CellError

# sub-command -> the module of this package implementing `command(args) -> int`, imported only
# when run: `cell check` loads no Warp, SciPy optimizer or matplotlib
COMMANDS = {
    "check": "cell.cli.check",
    "fit-brdf": "cell.cli.fit_brdf",
    "plan": "cell.cli.plan",
    "run": "cell.cli.run",
    "bench": "cell.cli.bench",
    "calibrate": "cell.cli.calibrate",
}


def output_folder(out, default):
    """The run folder `--out` names (or `default`), created now, before any work: a path that
    is a file or cannot be created is bad input (exit 2), not a traceback after the work."""
    from pathlib import Path

    from cell.errors import TaskError
    folder = Path(out or default)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise TaskError("command line", "--out", str(folder),
                        f"a folder that can be created ({err.strerror or err})") from None
    return folder


def build_parser():
    parser = argparse.ArgumentParser(prog="cell", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("check", help="load a task and everything it references, print a summary")
    p.add_argument("task")

    p = sub.add_parser("fit-brdf", help="fit the BRDF of eq. (6)-(7) to goniometer data per phase angle")
    p.add_argument("data", help="CSV with theta_i_deg,theta_e_deg,phase_deg,reflectance")
    p.add_argument("--out", help="material YAML to write")
    p.add_argument("--name", help="material name (default: the CSV's stem)")
    p.add_argument("--json", action="store_true", help="print the material as JSON")

    p = sub.add_parser("plan", help="plan lamp position, shutter, f-number and focus for a task")
    p.add_argument("task")
    p.add_argument("--out", help="folder for plan.json and the pictures (default runs/<task>-plan)")
    p.add_argument("--json", action="store_true", help="print plan.json to stdout")

    p = sub.add_parser("run", help="plan, drive the cell, capture, measure and correct in a closed loop")
    p.add_argument("task")
    p.add_argument("--backend", choices=("sim", "hw"), help="override the task's cell.backend")
    p.add_argument("--out", help="run folder (default runs/<task>-<time>)")
    p.add_argument("--max-iterations", type=int, default=6, metavar="N",
                   help="captures at most before giving up (default 6)")
    p.add_argument("--yes", action="store_true", help="confirm operator prompts (manual lamp radius) on "
                                                      "the real cell; the simulated cell confirms its own")

    p = sub.add_parser("bench", help="what accuracy costs in time; kernel throughput")
    p.add_argument("tasks", nargs="*", help="default: the example tasks hinge.yaml and conrod.yaml, installed with the package")
    p.add_argument("--quick", action="store_true", help="small sweep (< 1 min) for smoke tests")
    p.add_argument("--out", help="folder for bench.json and bench.png (default runs/bench)")
    p.add_argument("--json", action="store_true", help="print bench.json to stdout")

    p = sub.add_parser("calibrate", help="operator routine: fit the camera constant c from a shutter sweep")
    p.add_argument("task", help="a task whose part and material table you trust (the reference)")
    p.add_argument("--backend", choices=("sim", "hw"), help="override the task's cell.backend")
    p.add_argument("--out", help="folder for calibration.json and calibration.png "
                                 "(default runs/<task>-calibration)")
    p.add_argument("--shots", type=int, default=6, metavar="N",
                   help="shutter times in the sweep, at least 3 (default 6)")
    p.add_argument("--yes", action="store_true", help="confirm operator prompts (manual lamp radius, "
                                                      "lens) on the real cell; the simulated cell "
                                                      "confirms its own")
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that a run's safe stop and its report still happen."""


def _terminate(signum, frame):
    raise Terminated()


def main(argv=None):
    args = build_parser().parse_args(argv)
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        module = importlib.import_module(COMMANDS[args.command])
        return int(module.command(args) or 0)
    except CellError as err:
        print(f"cell {args.command}: {err}", file=sys.stderr, flush=True)
        return err.exit_code
    except KeyboardInterrupt as err:
        terminated = isinstance(err, Terminated)
        print(f"cell {args.command}: {'terminated (SIGTERM)' if terminated else 'interrupted'}",
              file=sys.stderr, flush=True)
        return 143 if terminated else 130
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
