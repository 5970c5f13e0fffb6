"""The requirements a plan must meet (sec. 2.1, 5), one registry: each has a name (plan.json's),
its value over candidates as ln f_i (met when <= 0, i.e. f_i <= 1: eq. 1 and the erratum of eq. 25;
uncapped, so the objective ranks however far a pose misses) and the sentence that explains it for
a chosen pose - the fact, and where it is missed what would fix it.

A new requirement is one entry in REGISTRY; its value and explanation read only the
planning Problem and the Candidates (cell.planning.evaluate). The registry's order breaks ties between
equally binding requirements.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace
from typing import Callable
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from cell.collision.rays import NEAR_MARGIN_M, SightCone, SpokesNear, segments_cross_boxes, segments_near_segments
from cell.collision.scene import lamp_boxes, rig_links, servo_front_m
from cell.devices.rig import RIG_ARM_RADIUS_M, TILT_SERVO_SIZE_M
from cell.core import geometry
from cell.core.numbers import number
from cell.devices import rig
from cell.physics import projection
from cell.planning import evaluate, occluders, regions
from cell.physics import brdf, costs, depth_of_field as dof
from cell.task import winding

if TYPE_CHECKING:
    from cell.planning.evaluate import Candidates, Problem
    from cell.planning.plan import Maps
    from cell.planning.scene import Scene
    from cell.task.types import Task

ON_SURFACE_M = 1e-5     # a sample this close to a triangle lies on it (Warp's closest points: float32)


@dataclass(frozen=True)
class Requirement:
    name: str
    ln_value: Callable[[Problem, Candidates], np.ndarray]  # (Problem, Candidates) -> (C,) ln f_i
    explain: Callable[[Problem, Candidates, bool], str]    # (Problem, Candidates of one, met) -> sentence
    asked: Callable[[Problem], bool] | None = None         # (Problem) -> whether the task asks for it; None: always
    amount: Callable[[Problem, Candidates], costs.Amount | None] | None = None  # (Problem, Candidates of one) -> what it compares


def _maps(p: Problem) -> Maps:
    """The Problem's maps: a viewpoint's Problem has none (cell.planning.viewpoints), and asks
    only requirements that do not read them."""
    if p.maps is None:
        raise ValueError("this requirement reads the maps, and the Problem has none")
    return p.maps


def _wanted(limit: float | None) -> float:
    """A limit the task may leave out (view_angle, resolution): REGISTRY asks its requirement only
    where the task gives it."""
    if limit is None:
        raise ValueError("the task does not ask for this requirement")
    return limit


def _unlit(c):
    return not np.isfinite(c.t_need[0])


UNLIT = "no feature sample is lit by the lamp at any shutter time"


def at_least(x: ArrayLike, low: float) -> np.ndarray:
    """ln f_min(x, low) of eq. (1); a band from 0 asks nothing of the darkest sample (-inf: met)."""
    return costs.ln_f_min(x, low) if low > 0 else np.full(np.shape(x), -np.inf)


def gray_min(p: Problem, c: Candidates) -> np.ndarray:
    return at_least(np.min(c.gray, axis=-1), p.band[0])


def explain_gray_min(p: Problem, c: Candidates, met: bool) -> str:
    low, high = p.band
    t_hi = p.task.camera.shutter_range_s[1]
    if _unlit(c):
        return UNLIT
    if c.t_need[0] > t_hi:
        return (f"gray band needs shutter {number(1e3 * c.t_need[0], ' ms')} > max {1e3 * t_hi:.1f} ms at "
                f"f/{c.kappa[0]:.1f}; move the lamp closer, open the aperture (less depth of field) "
                f"or use a brighter lamp")
    return f"darkest sample gray {number(c.gray[0].min())} (band {low:g}-{high:g})"


def gray_max(p: Problem, c: Candidates) -> np.ndarray:
    return costs.ln_f_max(np.max(c.gray, axis=-1), p.band[1])


def explain_gray_max(p: Problem, c: Candidates, met: bool) -> str:
    low, high = p.band
    g = c.gray[0]
    t_lo, k_hi = p.task.camera.shutter_range_s[0], p.task.camera.lens.f_number_range[1]
    if not met and c.shutter[0] <= t_lo and c.kappa[0] >= k_hi:
        return (f"too bright even at f/{k_hi:g} and {1e3 * t_lo:.3g} ms: gray {number(g.min())}-{number(g.max())}, "
                f"band {low:g}-{high:g}; move the lamp farther away or use a weaker lamp")
    if not met and g.max() * low > max(g.min(), 1e-12) * high:
        return (f"feature too uneven: gray {number(g.min())}-{number(g.max())} spans more than the band "
                f"{low:g}-{high:g}; move the lamp farther away or toward the camera direction")
    return f"brightest sample gray {number(g.max())} (band {low:g}-{high:g})"


def wrong_reflection(p: Problem, c: Candidates) -> np.ndarray:
    """(C, P) lit samples whose dominant BRDF term (brdf.judged_term's) is not the wanted one;
    with `any`, those where a spike the goniometer did not resolve may be (brdf.UNKNOWN)."""
    reflection = p.task.requirements.reflection
    lit = ~c.shadowed & (c.gray > p.black_level)
    if reflection == "any":
        return lit & (c.dominant == brdf.UNKNOWN)
    return lit & (c.dominant != regions.WANTED_TERM[reflection])


def other_reflection(p: Problem, c: Candidates) -> np.ndarray:
    """(C,) count of wrong_reflection's samples."""
    return np.sum(wrong_reflection(p, c), axis=-1)


def unresolved_note(p: Problem) -> str:
    """What the material's goniometer left unresolved, for a sentence ('' when nothing)."""
    u = p.material.unresolved
    if u is None or "spike" not in u.terms:
        return ""
    phases = ", ".join(f"{np.degrees(a):g}" for a in u.terms["spike"])
    return (f"the material's spike is not resolved at phase {phases} deg (its goniometer's step "
            f"{np.degrees(u.step_rad):g} deg sees exponents up to {u.resolvable_m_max:.4g}): a lamp whose half "
            f"vector lies within {np.degrees(brdf.spike_keep_out(u)):g} deg of a sample's normal may meet a spike "
            f"of unknown brightness")


def reflection_region(p: Problem, c: Candidates) -> np.ndarray:
    """ln of exp(d / margin + 1): 0 at `margin` inside the wanted region (sec. 5.2), judged for
    the lamp seen from the feature centre where it is on; and at each lit sample its dominant term
    (of the light adding the most there) must be the wanted one (ln(0.5 + count) where some are not)."""
    local = (c.position - p.scene.center) @ p.scene.frame
    az, el = geometry.angles_from_direction(local)
    maps = _maps(p)
    d = maps.distance.sample(az, el)
    margin = max(p.task.requirements.region_margin_rad, 1e-6)
    region = np.where(c.drive[:, 0] > 0.0, d / margin + 1.0, -np.inf)     # the spot off: where it is does not matter
    others = other_reflection(p, c)
    if not others.any():
        return region
    return np.where(others > 0, np.maximum(region, costs.ln_count_cost(others)), region)


def explain_reflection_region(p: Problem, c: Candidates, met: bool) -> str:
    req = p.task.requirements
    unresolved = unresolved_note(p)
    maps = _maps(p)
    if not maps.wanted.any():
        if req.reflection == "spike" and unresolved:
            return (f"the spike was not resolved: {unresolved}; no lamp direction is known to give spike "
                    f"reflection: re-measure the material with a finer calibration.goniometer.step_deg")
        return (f"no lamp direction gives {req.reflection} reflection where every sample sees the lamp "
                f"(none of the map's {np.degrees(maps.grid.step):g} deg cells): want another reflection "
                f"or change the view" + (f"; {unresolved} (kept out)" if unresolved else ""))
    wrong = wrong_reflection(p, c)[0]
    unknown = int(np.sum(wrong & (c.dominant[0] == brdf.UNKNOWN)))
    if unknown:
        return (f"{unknown} of {len(p.scene.points)} lit samples see the lamp where an unresolved spike may be: "
                f"{unresolved}; keep the lamp out, or re-measure the material with a finer "
                f"calibration.goniometer.step_deg")
    others = int(np.sum(wrong))
    if others:
        return (f"{others} of {len(p.scene.points)} lit samples see another reflection than {req.reflection}: "
                f"the term changes across the patch; inspect a smaller feature or want 'any'")
    fact = (f"lamp at least {np.degrees(req.region_margin_rad):.1f} deg inside the region where "
            f"{req.reflection} reflection dominates and every sample sees the lamp "
            f"({maps.wanted.mean():.1%} of directions qualify)")
    return fact if met else f"needs the {fact}"


def lamp_tolerance(p: Problem, c: Candidates) -> np.ndarray:
    """The worst band miss with the lamp moved by its tolerance (-inf, f = 0, when not evaluated)."""
    low, high = p.band
    moved = c.moved_gray                                    # (M, C, P)
    if not len(moved):
        return np.full(len(c.shutter), -np.inf)
    return np.maximum(at_least(moved.min(axis=-1), low), costs.ln_f_max(moved.max(axis=-1), high)).max(axis=0)


def explain_lamp_tolerance(p: Problem, c: Candidates, met: bool) -> str:
    low, high = p.band
    tol = f"lamp errors of {np.degrees(p.task.requirements.lamp_tolerance_rad):.1f} deg"
    if p.lights.turned.size:
        tol += f" and errors of {np.degrees(p.task.requirements.light_tolerance_rad):.1f} deg in the other lights' aims"
    return (f"gray stays in band for {tol}" if met else
            f"{tol} move some sample's gray out of the band {low:g}-{high:g}; inspect a smaller "
            f"feature, widen the band or want a reflection whose BRDF changes more slowly")


def no_shadow(p: Problem, c: Candidates) -> np.ndarray:
    return costs.ln_count_cost(c.shadowed.sum(axis=-1))


def explain_no_shadow(p: Problem, c: Candidates, met: bool) -> str:
    fact = (f"{int(c.shadowed[0].sum())} of {len(p.scene.points)} feature samples are shadowed from "
            f"the lamp ({_maps(p).visible.mean():.0%} of directions see every sample)")
    lights = _blocking(p.scene, c.shadowed[0], c.position[0])
    if lights:
        return f"{fact}; the housing of {lights} stands in the lamp's beam"
    arm = int(evaluate.spot_blocked(p, c.position[:1]).sum())
    return f"{fact}; the camera body or the arm stands in the lamp's beam at {arm} of them" if arm else fact


def _blocking(scene: Scene, which: np.ndarray, to: np.ndarray) -> str:
    """The fixed lights whose housings cross the rays from the samples `which` (P,) to the point
    `to`, with how many each ('' when none): named where one blocks (occluders.blockers)."""
    if not scene.housings or not np.any(which):
        return ""
    return occluders.named(scene.housings, occluders.blockers(scene.housings, scene.points[which], to))


def cone_coverage(p: Problem, c: Candidates) -> np.ndarray:
    """Every sample within the angle the lamp lights at all (lit_half_angle_rad: its profile's
    end, gamma / 2 for the ideal cone); how evenly is the band's and the lamp tolerance's to judge,
    with the profile in the gray."""
    return costs.ln_f_max(np.max(c.off_axis, axis=-1), p.fixed("lit_half_angle", lambda: p.task.lamp.lit_half_angle_rad))


def explain_cone_coverage(p: Problem, c: Candidates, met: bool) -> str:
    if met:
        return "the lamp's cone covers every sample"
    half, radius = p.task.lamp.lit_half_angle_rad, p.task.feature.radius_m
    needed, reach = radius / np.tan(half), p.task.lamp.rig.radius_range_m[1]
    if needed > reach:
        return (f"the lamp lights {np.degrees(half):.3g} deg off its axis and covers the {2e3 * radius:g} mm "
                f"patch only from {needed:.2f} m, the rig reaches {reach:g} m: use a wider cone or a "
                f"smaller feature")
    return "the lamp's cone does not cover the whole feature; move the lamp farther away"


def lamp_hides(p: Problem, positions: np.ndarray) -> np.ndarray:
    """(C, P) the samples the camera sees that the spot lamp's housing or the pan-tilt's links
    hide with the lamp at each position (C, 3) (rig_hides), read-only, the last lamps' rows kept
    (Problem.at_lamps)."""
    def hides(at: np.ndarray) -> np.ndarray:
        housing, links = rig_hides(p, at)
        return housing | links
    return p.at_lamps("hides", np.asarray(positions, float).reshape(-1, 3), hides)


@dataclass(frozen=True)
class RigSight:
    """What rig_hides reads of a problem while the lamp moves: the cone from the camera tangent to their sphere (rays.SightCone), the lamp's half
    sizes (half), the links' width across the aim (width: the arm's radius, the servo's half
    diagonal across the aim, the larger), the housing's and links' together (whole), the rig's
    declared reach (reach: cell.collision.rig_reach_m, the servo's front from the pivot; None: at
    the lamp's back), and the segment camera -> m as seen from the pivot, which the lamp's axis
    runs straight away from (spokes: rays.SpokesNear)."""

    cone: SightCone
    half: np.ndarray
    width: float
    whole: float
    reach: float | None
    spokes: SpokesNear

    @classmethod
    def of(cls, p: Problem) -> RigSight:
        half = 0.5 * np.asarray(p.task.cell.collision.lamp_size_m, float)
        cone = SightCone.of(p.scene.camera_position, *evaluate.samples_sphere(p))
        servo_half = 0.5 * np.asarray(TILT_SERVO_SIZE_M)
        width = max(RIG_ARM_RADIUS_M, float(np.hypot(servo_half[0], servo_half[1])))
        whole = max(width, float(np.hypot(half[0], half[1])))
        return cls(cone, half, width, whole, p.task.cell.collision.rig_reach_m,
                   SpokesNear.of(p.task.lamp.rig.pivot_m, cone.apex, cone.middle))

    def end(self, radius: np.ndarray) -> np.ndarray:
        """(C,) the servo's back from the pivot with the lamp at each radius (C,): its front
        (collision.scene.servo_front_m) plus its depth."""
        return servo_front_m(radius, 2.0 * float(self.half[2]), self.reach) + TILT_SERVO_SIZE_M[2]


def rig_hides(p: Problem, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((C, P), (C, P)) the samples the camera sees (Problem.camera_seen) that the spot lamp's
    housing, and that the pan-tilt's links, hide with the lamp at each position (C, 3): the line
    of sight camera -> sample crosses the lamp's box (collision.scene.lamp_boxes: cell.collision's
    lamp_size_m) or the tilt servo's box (rays.segments_cross_boxes, both in one call) or, where
    the rig's reach is declared, passes within the arm's radius of its axis
    (collision.scene.rig_links; rays.segments_near_segments, every lamp's arm in one call). A position not finite is a lamp not placed (a viewpoint judged
    before any lamp), hiding none. Only lamps that may meet the lines of sight are tested: those
    lie in the cone from the camera tangent to the samples' sphere (rays.SightCone), and the
    housing and the links together within W' (the widest across the aim) of the lamp's axis from
    its front to the servo's back, straight out from the pivot (RigSight.spokes); then the box by the ball about its centre,
    h_z behind the lamp along the aim, of radius |h|; the links by their axis from the lamp's back
    to the servo's within W (the arm's radius, the servo's half diagonal across the aim, the
    larger) + rho of the segment camera -> m (the line camera c -> sample s at c + t (s - c) lies
    t |s - m| <= rho from c + t (m - c)).
    The links lie behind the lamp, beyond its housing's back face, so they never block its own
    beam (spot_blocked leaves them out): each ray of the spot runs from its front towards a sample
    in front of it (within its cone, under 90 deg off its aim)."""
    positions = np.asarray(positions, float).reshape(-1, 3)
    housing = np.zeros((len(positions), len(p.scene.points)), bool)
    links = np.zeros_like(housing)
    seen = p.camera_seen
    if seen is None or not seen.any():
        return housing, links
    sight: RigSight = p.fixed("rig_sight", lambda: RigSight.of(p))
    pivot = p.task.lamp.rig.pivot_m
    half, cone = sight.half, sight.cone
    out = positions - pivot
    with np.errstate(invalid="ignore", divide="ignore"):        # a lamp not placed (NaN) is not near
        radius = np.sqrt(np.sum(out * out, axis=1))
        out /= radius[:, None]
        # the housing and the links together: the lamp's axis from its front to the servo's back
        near = sight.spokes.near(out, radius, sight.end(radius), sight.whole + cone.rho + NEAR_MARGIN_M)
    if not near.any():
        return housing, links
    k, out, radius = np.flatnonzero(near), out[near], radius[near]
    near_housing = np.zeros(len(positions), bool)
    near_housing[k] = cone.meets(pivot + (radius + half[2])[:, None] * out, float(np.linalg.norm(half)) + NEAR_MARGIN_M)
    near_links = np.zeros(len(positions), bool)     # the links' axis within their width of the segment camera -> m widened by rho
    near_links[k] = sight.spokes.near(out, radius + 2.0 * half[2], sight.end(radius),
                                      sight.width + cone.rho + NEAR_MARGIN_M)
    if near_housing.any() or near_links.any():
        points = p.scene.points[seen]
        R = rig.lamp_frame(pivot, positions[k])
        at_housing, at_links = near_housing[k], near_links[k]
        held = rig_links(pivot, half, sight.reach, positions[k][at_links], R[at_links])
        count = int(at_housing.sum())
        crossed = segments_cross_boxes(
            p.scene.camera_position, points,
            np.concatenate([lamp_boxes(pivot, half, positions[k][at_housing], R[at_housing]), held.T_cell_servo]),
            np.vstack([np.broadcast_to(half, (count, 3)), np.broadcast_to(held.servo_half_m, (len(held.a), 3))]))
        housing[np.ix_(near_housing, seen)] = crossed[:count]
        if len(held.a):
            links[np.ix_(near_links, seen)] = crossed[count:] | (segments_near_segments(
                p.scene.camera_position, points, held.a, held.b, held.radius_m) if held.arm else False)
    return housing, links


def camera_view(p: Problem, c: Candidates) -> np.ndarray:
    """Every sample seen: none hidden by the part or a fixed light's housing or outside the image
    (Problem.camera_unseen), none hidden by the spot lamp's housing or the pan-tilt's links at
    the candidate's pose (lamp_hides)."""
    unseen = p.camera_unseen + lamp_hides(p, c.position).sum(axis=-1)
    return np.broadcast_to(costs.ln_count_cost(unseen), c.shutter.shape)


