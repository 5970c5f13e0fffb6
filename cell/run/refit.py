"""Refit the material in the closed loop: when a capture's shape disagrees with the
model (control's `spread`), probe shots with the lamp tilted PROBE_TILT either way from the plan,
then fit the material's scale and shape and the black level to every captured pixel.

One capture's pixels lie almost on one (ti, te, alpha) curve, so it measures the level and one
shape number; captures with the lamp tilted a few degrees apart add independent curves. Each
pixel of the feature region gets its (ti, te, alpha) and its irradiance from the model's geometry
at the read-back poses (its ray cast into the task's mesh, kernels.render, lit like the planner
lights it), and

    G = b + (t / kappa^2) E R(ti, te, alpha; a rho, f1 sigma1, g1 m1, f2 sigma2, g2 m2)     (eq. 6-7, 10)

with E the signal per unit exposure and unit R (the model's gray of a unit-diffuse surface over
cos ti) and rho, sigma_k, m_k the task's table at the pixel's phase angle. The factors (their
logarithms) and b are fitted by nonlinear least squares (scipy.optimize.least_squares) over the
unsaturated pixels the model lights, standard errors from the Jacobian (cell.physics.brdf_fit.standard_errors).
A parameter whose relative standard error exceeds RELATIVE_STDERR_MAX (b: BLACK_STDERR_MAX gray)
is not determined by the data: the worst is fixed at the task's value and the rest refitted, until
every free one is determined; the fixed ones are reported as unknown, never invented.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import optimize

from cell.core import geometry
from cell.collision.scene import CollisionScene, reaching_joints

from cell.physics import projection
from cell.run import motion
from cell.run.acquisition import acquire
from cell.devices.interfaces import speaking_for
from cell.core.errors import GoalNotReached
from cell.physics.brdf_fit import standard_errors
from cell.physics.material import PARAMETERS, BrdfParameters, Material
from cell.physics.brdf import brdf_terms, reflectance, reflectance_jacobian
from cell.devices.rig import lamp_aim, lamp_position
from cell.planning.lights import drive_level

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.report.recorder import Recorder
    from cell.run.context import RunContext
    from cell.run.measurement import BlackLevel, Measurement
    from cell.task.types import Task

LampPose = tuple[np.ndarray, np.ndarray]    # the lamp's position and aim in the cell frame
Pixels = dict[str, np.ndarray]              # the Observations' pixels stacked: gray, irradiance, cosines, exposure

NAMES = PARAMETERS + ("black_level",)
BLACK = len(PARAMETERS)                 # index of b among NAMES
SPIKE = (3, 4)                          # sigma2, m2: fitted only where the data resolve them, so
                                        # given up first when anything is not determined
PROBE_TILT = np.radians(5.0)            # the probes' lamp tilt either way from the plan's
PROBE_TARGET = 0.7                      # the probe's brightest pixel expected at this fraction of
                                        # the sensor's signal range (room for the model's error)
RELATIVE_STDERR_MAX = 0.5               # a factor's stderr beyond this: not determined
BLACK_STDERR_MAX = 1.0                  # gray: a black level known worse than one level is not
LN_FACTOR_MAX = np.log(100.0)           # factors within x0.01-x100 of the task's table
M1_GRID = np.linspace(np.log(0.125), np.log(8.0), 25)   # the lobe exponent's factor: start grid
RESIDUAL_MAX = 0.03                     # rms residual / median signal the refit must reach to
                                        # explain the captures (a lamp off its aim does not fit)
UNIT_DIFFUSE = np.array([[0.0, 1.0, 0.0, 1.0, 0.0, 2.0]])   # Material.table() of R = cos ti


@dataclass(frozen=True)
class Observation:
    """One capture's usable feature pixels: gray, exposure t / kappa^2 [s], the signal per unit
    exposure and unit reflectance E, and the cosines of ti, te, alpha; with its name, the lamp
    joints read back [rad, rad, m] and the region's gray range (for the pictures)."""

    name: str
    joints: tuple[float, float, float]
    exposure: float
    gray: np.ndarray
    irradiance: np.ndarray
    cos_i: np.ndarray
    cos_e: np.ndarray
    cos_alpha: np.ndarray
    gray_range: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        pan, tilt, radius = self.joints
        return {"capture": self.name, "pan_deg": float(np.degrees(pan)), "tilt_deg": float(np.degrees(tilt)),
                "radius_m": float(radius), "exposure_s": self.exposure, "pixels": int(self.gray.size),
                "measured_gray": self.gray_range}


