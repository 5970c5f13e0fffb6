"""`cell measure-brdf`: the cell as a goniometer (sec. 3.2-3.3). A flat sample of the material lies
at the lamp rig's pivot (`calibration.sample`); per phase angle alpha the lamp and the camera,
both aimed at the sample's centre, tilt together in the plane of incidence: the half-angle
direction h at beta from the normal, the lamp at beta + alpha/2, the camera at beta - alpha/2, so
ti = |beta + alpha/2|, te = |beta - alpha/2| and the mirror cosine of eq. (7) is cos 2 beta (the
spike's peak at beta = 0). beta runs over [-(max - alpha/2), max - alpha/2] in steps of
`step_deg` (ti, te within max_angle_deg, about 90 deg of range as the paper's). Poses the arm or
the rig would refuse are skipped, with the reason, and counted.

Per pose the mean gray of a PATCH_PX square patch about the sample's centre in the image,
exposed so that it is unsaturated (re-taken shorter when a pixel clips, longer when it is too
dark), gives R by the corrected eq. (18): R = 8 kappa^2 (G - b) / (c t A_pixel Phi), Phi by eq.
(11) at the read-back lamp distance. The goniometer CSV is fitted by cell.physics.brdf_fit per phase angle.

Resolution: near the peak c^m = cos(2 beta)^m ~ exp(-2 m beta^2), whose half width at half
maximum is sqrt(ln 2 / (2 m)); a term narrower than the step falls between the poses, so an
exponent above M = ln 2 / (2 step^2) cannot be measured: such a term (or one the data do not show)
is reported unresolved, with sigma 0, m = M (at least that narrow) and infinite standard errors.
The step is the CSV's own (cell.physics.brdf_fit.fit_goniometer, the fit `cell fit-brdf` makes of
the same file): step_deg when the mirror pose was measured, coarser where the arm refused it.
"""
from __future__ import annotations

from dataclasses import asdict, astuple, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import numpy as np
import trimesh

from cell.physics.sensor import levels, saturation_level
from cell.core import geometry

from cell.run import motion
from cell.run.acquisition import acquire, find_black_level
from cell.devices.interfaces import speaking_for
from cell.core.files import write_yaml
from cell.core.errors import GoalNotReached
from cell.physics.brdf_fit import MIN_ROWS, SIGNIFICANCE, fit_goniometer, read_goniometer
from cell.task.loader import load_material
from cell.physics.brdf import reflectance
from cell.physics.radiometry import cone_irradiance, gray_per_exposure, reflectance_from_gray
from cell.physics.projection import intrinsics, project
from cell.report.recorder import Ending, Recorder
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.devices.operator import Operator
    from cell.physics.material import BrdfParameters
    from cell.planning.scene import Scene
    from cell.run.acquisition import Capture
    from cell.run.measurement import BlackLevel
    from cell.task.types import Sample, Task
from cell.devices.rig import lamp_joints
from cell.planning.scene import look_at
from cell.task.types import Feature, Part

PATCH_PX = 17               # the paper's patch (sec. 3.2)
TARGET = 0.5                # the patch's mean gray aimed at, of the range above the black level
MIN_SIGNAL = 0.1            # a mean below this of the range is re-taken longer
MAX_TAKES = 6               # exposures at most per pose
DEFAULT_F_NUMBER = 8.0      # kept while the shutter range allows (clipped to the lens's range)
SAMPLE_FEATURE_RADIUS_M = 1e-3
CSV_COLUMNS = ("theta_i_deg", "theta_e_deg", "phase_deg", "reflectance")


@dataclass(frozen=True)
class Pose:
    """One goniometer geometry: phase angle, half-angle tilt beta, ti, te [rad]; unit directions
    from the sample's centre to the lamp and to the camera (cell frame)."""

    phase_rad: float
    beta_rad: float
    theta_i_rad: float
    theta_e_rad: float
    to_lamp: tuple[float, float, float]
    to_camera: tuple[float, float, float]


@dataclass(frozen=True)
class Reading:
    """A pose's measurement: the patch's mean gray above the black level, the exposure, R."""

    pose: int
    phase_deg: float
    theta_i_deg: float
    theta_e_deg: float
    beta_deg: float
    signal: float
    shutter_s: float
    f_number: float
    irradiance_w_m2: float
    reflectance: float
    takes: int
    capture: str