def explain_camera_view(p: Problem, c: Candidates | None, met: bool) -> str:
    n = len(p.scene.points)
    if met:
        return f"the camera sees all {n} feature samples"
    housing, links = (np.zeros((1, n), bool),) * 2 if c is None else rig_hides(p, c.position[:1])
    by_lamp = int(np.sum(housing | links))
    fact = f"the camera cannot see {p.camera_unseen + by_lamp} of {n} feature samples"
    if by_lamp:
        names = (("the spot lamp's housing (lamp_body)", housing),
                 ("the pan-tilt's links behind the lamp (its arm and tilt servo)", links))
        which = " and ".join(name for name, hides in names if hides.any())
        return (f"{fact}: {which} {'stand' if links.any() else 'stands'} between {by_lamp} of them and the camera; "
                f"move the lamp out of the camera's view")
    on_flipped, flipped = on_flipped_faces(p)
    if on_flipped:
        return (f"{fact}: {on_flipped} lie on triangles wound against their neighbours (the mesh's winding is "
                f"flipped there, {flipped.where()}), so their surface faces away from the camera; "
                f"fix the mesh's winding")
    lights = _blocking(p.scene, np.ones(n, bool), p.scene.camera_position)
    if lights:
        return f"{fact}: the housing of {lights} stands between them and the camera; move the camera or the light"
    return f"{fact}; change the view direction"


