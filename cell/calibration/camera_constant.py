"""Operator routine for the camera constant c of G = c P_pixel t (eq. 10) with a laser of known
power at several shutter times (sec. 4.1): all of the beam's power P lands on a few pixels, so the
spot's summed gray above the dark, S = sum (G - dark), is c P t.

The operator aims the laser through the lens at the sensor (its transmission then counts in c,
as eq. (17) assumes a lossless lens) and blocks and unblocks the beam when told (Laser). Dark
frames at both ends of the shutter range give each pixel's dark gray, linear in t (black level
plus dark current); a ladder of probes finds a shutter time at which the spot is neither
saturated nor too dark, and the sweep spans its peak from 10 % to 90 % of the range above the
dark (cell.calibration.reference_part.shutter_sweep). The spot's window is where its rings fade into the dark
noise. S is fitted against t by ordinary least squares with an intercept (scipy.stats.linregress,
which absorbs a constant dark error or a shutter offset); c = slope / P with the slope's standard
error from the residuals. Weighted least squares would need each frame's variance K S + the
window's dark variance, and the system gain K is what a camera without a datasheet does not tell:
over the sweep's decade OLS stays unbiased and its standard error holds (tests/test_camera_constant.py).
The arm and the lamp are connected (a fault stops them) but never moved.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.stats import linregress

from cell.physics.sensor import saturation_level
from cell.run import measurement
from cell.run.acquisition import acquire
from cell.calibration.reference_part import shutter_sweep
from cell.core.files import write_yaml
from cell.core.errors import CellError, DeviceFault, GoalNotReached, TaskError
from cell.report.pictures import write_laser_fit
from cell.report.recorder import Ending, Recorder
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.devices.operator import Operator
    from cell.task.types import Sensor, Task

DARK_FRAMES = 3             # at each end of the shutter range
MIN_PEAK = 0.05             # a spot peaking below this share of the range above the dark is too dark
PROBE_STEP = 4.0            # the probes' shutter ratio
MAX_PROBES = 8
MIN_FRAMES = 4              # usable sweep frames: two parameters and a residual to judge linearity by
MIN_R2 = 0.999              # below: S is not proportional to t
RING_SIGMAS = 3.0           # a ring of the spot counts while it holds more than this many noise rms
MAX_WINDOW_PX = 64          # the window's largest half-size


class Laser:
    """A laser of power_w (what reaches the sensor, after its neutral-density filters) aimed at
    the sensor; the operator blocks and unblocks its beam when told, on either backend (the
    simulated cell renders its spot while unblocked, sim.laser)."""

    device = "laser"

    def __init__(self, power_w: float, operator: Operator) -> None:
        self.power_w, self.operator, self.blocked = power_w, operator, True

    def block(self, instruction: str = "block the beam") -> None:
        self.operator.confirm(self.device, instruction)
        self.blocked = True

    def unblock(self, instruction: str = "unblock the beam") -> None:
        self.operator.confirm(self.device, instruction)
        self.blocked = False


@dataclass(frozen=True)
class Frame:
    """One frame: its kind (dark, probe, sweep), the shutter the camera reports, and, lit, its spot:
    the peak above the dark, saturated (at the ADC's top or the datasheet's full well) or too
    dark, and the sum S over the spot's window (None until the window is known)."""

    kind: str
    shutter_s: float
    capture: str
    peak: float = float("nan")
    saturated: bool = False
    too_dark: bool = False
    spot_sum: float | None = None

    @property
    def usable(self) -> bool:
        return self.kind != "dark" and not (self.saturated or self.too_dark)


@dataclass(frozen=True)
class LaserFit:
    """S = offset + slope t by least squares over the usable sweep frames, c = slope / P."""

    camera_constant: float              # [1/(W s)]
    camera_constant_stderr: float
    offset: float                       # S at t = 0 [gray]
    r_squared: float
    frames_used: int
    frames_saturated: int
    frames_too_dark: int


