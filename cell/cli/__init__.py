"""The `cell` command line. Every CellError becomes one line on stderr and its exit code:
0 done, 1 goal not reached, 2 bad input, 3 device fault."""

from __future__ import annotations

import argparse
import importlib
import re
import os
import signal
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, NoReturn

from cell.core.errors import CellError

if TYPE_CHECKING:
    from pathlib import Path
    from cell.task.types import Task

# sub-command -> the module of this package implementing `command(args) -> int`, imported only
# when run: `cell check` loads no Warp, SciPy optimizer or matplotlib
COMMANDS = {
    "check": "cell.cli.check",
    "fit-brdf": "cell.cli.fit_brdf",
    "plan": "cell.cli.plan",
    "run": "cell.cli.run",
    "bench": "cell.cli.bench",
    "calibrate": "cell.cli.calibrate",
    "hw-check": "cell.cli.hw_check",
    "measure-brdf": "cell.cli.measure_brdf",
}

# `cell calibrate`'s routines
ROUTINES = {"camera-constant": "c by a laser of known power aimed at the sensor at several shutter times "
                               "(sec. 4.1); writes a camera file",
            "reference-part": "c by a shutter sweep on a reference part, against the task's material table "
                              "(G = b + c P t): a cross-check",
            "hand-eye": "the camera's focal length and the hand-eye transform T_flange_cam from views of the "
                        "ChArUco board of calibration.board; writes the task's hand-eye keys"}


def output_folder(out: str | None, name: str) -> Path:
    """The run folder `--out` names, checked now, before any work, and not yet created: a task
    that fails to load leaves no folder behind (create_folder makes it once the task loaded).
    Bad input (exit 2): an empty --out, a path that is a file or cannot be created, and an
    existing folder that is not empty, so that runs never mix in one log or report. Without
    --out: runs/<name>-<YYYYmmdd-HHMMSS>, with -2, -3, ... if that exists already."""
    import time
    from pathlib import Path

    if out is None:
        stamp = Path("runs") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"
        folder, n = stamp, 1
        while folder.exists() or folder.is_symlink():
            n += 1
            folder = stamp.with_name(f"{stamp.name}-{n}")
    elif not out.strip():
        raise _bad_out("''", "a folder path (an empty --out names no folder)")
    else:
        folder = Path(out)
    _check_folder(folder)
    return folder


def one_feature(task: Task, command: str) -> Task:
    """The task, refused (bad input, exit 2) when it has several features or a planned camera
    viewpoint: `command` drives one shot at the fixed camera rule; running several, or a planned
    viewpoint, is not yet supported (`cell plan` plans them)."""
    from cell.core.errors import TaskError
    if len(task.features) != 1:
        raise TaskError(task.path, "features", f"{len(task.features)} features",
                        f"one feature for `cell {command}`: running several shots is not yet supported "
                        f"(`cell plan` plans them)")
    if task.camera.viewpoint.mode != "fixed":
        raise TaskError(task.path, "camera.viewpoint", task.camera.viewpoint.mode,
                        f"fixed for `cell {command}`: running a planned viewpoint is not yet supported "
                        f"(`cell plan` plans it)")
    return task


def backend_of(task: Task, given: str | None) -> str:
    """The backend a command runs on (--backend, else the task's cell.backend), with the task's cell
    section checked for it now, before any planning or folder: for hw everything the real cell's
    devices need (cell.task.device_config.for_hw; bad input, exit 2), on either backend every
    light's channel one of cell.lighting's (check_channels)."""
    from cell.task.device_config import check_channels, for_hw
    backend = given or task.cell.backend
    if backend == "hw":
        for_hw(task.cell.devices, task.channels)
    check_channels(task.cell.devices, task.channels)
    return backend