def on_flipped_faces(p: Problem) -> tuple[int, winding.Flipped]:
    """(how many feature samples lie on the part's flipped triangles, cell.task.winding's Flipped of
    the part mesh): a sample within ON_SURFACE_M of one, in the part frame."""
    flipped = winding.flipped_faces(p.task.part.mesh)
    if not len(flipped):
        return 0, flipped
    points = geometry.apply(np.linalg.inv(p.task.frames.T_cell_part), p.scene.points)
    triangles = p.task.part.mesh.triangles[flipped.faces]
    closest = trimesh.triangles.closest_point(np.repeat(triangles, len(points), axis=0),
                                              np.tile(points, (len(triangles), 1)))
    distance = np.linalg.norm(closest - np.tile(points, (len(triangles), 1)), axis=1).reshape(len(triangles), -1)
    return int(np.sum(distance.min(axis=0) <= ON_SURFACE_M)), flipped


def largest_view_angle(scene: Scene) -> float:
    """The largest angle between a sample's normal and its direction to the camera [rad]."""
    return float(projection.view_angles(scene.camera_position, scene.points, scene.normals).max())


def view_angle_ln(task: Task, scene: Scene, largest: float | None = None) -> float:
    """ln f of view_angle at a scene's camera (the camera's alone: the prefilter's too), the
    largest view angle [rad] given (the prefilter's, of many features' samples at once) or the scene's."""
    angle = largest_view_angle(scene) if largest is None else largest
    return float(costs.ln_f_max(angle, _wanted(task.requirements.view_angle_rad)))