class Darks:
    """Each pixel's dark gray at shutter t, linear between the mean dark frames at the two ends
    of the shutter range (black level plus dark current), the pixels' dark noise, and the
    sensor's black level b of G = b + c P t: the shortest shutter's frames' (measurement.black_level_of,
    as `cell run` takes it from a dark frame)."""

    def __init__(self, frames: dict[float, list[np.ndarray]]) -> None:
        ends = sorted(frames.items())           # one end only when the shutter range is one time
        (t0, d0), (t1, d1) = ends[0], ends[-1]
        self.t0, self.t1 = t0, t1
        self.black = measurement.black_level_of(np.asarray(d0))
        self.d0, self.d1 = (np.mean(d, axis=0) for d in (d0, d1))
        self.noise_rms = float(np.sqrt(np.mean([np.var(d, axis=0, ddof=1).mean() for d in (d0, d1)])))

    def at(self, shutter_s: float) -> np.ndarray:
        w = 0.0 if self.t1 == self.t0 else (shutter_s - self.t0) / (self.t1 - self.t0)
        return (1.0 - w) * self.d0 + w * self.d1


def saturation_margin(sensor: Sensor) -> float:
    """The gray above the dark a pixel cannot exceed when the full well (the datasheet's
    K mu_e,sat) fills before the ADC's top: one level below it; inf without those keys."""
    if sensor.system_gain_dn_per_e and sensor.saturation_capacity_e:
        return sensor.system_gain_dn_per_e * sensor.saturation_capacity_e - 1.0
    return np.inf


class Spot:
    """Judges a lit frame: the signal above the dark, its peak, saturation and darkness."""

    def __init__(self, task: Task, darks: Darks) -> None:
        self.darks, self.top = darks, saturation_level(task.camera.sensor.bit_depth)
        self.full_well = saturation_margin(task.camera.sensor)

    def signal(self, image: np.ndarray, shutter_s: float) -> np.ndarray:
        return np.asarray(image, float) - self.darks.at(shutter_s)

    def judge(self, image: np.ndarray, shutter_s: float,
              where: tuple[slice, slice] = np.s_[:, :]) -> tuple[float, bool, bool]:
        """(peak, saturated, too dark) within `where` (the whole frame until the window is known)."""
        image, signal = np.asarray(image, float)[where], self.signal(image, shutter_s)[where]
        peak = float(signal.max())
        saturated = bool(np.any(image >= self.top) or np.any(signal >= self.full_well))
        return peak, saturated, peak < MIN_PEAK * self.room(shutter_s)

    def room(self, shutter_s: float) -> float:
        """Gray levels a pixel can rise above the dark: to the ADC's top from the frame's brightest
        dark pixel, or to the full well if that fills first."""
        return min(self.top - float(self.darks.at(shutter_s).max()), self.full_well)


def spot_window(signal: np.ndarray, noise_rms: float) -> tuple[tuple[slice, slice] | None, tuple[int, int, int]]:
    """The window (row slice, column slice) about the spot's brightest 3x3 patch: its half-size
    twice the first ring (the square's border, one pixel wide) that holds less than RING_SIGMAS
    noise rms (sqrt(pixels) sigma, sigma^2 the dark noise plus 1/12 of rounding), so that the
    tail beyond it is lost in the noise. None when the window would leave the image."""
    row, col = np.unravel_index(np.argmax(uniform_filter(signal, 3)), signal.shape)
    sigma = np.sqrt(noise_rms**2 + 1.0 / 12.0)
    inner = signal[row, col]
    for h in range(1, MAX_WINDOW_PX + 1):
        square = signal[max(row - h, 0):row + h + 1, max(col - h, 0):col + h + 1]
        ring = square.sum() - inner
        if abs(ring) < RING_SIGMAS * sigma * np.sqrt(8 * h):
            break
        inner = square.sum()
    half = min(2 * h, MAX_WINDOW_PX)
    if row < half or col < half or row + half >= signal.shape[0] or col + half >= signal.shape[1]:
        return None, (int(row), int(col), half)
    return np.s_[row - half:row + half + 1, col - half:col + half + 1], (int(row), int(col), half)


