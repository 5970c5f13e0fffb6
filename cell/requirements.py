"""The requirements a plan must meet (sec. 2.1, 5), one registry: each has a name (plan.json's),
its value f_i over candidates (met when <= 1, eq. 1 and the erratum of eq. 25) and the sentence
that explains it for a chosen pose - the fact, and where it is missed what would fix it.

A new requirement is one entry in REGISTRY; its value and explanation read only the
planning Problem and the Candidates (cell.evaluate). The registry's order breaks ties between
equally binding requirements.
"""
from dataclasses import dataclass
from typing import Callable

import numpy as np

from cell import geometry
from cell.physics import costs, depth_of_field as dof


@dataclass(frozen=True)
class Requirement:
    name: str
    value: Callable         # (Problem, Candidates) -> (C,) values f_i
    explain: Callable       # (Problem, Candidates of one, met) -> sentence
    applies: Callable = lambda problem: True


def _unlit(c):
    return not np.isfinite(c.t_need[0])


UNLIT = "no feature sample is lit by the lamp at any shutter time"


def gray_min(p, c):
    return costs.f_min(np.min(c.gray, axis=-1), p.band[0])


def explain_gray_min(p, c, met):
    low, high = p.band
    t_hi = p.task.camera.shutter_range_s[1]
    if _unlit(c):
        return UNLIT
    if c.t_need[0] > t_hi:
        return (f"gray band needs shutter {1e3 * c.t_need[0]:.1f} ms > max {1e3 * t_hi:.1f} ms at "
                f"f/{c.kappa[0]:.1f}; move the lamp closer, open the aperture (less depth of field) "
                f"or use a brighter lamp")
    return f"darkest sample gray {c.gray[0].min():.1f} (band {low:g}-{high:g})"


def gray_max(p, c):
    return costs.f_max(np.max(c.gray, axis=-1), p.band[1])


def explain_gray_max(p, c, met):
    low, high = p.band
    g = c.gray[0]
    if not met and g.max() / max(g.min(), 1e-12) > high / low:
        return (f"feature too uneven: gray {g.min():.1f}-{g.max():.1f} spans more than the band "
                f"{low:g}-{high:g}; move the lamp farther away or toward the camera direction")
    return f"brightest sample gray {g.max():.1f} (band {low:g}-{high:g})"


def reflection_region(p, c):
    """exp(d / margin + 1): 1 at `margin` inside the wanted region (sec. 5.2)."""
    local = (c.position - p.scene.center) @ p.scene.frame
    az, el = geometry.angles_from_direction(local)
    d = p.maps.grid.sample(p.maps.distance, az, el)
    margin = max(p.task.requirements.region_margin_rad, 1e-6)
    return np.exp(np.minimum(d / margin + 1.0, costs.EXP_LIMIT))


def explain_reflection_region(p, c, met):
    req = p.task.requirements
    fact = (f"lamp at least {np.degrees(req.region_margin_rad):.1f} deg inside the region where "
            f"{req.reflection} reflection dominates and every sample sees the lamp "
            f"({p.maps.wanted.mean():.1%} of directions qualify)")
    return fact if met else f"needs the {fact}"


def lamp_tolerance(p, c):
    """The worst band miss with the lamp moved by its tolerance (0 when not evaluated)."""
    low, high = p.band
    value = np.zeros(len(c.shutter))
    for moved in c.moved_gray:
        value = np.maximum(value, np.maximum(costs.f_min(moved.min(axis=-1), low),
                                             costs.f_max(moved.max(axis=-1), high)))
    return value


def explain_lamp_tolerance(p, c, met):
    low, high = p.band
    tol = f"lamp errors of {np.degrees(p.task.requirements.lamp_tolerance_rad):.1f} deg"
    return (f"gray stays in band for {tol}" if met else
            f"{tol} move some sample's gray out of the band {low:g}-{high:g}; inspect a smaller "
            f"feature, widen the band or want a reflection whose BRDF changes more slowly")


def no_shadow(p, c):
    return costs.count_cost(c.shadowed.sum(axis=-1))


def explain_no_shadow(p, c, met):
    return (f"{int(c.shadowed[0].sum())} of {len(p.scene.points)} feature samples are shadowed from "
            f"the lamp ({p.maps.visible.mean():.0%} of directions see every sample)")


def cone_coverage(p, c):
    return costs.f_max(np.max(c.off_axis, axis=-1), 0.5 * p.task.lamp.cone_angle_rad)