def pixel_geometry(task: Task, scene: Scene, T_cell_cam: np.ndarray, region: np.ndarray, lamp_pos: np.ndarray,
                   lamp_aim: np.ndarray, shift_px: tuple[float, float] = (0.0, 0.0),
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lit, E, cos ti, cos te, cos alpha) of the region's pixels (row-major, as image[region]):
    each pixel's ray, less the shift registration found (where the model sees what the pixel
    shows), cast into the model's mesh from the camera pose, shaded unit-diffuse with the
    planner's lamp (kernels.render: its cone and profile, cast shadows), E = that gray per
    exposure / cos ti; `lit` marks the pixels the model lights (the others have no E)."""
    from kernels.render import render
    rows, cols = np.nonzero(region)
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    dx, dy = shift_px
    local = np.column_stack([cols - dx, rows - dy, np.ones(rows.size)]) @ np.linalg.inv(K).T
    dirs = geometry.unit(geometry.rotate(T_cell_cam, local))
    origin = T_cell_cam[:3, 3]
    r = render(scene.shadow_mesh, origin, dirs, lamp_pos, lamp_aim, task.lamp.power_w, task.lamp.cone_angle_rad,
               UNIT_DIFFUSE, task.camera.sensor.camera_constant, task.camera.sensor.pixel_area_m2,
               profile=task.lamp.profile, part_faces=len(scene.faces))
    point = origin + np.where(r.hit, r.depth, 0.0)[:, None] * dirs
    s, v = geometry.unit(lamp_pos - point), geometry.unit(origin - point)
    cos_i, cos_e = np.einsum("nj,nj->n", r.normal, s), np.einsum("nj,nj->n", r.normal, v)
    cos_alpha = np.clip(np.einsum("nj,nj->n", s, v), -1.0, 1.0)
    lit = r.hit & (r.value > 0) & (cos_i > 0) & (cos_e > 0)
    return lit, np.where(lit, r.value / np.where(lit, cos_i, 1.0), 0.0), cos_i, cos_e, cos_alpha


def observe(task: Task, scene: Scene, name: str, gray: np.ndarray, T_cell_cam: np.ndarray, lamp: LampPose,
            joints: tuple[float, float, float], shutter_s: float, f_number: float, region: np.ndarray,
            saturation: float, shift_px: tuple[float, float] = (0.0, 0.0)) -> Observation:
    """The Observation of a capture's region pixels `gray` (image[region]) taken with the lamp at
    lamp = (position, aim) and joints, the feature found shift_px from where the model puts it:
    the pixels the model lights and the sensor resolves (below saturation)."""
    lit, e, ci, ce, ca = pixel_geometry(task, scene, T_cell_cam, region, *lamp, shift_px)
    gray = np.asarray(gray, float)
    keep = lit & (gray < saturation)
    stats = {"min": float(gray.min()), "max": float(gray.max()), "mean": float(gray.mean())}
    pan, tilt, radius = joints
    return Observation(name, (float(pan), float(tilt), float(radius)), shutter_s / f_number**2, gray[keep], e[keep],
                       ci[keep], ce[keep], ca[keep], stats)


@dataclass(frozen=True)
class Refit:
    """A refit: per parameter of NAMES the factor on the task's table (b: its value) and its
    stderr (relative for a factor, gray for b), the parameters the data did not determine (kept
    at the task's / the loop's values), the condition number of the column-scaled Jacobian of the
    free parameters (and of all of them), the rms residual [gray] and the refitted material."""

    factors: np.ndarray
    stderr: np.ndarray
    unknown: tuple[str, ...]
    condition_number: float
    condition_number_all: float
    rms_residual: float
    median_signal: float
    observations: tuple[Observation, ...]
    material: Material
    phase_deg: tuple[float, float, float]   # the captures' phase angles: least, median, most

    @property
    def explains(self) -> bool:
        """Whether the refitted material explains the captures to RESIDUAL_MAX of their signal."""
        return self.rms_residual <= RESIDUAL_MAX * self.median_signal

    @property
    def determined_shape(self) -> list[str]:
        """The shape parameters (lobe, spike) the data determined."""
        return [n for n in NAMES[1:BLACK] if n not in self.unknown]

    def value(self, name: str) -> float:
        """A parameter's refitted value at the captures' median phase angle (b: its value)."""
        if name == "black_level":
            return float(self.factors[BLACK])
        return float(np.interp(np.radians(self.phase_deg[1]), self.material.phase_rad, getattr(self.material, name)))

    def to_json(self) -> dict[str, Any]:
        parameters = {}
        for i, n in enumerate(NAMES):
            known = n not in self.unknown
            value = self.value(n)
            stderr = (self.stderr[i] if i == BLACK else self.stderr[i] * value) if known else None
            parameters[n] = {"value": value, "stderr": None if stderr is None else float(stderr),
                             "relative_stderr": (float(self.stderr[i]) if i != BLACK else None) if known else None,
                             "determined": known} | ({"factor": float(self.factors[i])} if i != BLACK else {})
        return {"captures": [o.name for o in self.observations], "shots": [o.to_json() for o in self.observations],
                "pixels": int(sum(o.gray.size for o in self.observations)),
                "phase_deg": [self.phase_deg[0], self.phase_deg[2]], "parameters": parameters,
                "unknown": list(self.unknown), "condition_number": self.condition_number,
                "condition_number_all": self.condition_number_all, "rms_residual": self.rms_residual,
                "median_signal": self.median_signal, "explains": self.explains}

    def summary(self) -> str:
        """One line: the values with their stderr, what stayed unknown, the condition number."""
        parts = []
        for i, n in enumerate(NAMES):
            if n in self.unknown:
                continue
            if i == BLACK:
                parts.append(f"black level {self.factors[i]:.2f} +- {self.stderr[i]:.2f}")
            else:
                parts.append(f"{n} {self.value(n):.4g} +- {100 * self.stderr[i]:.2g} % (x{self.factors[i]:.3g})")
        unknown = (f"; not determined (kept as they were): {', '.join(self.unknown)}" if self.unknown else "")
        pixels = sum(o.gray.size for o in self.observations)
        return (f"refit from {len(self.observations)} captures ({pixels} px, phase {self.phase_deg[0]:.1f}-"
                f"{self.phase_deg[2]:.1f} deg): {', '.join(parts)}{unknown}; condition number "
                f"{self.condition_number:.3g}, rms residual {self.rms_residual:.2f} gray")


def _model(x: np.ndarray, obs: Pixels, base: BrdfParameters) -> tuple[np.ndarray, np.ndarray]:
    """(predicted gray, Jacobian by x = (ln factors of PARAMETERS, b)) over the stacked pixels."""
    factors = np.exp(np.clip(x[:BLACK], -LN_FACTOR_MAX, LN_FACTOR_MAX))
    p = [getattr(base, n) * f for n, f in zip(PARAMETERS, factors)]
    scale = obs["exposure"] * obs["irradiance"]
    geometry_ = (obs["cos_i"], obs["cos_e"], obs["cos_alpha"])
    gray = x[BLACK] + scale * reflectance(*geometry_, *p)
    inside = np.abs(x[:BLACK]) < LN_FACTOR_MAX                   # a clipped factor does not move
    jac = reflectance_jacobian(*geometry_, *p) * np.column_stack(p) * (scale[:, None] * inside)
    return gray, np.column_stack([jac, np.ones(gray.size)])


def _grid_start(obs: Pixels, base: BrdfParameters, black_level: float) -> np.ndarray:
    """Fit vector to start from: for each lobe-exponent factor of M1_GRID (the spike's held), G is
    linear in (b, a, a f1, a f2) (eq. 6 times the exposure), solved by linear least squares; the
    grid point of least RSS with positive factors."""
    scale = obs["exposure"] * obs["irradiance"] * base.rho
    best: tuple[float, np.ndarray | None] = (np.inf, None)
    for g in M1_GRID:
        terms = brdf_terms(obs["cos_i"], obs["cos_e"], obs["cos_alpha"], base.sigma1, base.m1 * np.exp(g),
                           base.sigma2, base.m2)
        a = np.column_stack([np.ones(scale.size)] + [scale * t for t in terms])
        coef, rss, *_ = np.linalg.lstsq(a, obs["gray"], rcond=None)
        if coef[1] > 0 and np.all(coef[2:] > 0) and rss.size and rss[0] < best[0]:
            best = (rss[0], np.array([np.log(coef[1]), *np.log(coef[2:3] / coef[1]), g,
                                      *np.log(coef[3:] / coef[1]), 0.0, coef[0]]))
    if best[1] is None:
        x = np.zeros(len(NAMES))
        x[BLACK] = black_level
        return x
    return np.clip(best[1], [-LN_FACTOR_MAX] * BLACK + [-np.inf], [LN_FACTOR_MAX] * BLACK + [np.inf])


def _solve(x0: np.ndarray, free: list[int], obs: Pixels, base: BrdfParameters) -> tuple[np.ndarray, float]:
    """Least squares (MINPACK's Levenberg-Marquardt: the Jacobian's QR, fast on tens of thousands
    of pixels) over the free entries of x from x0, the others held."""
    memo: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def model(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = z.tobytes()
        if key not in memo:
            x = x0.copy()
            x[free] = z
            memo.clear()
            memo[key] = _model(x, obs, base)
        return memo[key]

    best = optimize.least_squares(lambda z: model(z)[0] - obs["gray"], x0[free],
                                  jac=lambda z: model(z)[1][:, free], method="lm", x_scale="jac")
    x = x0.copy()
    x[free] = best.x
    return x, 2.0 * best.cost


def _condition(jac: np.ndarray) -> float:
    """Condition number of the Jacobian with unit columns (inf with a zero column)."""
    norms = np.linalg.norm(jac, axis=0)
    if np.any(norms == 0):
        return float("inf")
    s = np.linalg.svd(jac / norms, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def fit(observations: Sequence[Observation], material: Material, black_level: float) -> Refit:
    """The Refit of `material` (the task's table; its shape kept where the data do not tell) and
    the black level (the loop's b where they do not) to the Observations."""
    obs = {k: np.concatenate([getattr(o, k) for o in observations])
           for k in ("gray", "irradiance", "cos_i", "cos_e", "cos_alpha")}
    obs["exposure"] = np.concatenate([np.full(o.gray.size, o.exposure) for o in observations])
    alpha = np.arccos(obs["cos_alpha"])
    base = material.at(alpha)
    x = _grid_start(obs, base, black_level)
    free, unknown, n = list(range(len(NAMES))), [], obs["gray"].size
    condition_all = None
    while True:
        x, rss = _solve(x, free, obs, base)
        jac = _model(x, obs, base)[1][:, free]
        condition = _condition(jac)
        condition_all = condition if condition_all is None else condition_all
        se = standard_errors(jac, rss, max(n - len(free), 1))
        limit = np.array([BLACK_STDERR_MAX if i == BLACK else RELATIVE_STDERR_MAX for i in free])
        if np.all(se <= limit):
            break
        worst = max(np.flatnonzero(se > limit), key=lambda j: (free[j] in SPIKE, se[j] / limit[j]))
        unknown.append(free.pop(worst))
        x[unknown[-1]] = black_level if unknown[-1] == BLACK else 0.0
        if not free:
            se = np.zeros(0)
            break
    stderr = np.full(len(NAMES), np.inf)
    stderr[free] = se
    factors = np.concatenate([np.exp(x[:BLACK]), x[BLACK:]])
    rho, sigma1, m1, sigma2, m2 = (getattr(material, p) * f for p, f in zip(PARAMETERS, factors[:BLACK]))
    refitted = Material(f"{material.name}, refit in the loop", "", material.phase_rad, rho, sigma1, m1, sigma2, m2,
                        unresolved=material.unresolved)   # what the goniometer could not resolve stays so
    predicted = _model(x, obs, base)[0]
    least, median, most = (float(v) for v in np.degrees(np.percentile(alpha, [0, 50, 100])))
    return Refit(factors, stderr, tuple(NAMES[i] for i in sorted(unknown)), condition, condition_all,
                 float(np.sqrt(np.mean((predicted - obs["gray"]) ** 2))), float(np.median(obs["gray"] - x[BLACK])),
                 tuple(observations), refitted, (least, median, most))


def probe_joints(joints: tuple[float, float, float],
                 tilt_range: tuple[float, float]) -> list[tuple[float, float, float]]:
    """The probes' lamp joints: the tilt PROBE_TILT below and above the plan's, within the rig's
    range (a probe the range would put on the plan's own tilt is left out)."""
    pan, tilt, radius = joints
    tilts = np.clip([tilt - PROBE_TILT, tilt + PROBE_TILT], *tilt_range)
    return [(pan, float(t), radius) for t in tilts if abs(t - tilt) > 0.2 * PROBE_TILT]


def clear_probes(task: Task, T_cell_cam: np.ndarray, arm_joints: np.ndarray | None,
                 probes: Sequence[tuple[float, float, float]]
                 ) -> tuple[list[tuple[float, float, float]], list[tuple[tuple[float, float, float], str]]]:
    """The probes whose lamp pose the collision check clears with the camera at T_cell_cam and the
    arm at arm_joints (CollisionScene.clearance; None: where
    the inverse kinematics puts it, reaching_joints), and for each one left out the refusal's reason: a
    probe tilted towards the camera can bring the lamp within the padding of the camera's body
    where the plan's own tilt keeps it; the refit goes on with the probes that are clear."""
    bodies, arm = CollisionScene.of(task), reaching_joints(task.frames, T_cell_cam, arm_joints)
    kept, refused = [], []
    for joints in probes:
        c = bodies.clearance(T_cell_cam, arm, lamp_position(task.lamp.rig.pivot_m, *joints))
        if c.ok:
            kept.append(joints)
        else:
            refused.append((joints, c.reason()))
    return kept, refused


@dataclass(frozen=True)
class Disagreement:
    """The capture whose shape disagreed with the model: its iteration k, its Measurement, its
    exposure (shutter_s, f_number, focus_m), the shift (dx, dy) [px] registration found the
    feature at, the black level and albedo scale the loop measured it with, and the light
    channels' levels it was taken at (None: every light at full)."""

    iteration: int
    measurement: Measurement
    exposure: tuple[float, float, float]
    black: BlackLevel
    albedo_scale: float
    shift_px: tuple[float, float]
    drives: Mapping[int, float] | None = None


def other_lights_on(task: Task, drives: Mapping[int, float] | None) -> list[str]:
    """The names of the task's lights besides the spot that shine at these drives
    (cell.planning.lights.drive_level; a light on no channel always does)."""
    return [light.name for light in task.lights if drive_level(light.channel.number, drives) > 0.0]


def probe_and_refit(ctx: RunContext, task: Task, scene: Scene, disagreement: Disagreement) -> Refit:
    """After the Disagreement's capture k (the lamp still at the plan's pose): probe shots at
    probe_joints through the loop's own acquisition path (a device fault exits 3), each exposed so
    that its brightest pixel is expected at PROBE_TARGET of the signal range (capture k's measured
    brightness times the model's ratio probe / capture k), then fit() to capture k and the probes,
    their pixels seen where registration found the feature. Logs each probe and the refit;
    returns the Refit. Refuses (GoalNotReached, cause material shape) before any probe when
    capture k was lit by lights besides the spot: the model fitted is the spot's alone and the
    probes tilt only it, so their light would be taken for the material's."""
    devices, recorder, k, m = ctx.devices, ctx.recorder, disagreement.iteration, disagreement.measurement
    others = other_lights_on(task, disagreement.drives)
    if others:
        raise GoalNotReached(f"the feature's gray disagrees with the model's shape, but capture {k} was lit by "
                             f"{', '.join(others)} besides the spot, and the refit models the spot alone: no "
                             f"material is fitted to captures lit by other lights", "material shape")
    saturation, b, shift_px, region = m.saturation, disagreement.black.value, disagreement.shift_px, m.region
    assert region is not None, "one feature's own Measurement has its region (only a joined one has none)"
    shutter_s, f_number, focus_m = disagreement.exposure
    material = task.part.material.scaled(disagreement.albedo_scale)
    with speaking_for(devices.lamp):
        plan_joints, plan_lamp = devices.lamp.joints(), devices.lamp.lamp_pose()
    with speaking_for(devices.arm):
        T_cell_cam = devices.arm.camera_pose()
    disagreed = observe(task, scene, f"capture-{k}.png", m.gray, T_cell_cam, plan_lamp, plan_joints,
                        shutter_s, f_number, region, saturation, shift_px)

    def brightest(lamp: LampPose) -> float:
        lit, e, ci, ce, ca = pixel_geometry(task, scene, T_cell_cam, region, *lamp, shift_px)
        p = material.at(np.arccos(ca[lit]))
        return float(np.max(e[lit] * reflectance(ci[lit], ce[lit], ca[lit], p.rho, p.sigma1, p.m1, p.sigma2, p.m2),
                            initial=0.0))

    measured = (float(np.max(m.gray)) - b) / (shutter_s / f_number**2)
    planned = brightest(plan_lamp)
    observations = [disagreed]
    with speaking_for(devices.arm):
        arm_joints = devices.arm.joint_angles()
    probes, refused = clear_probes(task, T_cell_cam, arm_joints, probe_joints(plan_joints, task.lamp.rig.tilt_range_rad))
    for joints, reason in refused:
        recorder.step("probe", f"the probe at tilt {np.degrees(joints[1] - plan_joints[1]):+.1f} deg left out: {reason}",
                      iteration=k)
    for j, joints in enumerate(probes, 1):
        position = lamp_position(task.lamp.rig.pivot_m, *joints)
        expected = brightest((position, lamp_aim(task.lamp.rig.pivot_m, position))) * measured / max(planned, 1e-300)
        shutter = float(np.clip(PROBE_TARGET * (saturation - b) / max(expected, 1e-300) * f_number**2,
                                *task.camera.shutter_range_s))
        read = motion.move_lamp(task, devices, joints, recorder, k, why=f"probe {j} of {len(probes)}, tilt "
                                                             f"{np.degrees(joints[1] - plan_joints[1]):+.1f} deg: ")
        capture = acquire(devices, recorder, k, shutter, f_number, focus_m, name=f"capture-{k}-probe-{j}")
        image = np.asarray(capture.image, float)
        with speaking_for(devices.lamp):
            lamp = devices.lamp.lamp_pose()
        o = observe(task, scene, capture.name, image[region], capture.T_cell_cam, lamp, read,
                    capture.shutter_s, f_number, region, saturation, shift_px)
        g = o.gray_range
        recorder.step("probe", f"probe {j}: gray {g['min']:.1f}-{g['max']:.1f} over the feature, {o.gray.size} px "
                               f"usable", iteration=k, **o.to_json())
        observations.append(o)
    usable = sum(o.gray.size for o in observations)
    if usable <= len(NAMES):
        raise GoalNotReached(f"the feature's gray disagrees with the model's shape, but the probe shots left "
                             f"{usable} usable pixels (lit by the model, below saturation): nothing to refit", "material shape")
    refit = fit(observations, task.part.material, b)
    recorder.step("refit", refit.summary(), iteration=k, **refit.to_json())
    return refit


def material_document(refit: Refit, name: str, source: str) -> dict[str, Any]:
    """The refitted material as a material file's keys (docs/formats.md, "Material"): the task's
    table times the factors, the stderr of each parameter (.inf where not determined, a zero
    entry's too) and the task's `unresolved` section, if any (a refit resolves no spike)."""
    mat = refit.material
    doc: dict[str, Any] = {"name": name, "source": source,
                           "phase_deg": [round(float(a), 6) for a in np.degrees(mat.phase_rad)]}
    for p in PARAMETERS:
        doc[p] = [float(f"{v:.6g}") for v in getattr(mat, p)]
    for i, p in enumerate(PARAMETERS):
        known = np.isfinite(refit.stderr[i])
        doc[f"{p}_stderr"] = [float(f"{v * refit.stderr[i]:.3g}") if known else float("inf") for v in getattr(mat, p)]
    if mat.unresolved is not None:
        u = mat.unresolved
        doc["unresolved"] = {"terms": {t: [round(float(np.degrees(a)), 6) for a in phases] for t, phases in u.terms.items()},
                             "step_deg": float(f"{np.degrees(u.step_rad):.6g}"),
                             "resolvable_m_max": float(f"{u.resolvable_m_max:.6g}")}
    return doc


def keep(refit: Refit, task: Task, recorder: Recorder, k: int) -> str:
    """Write the refitted material as refit-k-material.yaml in the run folder (a file the user can
    keep and name as part.material); returns its name."""
    from datetime import date

    from cell.core.files import write_yaml
    captures = ", ".join(o.name for o in refit.observations)
    source = (f"refit in the closed loop of cell run {task.path} on {date.today().isoformat()}: the factors and "
              f"the black level of G = b + (t / kappa^2) E R fitted to {sum(o.gray.size for o in refit.observations)} "
              f"pixels of {captures} (phase {refit.phase_deg[0]:.1f}-{refit.phase_deg[2]:.1f} deg), on the "
              f"table of {task.part.material.name!r}; condition number {refit.condition_number:.3g}"
              + (f"; not determined, kept as the task's: {', '.join(refit.unknown)}" if refit.unknown else ""))
    name = f"refit-{k}-material.yaml"
    document = material_document(refit, f"{task.part.material.name} (refit)", source)
    write_yaml(recorder.folder / name, document, inline_lists=True)
    return name


def require_usable(refit: Refit, spread_reason: str) -> None:
    """A refit the loop can re-plan with: it explains the captures (rms residual within
    RESIDUAL_MAX of the signal) and determined a shape parameter; else GoalNotReached saying why
    (the shape disagreement's reason first)."""
    if not refit.explains:
        raise GoalNotReached(f"{spread_reason}; {refit.summary()}: the refitted material does not explain the "
                             f"captures either (rms residual {refit.rms_residual:.2f} gray > {100 * RESIDUAL_MAX:g} % "
                             f"of the signal {refit.median_signal:.1f}), so the material is not the cause: check the "
                             f"lamp's aim and shadows on the feature", "lamp aim")
    if not refit.determined_shape:
        raise GoalNotReached(f"{spread_reason}; {refit.summary()}: the captures determine none of the lobe's and "
                             f"spike's parameters, so there is nothing to re-plan with", "material shape")


def task_with(task: Task, refit: Refit) -> Task:
    """The task with the refitted material (the planner's and every later re-plan's)."""
    return replace(task, part=replace(task.part, material=refit.material))