def problem_view_angles(p: Problem) -> np.ndarray:
    """(P,) each sample's view angle at the Problem's camera (projection.view_angles), once per
    Problem (Problem.fixed): the view angle and the pixel footprints (resolution) both read them."""
    scene = p.scene
    return p.fixed("view_angles", lambda: projection.view_angles(scene.camera_position, scene.points, scene.normals))


def problem_view_angle(p: Problem) -> float:
    """largest_view_angle of the Problem's scene, once per Problem (Problem.fixed)."""
    return p.fixed("largest_view_angle", lambda: float(problem_view_angles(p).max()))


def view_angle(p: Problem, c: Candidates) -> np.ndarray:
    """The largest angle between a sample's normal and its direction to the camera, at most the
    task's view_angle_deg (a camera nearly grazing the surface sees it foreshortened)."""
    return np.broadcast_to(p.fixed("view_angle", lambda: view_angle_ln(p.task, p.scene, problem_view_angle(p))),
                           c.shutter.shape)


def explain_view_angle(p: Problem, c: Candidates, met: bool) -> str:
    angle = problem_view_angle(p)
    fact = (f"the camera sees the samples at most {np.degrees(angle):.1f} deg from their normals "
            f"(at most {np.degrees(_wanted(p.task.requirements.view_angle_rad)):g} deg wanted)")
    return fact if met else f"{fact}; view the feature more squarely (camera.viewpoint: planned)"


