"""Illumination and sensor planning (sec. 5): lamp pose on the rig, shutter, f-number and focus.

Global search over the rig's reachable candidates with the bulk Warp kernels, then Nelder-Mead
refinement from several starts (the problem is not convex, physics notes sec. 5). Shutter and
f-number follow the near closed form G ~ t / kappa^2 for every lamp pose (sec. 5.4).
Feasibility is max_i f_i <= 1 over the requirement values (erratum eq. 25).
"""
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize

from cell import geometry, regions, rig
from cell.physics import costs, depth_of_field as dof

# Requirement order in the value arrays below; names appear in plan.json.
REQUIREMENTS = ("gray_min", "gray_max", "reflection_region", "lamp_tolerance", "no_shadow",
                "cone_coverage", "camera_view", "shutter_min", "shutter_max", "f_number_min",
                "f_number_max", "depth_of_field")


@dataclass(frozen=True)
class PlannerSettings:
    """Resolution knobs (what accuracy costs in time: `cell bench` sweeps them)."""

    grid_step_deg: float = 2.0      # visibility / region map cell size
    pan_step_deg: float = 10.0      # global candidate grid on the rig
    tilt_step_deg: float = 5.0
    radius_steps: int = 6
    samples: int | None = None      # feature samples (None: the task's)
    refine: bool = True             # Nelder-Mead from the best starts
    starts: int = 4


@dataclass(frozen=True)
class Exposure:
    shutter_s: float
    f_number: float
    focus_m: float
    depth_of_field_m: float


@dataclass(frozen=True)
class Maps:
    """The paper's spherical maps in the feature frame (sec. 2.2, 5.2), for pictures and tests."""

    grid: regions.SphereGrid
    visible: np.ndarray          # (E, A) every sample sees this direction
    reflectance: np.ndarray      # (E, A) R at the feature centre for a lamp there
    dominant: np.ndarray         # (E, A) dominant term, brdf.OCCLUDED behind
    wanted: np.ndarray           # (E, A) wanted reflection and visible
    distance: np.ndarray         # (E, A) signed haversine distance to the wanted region [rad]
    candidate_pan: np.ndarray    # (C,) global candidates [rad]
    candidate_tilt: np.ndarray
    candidate_objective: np.ndarray


@dataclass
class Plan:
    """A plan with its verdict, like scipy's OptimizeResult: feasible, binding, each requirement."""

    task_name: str
    feasible: bool
    binding: str
    miss: float
    objective: float
    requirements: list
    joints: tuple                # (pan, tilt, radius) [rad, rad, m]
    lamp_position: np.ndarray
    exposure: Exposure
    gray: np.ndarray             # predicted gray per feature sample
    distance_m: float            # lamp -> feature centre
    phase_angle_rad: float       # between lamp and camera, at the feature centre
    camera_position: np.ndarray
    hint: str
    maps: Maps
    settings: PlannerSettings
    scene: object                # the Scene planned on (not serialized)
    timing_s: dict = field(default_factory=dict)

    def to_json(self):
        """plan.json per design.md's output contract."""
        pan, tilt, radius = self.joints
        return {
            "task": self.task_name,
            "feasible": self.feasible,
            "binding": self.binding,
            "miss": self.miss,
            "objective": self.objective,
            "hint": self.hint,
            "requirements": [{"name": r.name, "value": r.value, "met": r.met, "detail": r.detail}
                             for r in self.requirements],
            "lamp": {"position_m": self.lamp_position.tolist(), "distance_m": self.distance_m,
                     "phase_angle_deg": float(np.degrees(self.phase_angle_rad)),
                     "joints": {"pan_deg": float(np.degrees(pan)), "tilt_deg": float(np.degrees(tilt)),
                                "radius_m": float(radius)}},
            "camera": {"shutter_s": self.exposure.shutter_s, "f_number": self.exposure.f_number,
                       "focus_m": self.exposure.focus_m, "depth_of_field_m": self.exposure.depth_of_field_m,
                       "position_m": self.camera_position.tolist()},
            "predicted_gray": gray_stats(self.gray),
            "timing_s": self.timing_s,
            "settings": self.settings.__dict__,
        }