def plate_mesh(sample: Sample, centre: np.ndarray) -> trimesh.Trimesh:
    """The sample as a disc (64-gon prism) whose top face lies at `centre`, facing sample.normal."""
    disc = trimesh.creation.cylinder(radius=sample.radius_m, height=sample.thickness_m, sections=64)
    disc.apply_translation([0.0, 0.0, -0.5 * sample.thickness_m])
    disc.apply_transform(geometry.transform(geometry.frame_from_normal(sample.normal), centre))
    return disc


def sample_task(task: Task) -> Task:
    """The task with the sample in the part's place (the operator swaps them for this routine):
    its plate mesh in the cell frame, its material, one small feature at the pivot."""
    sample, pivot = task.calibration.sample, np.asarray(task.lamp.rig.pivot_m, float)
    material = sample.material or task.part.material
    feature = Feature("sample", pivot, np.asarray(sample.normal, float), SAMPLE_FEATURE_RADIUS_M, 8,
                      task.features[0].requirements, key="calibration.sample")
    return replace(task, part=Part(task.part.mesh_path, plate_mesh(sample, pivot), material),
                   frames=task.frames.with_transform("T_cell_part", np.eye(4)), features=(feature,))


def poses(task: Task) -> list[Pose]:
    """Every Pose of the task's goniometer (module docstring), phase by phase, beta ascending."""
    gonio, normal = task.calibration.goniometer, geometry.unit(task.calibration.sample.normal)
    along = geometry.frame_from_normal(normal)[:, 0]

    def direction(angle: float) -> tuple[float, float, float]:
        return tuple(np.cos(angle) * normal + np.sin(angle) * along)

    out = []
    for alpha in gonio.phase_rad:
        reach = gonio.max_angle_rad - 0.5 * alpha
        n = int(np.floor(reach / gonio.step_rad + 1e-9))
        for beta in gonio.step_rad * np.arange(-n, n + 1):
            li, le = beta + 0.5 * alpha, beta - 0.5 * alpha
            out.append(Pose(float(alpha), float(beta), abs(li), abs(le), direction(li), direction(le)))
    return out


def refusal(devices: Devices, task: Task, pose: Pose) -> tuple[np.ndarray, tuple[float, float, float], str | None]:
    """(T_cell_cam, lamp joints, why the arm or the rig would refuse the pose or None)."""
    pivot, gonio = np.asarray(task.lamp.rig.pivot_m, float), task.calibration.goniometer
    T = look_at(pivot + task.camera.distance_m * np.asarray(pose.to_camera), pivot)
    pan, tilt, radius = lamp_joints(pivot, pivot + gonio.lamp_radius_m * np.asarray(pose.to_lamp))
    joints = (float(pan), float(tilt), float(radius))     # one pose's: 0-d arrays as floats
    why = devices.arm.refusal(T)
    why = why and f"arm: {why}"
    lamp = devices.lamp.refusal(*joints)
    return T, joints, why or (lamp and f"pan-tilt: {lamp}")


def split_exposure(task: Task, exposure: float) -> tuple[float, float]:
    """(shutter, f-number) giving t / kappa^2 = exposure: DEFAULT_F_NUMBER while the shutter range
    allows, else the shutter at its end and kappa to match, within the lens's range."""
    (t_lo, t_hi), (k_lo, k_hi) = task.camera.shutter_range_s, task.camera.lens.f_number_range
    kappa = float(np.clip(DEFAULT_F_NUMBER, k_lo, k_hi))
    t = exposure * kappa**2
    if not t_lo <= t <= t_hi:
        t = float(np.clip(t, t_lo, t_hi))
        kappa = float(np.clip(np.sqrt(t / exposure), k_lo, k_hi))
    return t, kappa


def patch_at(image: np.ndarray, K: np.ndarray, T_cell_cam: np.ndarray, point: np.ndarray) -> np.ndarray | None:
    """The PATCH_PX square of the image about the point's pixel; None when it leaves the image."""
    (u, v), = project(K, T_cell_cam, point[None])[0]
    h = PATCH_PX // 2
    if not np.isfinite(u + v):
        return None
    row, col = int(round(v)), int(round(u))
    if row < h or col < h or row + h >= image.shape[0] or col + h >= image.shape[1]:
        return None
    return np.asarray(image, float)[row - h:row + h + 1, col - h:col + h + 1]