def fit_series(frames: list[Frame], power_w: float) -> LaserFit:
    """LaserFit of the usable sweep frames' S over t, or GoalNotReached with the reason: a spot
    saturated, or too dark, at every shutter time, too few usable frames, poor linearity."""
    sweep = [f for f in frames if f.kind == "sweep"]
    used = [f for f in sweep if f.usable]
    saturated, dark = sum(f.saturated for f in sweep), sum(f.too_dark and not f.saturated for f in sweep)
    if sweep and saturated == len(sweep):
        raise GoalNotReached(f"the spot is saturated at every shutter time of the sweep ({len(sweep)} frames): "
                             "put a denser neutral-density filter in the beam", "saturated")
    if len(used) < MIN_FRAMES:
        raise GoalNotReached(f"too few usable frames: {len(used)} of {len(sweep)} ({saturated} saturated, "
                             f"{dark} too dark), at least {MIN_FRAMES} are needed", "too_few_frames")
    t, s = np.array([f.shutter_s for f in used]), np.array([f.spot_sum for f in used])
    line = linregress(t, s)
    r2 = float(line.rvalue**2)
    if not r2 >= MIN_R2:
        raise GoalNotReached(f"poor linearity: r2 {r2:.5f} below {MIN_R2} over {len(used)} frames: the spot's sum "
                             "is not proportional to the shutter time (a gain or gamma that is not linear, "
                             "the laser's power drifting, room light changing)", "linearity")
    return LaserFit(float(line.slope / power_w), float(line.stderr / power_w), float(line.intercept), r2,
                    len(used), saturated, dark)


def take(devices: Devices, recorder: Recorder, frames: list[Frame], shutter_s: float, f_number: float,
         focus_m: float) -> tuple[np.ndarray, float, str]:
    """acquire one frame (capture-N.png, logged); returns (image, the shutter the camera used, its
    file's name)."""
    capture = acquire(devices, recorder, len(frames) + 1, shutter_s, f_number, focus_m)
    return np.asarray(capture.image, float), capture.shutter_s, capture.name


def dark_frames(devices: Devices, recorder: Recorder, frames: list[Frame], shutter_range_s: tuple[float, float],
                f_number: float, focus_m: float) -> Darks:
    """DARK_FRAMES at each end of the shutter range, beam blocked: Darks."""
    stacks: dict[float, list[np.ndarray]] = {}
    wanted_times = [t for t in shutter_range_s for _ in range(DARK_FRAMES)]
    with recorder.stage("dark frames", len(wanted_times)) as stage:
        for wanted in stage.each(wanted_times):
            image, t, name = take(devices, recorder, frames, wanted, f_number, focus_m)
            stacks.setdefault(t, []).append(image)
            frames.append(Frame("dark", t, name))
            recorder.step("dark", f"dark frame at {1e3 * t:.3f} ms: mean {image.mean():.2f}", iteration=len(frames),
                          shutter_s=t, mean=float(image.mean()))
    darks = Darks(stacks)
    b = darks.black
    recorder.step("black_level", f"black level {b.value:.2f} gray, noise {b.noise_rms:.2f} rms (the dark frames at "
                                 f"{1e3 * darks.t0:.3g} ms)", **b.to_json())
    return darks