def footprints(p: Problem) -> np.ndarray:
    """footprints_at of the Problem's task and scene, once per Problem (Problem.fixed)."""
    return p.fixed("footprints", lambda: footprints_at(p.task, p.scene, problem_view_angles(p)))


def footprints_at(task: Task, scene: Scene, angles: np.ndarray | None = None) -> np.ndarray:
    """(P,) each sample's pixel footprint at the scene's camera [m] (projection.pixel_footprint),
    the samples' view angles given where known."""
    sensor, lens = task.camera.sensor, task.camera.lens
    return projection.pixel_footprint(scene.camera_position, scene.points, scene.normals,
                                      sensor.pixel_pitch_m, lens.focal_length_m, angles)


def resolution_ln(task: Task, scene: Scene, largest: float | None = None) -> float:
    """ln f of resolution at a scene's camera (the camera's alone: the prefilter's too), the
    largest pixel footprint [m] given (the prefilter's) or the scene's."""
    footprint = footprints_at(task, scene).max() if largest is None else largest
    return float(costs.ln_f_max(footprint, _wanted(task.requirements.resolution_m)))


def resolution(p: Problem, c: Candidates) -> np.ndarray:
    """The largest pixel footprint on the feature (|p - C| pitch / f / cos(view angle), the
    pinhole's), at most the task's resolution_m per pixel."""
    return np.broadcast_to(p.fixed("resolution", lambda: resolution_ln(p.task, p.scene, float(footprints(p).max()))),
                           c.shutter.shape)