class Exposer:
    """Takes a pose's frames until its patch is unsaturated and bright enough."""

    def __init__(self, task: Task, devices: Devices, recorder: Recorder, black: BlackLevel) -> None:
        self.task, self.devices, self.recorder, self.black = task, devices, recorder, black
        sensor = task.camera.sensor
        self.top = saturation_level(sensor.bit_depth)
        self.range = self.top - black.value
        self.K = intrinsics(sensor, task.camera.lens)
        (t_lo, t_hi), (k_lo, k_hi) = task.camera.shutter_range_s, task.camera.lens.f_number_range
        self.limits = (t_lo / k_hi**2, t_hi / k_lo**2)
        self.captures = 0

    def take(self, k: int, exposure: float, centre: np.ndarray) -> tuple[Capture, np.ndarray, str]:
        """A frame at t / kappa^2 = exposure and its patch about centre (saved as patch-N.png) for pose
        k: (Capture, patch, patch file); GoalNotReached when the patch leaves the image."""
        t, kappa = split_exposure(self.task, exposure)
        self.captures += 1
        capture = acquire(self.devices, self.recorder, self.captures, t, kappa, self.task.camera.distance_m)
        patch = patch_at(capture.image, self.K, capture.T_cell_cam, centre)
        if patch is None:
            raise GoalNotReached(f"pose {k}: the sample's centre is not {PATCH_PX // 2} px inside the image: "
                                 "is the camera looking at the pivot (hand-eye)?", "not_in_view")
        name = self.recorder.write_image(f"patch-{self.captures}.png", levels(patch, self.task.camera.sensor.bit_depth))
        return capture, patch, name

    def expose(self, k: int, guess: float, centre: np.ndarray) -> tuple[Capture, float, int, str] | str:
        """(Capture, mean signal, takes, patch file) at an exposure keeping the patch unclipped:
        from `guess` (t / kappa^2), shorter by the clipped fraction, longer toward TARGET; why not
        when no exposure gives one."""
        lo, hi = self.limits
        exposure = float(np.clip(guess, lo, hi))
        for takes in range(1, MAX_TAKES + 1):
            capture, patch, name = self.take(k, exposure, centre)
            used = capture.shutter_s / capture.f_number**2
            signal = float(patch.mean() - self.black.value)
            clipped = bool(patch.max() >= self.top)
            verdict = "clipped" if clipped else "too dark" if signal < MIN_SIGNAL * self.range else "usable"
            self.recorder.step("patch", f"pose {k}: {1e3 * capture.shutter_s:.3f} ms f/{capture.f_number:.2f}: "
                                        f"patch mean {signal:.1f} above the black level, {verdict}",
                               iteration=self.captures, pose=k, signal=signal, clipped=clipped, patch=name)
            if clipped:
                nxt = used * max(0.25, TARGET * self.range / max(float(patch.max()) - self.black.value, 1.0))
                if used <= lo * (1 + 1e-9):
                    return f"the patch clips at the shortest exposure ({1e3 * capture.shutter_s:.3g} ms, " \
                           f"f/{capture.f_number:.3g})"
            elif signal < MIN_SIGNAL * self.range:
                if used >= hi * (1 - 1e-9):
                    # dim, but measured: above 3 standard errors of a PATCH_PX^2 pixel mean
                    if signal > 3.0 * max(self.black.noise_rms, 0.5) / PATCH_PX:
                        return capture, signal, takes, name
                    return f"the patch is dark at the longest exposure ({signal:.2g} gray above the black level)"
                nxt = used * TARGET * self.range / max(signal, 0.05 * MIN_SIGNAL * self.range)
            else:
                return capture, signal, takes, name
            exposure = float(np.clip(nxt, lo, hi))
        return f"no usable exposure in {MAX_TAKES} takes"