def gray_stats(gray):
    gray = np.asarray(gray, dtype=float)
    return {"mean": float(gray.mean()), "min": float(gray.min()), "max": float(gray.max())}


def depth_of_field_limits(task, scene):
    """(focus [m], depth of field needed [m], widest f-number giving it within the lens's range)
    for the camera focused on the feature centre (sec. 4.3, 5.4): the needed depth is the larger
    of the task's and the feature samples' own depth range."""
    lens = task.camera.lens
    focus = float(np.linalg.norm(scene.camera_position - scene.center))
    depths = scene.sample_depths()
    needed = max(task.requirements.depth_of_field_m, float(depths.max() - depths.min()))
    kappa = dof.f_number_for_depth(focus, lens.focal_length_m, lens.circle_of_confusion_m, needed)
    # rounded up by 1e-9 so that the depth of field is met despite floating-point rounding
    return focus, needed, float(np.clip(kappa * (1 + 1e-9), *lens.f_number_range))


class Evaluator:
    """Requirement values for lamp poses on the rig, vectorized over candidates."""

    def __init__(self, task, scene, maps, albedo_scale=1.0):
        self.task, self.scene, self.maps = task, scene, maps
        self.material = task.part.material.scaled(albedo_scale)
        self.low, self.high = map(float, task.requirements.gray_band)
        self.focus, self.depth_needed, self.kappa_open = depth_of_field_limits(task, scene)
        self.camera_unseen = int(self.bulk(scene.camera_position[None], -scene.normal[None])[1].sum())

    def bulk(self, positions, aims):
        """(gray per exposure (C, P), shadowed (C, P), off-axis angle (C, P)) from the Warp kernel."""
        from kernels.gray import gray_per_exposure
        task = self.task
        out = gray_per_exposure(
            self.scene.warp_mesh, self.scene.points, self.scene.normals, self.scene.camera_position,
            positions, aims, task.lamp.power_w, task.lamp.cone_angle_rad, self.material.table(),
            task.camera.sensor.camera_constant, task.camera.sensor.pixel_area_m2)
        return out.value, out.shadowed, out.off_axis

    def exposure(self, unit_gray):
        """Shutter and f-number putting the geometric mean of the lit samples' gray at the band's
        geometric centre (G = u t / kappa^2), f-number no wider than the depth of field allows."""
        cam = self.task.camera
        lit = unit_gray > 0.0
        darkest = np.where(lit, unit_gray, np.inf).min(axis=-1)
        u_mid = np.where(lit.any(axis=-1), np.sqrt(np.where(lit.any(axis=-1), darkest, 0.0)
                                                   * unit_gray.max(axis=-1)), 0.0)
        target = np.sqrt(self.low * self.high)
        t_lo, t_hi = cam.shutter_range_s
        k_lo, k_hi = cam.lens.f_number_range
        with np.errstate(divide="ignore"):
            t_need = np.where(u_mid > 0, self.kappa_open**2 * target / np.where(u_mid > 0, u_mid, 1.0), np.inf)
        kappa = np.where(t_need < t_lo, np.sqrt(t_lo * u_mid / target), self.kappa_open)
        kappa = np.clip(kappa, self.kappa_open, k_hi)
        shutter = np.clip(t_need, t_lo, t_hi)
        return shutter, kappa, t_need

    def values(self, pan, tilt, radius, tolerance=True):
        """Requirement values (C, len(REQUIREMENTS)) and details for lamp joints (C,) arrays.
        With `tolerance` the lamp is also moved by lamp_tolerance in 4 directions (one bulk call
        for all); without it the lamp_tolerance column is 0 (global stage)."""
        task, rig_ = self.task, self.task.lamp.rig
        pan, tilt, radius = np.broadcast_arrays(*(np.atleast_1d(np.asarray(x, float)) for x in (pan, tilt, radius)))
        n = len(pan)
        moves = self.tolerance_moves(tilt) if tolerance else []
        all_pan = np.concatenate([pan] + [pan + dp for dp, _ in moves])
        all_tilt = np.concatenate([tilt] + [tilt + dt for _, dt in moves])
        all_pos = rig.lamp_position(rig_.pivot_m, all_pan, all_tilt, np.tile(radius, len(moves) + 1))
        all_u, all_shadowed, all_off_axis = self.bulk(all_pos, rig.lamp_aim(rig_.pivot_m, all_pos))
        pos, u, shadowed, off_axis = all_pos[:n], all_u[:n], all_shadowed[:n], all_off_axis[:n]
        shutter, kappa, t_need = self.exposure(u)
        gain = (shutter / kappa**2)[:, None]
        gray = u * gain
        v = np.zeros((n, len(REQUIREMENTS)))
        v[:, 0] = costs.f_min(np.min(gray, axis=-1), self.low)
        v[:, 1] = costs.f_max(np.max(gray, axis=-1), self.high)
        v[:, 2] = self.region_cost(pos)
        for k in range(1, len(moves) + 1):
            moved = all_u[k * n:(k + 1) * n] * gain
            v[:, 3] = np.maximum(v[:, 3], np.maximum(costs.f_min(moved.min(axis=-1), self.low),
                                                     costs.f_max(moved.max(axis=-1), self.high)))
        v[:, 4] = costs.count_cost(shadowed.sum(axis=-1))
        v[:, 5] = costs.f_max(np.max(off_axis, axis=-1), 0.5 * task.lamp.cone_angle_rad)
        v[:, 6] = costs.count_cost(self.camera_unseen)
        t_lo, t_hi = task.camera.shutter_range_s
        k_lo, k_hi = task.camera.lens.f_number_range
        v[:, 7] = costs.f_min(shutter, t_lo)
        # no sample lit: no shutter helps; value e marks the miss and leaves the cause (shadow,
        # cone, facing away) to bind
        v[:, 8] = costs.f_max(np.where(np.isfinite(t_need), t_need, 2.0 * t_hi), t_hi)
        v[:, 9] = costs.f_min(kappa, k_lo)
        v[:, 10] = costs.f_max(kappa, k_hi)
        lens = task.camera.lens
        depth = dof.depth_of_field(self.focus, lens.focal_length_m, kappa, lens.circle_of_confusion_m)
        v[:, 11] = costs.f_min(np.minimum(depth, 1e3), self.depth_needed) if self.depth_needed > 0 else 0.0
        return v, {"gray": gray, "shutter": shutter, "kappa": kappa, "t_need": t_need, "position": pos,
                   "shadowed": shadowed}

    def tolerance_moves(self, tilt):
        """(d_pan, d_tilt) moving the lamp direction by lamp_tolerance along pan and tilt."""
        tol = self.task.requirements.lamp_tolerance_rad
        if tol <= 0:
            return []
        dpan = tol / np.maximum(np.cos(tilt), 1e-3)
        return [(dpan, 0.0), (-dpan, 0.0), (0.0, tol), (0.0, -tol)]

    def region_cost(self, positions):
        """exp(d / margin + 1): 1 at `margin` inside the wanted region (sec. 5.2)."""
        local = (positions - self.scene.center) @ self.scene.frame
        az, el = geometry.angles_from_direction(local)
        d = self.maps.grid.sample(self.maps.distance, az, el)
        margin = max(self.task.requirements.region_margin_rad, 1e-6)
        return np.exp(np.minimum(d / margin + 1.0, costs.EXP_LIMIT))