def explain_cone_coverage(p, c, met):
    return ("the lamp's cone covers every sample" if met else
            "the lamp's cone does not cover the whole feature; move the lamp farther away")


def camera_view(p, c):
    return np.broadcast_to(costs.count_cost(p.camera_unseen), c.shutter.shape)


def explain_camera_view(p, c, met):
    n = len(p.scene.points)
    return (f"the camera sees all {n} feature samples" if met else
            f"the camera cannot see {p.camera_unseen} of {n} feature samples; change the view direction")


def shutter_min(p, c):
    return costs.f_min(c.shutter, p.task.camera.shutter_range_s[0])


def explain_too_bright(p, c, met):
    fact = f"f/{c.kappa[0]:.1f} and {1e3 * c.shutter[0]:.3f} ms"
    return fact if met else f"too bright even at {fact}; move the lamp farther away"


def shutter_max(p, c):
    """No sample lit: no shutter helps; value e marks the miss and leaves the cause (shadow,
    cone, facing away) to bind."""
    t_hi = p.task.camera.shutter_range_s[1]
    return costs.f_max(np.where(np.isfinite(c.t_need), c.t_need, 2.0 * t_hi), t_hi)


def explain_shutter_max(p, c, met):
    t_hi = p.task.camera.shutter_range_s[1]
    if _unlit(c):
        return UNLIT
    need = f"needs shutter {1e3 * c.t_need[0]:.1f} ms"
    return f"{need}, within the max {1e3 * t_hi:.1f} ms" if met else f"{need} > max {1e3 * t_hi:.1f} ms"


def f_number_min(p, c):
    return costs.f_min(c.kappa, p.task.camera.lens.f_number_range[0])


def explain_f_number_min(p, c, met):
    k_lo, k_hi = p.task.camera.lens.f_number_range
    return f"f/{c.kappa[0]:.1f} within the lens's range f/{k_lo:g}-f/{k_hi:g}"


def f_number_max(p, c):
    return costs.f_max(c.kappa, p.task.camera.lens.f_number_range[1])


def depth_of_field(p, c):
    lens = p.task.camera.lens
    depth = dof.depth_of_field(p.focus_m, lens.focal_length_m, c.kappa, lens.circle_of_confusion_m)
    return costs.f_min(np.minimum(depth, 1e3), p.depth_needed_m)


def explain_depth_of_field(p, c, met):
    return f"depth of field needs {1e3 * p.depth_needed_m:.1f} mm"


REGISTRY = (
    Requirement("gray_min", gray_min, explain_gray_min),
    Requirement("gray_max", gray_max, explain_gray_max),
    Requirement("reflection_region", reflection_region, explain_reflection_region),
    Requirement("lamp_tolerance", lamp_tolerance, explain_lamp_tolerance),
    Requirement("no_shadow", no_shadow, explain_no_shadow),
    Requirement("cone_coverage", cone_coverage, explain_cone_coverage),
    Requirement("camera_view", camera_view, explain_camera_view),
    Requirement("shutter_min", shutter_min, explain_too_bright),
    Requirement("shutter_max", shutter_max, explain_shutter_max),
    Requirement("f_number_min", f_number_min, explain_f_number_min),
    Requirement("f_number_max", f_number_max, explain_too_bright),
    Requirement("depth_of_field", depth_of_field, explain_depth_of_field,
                applies=lambda p: p.depth_needed_m > 0),
)


def values(problem, candidates):
    """{name: (C,) value} of every requirement that applies to the problem, in registry order."""
    return {r.name: np.asarray(r.value(problem, candidates), dtype=float)
            for r in REGISTRY if r.applies(problem)}


def stacked(values_by_name):
    """(C, R) of the values, for the objective and the feasibility test over all of them."""
    return np.column_stack(list(values_by_name.values()))


def objective(values_by_name):
    """Eq. (22) over the log-values ln f_i: a smooth max that the optimizer minimises (C,)."""
    return costs.log_sum_exp(np.log(np.maximum(stacked(values_by_name), 1e-300)), axis=-1)


def judged(problem, candidate, values_by_name):
    """costs.RequirementValue of each requirement for one candidate (Candidates of one)."""
    by_name = {r.name: r for r in REGISTRY}
    return tuple(costs.RequirementValue(name, float(v[0]), by_name[name].explain(problem, candidate, v[0] <= 1.0))
                 for name, v in values_by_name.items())
