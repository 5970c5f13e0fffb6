"""The closed loop of `cell run` (design.md, steps 3-4): plan, drive the cell, capture, measure the
feature's gray, correct, until every feature pixel is in the gray band or N iterations have run.

Correction from G = c P_pixel t with P_pixel ~ 1 / kappa^2 (eq. 10, 17): the gray scales with
t / kappa^2, so one gain k = sqrt(low high) / sqrt(G_min G_max) centres the measured range in the
band geometrically. The shutter takes k first; where it hits its limits the f-number takes the rest,
never wider than the depth of field allows. What neither absorbs is re-planned with the measured
model error as an effective albedo scale: only the product c rho is observable, so the scale also
absorbs an error in c. A range relatively wider than the band is no exposure problem and an albedo
scale does not change the predicted shape: the run ends at once and says so.
"""
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

from cell import backends, jsonio, measure
from cell.errors import DeviceFault, GoalNotReached, PlanInfeasible, TaskError
from cell.pictures import write_convergence
from cell.planner import depth_of_field_limits, gray_stats, plan as make_plan, write_plan
from cell.session import Session, stop_outcome

DARK = 0.5                  # a pixel reading 0 is below the first gray level: true gray < 0.5
SATURATED_STEP = 4.0        # every pixel saturated: step this far past the lower bound (2 stops)
RESOLVED = 0.5              # darkest pixel below this x the band's low end: noise and black level
                            # dominate its spread, so brighten and look again before judging it


class RunLog:
    """log.jsonl: one JSON line per step (time, step, message, data), appended, flushed and
    fsync'd so that a crash loses nothing measured; each step also as a progress line on stderr."""

    def __init__(self, path):
        self.file = open(path, "a", encoding="utf-8")

    def step(self, step, message, iteration=None, **data):
        """One step; `iteration` (the capture it belongs to) is left out when None."""
        where = {} if iteration is None else {"iteration": iteration}
        line = {"t": datetime.now(timezone.utc).isoformat(timespec="milliseconds"), "step": step,
                "message": message, **where, **data}
        self.file.write(jsonio.dumps(line) + "\n")
        self.file.flush()
        os.fsync(self.file.fileno())
        print(f"{'' if iteration is None else iteration:>2} {step:<12} {message}", file=sys.stderr, flush=True)

    def close(self):
        self.file.close()


class Measurement:
    """Gray of one capture over the feature's image region (the convex hull of the projected
    samples, seen from the arm's read-back pose) and at each sample's pixel (NaN off the image).

    The band is judged on the surface's gray at every pixel, measure.local_mean (5x5 within the
    region): a sensor's pixel noise, whose extremes over ten thousand pixels reach +-4 sigma, is
    no property of the lighting and no lamp pose or exposure could narrow it. Without noise the
    two agree to the rounding; the raw pixels' range and the noise are reported beside it."""

    def __init__(self, image, task, T_cell_cam, points, saturation):
        self.row, self.col, inside, self.sample_gray = measure.read_samples(image, task, T_cell_cam, points)
        image = np.asarray(image, float)
        self.region = measure.feature_mask(image.shape, self.row[inside], self.col[inside])
        self.gray = image[self.region]
        self.surface = measure.local_mean(image, self.region)[self.region]
        self.saturation = saturation
        self.saturated = self.region & (image >= saturation)
        self.min, self.max = float(self.surface.min()), float(self.surface.max())

    def stats(self):
        """measured_gray of report.json: mean/min/max of the surface's gray over the region,
        `pixels` in it, how many read saturation or more, the raw pixels' range as the camera
        delivered them (a real sensor clips at saturation; the sim without `quantization` does
        not) and the pixel noise (rms of raw minus surface)."""
        return {**gray_stats(self.surface), "pixels": int(self.gray.size),
                "saturated": int(self.saturated.sum()),
                "pixel_min": float(self.gray.min()), "pixel_max": float(self.gray.max()),
                "noise_rms": float(np.sqrt(np.mean((self.gray - self.surface) ** 2)))}

    def in_band(self, band):
        return not self.saturated.any() and band[0] <= self.min and self.max <= band[1]