def objective(values):
    """Eq. (22) over the log-values ln f_i: a smooth max that the optimizer minimises."""
    return costs.log_sum_exp(np.log(np.maximum(values, 1e-300)), axis=-1)


def build_maps(task, scene, settings):
    """Visibility (all samples), BRDF, dominant-term and region distance maps (sec. 2.2, 5.2)."""
    from kernels.visibility import visibility_maps
    grid = regions.SphereGrid(np.radians(settings.grid_step_deg))
    visible = visibility_maps(scene.warp_mesh, scene.points, scene.normals, scene.frame,
                              grid.azimuth, grid.elevation).all(axis=0)
    view = geometry.unit(scene.camera_position - scene.center)
    material = task.part.material
    dominant = regions.dominant_term_map(grid, scene.frame, scene.normal, view, material)
    reflectance = regions.reflectance_map(grid, scene.frame, scene.normal, view, material)
    wanted = regions.wanted_region(dominant, visible, task.requirements.reflection)
    distance = regions.signed_distance(grid, wanted)
    empty = np.zeros(0)
    return Maps(grid, visible, reflectance, dominant, wanted, distance, empty, empty, empty)


def candidate_grid(lamp_rig, settings):
    """Pan x tilt x radius grid over the rig's ranges (pan wraps: no duplicate at +-180)."""
    p0, p1 = lamp_rig.pan_range_rad
    full_turn = p1 - p0 >= 2 * np.pi - 1e-9
    n_pan = max(1, int(round((p1 - p0) / np.radians(settings.pan_step_deg)))) + (0 if full_turn else 1)
    pan = np.linspace(p0, p1, n_pan, endpoint=not full_turn)
    t0, t1 = lamp_rig.tilt_range_rad
    tilt = np.linspace(t0, t1, max(2, int(round((t1 - t0) / np.radians(settings.tilt_step_deg))) + 1))
    radius = np.linspace(*lamp_rig.radius_range_m, max(1, settings.radius_steps))
    P, T, R = np.meshgrid(pan, tilt, radius, indexing="ij")
    return P.ravel(), T.ravel(), R.ravel()