def explain_resolution(p: Problem, c: Candidates, met: bool) -> str:
    if not np.isfinite(footprints(p).max()):
        return "the camera sees some samples from behind their surface; change the view direction"
    fact = (f"a pixel covers up to {number(1e6 * footprints(p).max(), ' um')} of the feature (at most "
            f"{1e6 * _wanted(p.task.requirements.resolution_m):g} um wanted)")
    return fact if met else f"{fact}; bring the camera closer, view more squarely or use a longer lens"


def shutter_min(p: Problem, c: Candidates) -> np.ndarray:
    return costs.ln_f_min(c.shutter, p.task.camera.shutter_range_s[0])


def explain_too_bright(p: Problem, c: Candidates, met: bool) -> str:
    fact = f"f/{c.kappa[0]:.1f} and {1e3 * c.shutter[0]:.3f} ms"
    return fact if met else f"too bright even at {fact}; move the lamp farther away"


def shutter_max(p: Problem, c: Candidates) -> np.ndarray:
    """The shutter the band needs within the camera's. With no sample lit no shutter helps: inf,
    worse than any lit pose however dim, so the search prefers a lit one; the cause (shadow, cone,
    facing away) binds by CAUSES."""
    return costs.ln_f_max(c.t_need, p.task.camera.shutter_range_s[1])


def explain_shutter_max(p: Problem, c: Candidates, met: bool) -> str:
    t_hi = p.task.camera.shutter_range_s[1]
    if _unlit(c):
        return UNLIT
    need = f"needs shutter {number(1e3 * c.t_need[0], ' ms')}"
    return f"{need}, within the max {1e3 * t_hi:.1f} ms" if met else f"{need} > max {1e3 * t_hi:.1f} ms"


def f_number_min(p: Problem, c: Candidates) -> np.ndarray:
    return costs.ln_f_min(c.kappa, p.task.camera.lens.f_number_range[0])


def explain_f_number_min(p: Problem, c: Candidates, met: bool) -> str:
    k_lo, k_hi = p.task.camera.lens.f_number_range
    return f"f/{c.kappa[0]:.1f} within the lens's range f/{k_lo:g}-f/{k_hi:g}"


def f_number_max(p: Problem, c: Candidates) -> np.ndarray:
    return costs.ln_f_max(c.kappa, p.task.camera.lens.f_number_range[1])


def depth_of_field(p: Problem, c: Candidates) -> np.ndarray:
    """Near limit before the nearest sample, far limit beyond the farthest (where they fall, not
    only the width), and at least the task's depth of field."""
    nearest, farthest = p.fixed("depth_range", lambda: depth_range(p.scene))
    return depth_of_field_ln(p.task, p.scene, p.focus_m, c.kappa, nearest, farthest)


def depth_range(scene: Scene) -> tuple[float, float]:
    """(nearest, farthest) sample depth along the camera's axis [m] (Scene.sample_depths)."""
    depths = scene.sample_depths()
    return depths.min(), depths.max()


def depth_of_field_ln(task: Task, scene: Scene, focus_m: float, kappa: np.ndarray,
                      nearest: float | np.ndarray | None = None, farthest: float | np.ndarray | None = None) -> np.ndarray:
    """ln f of depth_of_field at f-numbers kappa, focused at focus_m [m] (a shot's focus and
    f-number alone: the prefilter's too); the samples' depth range given or the scene's (given
    as arrays: several features' ranges at one f-number, each value from its own range alone)."""
    lens = task.camera.lens
    f, sigma = lens.focal_length_m, lens.circle_of_confusion_m
    if nearest is None or farthest is None:
        nearest, farthest = depth_range(scene)
    near = dof.near_limit(focus_m, f, kappa, sigma)
    far = dof.far_limit(focus_m, f, kappa, sigma)
    value = np.maximum(costs.ln_f_max(near, nearest), costs.ln_f_min(np.minimum(far, 1e3), farthest))
    wanted = task.requirements.depth_of_field_m
    if wanted > 0:
        value = np.maximum(value, costs.ln_f_min(np.minimum(far - near, 1e3), wanted))
    return value


def explain_depth_of_field(p: Problem, c: Candidates, met: bool) -> str:
    lens = p.task.camera.lens
    f, sigma, k = lens.focal_length_m, lens.circle_of_confusion_m, c.kappa[0]
    near, far = dof.near_limit(p.focus_m, f, k, sigma), float(dof.far_limit(p.focus_m, f, k, sigma))
    depths = p.scene.sample_depths()
    fact = (f"in focus {number(1e3 * near)}-{number(1e3 * far, ' mm')} at f/{k:.1f}, "
            f"samples at {1e3 * depths.min():.1f}-"
            f"{1e3 * depths.max():.1f} mm, depth of field needs {1e3 * p.depth_needed_m:.1f} mm")
    return fact if met else (f"{fact}; stop the lens down (up to f/{lens.f_number_range[1]:g}, with more light "
                             f"or a longer shutter) or view the patch less obliquely")


