"""Operator routine for the camera constant c of G = c P_pixel t (eq. 10, 17).

The lamp and the camera go to the task's plan; the camera takes a sweep of shutter times at the
planned f-number; at every feature sample the model's pixel power P (eq. 10, from the task's
material and lamp) times the actual shutter t is paired with the measured gray G, and
G = b + c P t is fitted by linear least squares over the pairs that are neither saturated nor
outside the image (b absorbs a black level). Only the product c * rho is observable this way:
calibrate on a part whose material table you trust (the task's material is the reference).
"""
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell import measure

SWEEP = (0.25, 1.0)     # shutter times from this fraction of the planned one to it


@dataclass(frozen=True)
class Fit:
    camera_constant: float      # c [1/(W s)]
    stderr: float
    black_level: float          # b [gray]
    r2: float                   # linearity of G over P t
    used: int                   # (sample, shot) pairs fitted
    saturated: int              # pairs left out at the sensor's maximum


def fit_camera_constant(exposure, gray, saturation):
    """Least squares G = b + c x over pairs with G < saturation (x = P t [W s])."""
    exposure, gray = np.ravel(exposure), np.ravel(gray)
    valid = np.isfinite(gray) & np.isfinite(exposure)
    saturated = valid & (gray >= saturation)
    use = valid & ~saturated
    if use.sum() < 3 or np.ptp(exposure[use]) <= 0:
        return None
    scale = np.max(np.abs(exposure[use]))        # P t ~ 1e-16 W s: scaled for a well-posed fit
    A = np.column_stack([np.ones(use.sum()), exposure[use] / scale])
    (b, slope), *_ = np.linalg.lstsq(A, gray[use], rcond=None)
    residual = gray[use] - A @ (b, slope)
    dof = max(use.sum() - 2, 1)
    cov = residual @ residual / dof * np.linalg.inv(A.T @ A)
    total = np.sum((gray[use] - gray[use].mean()) ** 2)
    r2 = 1.0 - residual @ residual / total if total > 0 else 1.0
    return Fit(float(slope / scale), float(np.sqrt(cov[1, 1]) / scale), float(b), float(r2),
               int(use.sum()), int(saturated.sum()))


def calibrate(task, plan, devices, shots=6, say=lambda msg: None):
    """Drive the cell to the plan, sweep the shutter, fit c. Returns (Fit or None, shots list)."""
    pan, tilt, radius = plan.joints
    camera = devices.camera
    devices.arm.move_camera(plan.scene.T_cell_cam)
    devices.lamp.move(pan, tilt, radius)
    camera.set_aperture(plan.exposure.f_number)
    camera.set_focus(plan.exposure.focus_m)
    # the model's pixel power per sample at the planned f-number: G = c P t
    power = plan.gray / (task.camera.sensor.camera_constant * plan.exposure.shutter_s)
    row, col, inside = measure.sample_pixels(task, devices.arm.camera_pose(), plan.scene.points)
    t_lo, t_hi = task.camera.shutter_range_s
    sweep = np.unique(np.clip(plan.exposure.shutter_s * np.geomspace(*SWEEP, shots), t_lo, t_hi))
    exposures, grays, record = [], [], []
    for k, wanted in enumerate(sweep, 1):
        actual = camera.set_exposure(wanted)
        image = np.asarray(camera.capture(), dtype=float)
        gray = np.where(inside, image[np.clip(row, 0, image.shape[0] - 1), np.clip(col, 0, image.shape[1] - 1)], np.nan)
        exposures.append(power * actual)
        grays.append(gray)
        record.append({"shutter_s": float(actual), "gray_mean": float(np.nanmean(gray)) if inside.any() else None})
        say(f"shot {k}/{len(sweep)}: shutter {1e3 * actual:.3f} ms, mean gray at the samples "
            f"{record[-1]['gray_mean']}")
    fit = fit_camera_constant(np.array(exposures), np.array(grays), measure.saturation_level(camera.bit_depth))
    return fit, record, np.array(exposures), np.array(grays)


def write_picture(path, exposures, grays, fit, c_model):
    """G over the model's P t: the fitted line and the line the task's c predicts."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(exposures.ravel() * 1e12, grays.ravel(), ".", ms=3, label="measured (per sample and shot)")
    x = np.linspace(0.0, np.nanmax(exposures), 2)
    ax.plot(x * 1e12, c_model * x, "--", label=f"task's c = {c_model:.4g}")
    if fit:
        ax.plot(x * 1e12, fit.black_level + fit.camera_constant * x, label=f"fit c = {fit.camera_constant:.4g}")
    ax.set_xlabel("model pixel power x shutter  P t  [pW s]")
    ax.set_ylabel("measured gray G")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def command(args):
    """`cell calibrate TASK [--backend sim|hw] [--out DIR] [--shots N] [--yes]`."""
    from cell.errors import PlanInfeasible
    from cell.loader import load_task
    from cell.planner import plan as make_plan
    from cell.loop import open_devices

    def say(msg):
        print(msg, file=sys.stderr, flush=True)

    task = load_task(args.task)
    c_model = task.camera.sensor.camera_constant
    planned = make_plan(task)
    out = Path(args.out or Path("runs") / f"{Path(args.task).stem}-calibration")
    out.mkdir(parents=True, exist_ok=True)
    say("Place the reference part (the task's part and material) in the cell; the camera constant "
        "is measured against its material table.")
    devices = open_devices(task, planned.scene, args.backend, yes=args.yes)
    try:
        fit, record, exposures, grays = calibrate(task, planned, devices, args.shots, say)
    except Exception as fault:
        devices.safe_stop(fault)
        raise
    devices.close()
    result = {"task": str(task.path), "camera_constant_task": c_model, "shots": record,
              "fit": None if fit is None else fit.__dict__}
    (out / "calibration.json").write_text(json.dumps(result, indent=2) + "\n")
    write_picture(out / "calibration.png", exposures, grays, fit, c_model)
    if fit is None:
        raise PlanInfeasible("too few unsaturated samples in the image to fit c; check the "
                             "camera sees the feature and the lamp lights it")
    print(f"camera constant c = {fit.camera_constant:.5g} +- {fit.stderr:.2g} 1/(W s) "
          f"({fit.camera_constant / c_model:.3f} x the task's {c_model:.5g}); black level {fit.black_level:.2f}, "
          f"linearity r2 {fit.r2:.5f}, {fit.used} pairs ({fit.saturated} saturated left out)")
    print(f"  set camera.sensor.camera_constant: {fit.camera_constant:.5g} in {args.task}")
    print(f"  wrote {out}/calibration.json and calibration.png")
    return 0