def model_error(sample_gray, predicted, saturation):
    """(measured / predicted gray at the samples, relation): the median over samples the sensor
    resolves, "="; if every one saturates the tightest lower bound, ">="; if every one reads 0
    the tightest upper bound (true gray < DARK), "<="."""
    ok = np.isfinite(sample_gray) & (predicted > 0)
    g, p = sample_gray[ok], predicted[ok]
    resolved = (g > 0) & (g < saturation)
    if resolved.any():
        return float(np.median(g[resolved] / p[resolved])), "="
    if (g >= saturation).any():
        return float(np.max(saturation / p[g >= saturation])), ">="
    return float(np.min(DARK / p)), "<="


def true_range(m, predicted, error):
    """The feature's gray range (lo, hi) the capture implies: the measured extremes where the
    sensor resolves them; at saturation (true >= it) or at 0 (true < DARK) the model times the
    measured error, within what the reading allows."""
    def resolve(reading, estimate):
        if reading >= m.saturation:
            return max(m.saturation, estimate)
        return min(DARK, estimate) if reading <= 0 else reading
    return resolve(m.min, error * predicted.min()), resolve(m.max, error * predicted.max())


def spread_exceeds_band(lo, hi, band):
    """Whether the feature's gray range is relatively wider than the band (max/min > high/low), so
    that no exposure fits it, G ~ t / kappa^2 scaling all alike. A dim range (lo < RESOLVED low)
    is not judged: noise and black level inflate it."""
    low, high = band
    return lo >= RESOLVED * low and hi > lo * high / low


def correct_exposure(lo, hi, relation, shutter_s, f_number, band, shutter_range, f_number_range):
    """(shutter, f-number, reason): the gain sqrt(low high) / sqrt(lo hi) on G ~ t / kappa^2,
    shutter first, the f-number within f_number_range (its low end the widest the depth of field
    allows) for what the shutter's range leaves. With every pixel saturated (relation ">=", lo and
    hi lower bounds) it steps SATURATED_STEP further, so the next capture measures. A dim range
    (lo < RESOLVED low, whose spread is not judged: spread_exceeds_band) is brightened. reason is
    None when the range can then be in band (or, dim, is brighter), else says why not."""
    low, high = band
    dim = lo < RESOLVED * low
    step = SATURATED_STEP if relation == ">=" else 1.0
    exposure = shutter_s / f_number**2 * np.sqrt(low * high / (lo * hi)) / step
    shutter = float(np.clip(exposure * f_number**2, *shutter_range))
    kappa = float(np.clip(np.sqrt(shutter / exposure), *f_number_range))
    k = shutter / kappa**2 / (shutter_s / f_number**2)
    fits = {"=": low <= lo * k and hi * k <= high, ">=": lo * k <= high, "<=": hi * k >= low}[relation]
    if not fits and not (dim and k > 1.0 + 1e-9):
        bound = {"=": "at", ">=": "at least", "<=": "at most"}[relation]
        return shutter, kappa, (f"even at {1e3 * shutter:.3g} ms and f/{kappa:.1f} the feature would be "
                                f"{bound} {lo * k:.1f}-{hi * k:.1f}, band {low:g}-{high:g}")
    return shutter, kappa, None


def describe_error(error, relation):
    bound = {"=": "", ">=": "at least ", "<=": "at most "}[relation]
    return f"measured gray is {bound}{error:.3g}x the model's"