def _defect_ratios(p: Problem, c: Candidates) -> np.ndarray:
    """(C, D) ln(min_cnr / predicted CNR) of each of the feature's defects (cell.planning.defects)."""
    from cell.planning import defects
    wanted = np.array([d.min_cnr for d in p.task.feature.defects])
    return np.log(wanted / np.maximum(defects.predicted_cnr(p, c), defects.TINY_CNR))


def defect_cnr(p: Problem, c: Candidates) -> np.ndarray:
    """ln(min_cnr / predicted CNR) of the feature's least visible defect (met when it shows with
    at least its min_cnr): the predicted CNR the worst over the samples and orientations."""
    return np.max(_defect_ratios(p, c), axis=-1)


def _worst_defect(p: Problem, c: Candidates):
    from cell.planning import defects
    judged = defects.judge(p, c)
    return max(judged, key=lambda d: np.log(d.min_cnr / max(d.predicted_cnr, defects.TINY_CNR)))


def explain_defect_cnr(p: Problem, c: Candidates, met: bool) -> str:
    d = _worst_defect(p, c)
    where = {"scratch": " at its worst orientation", "dent": "", "coating": ""}[d.kind]
    fact = f"the {d.kind} '{d.name}' shows with CNR {number(d.predicted_cnr)}{where}"
    count = len(p.task.feature.defects)
    if met:
        return f"{fact} (at least {d.min_cnr:g} wanted)" + (f", the least visible of {count} defects" if count > 1 else "")
    fact = f"{fact}, {d.min_cnr:g} wanted"
    fix = {"scratch": "light it from across the scratch or lengthen the exposure",
           "dent": "light it from lower (grazing light shows a dent's slopes) or lengthen the exposure",
           "coating": "light it where the two materials' BRDFs differ more or lengthen the exposure"}[d.kind]
    return f"{fact}; {fix}"


def amount_defect_cnr(p: Problem, c: Candidates) -> costs.Amount | None:
    d = _worst_defect(p, c)
    return _finite(d.predicted_cnr, d.min_cnr, "", False)


def _finite(actual: float, limit: float, unit: str, at_most: bool, digits: int = 1) -> costs.Amount | None:
    """An Amount, or None where a number is not finite (an unlit pose: its sentence says why)."""
    if not (np.isfinite(actual) and np.isfinite(limit)):
        return None
    return costs.Amount(float(actual), float(limit), unit, at_most, digits)


def amount_gray_min(p: Problem, c: Candidates) -> costs.Amount | None:
    return None if _unlit(c) or p.band[0] <= 0 else _finite(c.gray[0].min(), p.band[0], "", False)


