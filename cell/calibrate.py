"""Operator routine for the camera constant c of G = c P_pixel t (eq. 10, 17).

The lamp and the camera go to the task's plan; the camera takes a sweep of shutter times at the
planned f-number, from the brightest feature sample at SWEEP_GRAY[0] of full scale up to
SWEEP_GRAY[1] by the model; at every feature sample the model's pixel power P (eq. 10, from the
task's material and lamp) times the actual shutter t is paired with the measured gray G, and
G = b + c P t is fitted by linear least squares over the pairs the sensor resolves (neither
saturated, nor 0, nor outside the image); b absorbs a black level. Only the product c * rho is
observable this way: calibrate on a part whose material table you trust (the task's material is
the reference).
"""
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cell import jsonio, measure
from cell.errors import GoalNotReached, PlanInfeasible, TaskError
from cell.operator import Operator
from cell.session import Session

# the brightest sample's gray by the model, as a fraction of full scale, at the first and the
# last shot: dim, up to near (not at) saturation; G ~ t, so the shutter times follow
SWEEP_GRAY = (0.1, 0.9)
MIN_SHOTS = 3               # two parameters (b, c) and one shot left to see a residual


@dataclass(frozen=True)
class Fit:
    """G = b + c x with x = P t [J]: c, its standard error (from the residuals, which also hold
    the model's per-sample error, so a lower bound on the real uncertainty), b, the linearity."""

    camera_constant: float      # c [1/(W s)]
    stderr: float
    black_level: float          # b [gray]
    r2: float                   # linearity of G over P t
    used: int                   # (sample, shot) pairs fitted
    saturated: int              # pairs left out at the sensor's maximum
    dark: int                   # pairs left out at 0 (true gray below the first level)


def fit_camera_constant(exposure, gray, saturation):
    """Least squares G = b + c x over the pairs 0 < G < saturation. exposure x = P t [W s] and
    gray are (shots, samples); None unless at least 3 pairs from at least 2 shots are usable
    (across samples alone, b and c would rest on the model's spatial shape of P)."""
    exposure, gray = np.atleast_2d(exposure), np.atleast_2d(gray)
    valid = np.isfinite(gray) & np.isfinite(exposure)
    saturated, dark = valid & (gray >= saturation), valid & (gray <= 0)
    use = valid & ~saturated & ~dark
    if use.sum() < 3 or np.sum(use.any(axis=1)) < 2 or np.ptp(exposure[use]) <= 0:
        return None
    x, g = exposure[use], gray[use]
    scale = np.max(np.abs(x))                    # P t ~ 1e-15 W s: scaled for a well-posed fit
    A = np.column_stack([np.ones(x.size), x / scale])
    (b, slope), *_ = np.linalg.lstsq(A, g, rcond=None)
    residual = g - A @ (b, slope)
    dof = max(x.size - 2, 1)
    cov = residual @ residual / dof * np.linalg.inv(A.T @ A)
    total = np.sum((g - g.mean()) ** 2)
    r2 = 1.0 - residual @ residual / total if total > 0 else 1.0
    return Fit(float(slope / scale), float(np.sqrt(cov[1, 1]) / scale), float(b), float(r2),
               int(x.size), int(saturated.sum()), int(dark.sum()))


def shutter_sweep(shutter_s, predicted_max, full_scale, shutter_range_s, shots):
    """`shots` shutter times, geometric, from the one that puts the brightest sample's predicted
    gray at SWEEP_GRAY[0] of full scale to SWEEP_GRAY[1] (G ~ t, predicted_max at shutter_s),
    both ends clipped to the camera's shutter range. Raises PlanInfeasible if nothing is left."""
    wanted = shutter_s * full_scale * np.array(SWEEP_GRAY) / predicted_max
    lo, hi = np.clip(wanted, *shutter_range_s)
    if not hi > lo * 1.01:
        need_ms, range_ms = 1e3 * wanted, 1e3 * np.asarray(shutter_range_s)
        raise PlanInfeasible(f"no shutter sweep: the brightest sample at {SWEEP_GRAY[0]:g}-{SWEEP_GRAY[1]:g} "
                             f"of full scale needs {need_ms[0]:.3g}-{need_ms[1]:.3g} ms, the camera's "
                             f"shutter range is {range_ms[0]:.3g}-{range_ms[1]:.3g} ms")
    return np.geomspace(lo, hi, shots)


def calibrate(task, plan, devices, log, shots=6, record=None):
    """Drive the cell to the plan, sweep the shutter, fit c. Each shot is logged and its summary
    appended to `record` as it is taken. Returns (Fit or None, exposures P t, grays), each
    (shots, samples)."""
    from cell.loop import drive
    record = [] if record is None else record
    camera = devices.camera
    full_scale = measure.saturation_level(camera.bit_depth)
    sweep = shutter_sweep(plan.exposure.shutter_s, plan.gray.max(), full_scale,
                          task.camera.shutter_range_s, shots)
    drive(devices, plan, log)
    camera.set_aperture(plan.exposure.f_number)
    camera.set_focus(plan.exposure.focus_m)
    # the model's pixel power per sample at the planned f-number: G = c P t
    power = plan.gray / (task.camera.sensor.camera_constant * plan.exposure.shutter_s)
    exposures, grays = [], []
    for k, wanted in enumerate(sweep, 1):
        actual = camera.set_exposure(wanted)
        image = camera.capture()
        _, _, inside, gray = measure.read_samples(image, task, devices.arm.camera_pose(), plan.scene.points)
        exposures.append(power * actual)
        grays.append(gray)
        seen = gray[inside]
        record.append({"shutter_s": float(actual), "f_number": plan.exposure.f_number,
                       "gray_min": float(seen.min()), "gray_mean": float(seen.mean()),
                       "gray_max": float(seen.max()), "samples": int(seen.size),
                       "saturated": int(np.sum(seen >= full_scale))})
        log.step("shot", f"{k}/{len(sweep)}: shutter {1e3 * actual:.3f} ms, gray at the samples "
                         f"{seen.min():.1f}-{seen.max():.1f} (mean {seen.mean():.1f}), "
                         f"{record[-1]['saturated']} of {seen.size} saturated", iteration=k, **record[-1])
    exposures, grays = np.array(exposures), np.array(grays)
    return fit_camera_constant(exposures, grays, full_scale), exposures, grays