def lit_frame(devices: Devices, recorder: Recorder, frames: list[Frame], spot: Spot, kind: str, shutter_s: float,
              f_number: float, focus_m: float) -> np.ndarray:
    """One lit frame (take) judged by the spot: its Frame appended to frames and logged; returns its image."""
    image, t, name = take(devices, recorder, frames, shutter_s, f_number, focus_m)
    peak, saturated, too_dark = spot.judge(image, t)
    frames.append(Frame(kind, t, name, peak, saturated, too_dark))
    verdict = "saturated" if saturated else "too dark" if too_dark else "usable"
    recorder.step(kind, f"{1e3 * t:.3f} ms: spot peak {peak:.1f} above the dark, {verdict}", iteration=len(frames),
                  shutter_s=t, peak=peak, saturated=saturated, too_dark=too_dark)
    return image


def probe(devices: Devices, recorder: Recorder, frames: list[Frame], spot: Spot, task: Task, power_w: float,
          f_number: float, focus_m: float) -> Frame:
    """Probes from the shutter at which the task's c puts the spot's sum at the range above the
    dark, PROBE_STEP shorter while saturated, longer while too dark, until one is usable: its
    Frame. GoalNotReached when the shutter range ends first."""
    lo, hi = task.camera.shutter_range_s
    t = float(np.clip(spot.room(lo) / (task.camera.sensor.camera_constant * power_w), lo, hi))
    for _ in range(MAX_PROBES):
        lit_frame(devices, recorder, frames, spot, "probe", t, f_number, focus_m)
        last = frames[-1]
        if last.usable:
            return last
        step = 1.0 / PROBE_STEP if last.saturated else PROBE_STEP
        nxt = float(np.clip(t * step, lo, hi))
        if nxt == t:
            break
        t = nxt
    if last.saturated:
        raise GoalNotReached(f"the spot is saturated at every shutter time down to {1e3 * t:.3g} ms "
                             f"(the camera's shortest is {1e3 * lo:.3g} ms): put a denser neutral-density "
                             "filter in the beam (and say its power with --laser-power-w)", "saturated")
    raise GoalNotReached(f"the spot is too dark at every shutter time up to {1e3 * t:.3g} ms: its peak is "
                         f"{last.peak:.1f} gray above the dark, less than {100 * MIN_PEAK:g} % of the range: "
                         "is the laser on and aimed at the sensor? a lighter neutral-density filter "
                         "(and --laser-power-w to match)", "too_dark")


def measure_series(devices: Devices, recorder: Recorder, frames: list[Frame], task: Task, laser: Laser,
                   shots: int) -> tuple[Spot, list[np.ndarray]]:
    """Dark frames, probes and the sweep, the operator told each step; returns the Spot and the
    sweep's images."""
    lens = task.camera.lens
    f_number, focus_m = lens.f_number_range[0], task.camera.distance_m
    recorder.step("setup", f"laser {laser.power_w:.4g} W; the arm and the lamp stay where they are (no motion is "
                           f"commanded); lens at f/{f_number:g}, focus {focus_m:.3f} m")
    laser.block(f"turn the lamp off and shade the camera from room light; aim the laser ({laser.power_w:.4g} W "
                f"after its neutral-density filters, as --laser-power-w says) through the lens at the middle of "
                f"the sensor, the lens at f/{f_number:g}; then block the beam for the dark frames")
    darks = dark_frames(devices, recorder, frames, task.camera.shutter_range_s, f_number, focus_m)
    spot = Spot(task, darks)
    laser.unblock("unblock the beam: the shutter series follows")
    try:
        found = probe(devices, recorder, frames, spot, task, laser.power_w, f_number, focus_m)
        times = shutter_sweep(found.shutter_s, found.peak, spot.room(found.shutter_s),
                              task.camera.shutter_range_s, shots)
        with recorder.stage("shutter sweep", len(times)) as stage:
            images = [lit_frame(devices, recorder, frames, spot, "sweep", t, f_number, focus_m)
                      for t in stage.each(times)]
    except CellError as err:
        if not isinstance(err, DeviceFault):    # a fault ends at once; a refusal first asks this
            laser.block("block the beam: the series is refused")
        raise
    laser.block("block the beam: the frames are taken")
    return spot, images