def pick_starts(pan, tilt, objective_values, count, min_separation):
    """Best candidates that are at least `min_separation` apart on the sphere (diverse starts)."""
    order = np.argsort(objective_values)
    chosen = []
    dirs = geometry.direction_from_angles(pan, tilt)
    for k in order:
        if all(np.arccos(np.clip(dirs[k] @ dirs[j], -1, 1)) >= min_separation for j in chosen):
            chosen.append(k)
        if len(chosen) == count:
            break
    return chosen


def refine(evaluator, start, lamp_rig):
    """Nelder-Mead over (pan, tilt, radius) in grid-step units, clipped to the rig's ranges."""
    lo = np.array([lamp_rig.pan_range_rad[0], lamp_rig.tilt_range_rad[0], lamp_rig.radius_range_m[0]])
    hi = np.array([lamp_rig.pan_range_rad[1], lamp_rig.tilt_range_rad[1], lamp_rig.radius_range_m[1]])
    scale = np.array([np.radians(5.0), np.radians(5.0), 0.05])

    def clipped(z):
        return np.clip(np.asarray(start) + z * scale, lo, hi)

    def f(z):
        x = clipped(z)
        values, _ = evaluator.values(x[:1], x[1:2], x[2:3])
        return float(objective(values)[0])

    simplex = np.vstack([np.zeros(3), np.eye(3)])
    res = minimize(f, np.zeros(3), method="Nelder-Mead",
                   options={"initial_simplex": simplex, "xatol": 0.02, "fatol": 1e-4, "maxfev": 90})
    return clipped(res.x)


def plan(task, settings=PlannerSettings(), albedo_scale=1.0, progress=None):
    """Plan a task: the CLI, the closed loop and the benchmark all call this."""
    from cell.scene import build_scene
    say = progress or (lambda msg: None)
    timing = {}
    t0 = time.perf_counter()
    scene = build_scene(task, settings.samples)
    timing["scene"] = time.perf_counter() - t0

    t = time.perf_counter()
    maps = build_maps(task, scene, settings)
    timing["maps"] = time.perf_counter() - t
    say(f"maps: {maps.visible.mean():.0%} of directions visible, {maps.wanted.mean():.1%} give "
        f"{task.requirements.reflection} reflection")

    t = time.perf_counter()
    evaluator = Evaluator(task, scene, maps, albedo_scale)
    lamp_rig = task.lamp.rig
    pan, tilt, radius = candidate_grid(lamp_rig, settings)
    values, _ = evaluator.values(pan, tilt, radius, tolerance=False)
    obj = objective(values)
    maps = replace(maps, candidate_pan=pan, candidate_tilt=tilt, candidate_objective=obj)
    timing["global_search"] = time.perf_counter() - t
    say(f"global search: {len(pan)} lamp poses x {len(scene.points)} samples")

    t = time.perf_counter()
    starts = pick_starts(pan, tilt, obj, settings.starts, np.radians(2 * settings.pan_step_deg))
    poses = [np.array([pan[k], tilt[k], radius[k]]) for k in starts]
    if settings.refine:
        poses += [refine(evaluator, x, lamp_rig) for x in poses]
    stack = np.array(poses)
    final_values, detail = evaluator.values(stack[:, 0], stack[:, 1], stack[:, 2])
    rank = np.lexsort((objective(final_values), final_values.max(axis=-1) > 1.0))
    best = int(rank[0])
    timing["refine"] = time.perf_counter() - t
    timing["total"] = time.perf_counter() - t0
    return assemble(task, scene, evaluator, maps, settings, stack[best], final_values[best],
                    {k: v[best] for k, v in detail.items()}, timing)