def plan_step(task, out, log, albedo_scale=1.0, iteration=None):
    """Plan (the same function `cell plan` uses), write plan.json and pictures, log it."""
    planned = make_plan(task, albedo_scale=albedo_scale,
                        progress=lambda msg: print(f"{'':16}{msg}", file=sys.stderr, flush=True))
    write_plan(planned, task, out)
    g, exposure = gray_stats(planned.gray), planned.exposure
    verdict = "feasible" if planned.feasible else f"INFEASIBLE, {planned.binding}: {planned.hint}"
    log.step("plan", f"{verdict}; lamp {planned.distance_m:.3f} m, phase "
                     f"{np.degrees(planned.phase_angle_rad):.1f} deg; {1e3 * exposure.shutter_s:.3f} ms, "
                     f"f/{exposure.f_number:.1f}; predicted gray {g['min']:.1f}-{g['max']:.1f}"
                     + (f" (albedo x{albedo_scale:.3g})" if albedo_scale != 1.0 else ""),
             iteration=iteration, albedo_scale=albedo_scale, feasible=planned.feasible, binding=planned.binding,
             hint=planned.hint, joints=planned.joints, shutter_s=exposure.shutter_s,
             f_number=exposure.f_number, predicted_gray=g, folder=str(out))
    return planned


def drive(devices, plan, log, iteration=None):
    """Camera and lamp to the plan's poses, each logged as read back from the device."""
    devices.arm.move_camera(plan.scene.T_cell_cam)
    position = devices.arm.camera_pose()[:3, 3]
    off = float(np.linalg.norm(position - plan.scene.camera_position))
    log.step("move_camera", f"camera at {np.round(position, 4).tolist()} m ({1e3 * off:.2f} mm from the plan)",
             iteration=iteration, position_m=position, error_m=off)
    devices.lamp.move(*plan.joints)
    pan, tilt, radius = devices.lamp.joints()
    log.step("move_lamp", f"pan {np.degrees(pan):.2f} deg, tilt {np.degrees(tilt):.2f} deg, "
                          f"radius {1e3 * radius:.1f} mm", iteration=iteration,
             joints={"pan_deg": np.degrees(pan), "tilt_deg": np.degrees(tilt), "radius_m": radius})


def draw_feature(image, m, bit_depth, caption):
    """8-bit colour copy: the measured region outlined (green), its saturated pixels red, the
    samples' pixels blue, a caption."""
    view = cv2.cvtColor((measure.levels(image, bit_depth) * (255.0 / measure.saturation_level(bit_depth))).astype(np.uint8),
                        cv2.COLOR_GRAY2BGR)
    view[m.saturated] = (0, 0, 255)
    contours, _ = cv2.findContours(m.region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.polylines(view, contours, True, (0, 255, 0), 1)
    for r, c in zip(m.row, m.col):
        cv2.circle(view, (int(c), int(r)), 1, (255, 128, 0), -1)
    cv2.putText(view, caption, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 255, 255), 1, cv2.LINE_AA)
    return view


def shoot(task, plan, devices, out, log, k, shutter, f_number):
    """Set the exposure, capture (saved at once), measure and compare with the current plan's
    model at these settings (G ~ t / kappa^2). Returns (record, Measurement, predicted gray)."""
    camera, bit_depth = devices.camera, devices.camera.bit_depth
    shutter = camera.set_exposure(shutter)
    camera.set_aperture(f_number)
    camera.set_focus(plan.exposure.focus_m)
    log.step("set_exposure", f"shutter {1e3 * shutter:.3f} ms, f/{f_number:.2f}, focus "
                             f"{plan.exposure.focus_m:.3f} m", iteration=k,
             shutter_s=shutter, f_number=f_number, focus_m=plan.exposure.focus_m)
    image = np.asarray(camera.capture())
    name, annotated = f"capture-{k}.png", f"capture-{k}-feature.png"
    cv2.imwrite(str(out / name), measure.levels(image, bit_depth))  # float (sim) rounded
    log.step("capture", name, iteration=k, capture=name, shape=image.shape, dtype=str(image.dtype))

    saturation = measure.saturation_level(bit_depth)
    m = Measurement(image, task, devices.arm.camera_pose(), plan.scene.points, saturation)
    predicted = plan.gray * (shutter / plan.exposure.shutter_s) * (plan.exposure.f_number / f_number) ** 2
    error, relation = model_error(m.sample_gray, predicted, saturation)
    band = task.requirements.gray_band
    in_band = m.in_band(band)
    stats, expected = m.stats(), gray_stats(predicted)
    verdict = f"{'in' if in_band else 'out of'} band {band[0]:g}-{band[1]:g}"
    caption = f"{k}: gray {m.min:.0f}-{m.max:.0f}, {stats['saturated']} saturated: {verdict}"
    cv2.imwrite(str(out / annotated), draw_feature(image, m, bit_depth, caption))
    record = {"iteration": k, "shutter_s": shutter, "f_number": f_number, "predicted_gray": expected,
              "measured_gray": stats, "model_error": error, "model_error_relation": relation,
              "in_band": in_band, "capture": name, "annotated": annotated}
    log.step("measure", f"gray mean {stats['mean']:.1f}, {m.min:.1f}-{m.max:.1f} over {stats['pixels']} px "
                        f"(pixels {stats['pixel_min']:.0f}-{stats['pixel_max']:.0f}, noise "
                        f"{stats['noise_rms']:.1f} rms, {stats['saturated']} saturated); the model predicts {expected['mean']:.1f}, "
                        f"{expected['min']:.1f}-{expected['max']:.1f}; {describe_error(error, relation)}; "
                        f"{verdict}",
             **record)
    return record, m, predicted


