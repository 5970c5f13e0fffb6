"""The judge's work over every feature a candidate shot may cover at once (prefilter.camera_side's
reductions over each feature's rows, depth_of_field_ln over several features' depth ranges) and
the view angles a Problem computes once for the view angle and the resolution: bit for bit what
each feature alone, and each requirement alone, computes."""
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from cell.core import geometry
from cell.physics import costs, projection
from cell.planning import coverage, evaluate, prefilter, requirements
from cell.planning.scene import build_scene, look_at
from cell.task.loader import load_task

TASKS = Path(__file__).resolve().parent.parent / "tasks"


def camera_side_alone(tasks, lent, shot):
    """prefilter.camera_side feature by feature: each feature's own slices of the stacked samples,
    depth_of_field_ln on its own depth range (the per-feature loop camera_side replaced)."""
    scene, bounds = coverage.stacked(lent, shot.T_cell_cam)
    outside = ~evaluate.in_image(tasks[0], scene)
    angles = projection.view_angles(scene.camera_position, scene.points, scene.normals)
    footprints = requirements.footprints_at(tasks[0], scene)
    depths = scene.sample_depths()
    e = shot.exposure
    found = []
    for task, (start, end) in zip(tasks, bounds):
        asked = task.requirements
        here = [prefilter._missed("camera_view", float(costs.ln_count_cost(np.sum(outside[start:end]))),
                                  f"samples outside the image, of {end - start}")]
        if asked.view_angle_rad is not None:
            here.append(prefilter._missed("view_angle", requirements.view_angle_ln(
                task, scene, float(angles[start:end].max())), "the camera sees the samples too obliquely"))
        if asked.resolution_m is not None:
            here.append(prefilter._missed("resolution", requirements.resolution_ln(
                task, scene, footprints[start:end].max()), "a pixel covers too much"))
        ln = requirements.depth_of_field_ln(task, scene, float(e.focus_m), np.array([float(e.f_number)]),
                                            depths[start:end].min(), depths[start:end].max())[0]
        here.append(prefilter._missed("depth_of_field", float(ln), f"samples out of focus at f/{e.f_number:.1f}"))
        found.append([r for r in here if r is not None])
    return found


def varied_tasks(rng):
    """The bracket's features, twice, at other sample counts and with other requirements each: a
    depth of field of 0, 2 or 5 mm, a view angle and a resolution asked or not, tight or loose."""
    task = load_task(TASKS / "bracket.yaml")
    out = []
    for copy in range(2):
        for g in range(len(task.features)):
            f = task.features[g]
            asked = replace(f.requirements, depth_of_field_m=float(rng.choice([0.0, 0.002, 0.005])),
                            view_angle_rad=None if rng.random() < 0.3 else float(rng.uniform(0.3, 1.4)),
                            resolution_m=None if rng.random() < 0.3 else float(rng.uniform(2e-5, 3e-4)))
            out.append(replace(task, features=(replace(f, requirements=asked, samples=f.samples + 7 * copy),)))
    return out


def test_the_camera_side_over_every_feature_at_once_is_each_features_own():
    """Shots from random camera poses about the bracket, random focus and f-number: camera_side's
    requirement values and sentences equal the per-feature loop's exactly, and the poses give
    both kinds (some features missed, some not) of each requirement."""
    rng = np.random.default_rng(28)
    tasks = varied_tasks(rng)
    lent = [SimpleNamespace(scene=build_scene(t)) for t in tasks]
    middle = np.mean([x.scene.center for x in lent], axis=0)
    missed_names, kept = set(), 0
    for _ in range(40):
        direction = geometry.unit(rng.normal(0.0, 1.0, 3))
        T = look_at(middle + rng.uniform(0.1, 0.5) * direction, middle + rng.normal(0.0, 0.01, 3))
        shot = SimpleNamespace(T_cell_cam=T, exposure=SimpleNamespace(focus_m=float(rng.uniform(0.08, 0.6)),
                                                                      f_number=float(rng.uniform(1.4, 16.0))))
        bulk, alone = prefilter.camera_side(tasks, lent, shot), camera_side_alone(tasks, lent, shot)
        assert bulk == alone
        missed_names |= {r.name for here in bulk for r in here}
        kept += sum(not here for here in bulk)
    assert missed_names == {"camera_view", "view_angle", "resolution", "depth_of_field"} and kept > 0


