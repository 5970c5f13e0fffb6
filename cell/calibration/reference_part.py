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
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Iterator

import numpy as np

from cell.physics.sensor import saturation_level
from cell.run import measurement, motion
from cell.run.acquisition import acquire, plan_and_connect
from cell.core.errors import GoalNotReached, PlanInfeasible
from cell.planning.evaluate import black_level
from cell.report.pictures import write_calibration
from cell.report.recorder import Ending, Recorder
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.planning.plan import Plan
    from cell.planning.scene import Scene
    from cell.task.types import Task

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


def fit_camera_constant(exposure: np.ndarray, gray: np.ndarray, saturation: float) -> Fit | None:
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


def shutter_sweep(shutter_s: float, predicted_max: float, full_scale: float, shutter_range_s: tuple[float, float],
                  shots: int) -> np.ndarray:
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


@dataclass(frozen=True)
class ShotRecord:
    """One shot of the sweep: the shutter the camera used and the gray at the feature samples."""

    shutter_s: float
    f_number: float
    gray_min: float
    gray_mean: float
    gray_max: float
    samples: int                # samples in the image
    saturated: int
    exposure: np.ndarray        # (P,) model pixel power x shutter, P t [W s]
    gray: np.ndarray            # (P,) measured gray, NaN off the image

    def to_json(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in ("shutter_s", "f_number", "gray_min", "gray_mean", "gray_max",
                                              "samples", "saturated")}


def sweep(task: Task, plan: Plan, devices: Devices, recorder: Recorder, shots: int = 6) -> Iterator[ShotRecord]:
    """Drive the cell to the plan and take the shutter sweep at the planned f-number and focus,
    yielding each ShotRecord as it is taken (and logged)."""
    shot = plan.shot
    full_scale = saturation_level(devices.camera.bit_depth)
    signal = shot.gray - black_level(task)               # the plan's G less the black level it knew
    times = shutter_sweep(shot.exposure.shutter_s, signal.max(), full_scale, task.camera.shutter_range_s, shots)
    motion.move_to(task, devices, shot, recorder)
    # the model's pixel power per sample at the planned f-number: G = b + c P t
    power = signal / (task.camera.sensor.camera_constant * shot.exposure.shutter_s)
    for k, wanted in enumerate(times, 1):
        capture = acquire(devices, recorder, k, wanted, shot.exposure.f_number, shot.exposure.focus_m)
        _, _, inside, gray = measurement.read_samples(capture.image, task, capture.T_cell_cam,
                                                      plan.planned_scene.points)
        seen = gray[inside]
        record = ShotRecord(capture.shutter_s, shot.exposure.f_number, float(seen.min()), float(seen.mean()),
                            float(seen.max()), int(seen.size), int(np.sum(seen >= full_scale)),
                            power * capture.shutter_s, gray)
        recorder.step("shot", f"{k}/{len(times)}: shutter {1e3 * capture.shutter_s:.3f} ms, gray at the samples "
                              f"{seen.min():.1f}-{seen.max():.1f} (mean {seen.mean():.1f}), "
                              f"{record.saturated} of {seen.size} saturated", iteration=k, **record.to_json())
        yield record


@dataclass(frozen=True)
class CalibrationResult(Result):
    """What the calibration achieved (cell.report.result's verdict: `success`, c fitted;
    `message`, why not; the device fault), the Fit, its ratio to the task's c, every shot and
    the plan. calibration.json is to_json(), with `reason` (the message) as well."""

    SUCCEEDED: ClassVar[str] = "calibrated"
    NOT_REACHED: ClassVar[str] = "not_calibrated"

    task: str
    camera_constant_task: float
    success: bool
    message: str
    plan: dict[str, Any] | None
    shots: tuple[ShotRecord, ...] = ()
    fit: Fit | None = None
    fault: dict[str, Any] | None = None
    cause: str | None = None

    @property
    def camera_fit(self) -> Fit:
        """The fit of a successful calibration (ValueError on one that made none)."""
        return self._made(self.fit, "fit of c")

    @property
    def camera_constant_ratio(self) -> float | None:
        return self.fit.camera_constant / self.camera_constant_task if self.fit else None

    @property
    def counters(self) -> dict[str, int]:
        return {"shots": len(self.shots), "pairs_used": self.fit.used if self.fit else 0}

    def details(self) -> dict[str, Any]:
        return {"task": self.task, "camera_constant_task": self.camera_constant_task, "plan": self.plan,
                "shots": [s.to_json() for s in self.shots], "fit": asdict(self.fit) if self.fit else None,
                "camera_constant_ratio": self.camera_constant_ratio}


def run(task: Task, out: str | Path, connect: Callable[[Scene], Devices], shots: int = 6) -> CalibrationResult:
    """Plan (the function `cell plan` uses, plan.json and pictures in out), connect(scene) ->
    Devices, sweep and fit c; out/log.jsonl as it happens, out/calibration.json however it ends,
    and out/calibration.png. Raises PlanInfeasible before anything moves, GoalNotReached when
    nothing usable was measured (exit 1), DeviceFault after the safe stop of every device (exit 3).
    Returns the CalibrationResult."""
    out = Path(out)
    c_model = task.camera.sensor.camera_constant
    records: list[ShotRecord] = []
    fit: Fit | None = None

    def result(reason: str, fault: dict[str, Any] | None) -> CalibrationResult:
        return CalibrationResult(str(task.path), c_model, fit is not None and not reason, reason, recorder.plan,
                                 tuple(records), fit, fault)

    with Recorder(out) as recorder, Ending(recorder, "no fit", "calibration.json", result) as end:
        with end.session:
            planned, devices = plan_and_connect(task, recorder, end.session, connect)
            for record in sweep(task, planned, devices, recorder, shots):
                records.append(record)
        exposures = np.array([r.exposure for r in records])
        grays = np.array([r.gray for r in records])
        fit = fit_camera_constant(exposures, grays, saturation_level(devices.camera.bit_depth))
        write_calibration(out / "calibration.png", exposures, grays, fit, c_model)
        if fit is None:
            n = sum(r.samples for r in records)
            saturated = sum(r.saturated for r in records)
            raise GoalNotReached(f"too few resolved samples to fit c ({saturated} of {n} readings "
                                 f"saturated, the rest at 0 or from a single shot): is the lamp "
                                 f"on, does it light the feature, is the part the task's?", "too_few_samples")
        recorder.step("done", f"c = {fit.camera_constant:.5g} 1/(W s), {fit.camera_constant / c_model:.3f} x "
                              f"the task's", **asdict(fit))
    return end.result