def assemble(task, scene, evaluator, maps, settings, joints, values, detail, timing):
    """The Plan object for the chosen lamp pose."""
    reqs = [costs.Requirement(name, float(values[i]), describe(name, detail, evaluator, values[i] <= 1.0))
            for i, name in enumerate(REQUIREMENTS)
            if not (name == "depth_of_field" and evaluator.depth_needed <= 0)]
    verdict = costs.verdict(reqs)
    pos = detail["position"]
    s = geometry.unit(pos - scene.center)
    v = geometry.unit(scene.camera_position - scene.center)
    lens = task.camera.lens
    kappa = float(detail["kappa"])
    exposure = Exposure(float(detail["shutter"]), kappa, evaluator.focus,
                        float(dof.depth_of_field(evaluator.focus, lens.focal_length_m, kappa,
                                                 lens.circle_of_confusion_m)))
    binding = next(r for r in reqs if r.name == verdict.binding)
    return Plan(task_name=task.name, feasible=verdict.feasible, binding=verdict.binding,
                miss=verdict.miss, objective=verdict.objective, requirements=reqs,
                joints=tuple(float(x) for x in joints), lamp_position=pos, exposure=exposure,
                gray=detail["gray"], distance_m=float(np.linalg.norm(pos - scene.center)),
                phase_angle_rad=float(np.arccos(np.clip(s @ v, -1, 1))),
                camera_position=scene.camera_position, hint="" if verdict.feasible else binding.detail,
                maps=maps, settings=settings, scene=scene, timing_s=timing)