def measure_poses(task: Task, devices: Devices, recorder: Recorder, nominal: Callable[[float], BrdfParameters],
                  readings: list[Reading], refused: list[tuple[int, str]], failed: list[tuple[int, str]]) -> None:
    """Visit every pose, appending to readings, refused [(pose, reason)] and failed [(pose,
    reason)] as it goes (so a fault keeps what was measured); nominal(phase) gives the parameters
    whose R guesses each pose's first exposure."""
    pivot, lamp, sensor = np.asarray(task.lamp.rig.pivot_m, float), task.lamp, task.camera.sensor
    c, area = sensor.camera_constant, sensor.pixel_area_m2
    wanted = poses(task)
    exposer: Exposer | None = None
    with recorder.stage("poses", len(wanted)) as stage:     # the log has every step, the terminal a bar
        for k, pose in enumerate(stage.each(wanted), 1):
            T, joints, why = refusal(devices, task, pose)
            where = (f"phase {np.degrees(pose.phase_rad):.1f} deg, ti {np.degrees(pose.theta_i_rad):.1f}, "
                     f"te {np.degrees(pose.theta_e_rad):.1f} deg")
            move = None if why else motion.check(task, devices, T, joints, f"pose {k}")
            if move is not None and not move.clear:
                why = str(motion.refusal(move))
            if why:
                refused.append((k, why))
                recorder.step("refused", f"pose {k} of {len(wanted)} ({where}) skipped: {why}", pose=k, reason=why)
                continue
            motion.go(task, devices, recorder, T, joints, f"pose {k}", checked=move)
            with speaking_for(devices.lamp):
                lamp_pos, _ = devices.lamp.lamp_pose()
            if exposer is None:                      # the dark frame once the lamp is somewhere (its radius set),
                k_hi = task.camera.lens.f_number_range[1]   # at the largest f-number: the least light
                exposer = Exposer(task, devices, recorder, find_black_level(task, devices, recorder, k_hi,
                                                                            task.camera.distance_m))
            distance = float(np.linalg.norm(lamp_pos - pivot))
            phi = float(cone_irradiance(lamp.power_w, lamp.cone_angle_rad, distance, 0.0, lamp.profile))
            r_guess = float(reflectance(np.cos(pose.theta_i_rad), np.cos(pose.theta_e_rad), np.cos(pose.phase_rad),
                                        *astuple(nominal(pose.phase_rad))))
            unit = gray_per_exposure(c, area, phi, max(r_guess, 1e-6))
            recorder.step("pose", f"pose {k} of {len(wanted)}: {where}; lamp {1e3 * distance:.1f} mm, "
                                  f"Phi {phi:.4g} W/m^2", pose=k, beta_deg=np.degrees(pose.beta_rad),
                          lamp_distance_m=distance, irradiance_w_m2=phi)
            taken = exposer.expose(k, TARGET * exposer.range / float(unit), pivot)
            if isinstance(taken, str):
                why = taken
                failed.append((k, why))
                recorder.step("no_reading", f"pose {k}: {why}", pose=k, reason=why)
                continue
            capture, signal, takes, name = taken
            r = float(reflectance_from_gray(signal, c, capture.shutter_s, capture.f_number, area, phi))
            readings.append(Reading(k, float(np.degrees(pose.phase_rad)), float(np.degrees(pose.theta_i_rad)),
                                    float(np.degrees(pose.theta_e_rad)), float(np.degrees(pose.beta_rad)), signal,
                                    capture.shutter_s, capture.f_number, phi, r, takes, name))
            recorder.step("reading", f"pose {k}: R = {r:.5g}", pose=k, reflectance=r)


def write_csv(path: Path, readings: list[Reading]) -> Path:
    """The goniometer CSV (docs/formats.md) of the commanded angles and the measured R."""
    lines = [",".join(CSV_COLUMNS)]
    lines += [f"{r.theta_i_deg:.10g},{r.theta_e_deg:.10g},{r.phase_deg:.10g},{r.reflectance:.8g}" for r in readings]
    Path(path).write_text("\n".join(lines) + "\n")
    return path


@dataclass(frozen=True)
class Goniometry(Result):
    """What the routine achieved (cell.report.result's verdict: `success`, the material fitted
    and written; `message`, why not; the device fault), the readings, the poses refused and
    failed [(pose, reason)], the material document written. measurement.json is to_json(), with
    `reason` (the message) as well."""

    SUCCEEDED: ClassVar[str] = "measured"
    NOT_REACHED: ClassVar[str] = "not_measured"

    task: str
    success: bool
    message: str
    poses: int = 0
    readings: tuple[Reading, ...] = ()
    refused: tuple[tuple[int, str], ...] = ()
    failed: tuple[tuple[int, str], ...] = ()
    material: dict[str, Any] | None = None
    material_file: str | None = None
    fault: dict[str, Any] | None = None
    cause: str | None = None

    @property
    def counters(self) -> dict[str, int]:
        return {"poses": self.poses, "readings": len(self.readings), "refused": len(self.refused),
                "failed": len(self.failed)}

    @property
    def measured_material(self) -> dict[str, Any]:
        """The material document of a successful measurement (ValueError on one that fitted none)."""
        return self._made(self.material, "material")

    def summary(self) -> dict[str, Any]:
        """--json's keys: the material's table and standard errors, what is unresolved."""
        if not self.material:
            return {}
        keys = ["phase_deg", "rho", "sigma1", "m1", "sigma2", "m2"]
        keys += [f"{k}_stderr" for k in keys[1:]] + ["unresolved"]
        return {k: self.material[k] for k in keys if k in self.material}

    def details(self) -> dict[str, Any]:
        return {"task": self.task, "poses": self.poses,
                "refused": [{"pose": k, "reason": r} for k, r in self.refused],
                "failed": [{"pose": k, "reason": r} for k, r in self.failed],
                "readings": [asdict(r) for r in self.readings], "material": self.material,
                "material_file": self.material_file}