def sum_spots(frames: list[Frame], images: list[np.ndarray], spot: Spot) -> tuple[list[Frame], dict[str, int] | None]:
    """The window from the brightest usable sweep frame; each sweep frame judged again within it,
    with its sum S. Returns (frames, window description) or GoalNotReached when the spot lies
    too near the image's edge."""
    sweep = [i for i, f in enumerate(frames) if f.kind == "sweep"]
    usable = [i for i in sweep if frames[i].usable]
    if not usable:
        return frames, None
    best = max(usable, key=lambda i: frames[i].peak)
    signal = spot.signal(images[sweep.index(best)], frames[best].shutter_s)
    where, (row, col, half) = spot_window(signal, spot.darks.noise_rms)
    window = {"row": row, "col": col, "half_size_px": half}
    if where is None:
        raise GoalNotReached(f"the spot at row {row}, column {col} lies within {half} px of the image's edge: "
                             "aim the laser nearer the middle of the sensor", "spot_at_edge")
    out = list(frames)
    for i, image in zip(sweep, images):
        f = frames[i]
        peak, saturated, too_dark = spot.judge(image, f.shutter_s, where)
        out[i] = Frame(f.kind, f.shutter_s, f.capture, peak, saturated, too_dark,
                       float(spot.signal(image, f.shutter_s)[where].sum()))
    return out, window


@dataclass(frozen=True)
class LaserCalibration(Result):
    """What the routine achieved (cell.report.result's verdict: `success`, c fitted and the
    camera file written; `message`, why not; the device fault), the LaserFit, every frame, the
    spot's window, the camera file and the black level of the dark frames. calibration.json is
    to_json(), with `reason` (the message) as well."""

    SUCCEEDED: ClassVar[str] = "calibrated"
    NOT_REACHED: ClassVar[str] = "not_calibrated"

    task: str
    laser_power_w: float
    camera_constant_task: float
    success: bool
    message: str
    frames: tuple[Frame, ...] = ()
    fit: LaserFit | None = None
    window: dict[str, int] | None = None
    camera_file: str | None = None
    fault: dict[str, Any] | None = None
    black_level: measurement.BlackLevel | None = None
    cause: str | None = None

    @property
    def laser_fit(self) -> LaserFit:
        """The fit of a successful calibration (ValueError on one that made none)."""
        return self._made(self.fit, "laser fit")

    @property
    def dark_black_level(self) -> measurement.BlackLevel:
        """The black level of the dark frames (ValueError when the routine took none)."""
        return self._made(self.black_level, "black level")

    @property
    def written_camera_file(self) -> str:
        """The camera file a successful calibration wrote (ValueError when it wrote none)."""
        return self._made(self.camera_file, "camera file")

    def fitted(self) -> dict[str, float]:
        """c, its standard error, the linearity and the frames used ({} without a fit)."""
        fit = self.fit
        return {"camera_constant": fit.camera_constant, "camera_constant_stderr": fit.camera_constant_stderr,
                "r_squared": fit.r_squared, "frames_used": fit.frames_used} if fit else {}

    def summary(self) -> dict[str, Any]:
        """--json's keys: fitted()'s, the black level [gray] and the camera file."""
        return self.fitted() | {"black_level": self.black_level.value if self.black_level else None,
                                "camera_file": self.camera_file}

    @property
    def counters(self) -> dict[str, int]:
        return {"frames": len(self.frames), "frames_used": self.fit.frames_used if self.fit else 0}

    def details(self) -> dict[str, Any]:
        return {"task": self.task, "laser_power_w": self.laser_power_w, "camera_constant_task": self.camera_constant_task,
                **self.fitted(), "fit": asdict(self.fit) if self.fit else None,
                "camera_constant_ratio": self.fit.camera_constant / self.camera_constant_task if self.fit else None,
                "black_level": self.black_level.to_json() if self.black_level else None,
                "window": self.window, "frames": [asdict(f) for f in self.frames], "camera_file": self.camera_file}