def describe(name, d, ev, met):
    """What a requirement's value means for the chosen pose: the fact, and where it is not met
    (met False) what would fix it, in a sentence a person can act on."""
    low, high = ev.low, ev.high
    g = d["gray"]
    cam, req = ev.task.camera, ev.task.requirements
    t_lo, t_hi = cam.shutter_range_s
    if name in ("gray_min", "shutter_max") and not np.isfinite(d["t_need"]):
        return "no feature sample is lit by the lamp at any shutter time"
    if name == "gray_min":
        if d["t_need"] > t_hi:
            return (f"gray band needs shutter {1e3 * d['t_need']:.1f} ms > max {1e3 * t_hi:.1f} ms at "
                    f"f/{d['kappa']:.1f}; move the lamp closer, open the aperture (less depth of field) "
                    f"or use a brighter lamp")
        return f"darkest sample gray {g.min():.1f} (band {low:g}-{high:g})"
    if name == "gray_max":
        if not met and g.max() / max(g.min(), 1e-12) > high / low:
            return (f"feature too uneven: gray {g.min():.1f}-{g.max():.1f} spans more than the band "
                    f"{low:g}-{high:g}; move the lamp farther away or toward the camera direction")
        return f"brightest sample gray {g.max():.1f} (band {low:g}-{high:g})"
    if name == "reflection_region":
        fact = (f"lamp at least {np.degrees(req.region_margin_rad):.1f} deg inside the region where "
                f"{req.reflection} reflection dominates and every sample sees the lamp "
                f"({ev.maps.wanted.mean():.1%} of directions qualify)")
        return fact if met else f"needs the {fact}"
    if name == "lamp_tolerance":
        tol = f"lamp errors of {np.degrees(req.lamp_tolerance_rad):.1f} deg"
        return (f"gray stays in band for {tol}" if met else
                f"{tol} move some sample's gray out of the band {low:g}-{high:g}; inspect a smaller "
                f"feature, widen the band or want a reflection whose BRDF changes more slowly")
    if name == "no_shadow":
        return (f"{int(d['shadowed'].sum())} of {len(ev.scene.points)} feature samples are shadowed from "
                f"the lamp ({ev.maps.visible.mean():.0%} of directions see every sample)")
    if name == "cone_coverage":
        return ("the lamp's cone covers every sample" if met else
                "the lamp's cone does not cover the whole feature; move the lamp farther away")
    if name == "camera_view":
        return (f"the camera sees all {len(ev.scene.points)} feature samples" if met else
                f"the camera cannot see {ev.camera_unseen} of {len(ev.scene.points)} feature samples; "
                f"change the view direction")
    if name in ("shutter_min", "f_number_max"):
        fact = f"f/{d['kappa']:.1f} and {1e3 * d['shutter']:.3f} ms"
        return fact if met else f"too bright even at {fact}; move the lamp farther away"
    if name == "shutter_max":
        need = f"needs shutter {1e3 * d['t_need']:.1f} ms"
        return f"{need}, within the max {1e3 * t_hi:.1f} ms" if met else f"{need} > max {1e3 * t_hi:.1f} ms"
    if name == "f_number_min":
        return f"f/{d['kappa']:.1f} within the lens's range f/{cam.lens.f_number_range[0]:g}-f/{cam.lens.f_number_range[1]:g}"
    return f"depth of field needs {1e3 * ev.depth_needed:.1f} mm"


def write_plan(plan, task, out_dir):
    """plan.json and the pictures into out_dir."""
    from pathlib import Path

    from cell import jsonio

    from cell.pictures import write_plan_pictures
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "plan.json").write_text(jsonio.dumps(plan.to_json(), indent=2) + "\n")
    write_plan_pictures(plan, task, plan.scene, out_dir)
    return out_dir


def summary(plan):
    """A few lines for the terminal."""
    pan, tilt, radius = plan.joints
    g = gray_stats(plan.gray)
    verdict = "feasible" if plan.feasible else f"INFEASIBLE ({plan.binding} misses by {plan.miss:.3g})"
    return "\n".join([
        f"{plan.task_name}: {verdict}",
        f"  lamp   {plan.distance_m:.3f} m from the feature, phase angle {np.degrees(plan.phase_angle_rad):.1f} deg"
        f" (pan {np.degrees(pan):.1f} deg, tilt {np.degrees(tilt):.1f} deg, radius {radius:.3f} m)",
        f"  camera shutter {1e3 * plan.exposure.shutter_s:.2f} ms, f/{plan.exposure.f_number:.1f},"
        f" focus {plan.exposure.focus_m:.3f} m (depth of field {1e3 * plan.exposure.depth_of_field_m:.1f} mm)",
        f"  gray   mean {g['mean']:.1f}, min {g['min']:.1f}, max {g['max']:.1f}",
        f"  binding {plan.binding} = {max(r.value for r in plan.requirements):.4g};"
        f" time {plan.timing_s['total']:.2f} s",
    ])


def command(args):
    """`cell plan TASK [--out DIR] [--json]`: exit 0 feasible, 1 infeasible (with the reason)."""
    import sys
    from pathlib import Path

    from cell import jsonio
    from cell.cli import output_folder
    from cell.errors import PlanInfeasible
    from cell.loader import load_task
    task = load_task(args.task)
    out = output_folder(args.out, Path("runs") / f"{Path(args.task).stem}-plan")
    result = plan(task, progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    write_plan(result, task, out)
    if args.json:
        print(jsonio.dumps(result.to_json(), indent=2))
    else:
        print(summary(result))
        print(f"  wrote {out}/plan.json and pictures")
    if not result.feasible:
        raise PlanInfeasible(f"infeasible: {result.binding} binds: {result.hint}")
    return 0