def test_depth_of_field_over_several_ranges_is_each_ranges_own():
    """depth_of_field_ln given arrays of nearest and farthest depths: each value is the one of its
    range alone, at random focus, f-numbers and ranges (some beyond the hyperfocal distance)."""
    rng = np.random.default_rng(7)
    task = load_task(TASKS / "bracket.yaml").with_feature(0)
    scene = build_scene(task)
    for wanted in (0.0, 0.004):
        t = replace(task, features=(replace(task.feature, requirements=replace(task.requirements,
                                                                               depth_of_field_m=wanted)),))
        for _ in range(50):
            focus, kappa = float(rng.uniform(0.05, 3.0)), np.array([float(rng.uniform(1.0, 32.0))])
            nearest = rng.uniform(0.03, 2.0, 9)
            farthest = nearest + rng.uniform(0.0, 0.5, 9)
            together = requirements.depth_of_field_ln(t, scene, focus, kappa, nearest, farthest)
            alone = [requirements.depth_of_field_ln(t, scene, focus, kappa, nearest[k], farthest[k])[0]
                     for k in range(9)]
            assert np.array_equal(together, alone)


def test_a_problems_view_angles_serve_the_view_angle_and_the_resolution_as_each_computes_them():
    """The view angle and the resolution of a Problem read its view angles once (Problem.fixed):
    the footprints and the largest angle equal those computed from the scene alone, bit for bit,
    and a footprint given the angles equals one that computes them."""
    task = load_task(TASKS / "bracket.yaml")
    rng = np.random.default_rng(3)
    for g in range(len(task.features)):
        t = task.with_feature(g)
        base = build_scene(t, 400)
        direction = geometry.unit(base.normal + 0.6 * rng.normal(0.0, 1.0, 3))
        scene = replace(base, T_cell_cam=look_at(base.center + 0.25 * direction, base.center))
        p = evaluate.build_problem(t, scene, None)
        assert np.array_equal(requirements.footprints(p), projection.pixel_footprint(
            scene.camera_position, scene.points, scene.normals, t.camera.sensor.pixel_pitch_m,
            t.camera.lens.focal_length_m))
        assert requirements.problem_view_angle(p) == requirements.largest_view_angle(scene)
        angles = requirements.problem_view_angles(p)
        assert np.array_equal(requirements.footprints_at(t, scene, angles), requirements.footprints_at(t, scene))


def test_a_shared_launchs_shadow_flags_are_each_scenes_own():
    """SharedLaunches over the bracket's features seen by one camera: each scene's rows of the
    shadow flags of a lamp at the camera (build_problem's hidden samples) equal those of its own
    GrayInputs, alone and in a gray call, and its Problem counts the same samples unseen."""
    task = load_task(TASKS / "bracket.yaml")
    tasks = [task.with_feature(g) for g in range(len(task.features))]
    scenes = [build_scene(t) for t in tasks]
    middle = np.mean([s.center for s in scenes], axis=0)
    unseen = 0
    for k, T in enumerate([s.T_cell_cam for s in scenes] + [look_at(middle + (0.1, -0.2, 0.25), middle)]):
        seen = [replace(s, T_cell_cam=T) for s in scenes]
        joined = replace(seen[0], points=np.vstack([s.points for s in seen]), normals=np.vstack([s.normals for s in seen]))
        shared = evaluate.SharedLaunches(evaluate.gray_inputs(tasks[0], joined, task.part.material),
                                         [len(s.points) for s in seen])
        camera = T[:3, 3][None]
        for g, (t, s) in enumerate(zip(tasks, seen)):
            own = evaluate.gray_inputs(t, s, task.part.material)
            flags = shared.rows(g).shadowed(camera)
            assert np.array_equal(flags, own.shadowed(camera)) and np.array_equal(flags, own(camera, T[None, :3, 2]).shadowed)
            together = evaluate.build_problem(t, s, None, gray=shared.rows(g))
            alone = evaluate.build_problem(t, s, None)
            assert together.camera_unseen == alone.camera_unseen
            assert np.array_equal(together.camera_seen, alone.camera_seen)
            unseen += int(flags.sum())
    assert unseen > 0
