"""`cell calibrate ROUTINE TASK ...`, the routines measuring the camera constant c:
`camera-constant` (a laser of known power at several shutter times, sec. 4.1; writes a camera
file) and `reference-part` (a shutter sweep on a reference part, c against the task's material:
a cross-check). Exit 0 with c measured, 1 infeasible plan or an untrustworthy series, 2 bad
input (an unknown routine: cell.cli's parser), 3 device fault."""
import sys
from pathlib import Path

from cell import backends, jsonio
from cell.cli import create_folder, one_feature, output_folder
from cell.errors import TaskError
from cell.loader import load_task
from cell.operator import Operator

def command(args):
    return camera_constant(args) if args.routine == "camera-constant" else reference_part(args)


def camera_constant(args):
    from cell import camera_constant as routine

    if args.shots < routine.MIN_FRAMES:
        raise TaskError("command line", "--shots", args.shots, f"an integer >= {routine.MIN_FRAMES}")
    if not 0 < args.laser_power_w < float("inf"):
        raise TaskError("command line", "--laser-power-w", args.laser_power_w,
                        "the laser's power at the sensor, a positive number of watts")
    out = output_folder(args.out, f"{Path(args.task).stem}-calibration")
    camera_file = routine.check_camera_file(args.camera_file or Path(args.task).parent / "camera.yaml", args.force)
    task = load_task(args.task)
    backend = args.backend or task.cell.backend
    # the simulated cell has no operator at the laser: it confirms for itself
    operator = Operator(yes=args.yes or backend == "sim", stdout=sys.stderr)
    operator.require("laser", "aiming, blocking and unblocking the laser")
    laser = routine.Laser(args.laser_power_w, operator)
    create_folder(out)
    result = routine.run(task, out, lambda: backends.open_devices(task, None, backend, yes=args.yes, laser=laser),
                         laser, camera_file, args.shots, args.force)
    fit = result.fit
    if args.json:
        print(jsonio.dumps(result.summary() | {"camera_file": result.camera_file}, indent=2))
        return 0
    c_task = result.camera_constant_task
    print(f"camera constant c = {fit.camera_constant:.5g} +- {fit.camera_constant_stderr:.2g} 1/(W s) "
          f"({fit.camera_constant / c_task:.3f} x the task's {c_task:.5g}); linearity r2 {fit.r_squared:.6f}, "
          f"{fit.frames_used} frames ({fit.frames_saturated} saturated, {fit.frames_too_dark} too dark left out)")
    print(f"  wrote {result.camera_file}: a task uses it as camera: {{sensor: "
          f"{Path(result.camera_file).name}, ...}} (relative to the task file)")
    print(f"  wrote {out}/calibration.json, calibration.png, log.jsonl and {len(result.frames)} captures")
    return 0


def reference_part(args):
    from cell.calibrate import MIN_SHOTS, run

    if args.shots < MIN_SHOTS:
        raise TaskError("command line", "--shots", args.shots, f"an integer >= {MIN_SHOTS}")
    out = output_folder(args.out, f"{Path(args.task).stem}-calibration")
    task = one_feature(load_task(args.task), "calibrate")
    backend = args.backend or task.cell.backend
    c_model = task.camera.sensor.camera_constant
    # the simulated cell holds the task's part already: it confirms for itself, as for the lamp radius
    Operator(yes=args.yes or backend == "sim", stdout=sys.stderr).confirm(
        "calibration", "place the reference part (the task's part, of the task's material) in the cell; "
                       "the camera constant is measured against its material table")
    create_folder(out)
    result = run(task, out, lambda scene: backends.open_devices(task, scene, backend, yes=args.yes), args.shots)
    fit = result.fit
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
