"""`cell calibrate ROUTINE TASK ...`, the routines measuring the camera constant c:
`camera-constant` (a laser of known power at several shutter times, sec. 4.1; writes a camera
file into the run folder, or to --camera-file) and `reference-part` (a shutter sweep on a reference part, c against the task's material:
a cross-check), and the camera's intrinsics and hand-eye: `hand-eye` (views of a ChArUco board;
writes a hand-eye file into the run folder, or to --hand-eye-file). Exit 0 measured, 1 infeasible plan, an untrustworthy series or
too few views of the board, 2 bad input (an unknown routine: cell.cli's parser), 3 device fault."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from cell.run import backends
from cell.core import jsonio
from cell.cli import backend_of, create_folder, one_feature, output_folder
from cell.core.errors import TaskError
from cell.task.loader import load_task
from cell.devices.operator import Operator

def relative_to_task(written: str | Path, task: str | Path) -> str:
    """The written file as the task names it: relative to the task file's folder."""
    return Path(os.path.relpath(Path(written).resolve(), Path(task).resolve().parent)).as_posix()


def command(args: argparse.Namespace) -> int:
    routine = {"camera-constant": camera_constant, "reference-part": reference_part, "hand-eye": hand_eye}
    return routine[args.routine](args)


def camera_constant(args: argparse.Namespace) -> int:
    from cell.calibration import camera_constant as routine

    if args.shots < routine.MIN_FRAMES:
        raise TaskError("command line", "--shots", args.shots, f"an integer >= {routine.MIN_FRAMES}")
    if not 0 < args.laser_power_w < float("inf"):
        raise TaskError("command line", "--laser-power-w", args.laser_power_w,
                        "the laser's power at the sensor, a positive number of watts")
    out = output_folder(args.out, f"{Path(args.task).stem}-calibration")
    # the run's own folder unless asked: a calibration leaves the task's folder (a checkout) as it was
    camera_file = (routine.check_camera_file(args.camera_file, args.force) if args.camera_file
                   else out / "camera.yaml")
    task = load_task(args.task)
    backend = backend_of(task, args.backend)
    # the simulated cell has no operator at the laser: it confirms for itself
    operator = Operator(yes=args.yes, simulated=backend == "sim", stdout=sys.stderr)
    operator.require("laser", "aiming, blocking and unblocking the laser")
    laser = routine.Laser(args.laser_power_w, operator)
    create_folder(out)
    result = routine.run(task, out, lambda: backends.open_devices(task, None, backend, yes=args.yes, laser=laser),
                         laser, camera_file, args.shots, args.force)
    if args.json:
        print(jsonio.dumps(result.summary(), indent=2))
        return 0
    # routine.run returns only once it has calibrated (else it raises): its fit, black level and file are there
    fit, black = result.laser_fit, result.dark_black_level
    c_task = result.camera_constant_task
    print(f"camera constant c = {fit.camera_constant:.5g} +- {fit.camera_constant_stderr:.2g} 1/(W s) "
          f"({fit.camera_constant / c_task:.3f} x the task's {c_task:.5g}); linearity r2 {fit.r_squared:.6f}, "
          f"{fit.frames_used} frames ({fit.frames_saturated} saturated, {fit.frames_too_dark} too dark left out)")
    print(f"black level {black.value:.2f} gray, noise {black.noise_rms:.2f} rms (the dark "
          "frames at the shortest shutter time)")
    print(f"  wrote {result.written_camera_file}: to use it, write camera: {{sensor: "
          f"{relative_to_task(result.written_camera_file, args.task)}, ...}} in {args.task}")
    print(f"  wrote {out}/calibration.json, calibration.png, log.jsonl and {len(result.frames)} captures")
    return 0