def iterate(task, plan, devices, out, log, report, max_iterations):
    """Drive, shoot, correct until every feature pixel is in the band; raises GoalNotReached
    saying why when no correction is possible or the iterations run out."""
    band = tuple(map(float, task.requirements.gray_band))
    lens_range = (depth_of_field_limits(task, plan.scene)[2], task.camera.lens.f_number_range[1])
    albedo, shutter, f_number, moved = 1.0, plan.exposure.shutter_s, plan.exposure.f_number, False
    for k in range(1, max_iterations + 1):
        if not moved:
            drive(devices, plan, log, k)
            moved = True
        record, m, predicted = shoot(task, plan, devices, out, log, k, shutter, f_number)
        shutter, error, relation = (record[key] for key in ("shutter_s", "model_error", "model_error_relation"))
        report["iterations"].append({**record, "albedo_scale": albedo})
        report["captures"].append(record["capture"])
        if record["in_band"]:
            report["converged"] = True
            return
        if k == max_iterations:
            saturated = record["measured_gray"]["saturated"]
            raise GoalNotReached(f"not in band {band[0]:g}-{band[1]:g} after {_count(k, 'iteration')}: "
                                 f"feature gray {m.min:.1f}-{m.max:.1f} ({saturated} pixels saturated) at "
                                 f"{1e3 * shutter:.3g} ms, f/{f_number:.1f}; {describe_error(error, relation)}")

        lo, hi = true_range(m, predicted, error)
        if spread_exceeds_band(lo, hi, band):
            p = gray_stats(predicted * error)
            raise GoalNotReached(
                f"the feature's gray spans {lo:.1f}-{hi:.1f}, max/min {hi / lo:.2f} > the band's "
                f"{band[1] / band[0]:.2f}, where the model (its albedo corrected) predicts "
                f"{p['min']:.1f}-{p['max']:.1f}: no exposure narrows it, and a re-plan with a corrected "
                f"albedo would not either; the light falls otherwise than modelled (check the lamp's "
                f"aim, shadows on the feature and the material table)")
        new_shutter, new_f_number, why = correct_exposure(lo, hi, relation, shutter, f_number, band,
                                                          task.camera.shutter_range_s, lens_range)
        if why is None:
            correction = {"action": "exposure", "shutter_s": new_shutter, "f_number": new_f_number,
                          "gray_range": [lo, hi]}
            message = (f"exposure: shutter {1e3 * shutter:.3f} -> {1e3 * new_shutter:.3f} ms, "
                       f"f/{f_number:.2f} -> f/{new_f_number:.2f} (gray range taken as {lo:.1f}-{hi:.1f})")
        else:
            albedo *= error
            correction = {"action": "replan", "albedo_scale": albedo, "reason": why}
            message = f"re-plan with albedo x{albedo:.3g}: {why}"
        report["iterations"][-1]["correction"] = correction
        log.step("correct", message, iteration=k, **correction)
        if why is None:
            shutter, f_number = new_shutter, new_f_number
            continue
        plan = plan_step(task, out / f"replan-{k}", log, albedo, iteration=k)
        report["replans"].append({"iteration": k, "albedo_scale": albedo, "plan": plan.to_json()})
        if not plan.feasible:
            raise GoalNotReached(f"{describe_error(error, relation)}; {why}; re-planned for an albedo "
                                 f"x{albedo:.3g}: infeasible, {plan.binding}: {plan.hint}")
        shutter, f_number, moved = plan.exposure.shutter_s, plan.exposure.f_number, False