def create_folder(folder: Path) -> Path:
    """The folder output_folder checked, created now that the task loaded (checked again: a
    folder that filled up meanwhile is refused as well)."""
    _check_folder(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise _bad_out(folder, f"a folder that can be created ({err.strerror or err})") from None
    return folder


def _check_folder(folder):
    import os

    try:
        if folder.is_dir():
            if any(folder.iterdir()):
                raise _bad_out(f"{folder}, a folder that exists and is not empty",
                               "a new or empty folder: pass another --out (runs never mix)")
            return
        if folder.exists() or folder.is_symlink():
            raise _bad_out(f"{folder}, which is not a folder", "a folder that can be created")
        parent = folder.absolute().parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise _bad_out(folder, f"a folder that can be created ({parent} is a file)")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise _bad_out(folder, f"a folder that can be created (no permission in {parent})")
    except OSError as err:
        raise _bad_out(folder, f"a folder that can be created ({err.strerror or err})") from None


def _bad_out(found, expected):
    from cell.core.errors import TaskError
    return TaskError("command line", "--out", found, expected)


DESCRIPTION = ("Plan where the lamp goes and how the camera exposes for a visual inspection, then run, "
               "measure and calibrate the cell (simulated or real).")
EPILOG = "exit status: 0 done, 1 goal not reached (e.g. no feasible plan), 2 bad input, 3 device fault"


def version() -> str:
    """The installed distribution's version (importlib.metadata), or 'unknown' when run from a
    checkout that is not installed."""
    from importlib import metadata
    try:
        return metadata.version("lightplan-cell")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cell", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}",
                        help="print the version of lightplan-cell and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("check", help="load a task and everything it references, print a summary")
    p.add_argument("task")
    p.add_argument("--backend", choices=("sim", "hw"), help="check for this backend instead of the task's "
                                                            "cell.backend (hw: what `cell run --backend hw` needs)")

    p = sub.add_parser("fit-brdf", help="fit the BRDF of eq. (6)-(7) to goniometer data per phase angle")
    p.add_argument("data", help="CSV with theta_i_deg,theta_e_deg,phase_deg,reflectance")
    p.add_argument("--out", help="material YAML to write")
    p.add_argument("--name", help="material name (default: the CSV's stem)")
    p.add_argument("--json", action="store_true", help="print the material as JSON")

    p = sub.add_parser("plan", help="plan lamp position, shutter, f-number and focus for a task")
    p.add_argument("tasks", nargs="+", metavar="TASK")
    p.add_argument("--out", help="folder for plan.json and the pictures, new or empty (default "
                                 "runs/<task>-plan-<time>); with several tasks, a folder <task> in it for each")
    p.add_argument("--json", action="store_true", help="print plan.json to stdout (several tasks: a list)")
    p.add_argument("--pictures", choices=("chosen", "all"), default="chosen",
                   help="pictures of a multi-feature plan's candidate shots: of the chosen ones (default) or all")
    p.add_argument("--workers", metavar="N", help="plan on a Dask LocalCluster of N worker processes "
                                                  "on this machine (127.0.0.1)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="plan on the running Dask cluster of this "
                                                          "scheduler, e.g. tcp://127.0.0.1:8786")

    p = sub.add_parser("run", help="plan, drive the cell, capture, measure and correct in a closed loop")
    p.add_argument("task")
    p.add_argument("--backend", choices=("sim", "hw"), help="override the task's cell.backend")
    p.add_argument("--out", help="run folder, new or empty (default runs/<task>-<time>)")
    p.add_argument("--max-iterations", type=int, default=6, metavar="N",
                   help="captures at most before giving up (default 6)")
    p.add_argument("--yes", action="store_true", help="confirm operator prompts (manual lamp radius) on "
                                                      "the real cell; the simulated cell confirms its own")

    p = sub.add_parser("bench", help="what accuracy costs in time; kernel throughput")
    p.add_argument("tasks", nargs="*", help="default: the example tasks hinge.yaml and conrod.yaml, installed with "
                                            "the package, the multi-feature example bracket.yaml (its planning time "
                                            "on 1 and 2 workers) and the lights example ring.yaml (per channel)")
    p.add_argument("--quick", action="store_true", help="small sweep (< 1 min) for smoke tests")
    p.add_argument("--out", help="folder for bench.json and bench.png, new or empty (default runs/bench-<time>)")
    p.add_argument("--json", action="store_true", help="print bench.json to stdout")

    p = sub.add_parser("calibrate", help="operator routines measuring the camera constant c, the intrinsics "
                                         "and the hand-eye transform")
    p.routines = ROUTINES
    routines = p.add_subparsers(dest="routine", required=True, metavar="ROUTINE")
    r = routines.add_parser("camera-constant", help=ROUTINES["camera-constant"])
    r.add_argument("task", help="a task whose camera it is (its sensor section, sim effects and truth)")
    r.add_argument("--laser-power-w", type=float, required=True, metavar="P",
                   help="the laser's power reaching the sensor, after its neutral-density filters [W]")
    r.add_argument("--camera-file", metavar="PATH", help="the camera file to write, e.g. beside the task "
                                                         "(default camera.yaml in the run folder)")
    r.add_argument("--force", action="store_true", help="replace an existing camera file")
    r.add_argument("--shots", type=int, default=8, metavar="N",
                   help="shutter times in the sweep, at least 4 (default 8)")
    r.add_argument("--json", action="store_true", help="print camera_constant, camera_constant_stderr, "
                                                       "r_squared, frames_used as JSON")
    r = routines.add_parser("reference-part", help=ROUTINES["reference-part"])
    r.add_argument("task", help="a task whose part and material table you trust (the reference)")
    r.add_argument("--shots", type=int, default=6, metavar="N",
                   help="shutter times in the sweep, at least 3 (default 6)")
    r = routines.add_parser("hand-eye", help=ROUTINES["hand-eye"])
    r.add_argument("task", help="a task whose camera, arm and calibration.board it is")
    r.add_argument("--poses", type=int, default=12, metavar="N",
                   help="viewpoints around the board, at least 10 (default 12)")
    r.add_argument("--hand-eye-file", metavar="PATH", help="the file of the task's cell.arm hand-eye keys to "
                                                           "write (default hand-eye.yaml in the run folder)")
    r.add_argument("--force", action="store_true", help="replace an existing hand-eye file")
    r.add_argument("--json", action="store_true", help="print hand_eye_position_m, hand_eye_rpy_deg, "
                                                       "focal_length_px, reprojection_error_px as JSON")
    for r in routines.choices.values():
        r.add_argument("--backend", choices=("sim", "hw"), help="override the task's cell.backend")
        r.add_argument("--out", help="folder for calibration.json and calibration.png, new or empty "
                                     "(default runs/<task>-calibration-<time>)")
        r.add_argument("--yes", action="store_true", help="confirm operator prompts on the real cell; the "
                                                          "simulated cell confirms its own")

    p = sub.add_parser("measure-brdf", help="the cell as a goniometer: a flat sample's BRDF measured and "
                                            "fitted, a material file written")
    p.add_argument("task", help="a task whose calibration.sample and calibration.goniometer say what and how")
    p.add_argument("--backend", choices=("sim", "hw"), help="override the task's cell.backend")
    p.add_argument("--out", help="run folder for material.yaml, goniometer.csv, fit.png, measurement.json, "
                                 "new or empty (default runs/<task>-brdf-<time>)")
    p.add_argument("--yes", action="store_true", help="confirm operator prompts (placing the sample) on the real "
                                                      "cell; the simulated cell confirms its own")
    p.add_argument("--json", action="store_true", help="print the material (phase_deg, rho, sigma1, m1, sigma2, "
                                                       "m2, their *_stderr, unresolved) as JSON")

    p = sub.add_parser("hw-check", help="connect to each real device of the task, print its state; "
                                        "moves and sets nothing")
    p.add_argument("task", help="a task whose cell section names the devices (cell.arm.host, "
                                "cell.pan_tilt.port, cell.camera.source)")
    p.add_argument("--json", action="store_true", help="print the states as JSON")
    return parser


class _Parser(argparse.ArgumentParser):
    """argparse's parser, but `cell calibrate` naming no routine (`cell calibrate TASK`, the form
    before there were two) is one line listing the routines and exit 2, as bad input is elsewhere."""

    routines: dict[str, str] | None = None  # {name: what it does}, on the parser whose ROUTINE it is

    def error(self, message: str) -> NoReturn:
        if not (self.routines and message.startswith("argument ROUTINE: invalid choice")):
            super().error(message)
        found = re.search(r"invalid choice: (.*?) \(choose", message)
        self.exit(2, f"{self.prog}: command line: ROUTINE: found {found.group(1) if found else message}, "
                     f"expected {', '.join(list(self.routines)[:-1])} or {list(self.routines)[-1]} before the task ({self.prog} -h says what each "
                     "does)\n")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that a run's safe stop and its report still happen."""


def _terminate(signum, frame):
    raise Terminated()


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from kernels.cores import available_cores
    try:
        available_cores()                   # LIGHTPLAN_CORES, if set, read before any work
    except ValueError as err:
        print(f"cell {args.command}: {err}", file=sys.stderr, flush=True)
        return 2
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        module = importlib.import_module(COMMANDS[args.command])
        return int(module.command(args) or 0)
    except CellError as err:
        print(f"cell {args.command}: {err.said}", file=sys.stderr, flush=True)
        return err.exit_code
    except BrokenPipeError:
        # whoever read our output has gone (`cell check TASK | head`): nothing more to say to it,
        # and Python's own flush of stdout at exit must not fail again (its docs' recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except KeyboardInterrupt as err:
        terminated = isinstance(err, Terminated)
        print(f"cell {args.command}: {'terminated (SIGTERM)' if terminated else 'interrupted'}",
              file=sys.stderr, flush=True)
        return 143 if terminated else 130
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