def write_picture(path, exposures, grays, fit, c_model):
    """G over the model's P t: the fitted line and the line the task's c predicts."""
    from cell.pictures import pyplot
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(exposures.ravel() * 1e15, grays.ravel(), ".", ms=3, label="measured (per sample and shot)")
    x = np.linspace(0.0, np.nanmax(exposures), 2)
    ax.plot(x * 1e15, c_model * x, "--", label=f"task's c = {c_model:.4g}")
    if fit:
        ax.plot(x * 1e15, fit.black_level + fit.camera_constant * x,
                label=f"fit c = {fit.camera_constant:.4g}, b = {fit.black_level:.2f}")
    ax.set_xlabel("model pixel power x shutter  P t  [fJ]")
    ax.set_ylabel("measured gray G")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(task, out, connect, shots=6):
    """Plan (the function `cell plan` uses, plan.json and pictures in out), connect(scene) ->
    Devices, calibrate; out/log.jsonl as it happens, out/calibration.json however it ends, and
    out/calibration.png. Raises PlanInfeasible before anything moves, GoalNotReached when nothing
    usable was measured (exit 1), DeviceFault after the safe stop of every device (exit 3).
    Returns the result written."""
    from cell.loop import RunLog, log_fault, plan_and_connect
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    c_model = task.camera.sensor.camera_constant
    result = {"task": str(task.path), "camera_constant_task": c_model, "plan": None, "shots": [],
              "fit": None, "camera_constant_ratio": None, "reason": ""}
    log = RunLog(out / "log.jsonl")
    session = Session(on_fault=lambda fault: log_fault(log, fault))
    try:
        with session:
            planned = plan_and_connect(task, out, log, session, connect, result)
            fit, exposures, grays = calibrate(task, planned, session.devices, log, shots, result["shots"])
        write_picture(out / "calibration.png", exposures, grays, fit, c_model)
        if fit is None:
            n = sum(s["samples"] for s in result["shots"])
            saturated = sum(s["saturated"] for s in result["shots"])
            raise GoalNotReached(f"too few resolved samples to fit c ({saturated} of {n} readings "
                                 f"saturated, the rest at 0 or from a single shot): is the lamp "
                                 f"on, does it light the feature, is the part the task's?")
        result["fit"] = asdict(fit)
        result["camera_constant_ratio"] = fit.camera_constant / c_model
        log.step("done", f"c = {fit.camera_constant:.5g} 1/(W s), {result['camera_constant_ratio']:.3f} x "
                         f"the task's", **result["fit"])
        return result
    except BaseException as err:
        result["reason"] = str(err) or type(err).__name__
        if session.fault:
            result["fault"] = session.fault
        else:
            log.step("done", f"no fit: {err}", reason=str(err))
        raise
    finally:
        (out / "calibration.json").write_text(jsonio.dumps(result, indent=2) + "\n")
        log.close()


def command(args):
    """`cell calibrate TASK [--backend sim|hw] [--out DIR] [--shots N] [--yes]`: exit 0 with c
    fitted, 1 infeasible plan or nothing usable measured, 2 bad input, 3 device fault."""
    from cell import backends
    from cell.cli import output_folder
    from cell.loader import load_task

    if args.shots < MIN_SHOTS:
        raise TaskError("command line", "--shots", args.shots, f"an integer >= {MIN_SHOTS}")
    out = output_folder(args.out, Path("runs") / f"{Path(args.task).stem}-calibration")
    task = load_task(args.task)
    backend = args.backend or task.cell.backend
    c_model = task.camera.sensor.camera_constant
    # the simulated cell holds the task's part already: it confirms for itself, as for the lamp radius
    Operator(yes=args.yes or backend == "sim", stdout=sys.stderr).confirm(
        "calibration", "place the reference part (the task's part, of the task's material) in the cell; "
                       "the camera constant is measured against its material table")
    result = run(task, out, lambda scene: backends.open_devices(task, scene, backend, yes=args.yes), args.shots)
    fit = Fit(**result["fit"])
    print(f"camera constant c = {fit.camera_constant:.5g} +- {fit.stderr:.2g} 1/(W s) "
          f"({result['camera_constant_ratio']:.3f} x the task's {c_model:.5g}); black level "
          f"{fit.black_level:.2f}, linearity r2 {fit.r2:.5f}, {fit.used} pairs "
          f"({fit.saturated} saturated, {fit.dark} at 0 left out)")
    print(f"  set camera.sensor.camera_constant: {fit.camera_constant:.5g} in the tasks that use "
          f"this camera (e.g. {args.task})")
    print(f"  wrote {out}/calibration.json, calibration.png, log.jsonl and the plan's pictures")
    return 0