def run(task: Task, out: str | Path, connect: Callable[[Scene], Devices], operator: Operator) -> Goniometry:
    """connect(scene) -> Devices of the sample's scene; the operator places the sample; every
    pose measured, the CSV fitted, out/material.yaml, goniometer.csv, fit.png, measurement.json,
    log.jsonl. GoalNotReached (exit 1) when a phase angle has too few readings to fit; DeviceFault
    after the safe stop (exit 3). Returns the Goniometry."""
    from cell.report.pictures import write_goniometer_fit
    from cell.planning.scene import build_scene

    out, sample = Path(out), task.calibration.sample
    gonio, staged = task.calibration.goniometer, sample_task(task)
    material = staged.part.material
    readings: list[Reading] = []
    refused: list[tuple[int, str]] = []
    failed: list[tuple[int, str]] = []
    doc: dict[str, Any] | None = None
    written: Path | None = None
    total = len(poses(staged))

    def result(reason: str, fault: dict[str, Any] | None) -> Goniometry:
        return Goniometry(str(task.path), doc is not None and not reason, reason, total, tuple(readings),
                          tuple(refused), tuple(failed), doc, str(written) if written else None, fault)

    with Recorder(out) as recorder, Ending(recorder, "no material", "measurement.json", result) as end:
        with end.session:
            pivot = np.round(np.asarray(task.lamp.rig.pivot_m), 4).tolist()
            operator.confirm("sample", f"take the part out; lay the flat sample of {material.name} (a disc of "
                                       f"{2e3 * sample.radius_m:g} mm) with its top face's centre at the lamp "
                                       f"rig's pivot {pivot} m, facing {list(sample.normal)}")
            recorder.step("setup", f"{total} poses: phase {[round(float(np.degrees(a)), 2) for a in gonio.phase_rad]} deg, "
                                   f"step {np.degrees(gonio.step_rad):g} deg, ti and te up to "
                                   f"{np.degrees(gonio.max_angle_rad):g} deg; lamp at {1e3 * gonio.lamp_radius_m:g} mm")
            end.session.devices = connect(build_scene(staged))
            measure_poses(staged, end.session.devices, recorder, material.at, readings, refused, failed)
        csv = write_csv(out / "goniometer.csv", readings)
        short = [f"{np.degrees(a):g}" for a in gonio.phase_rad
                 if sum(abs(r.phase_deg - np.degrees(a)) < 1e-9 for r in readings) < MIN_ROWS]
        if short:
            raise GoalNotReached(f"fewer than {MIN_ROWS} readings at phase {', '.join(short)} deg "
                                 f"({len(refused)} of {total} poses refused, {len(failed)} without a reading): "
                                 "a finer step_deg, or a lamp radius and camera distance the arm can reach", "too_few_readings")
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        source = (f"measured by cell measure-brdf {task.path.name} on {stamp}: the cell as a goniometer, "
                  f"{len(readings)} poses ({len(refused)} refused, {len(failed)} without a reading) in the "
                  f"plane of incidence, step {np.degrees(gonio.step_rad):g} deg, ti and te up to "
                  f"{np.degrees(gonio.max_angle_rad):g} deg; R by eq. (17)-(19) with c "
                  f"{task.camera.sensor.camera_constant:.5g}; fitted per phase angle (cell.physics.brdf_fit, F-test p < "
                  f"{SIGNIFICANCE:g}); run folder {out}")
        fitted = fit_goniometer(read_goniometer(csv), f"{material.name} (measured)", source)
        doc, unresolved = fitted.material, fitted.unresolved
        written = out / "material.yaml"
        write_yaml(written, doc, inline_lists=True)
        write_goniometer_fit(out / "fit.png", readings, load_material(written))   # what tasks will read: checked now
        notes = "; ".join(f"{t} unresolved at phase {', '.join(f'{p:g}' for p in ps)} deg" for t, ps in unresolved.items())
        recorder.step("done", f"{len(readings)} readings fitted; wrote {written}" + (f"; {notes}" if notes else ""),
                      material_file=str(written), unresolved=unresolved)
    return end.result