def reference_part(args: argparse.Namespace) -> int:
    from cell.calibration.reference_part import MIN_SHOTS, run

    if args.shots < MIN_SHOTS:
        raise TaskError("command line", "--shots", args.shots, f"an integer >= {MIN_SHOTS}")
    out = output_folder(args.out, f"{Path(args.task).stem}-calibration")
    task = one_feature(load_task(args.task), "calibrate")
    backend = backend_of(task, args.backend)
    c_model = task.camera.sensor.camera_constant
    # the simulated cell holds the task's part already: it confirms for itself, as for the lamp radius
    Operator(yes=args.yes, simulated=backend == "sim", stdout=sys.stderr).confirm(
        "calibration", "place the reference part (the task's part, of the task's material) in the cell; "
                       "the camera constant is measured against its material table")
    create_folder(out)
    result = run(task, out, lambda scene: backends.open_devices(task, scene, backend, yes=args.yes), args.shots)
    fit = result.camera_fit                  # run returns only once it has fitted c (else it raises)
    print(f"camera constant c = {fit.camera_constant:.5g} +- {fit.stderr:.2g} 1/(W s) "
          f"({result.camera_constant_ratio:.3f} x the task's {c_model:.5g}); black level "
          f"{fit.black_level:.2f}, linearity r2 {fit.r2:.5f}, {fit.used} pairs "
          f"({fit.saturated} saturated, {fit.dark} at 0 left out)")
    print(f"  set camera.sensor.camera_constant: {fit.camera_constant:.5g} and camera.sensor.black_level: "
          f"{max(fit.black_level, 0.0):.3g} in the tasks that use this camera (e.g. {args.task}), or measure "
          f"c with the laser: cell calibrate camera-constant")
    print(f"  wrote {out}/calibration.json, calibration.png, log.jsonl, {len(result.shots)} captures and the "
          f"plan's pictures")
    return 0


def hand_eye(args: argparse.Namespace) -> int:
    from cell.calibration import hand_eye as routine
    from cell.calibration.camera_constant import check_camera_file

    if args.poses < routine.MIN_POSES:
        raise TaskError("command line", "--poses", args.poses, f"an integer >= {routine.MIN_POSES}")
    out = output_folder(args.out, f"{Path(args.task).stem}-calibration")
    hand_eye_file = (check_camera_file(args.hand_eye_file, args.force, option="--hand-eye-file")
                     if args.hand_eye_file else out / "hand-eye.yaml")
    task = load_task(args.task)
    backend = backend_of(task, args.backend)
    board = task.board
    # the simulated cell holds the board already: it confirms for itself
    Operator(yes=args.yes, simulated=backend == "sim", stdout=sys.stderr).confirm(
        "calibration", f"lay the ChArUco board ({board.squares[0]} x {board.squares[1]} squares of "
                       f"{1e3 * board.square_m:g} mm, {board.dictionary}) face up with its centre at "
                       f"{np.round(board.T_cell_centre[:3, 3], 4).tolist()} m as calibration.board says, and "
                       "light it evenly (a diffuse light over it; the arm will move around it)")
    create_folder(out)
    result = routine.run(task, out, lambda: backends.open_devices(task, None, backend, yes=args.yes, board=True),
                         hand_eye_file, args.poses, args.force)
    if args.json:
        print(jsonio.dumps(result.summary(), indent=2))
        return 0
    # routine.run returns only once it has solved the hand-eye (else it raises)
    h, k = result.solved_hand_eye, result.calibrated_intrinsics
    views = sum(v.usable for v in result.views)
    print(f"hand-eye T_flange_cam: position {np.round(1e3 * h.position_m, 3).tolist()} mm, rpy "
          f"{np.round(h.rpy_deg, 3).tolist()} deg ({h.method}); board pose spread over the views "
          f"{1e3 * h.board_spread_m:.3f} mm, {np.degrees(h.board_spread_rad):.3f} deg; corners reprojected through "
          f"it {h.reprojection_error_px:.3f} px rms")
    for name, other in result.solved_methods.items():
        dp = 1e3 * np.linalg.norm(other.position_m - h.position_m)
        print(f"  {name:<10} {np.round(1e3 * other.position_m, 3).tolist()} mm, {dp:.3f} mm from the result; "
              f"reprojected {other.reprojection_error_px:.3f} px rms")
    f_task = task.camera.lens.focal_length_m / task.camera.sensor.pixel_pitch_m
    print(f"camera: focal length {h.focal_length_px:.1f} px ({h.focal_length_px / f_task:.4f} x the task's "
          f"{f_task:.1f} px; calibrateCamera {k.focal_length_px:.1f} px, reprojection error {k.rms_px:.3f} px); "
          f"{views} views ({len(result.refused)} viewpoints refused by the arm)")
    print(f"  wrote {result.written_hand_eye_file}: to use it, write cell: {{arm: {{hand_eye: "
          f"{relative_to_task(result.written_hand_eye_file, args.task)}}}}} in {args.task}")
    print(f"  wrote {out}/calibration.json, log.jsonl and {len(result.views)} board-N.png frames with the corners "
          f"drawn")
    return 0
