"""Which features a candidate shot can possibly cover, decided cheaply before the full evaluation
(cell.planning.coverage.judge: the maps for the shot's view, the gray at its exposure, the lamp
moved by its tolerance, the dense certificate), so that the judge of a part with many features
evaluates in full only the pairs of a shot and a feature it may cover: a shot sees the few
features in its view, at a fitting angle, in focus and in its lamp's cone.

Exact by construction: coverage.judge covers a feature only when every requirement it asks is met
on the feature's samples (then the certificate decides). The prefilter computes some of those
requirements' values as the judge does, the same functions on the same arrays, and rejects a pair
only where one of them is missed (costs.value(ln f) > 1, RequirementValue.met's test):
- camera_view: samples outside the image (evaluate.in_image), then those hidden from the camera
  (the gray kernel's shadow flag for a lamp at the camera, as evaluate.build_problem casts it) and
  those the spot lamp's housing or the pan-tilt's links hide at the shot's lamp
  (requirements.lamp_hides): the judge counts all together, so a count of the first alone is
  missed there too (at least as much), and the count of all three is the judge's own;
- view_angle and resolution, where the task asks for them (requirements.view_angle_ln,
  resolution_ln), and depth_of_field at the shot's focus and f-number (depth_of_field_ln);
- no_shadow and cone_coverage at the shot's lamp, the spot alone lighting (a task with other
  lights skips these, and the two below: another light may reach a sample the spot does not):
  the kernel's shadow flag and off-axis angle, as evaluate.lit_by_all passes them on without
  other lights;
- gray_min and gray_max at the shot's exposure, the spot alone lighting: G = b + (drive u) t /
  kappa^2 with the kernel's gray per exposure u, the arithmetic of evaluate.at_exposure and
  lit_by_all in their order, so the same numbers (a pair whose gray misses the band skips the
  maps, the certificate and all).
The kernel's flags of a sample depend on the sample, its normal, the mesh and the lamp alone
(kernels.funcs.shade_point; the camera enters only the view and the BRDF), so one launch over the
samples of every feature in question gives each sample the flags the judge's own launch gives it.
lamp_hides tests each sample's line of sight alone (its prefilters only skip lamps and bodies that
can meet none of the lines), so one call over every feature's samples gives each sample its own.
A pair passed is judged in full: the coverage matrix is the full judge's exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, cast

import numpy as np

from cell.devices import rig
from cell.physics import costs, projection
from cell.physics.costs import RequirementValue
from cell.planning import coverage, evaluate, requirements

if TYPE_CHECKING:
    from cell.planning.coverage import Lent
    from cell.planning.plan import Shot
    from cell.task.types import Task


def _missed(name: str, ln: float, detail: str) -> RequirementValue | None:
    """The RequirementValue of a requirement the judge would find missed (None where it is met)."""
    value = float(costs.value(ln))
    return RequirementValue(name, value, f"{detail} (found before the full evaluation)") if value > 1.0 else None


def camera_side(tasks: Sequence[Task], lent: Sequence[Lent], shot: Shot) -> list[list[RequirementValue]]:
    """Per feature of `tasks` (one-feature tasks of one part, each with the samples its own plan
    lent) the requirements of the shot's camera alone (its pose, focus and f-number) missed on
    it: view_angle, resolution, depth_of_field, and camera_view as far as the image's bounds
    decide it. Each sample's numbers are computed over every feature's samples at once (a
    sample's row its own), each feature's extremes and counts over its rows by one reduceat
    each, depth_of_field over every feature asking the same depth at once (depth_of_field_ln
    reads a feature's nearest and farthest depth alone, element by element), and the four
    requirements' values of every feature at once: only a missed one makes its RequirementValue
    (a part's features are many, each shot's pairs with them as many)."""
    if not tasks:
        return []
    scene, bounds = coverage.stacked(lent, shot.T_cell_cam)
    starts = [start for start, _ in bounds]
    outside = np.add.reduceat((~evaluate.in_image(tasks[0], scene)).astype(np.intp), starts)  # the part's camera
    angles = projection.view_angles(scene.camera_position, scene.points, scene.normals)
    largest_angle = np.maximum.reduceat(angles, starts)
    largest_footprint = np.maximum.reduceat(requirements.footprints_at(tasks[0], scene, angles), starts)
    depths = scene.sample_depths()
    nearest, farthest = np.minimum.reduceat(depths, starts), np.maximum.reduceat(depths, starts)
    e = shot.exposure
    focus, kappa = float(e.focus_m), np.array([float(e.f_number)])
    depth_ln = np.empty(len(tasks))
    wanted = np.array([t.requirements.depth_of_field_m for t in tasks])
    for depth in np.unique(wanted):
        same = np.flatnonzero(wanted == depth)
        depth_ln[same] = requirements.depth_of_field_ln(tasks[same[0]], scene, focus, kappa, nearest[same], farthest[same])
    # the four requirements' ln f (rows) of every feature (columns) and their values f as _missed
    # finds them: costs.ln_count_cost's, requirements.view_angle_ln's and resolution_ln's arithmetic
    view_limit = np.array([np.nan if t.requirements.view_angle_rad is None else t.requirements.view_angle_rad
                           for t in tasks])
    pixel_limit = np.array([np.nan if t.requirements.resolution_m is None else t.requirements.resolution_m
                            for t in tasks])
    ln = np.vstack([costs.ln_count_cost(outside), costs.ln_f_max(largest_angle, view_limit),
                    costs.ln_f_max(largest_footprint, pixel_limit), depth_ln])
    value = costs.value(ln)
    missed = value > 1.0
    missed[1] &= ~np.isnan(view_limit)          # asked only where the task gives the limit
    missed[2] &= ~np.isnan(pixel_limit)
    found: list[list[RequirementValue]] = [[] for _ in tasks]
    for k in np.flatnonzero(missed.any(axis=0)).tolist():
        start, end = bounds[k]
        details = (f"samples outside the image, of {end - start}", "the camera sees the samples too obliquely",
                   "a pixel covers too much", f"samples out of focus at f/{e.f_number:.1f}")
        found[k] = [RequirementValue(name, float(value[r, k]), f"{detail} (found before the full evaluation)")
                    for r, (name, detail) in enumerate(zip(CAMERA_SIDE, details)) if missed[r, k]]
    return found


CAMERA_SIDE = ("camera_view", "view_angle", "resolution", "depth_of_field")     # camera_side's, in its order


def lamp_side(tasks: Sequence[Task], lent: Sequence[Lent], shot: Shot) -> list[list[RequirementValue]]:
    """Per feature of `tasks` (one-feature tasks of one part, each with its `lent`) the
    requirements the kernel finds missed: camera_view (a sample outside the image or hidden from
    the camera, by the part, a fixed light's housing, the lamp's housing or its links: the judge's
    count), and without other lights no_shadow, cone_coverage, gray_min and gray_max at the shot's
    lamp and exposure. One launch over every feature's samples, with two lamps: one at the camera,
    the shot's; one lamp_hides over them all."""
    if not tasks:
        return []
    task = tasks[0]
    scene, bounds = coverage.stacked(lent, shot.T_cell_cam)
    pivot = task.lamp.rig.pivot_m
    aims = np.vstack([shot.T_cell_cam[:3, 2], rig.lamp_aim(pivot, shot.lamp_position.reshape(1, 3))])
    out = evaluate.gray_inputs(task, scene, task.part.material)(np.vstack([shot.camera_position,
                                                                          shot.lamp_position]), aims)
    problem = evaluate.build_problem(task, scene, None, focus_m=shot.exposure.focus_m, hidden=out.shadowed[0])
    seen = cast(np.ndarray, problem.camera_seen)
    unseen = ~seen | requirements.lamp_hides(problem, shot.lamp_position.reshape(1, 3))[0]
    spot_drive = np.float64(task.lamp.channel.drive_range[1] if shot.drive is None else shot.drive[0])
    spot_on = spot_drive > 0.0
    half = task.lamp.lit_half_angle_rad
    gain = shot.exposure.shutter_s / shot.exposure.f_number ** 2
    found = []
    for t, (start, end) in zip(tasks, bounds):
        shadowed, off_axis = out.shadowed[1, start:end], out.off_axis[1, start:end]
        n = end - start
        here = [_missed("camera_view", float(costs.ln_count_cost(np.sum(unseen[start:end]))),
                        f"samples the camera cannot see (outside the image, hidden by the part, a light's housing, "
                        f"the lamp's or its links), of {n}")]
        if not t.lights:
            here.append(_missed("no_shadow", float(costs.ln_count_cost(np.sum(shadowed | ~spot_on))),
                                f"samples shadowed from the lamp, of {n}"))
            here.append(_missed("cone_coverage", float(costs.ln_f_max(np.max(np.where(spot_on, off_axis, 0.0)), half)),
                                "samples outside the lamp's cone"))
            gray = evaluate.black_level(t) + (spot_drive * out.value[1, start:end]) * gain
            low, high = evaluate.planning_band(t)
            here.append(_missed("gray_min", float(requirements.at_least(np.min(gray), low)),
                                f"darkest sample gray {np.min(gray):.1f} at the shot's exposure (band {low:g}-{high:g})"))
            here.append(_missed("gray_max", float(costs.ln_f_max(np.max(gray), high)),
                                f"brightest sample gray {np.max(gray):.1f} at the shot's exposure (band {low:g}-{high:g})"))
        found.append([r for r in here if r is not None])
    return found


def missed(tasks: Sequence[Task], lent: Sequence[Lent], shot: Shot, skip: int) -> list[tuple[RequirementValue, ...]]:
    """Per feature of `tasks` (one-feature tasks of one part, each with the samples its own plan
    lent) the requirements `shot` misses on it for sure (empty: it may cover it, the full judge
    decides; also at `skip`, the shot's own feature): the camera's first, then one launch of the
    kernel over the features left."""
    others = [g for g in range(len(tasks)) if g != skip]
    found: list[list[RequirementValue]] = [[] for _ in tasks]
    for g, here in zip(others, camera_side([tasks[g] for g in others], [lent[g] for g in others], shot)):
        found[g] = here
    left = [g for g in others if not found[g]]
    for g, more in zip(left, lamp_side([tasks[g] for g in left], [lent[g] for g in left], shot)):
        found[g] = more
    return [tuple(f) for f in found]