def plan_and_connect(task, out, log, session, connect, record):
    """Plan (plan_step; its plan.json in record["plan"]), refuse an infeasible plan before
    anything moves (PlanInfeasible), then connect(scene) the cell's devices into the session.
    Returns the plan."""
    planned = plan_step(task, out, log)
    record["plan"] = planned.to_json()
    if not planned.feasible:
        raise PlanInfeasible(f"infeasible: {planned.binding} binds: {planned.hint}")
    session.devices = connect(planned.scene)
    return planned


def run(task, out, connect, max_iterations=6):
    """Plan, connect(scene) -> Devices, then iterate; out/report.json is written however the run
    ends. Raises PlanInfeasible or GoalNotReached (exit 1), or DeviceFault (exit 3) after the safe
    stop of every device (session.Session). Returns the report."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"task": str(task.path), "plan": None, "iterations": [], "converged": False, "captures": [],
              "reason": "", "replans": []}
    log = RunLog(out / "log.jsonl")
    session = Session(on_fault=lambda fault: log_fault(log, fault))
    try:
        with session:
            planned = plan_and_connect(task, out, log, session, connect, report)
            iterate(task, planned, session.devices, out, log, report, max_iterations)
        n = len(report["iterations"])
        log.step("done", f"converged after {_count(n, 'iteration')}", converged=True, iterations=n)
        return report
    except BaseException as err:
        report["reason"] = str(err) or type(err).__name__
        if not session.fault:                   # the goal was not reached: the devices are fine
            log.step("done", f"not converged: {err}", converged=False, reason=str(err))
            raise
        report["fault"] = session.fault
        if isinstance(err, DeviceFault):
            raise DeviceFault(err.device, f"{err.reason}; log in {out / 'log.jsonl'}") from err
        raise
    finally:
        (out / "report.json").write_text(jsonio.dumps(report, indent=2) + "\n")
        log.close()
        if report["iterations"]:
            write_convergence(out / "convergence.png", report["iterations"], task.requirements.gray_band)


def _count(n, noun):
    return f"{n} {noun}{'s' * (n != 1)}"


def log_fault(log, fault):
    """The fault step of log.jsonl, after the safe stop."""
    log.step("fault", f"{fault['error']}: {stop_outcome(fault['stop_failures'])}", **fault)


def command(args):
    """`cell run TASK [--backend sim|hw] [--out DIR] [--max-iterations N] [--yes]`: exit 0 when
    every feature pixel ends in the gray band, 1 when not (with the reason), 3 on a device fault."""
    from cell.cli import output_folder
    from cell.loader import load_task
    if args.max_iterations < 1:
        raise TaskError("command line", "--max-iterations", args.max_iterations, "an integer >= 1")
    task = load_task(args.task)
    backend = args.backend or task.cell.backend
    out = output_folder(args.out, Path("runs") / f"{Path(args.task).stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    report = run(task, out, lambda scene: backends.open_devices(task, scene, backend, args.yes), args.max_iterations)
    last, n = report["iterations"][-1], len(report["iterations"])
    g, (low, high) = last["measured_gray"], task.requirements.gray_band
    print(f"{task.name}: converged after {_count(n, 'iteration')}: feature gray {g['min']:.0f}-{g['max']:.0f} "
          f"(mean {g['mean']:.1f}, band {low:g}-{high:g}) at {1e3 * last['shutter_s']:.3f} ms, "
          f"f/{last['f_number']:.2f}")
    print(f"  wrote {out}/report.json, log.jsonl, {_count(n, 'capture')} with the feature drawn, "
          f"plan pictures")
    return 0