def amount_gray_max(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(c.gray[0].max(), p.band[1], "", True)


def amount_cone_coverage(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(np.degrees(np.max(c.off_axis[0])), np.degrees(p.task.lamp.lit_half_angle_rad), " deg", True)


def amount_view_angle(p: Problem, c: Candidates) -> costs.Amount | None:
    angle = problem_view_angle(p)
    return _finite(np.degrees(angle), np.degrees(_wanted(p.task.requirements.view_angle_rad)), " deg", True)


def amount_resolution(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(1e6 * footprints(p).max(), 1e6 * _wanted(p.task.requirements.resolution_m), " um", True)


def amount_shutter_min(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(1e3 * c.shutter[0], 1e3 * p.task.camera.shutter_range_s[0], " ms", False, 3)


def amount_shutter_max(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(1e3 * c.t_need[0], 1e3 * p.task.camera.shutter_range_s[1], " ms", True)


def amount_f_number_min(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(c.kappa[0], p.task.camera.lens.f_number_range[0], "", False)


def amount_f_number_max(p: Problem, c: Candidates) -> costs.Amount | None:
    return _finite(c.kappa[0], p.task.camera.lens.f_number_range[1], "", True)


def amount_depth_of_field(p: Problem, c: Candidates) -> costs.Amount | None:
    """The depth of field the lens gives (far - near) against what the samples need; where they
    fall (near and far limits) is the sentence's, which the words read when the width suffices
    but the placement does not."""
    lens = p.task.camera.lens
    f, sigma, k = lens.focal_length_m, lens.circle_of_confusion_m, c.kappa[0]
    width = float(dof.far_limit(p.focus_m, f, k, sigma)) - float(dof.near_limit(p.focus_m, f, k, sigma))
    return costs.Amount(1e3 * width, 1e3 * p.depth_needed_m, " mm", False)


REGISTRY = (    Requirement("gray_min", gray_min, explain_gray_min, amount=amount_gray_min),
    Requirement("gray_max", gray_max, explain_gray_max, amount=amount_gray_max),
    Requirement("reflection_region", reflection_region, explain_reflection_region),
    Requirement("lamp_tolerance", lamp_tolerance, explain_lamp_tolerance),
    Requirement("no_shadow", no_shadow, explain_no_shadow),
    Requirement("cone_coverage", cone_coverage, explain_cone_coverage, amount=amount_cone_coverage),
    Requirement("camera_view", camera_view, explain_camera_view),
    Requirement("view_angle", view_angle, explain_view_angle,
                lambda p: p.task.requirements.view_angle_rad is not None, amount_view_angle),
    Requirement("resolution", resolution, explain_resolution,
                lambda p: p.task.requirements.resolution_m is not None, amount_resolution),
    Requirement("shutter_min", shutter_min, explain_too_bright, amount=amount_shutter_min),
    Requirement("shutter_max", shutter_max, explain_shutter_max, amount=amount_shutter_max),
    Requirement("f_number_min", f_number_min, explain_f_number_min, amount=amount_f_number_min),
    Requirement("f_number_max", f_number_max, explain_too_bright, amount=amount_f_number_max),
    Requirement("depth_of_field", depth_of_field, explain_depth_of_field, amount=amount_depth_of_field),
    Requirement("defect_cnr", defect_cnr, explain_defect_cnr, lambda p: bool(p.task.feature.defects),
                amount_defect_cnr),
)

# The order in which requirements that no lamp pose meets name the cause of an infeasible plan:
# the first is the true cause (an unlit pose misses every exposure by far, but the shadow, the
# cone or the view is what to fix).
CAUSES = ("camera_view", "view_angle", "resolution", "no_shadow", "cone_coverage", "reflection_region", "gray_min", "shutter_max",
          "shutter_min", "f_number_max", "f_number_min", "gray_max", "depth_of_field", "defect_cnr",
          "lamp_tolerance")


def ln_values(problem: Problem, candidates: Candidates) -> dict[str, np.ndarray]:
    """{name: (C,) ln f_i} of every requirement the task asks for, in registry order."""
    return {r.name: np.asarray(r.ln_value(problem, candidates), dtype=float) for r in REGISTRY
            if r.asked is None or r.asked(problem)}


def _table(ln_values_by_name: dict[str, np.ndarray]) -> np.ndarray:
    """(C, R) the R requirements' (C,) values side by side, C-ordered (np.column_stack's array,
    whose row sums log_sum_exp adds in its order; made as one array and transposed, a quarter of
    column_stack's cost on the few poses a search's round evaluates)."""
    return np.ascontiguousarray(np.array(list(ln_values_by_name.values()), dtype=float).T)


def missed(ln_values_by_name: dict[str, np.ndarray]) -> np.ndarray:
    """(C,) whether any requirement is missed (some ln f_i > 0)."""
    return np.any(_table(ln_values_by_name) > 0.0, axis=-1)


def objective(ln_values_by_name: dict[str, np.ndarray]) -> np.ndarray:
    """Eq. (22) over ln f_i: a smooth max that the optimizer minimises (C,); inf for a pose that
    no exposure can make work (unlit)."""
    with np.errstate(invalid="ignore"):        # -inf entries (met by construction) add nothing
        return costs.log_sum_exp(_table(ln_values_by_name), axis=-1)


def judged(problem: Problem, candidate: Candidates,
           ln_values_by_name: dict[str, np.ndarray]) -> tuple[costs.RequirementValue, ...]:
    """costs.RequirementValue of each requirement for one candidate (Candidates of one)."""
    by_name = {r.name: r for r in REGISTRY}

    def amount(r: Requirement) -> costs.Amount | None:
        return None if r.amount is None else r.amount(problem, candidate)

    return tuple(costs.RequirementValue(name, float(costs.value(v[0])),
                                        by_name[name].explain(problem, candidate, v[0] <= 0.0),
                                        amount(by_name[name]))
                 for name, v in ln_values_by_name.items())


def verdict(judged_values: Sequence[costs.RequirementValue], everywhere: Collection[str] = ()) -> costs.Verdict:
    """costs.verdict (feasible when max f_i <= 1, erratum eq. 25; the binding, largest value; the
    objective), except that an infeasible plan's binding requirement is the first in CAUSES
    order that fails at every lamp pose of the global search (`everywhere`) and at the chosen one:
    no lamp pose fixes that, so it is the cause, whatever else the compromise chosen misses."""
    v = costs.verdict(judged_values)
    failing = {r.name: r for r in judged_values if not r.met}
    cause = next((failing[name] for name in CAUSES if name in everywhere and name in failing), None)
    return v if cause is None else replace(v, binding=cause.name, miss=cause.value - 1.0)


def failing_everywhere(ln_values_by_name: dict[str, np.ndarray]) -> set[str]:
    """Names of the requirements that fail at every candidate."""
    return {name for name, v in ln_values_by_name.items() if np.all(v > 0.0)}