def check_camera_file(path: str | Path, force: bool, option: str = "--camera-file") -> Path:
    """Refuse (bad input, before any work) to replace an existing file (the `option` names it)
    without --force, a folder, or a file in a folder that does not exist."""
    path = Path(path)
    if path.is_dir():
        raise TaskError("command line", option, f"{path}, a folder", "a file path")
    if not path.parent.is_dir():
        raise TaskError("command line", option, f"{path}, in no existing folder",
                        "a file in an existing folder")
    if path.exists() and not force:
        raise TaskError("command line", option, f"{path}, a file that exists",
                        "a new file, or --force to replace it")
    return path


def camera_document(sensor: Sensor, fit: LaserFit, black: measurement.BlackLevel, source: str) -> dict[str, Any]:
    """The camera file: the task's sensor with the measured c (and its standard error) and the
    black level of the dark frames (BlackLevel); the datasheet's noise keys stay, its quantum
    efficiency and wavelength go (the measurement replaces the c they give)."""
    keep = ("width_px", "height_px", "pixel_pitch_m", "bit_depth")
    noise = ("system_gain_dn_per_e", "dark_noise_e", "saturation_capacity_e")
    doc = {k: getattr(sensor, k) for k in keep}
    doc |= {"camera_constant": float(f"{fit.camera_constant:.6g}"),
            "camera_constant_stderr": float(f"{fit.camera_constant_stderr:.3g}")}
    doc |= {k: getattr(sensor, k) for k in noise if getattr(sensor, k) is not None}
    return doc | {"black_level": float(f"{black.value:.4g}"), "source": source}


def run(task: Task, out: str | Path, connect: Callable[[], Devices], laser: Laser, camera_file: str | Path,
        shots: int = 8, force: bool = False) -> LaserCalibration:
    """connect() -> Devices; dark frames, probes, the sweep and the fit; out/log.jsonl as it
    happens, out/calibration.json however it ends, out/calibration.png, and the camera file on
    success. Raises GoalNotReached for an untrustworthy series (exit 1), DeviceFault after the safe
    stop (exit 3). Returns the LaserCalibration."""
    out, c_task = Path(out), task.camera.sensor.camera_constant
    frames: list[Frame] = []
    fit: LaserFit | None = None
    window: dict[str, int] | None = None
    written: str | None = None
    spot: Spot | None = None

    def result(reason: str, fault: dict[str, Any] | None) -> LaserCalibration:
        return LaserCalibration(str(task.path), laser.power_w, c_task, fit is not None and not reason, reason,
                                tuple(frames), fit, window, written, fault, spot.darks.black if spot else None)

    with Recorder(out) as recorder, Ending(recorder, "no fit", "calibration.json", result) as end:
        with end.session:
            end.session.devices = connect()
            spot, images = measure_series(end.session.devices, recorder, frames, task, laser, shots)
        frames[:], window = sum_spots(frames, images, spot)
        try:
            fit = fit_series(frames, laser.power_w)
        finally:
            write_laser_fit(out / "calibration.png", frames, fit, c_task, laser.power_w)
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        source = (f"cell calibrate camera-constant {task.path.name} on {stamp}: laser {laser.power_w:.4g} W, "
                  f"{fit.frames_used} frames, r2 {fit.r_squared:.6f}; black level from its dark frames; run folder {out}")
        black = spot.darks.black
        written = str(write_yaml(camera_file, camera_document(task.camera.sensor, fit, black, source), replace=force))
        recorder.step("done", f"c = {fit.camera_constant:.5g} +- {fit.camera_constant_stderr:.2g} 1/(W s), "
                              f"{fit.camera_constant / c_task:.3f} x the task's; black level {black.value:.2f} gray; "
                              f"wrote {written}", camera_file=written, black_level=black.value, **asdict(fit))
    return end.result
