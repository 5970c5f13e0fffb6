"""The judge's shared work (a candidate shot judged on every feature it may cover): what one
camera pose places, made once and served to every Problem on that pose, equals what each
Problem made alone; the judged coverage the same as before."""
from dataclasses import replace
from pathlib import Path

import numpy as np

from cell.collision.rays import box_capsules
from cell.collision.scene import arm_links, camera_body, reaching_joints
from cell.core import geometry
from cell.planning import evaluate
from cell.planning.scene import build_scene, look_at
from cell.task.loader import load_task

TASKS = Path(__file__).resolve().parent.parent / "tasks"


def arm_made_alone(task, T_cell_cam):
    """The camera body and the arm's links at T_cell_cam as arm_at_shot made them before the
    camera's part was kept (the same functions, called afresh)."""
    c, frames = task.cell.collision, task.frames
    box = camera_body(frames.T_cell_flange(T_cell_cam), 0.5 * np.asarray(c.camera_size_m, float), c.camera_offset_m)
    q = reaching_joints(frames, T_cell_cam)
    links = () if q is None else arm_links(frames.T_cell_base, q)
    a = np.array([k.a for k in links]).reshape(-1, 3)
    b = np.array([k.b for k in links]).reshape(-1, 3)
    radius = np.array([k.radius_m for k in links])
    box_a, box_b, box_radius = box_capsules(box.T_cell_box, box.half_m)
    return (box.T_cell_box, box.half_m, a, b, radius, np.vstack([box_a, a]), np.vstack([box_b, b]),
            np.concatenate([box_radius, radius]))


def poses(scene, rng, count):
    """Camera poses looking at the feature from random directions above it, 0.15-0.6 m away
    (some beyond the arm's reach), and one far out of reach."""
    directions = geometry.unit(rng.normal(0.0, 1.0, (count, 3)) + 2.0 * scene.normal)
    distances = rng.uniform(0.15, 0.6, count)
    out = [look_at(scene.center + d * u, scene.center) for d, u in zip(distances, directions)]
    return out + [look_at(scene.center + 5.0 * scene.normal, scene.center)]


def test_the_arm_at_a_camera_pose_made_once_equals_the_arm_made_for_each_problem():
    """arm_at_camera's bodies, asked again for many poses in turn and back (kept and evicted),
    for another robot base and hand-eye on the same pose, bit for bit those made afresh; arm_at_shot's
    balls about each scene's own samples."""
    task = load_task(TASKS / "bracket.yaml")
    rng = np.random.default_rng(28)
    scene = build_scene(task.with_feature(0))
    T = poses(scene, rng, 12)
    moved = replace(task, frames=replace(task.frames, T_cell_base=task.frames.T_cell_base
                                          @ geometry.transform(translation=(0.05, -0.03, 0.0))))
    moved = moved.with_feature(0)
    reached = 0
    for k in [*range(len(T)), 3, 0, 12, 1, 1]:
        for t in (task, moved):
            kept, alone = evaluate.arm_at_camera(t, T[k]), arm_made_alone(t, T[k])
            assert len(kept) == len(alone) == 8
            for x, y in zip(kept, alone):
                assert x.shape == y.shape and np.array_equal(x, y)
                assert not x.flags.writeable
            reached += len(kept[2]) > 0
    assert 0 < reached < 2 * 17             # poses the arm reaches and one it does not (no links)
    assert not np.array_equal(evaluate.arm_at_camera(task, T[0])[2], evaluate.arm_at_camera(moved, T[0])[2])
    for g in range(len(task.features)):      # arm_at_shot: the camera's bodies, the balls about the scene's samples
        s = build_scene(task.with_feature(g), T_cell_cam=T[0])
        arm = evaluate.arm_at_shot(task, s)
        middle, rho = geometry.bounding_sphere(s.points)
        assert np.array_equal(arm.middle, middle) and arm.rho == rho
        assert all(np.array_equal(x, y) for x, y in zip(
            (arm.T_cell_box, arm.half_m, arm.a, arm.b, arm.radius_m, arm.around_a, arm.around_b, arm.around_radius_m),
            arm_made_alone(task, T[0])))


def test_no_more_camera_poses_are_kept_than_the_limit():
    task = load_task(TASKS / "bracket.yaml")
    scene = build_scene(task.with_feature(0))
    for T in poses(scene, np.random.default_rng(5), 3 * evaluate._AT_CAMERA.most):
        evaluate.arm_at_camera(task, T)
    assert len(evaluate._AT_CAMERA) == evaluate._AT_CAMERA.most


def test_a_lamps_tolerance_moves_made_once_equal_those_made_for_each_problem():
    """moved_positions, asked for many lamps in turn and back (kept and evicted) and for another
    tolerance on the same joints, bit for bit each move's rig.lamp_position made afresh (as
    at_exposure placed them before), read-only, none without a tolerance; no more kept than the limit."""
    from cell.devices import rig
    task = load_task(TASKS / "bracket.yaml").with_feature(0)

    def tolerance(rad):
        feature = replace(task.feature, requirements=replace(task.requirements, lamp_tolerance_rad=rad))
        return replace(task, features=(feature,))
    wider, none = tolerance(2.0 * task.requirements.lamp_tolerance_rad), tolerance(0.0)
    scene = build_scene(task)
    problems = [evaluate.build_problem(t, scene, None) for t in (task, wider, none)]
    rng = np.random.default_rng(28)
    joints = [tuple(x) for x in np.column_stack([rng.uniform(-3.0, 3.0, 9), rng.uniform(-0.3, 1.4, 9),
                                                 rng.uniform(0.2, 0.6, 9)]).tolist()]
    pivot = task.lamp.rig.pivot_m
    for k in [*range(len(joints)), 2, 0, 8, 8]:
        for p in problems:
            d_pan, d_tilt = evaluate.tolerance_moves(p, np.array([joints[k][1]]))
            alone = [rig.lamp_position(pivot, joints[k][0] + dp, joints[k][1] + dt, joints[k][2]).reshape(1, 3)
                     for dp, dt in zip(d_pan, d_tilt)]
            kept = evaluate.moved_positions(p, joints[k])
            assert kept.shape == (len(alone), 3) and not kept.flags.writeable
            assert np.array_equal(kept, np.vstack([np.zeros((0, 3)), *alone]))
            assert len(kept) == (0 if p.task is none else evaluate.TOLERANCE_RING)
    assert not np.array_equal(evaluate.moved_positions(problems[0], joints[0]),
                              evaluate.moved_positions(problems[1], joints[0]))
    assert len(evaluate._MOVED) == evaluate._MOVED.most


def test_the_prefilter_counts_the_samples_the_lamp_hides_as_the_judge_does():
    """A bracket shot (a global search for its first feature) with its lamp moved onto the camera's
    lines of sight to the other features: the prefilter (one lamp_hides over every feature's
    samples) rejects a pair for camera_view only where the full judge (coverage.judge) misses it,
    with the judge's own value, and judge_column's coverage is the full judge's; the lamp's
    housing hides samples of some features the part and the image's bounds leave seen."""
    from cell.planning import coverage, one_shot, prefilter, regions, requirements
    from cell.planning.whole_part import judge_column
    task = load_task(TASKS / "bracket.yaml")
    tasks = [task.with_feature(g) for g in range(len(task.features))]
    settings = replace(one_shot.PlannerSettings(), refine=False)
    plan, _ = one_shot.search(tasks[0], settings, 1.0, np.zeros((0, 3)), lambda message: None)
    grid = regions.SphereGrid(np.radians(settings.grid_step_deg))
    scenes = [build_scene(t) for t in tasks]
    lent = [coverage.Lent(s, settings, one_shot.visibility_map(s, grid)) for s in scenes]
    camera = plan.shot.camera_position
    lamps = [plan.shot.lamp_position] + [s.center + t * (camera - s.center) for s in scenes[1:] for t in (0.3, 0.5, 0.7)]
    by_lamp = 0
    for lamp in lamps:
        shot = replace(plan.shot, lamp_position=np.asarray(lamp, float))
        missed = prefilter.missed(tasks, lent, shot, 0)
        column, _, _ = judge_column(tasks, 0, shot, lent, lambda message: None)
        for g in range(1, len(tasks)):
            alone = coverage.judge(tasks[g], lent[g], shot)
            assert column[g].covered == alone.covered
            values = {r.name: r.value for r in alone.requirements}
            named = {r.name: r.value for r in missed[g]}
            scene = replace(lent[g].scene, T_cell_cam=shot.T_cell_cam)
            # samples outside the image: the camera's side alone counts them, the judge those and the hidden ones
            inside = evaluate.in_image(tasks[g], scene).all()
            assert all(values[name] == value > 1.0 or name == "camera_view" and not inside and values[name] >= value > 1.0
                       for name, value in named.items())
            if "camera_view" in named and inside:
                problem = evaluate.build_problem(tasks[g], scene, None)
                by_lamp += problem.camera_unseen == 0 and requirements.lamp_hides(problem, lamp[None]).any()
    assert by_lamp >= 2


def test_a_shots_samples_of_several_features_at_once_give_each_what_its_own_problem_finds():
    """The bracket's first-feature shot, its lamp also moved onto the camera's lines of sight to
    the other features and next to the camera: each feature's samples judged with their rows of
    one Problem over every feature's (coverage.on_samples, what_whole_gives: the samples the camera
    sees, view angles, footprints, the lamp's hides, the camera body's and the arm's shadows)
    give the very values, sentences, gray, shadows and exposure of the feature's own Problem
    made alone as before (its own gray kernel, every value found from its own samples); some
    samples hidden by the lamp and some shadowed by the camera body or the arm among them."""
    from cell.planning import coverage, one_shot, regions, requirements
    task = load_task(TASKS / "bracket.yaml")
    tasks = [task.with_feature(g) for g in range(len(task.features))]
    settings = replace(one_shot.PlannerSettings(), refine=False)
    plan, _ = one_shot.search(tasks[0], settings, 1.0, np.zeros((0, 3)), lambda message: None)
    grid = regions.SphereGrid(np.radians(settings.grid_step_deg))
    lent = [coverage.Lent(s, settings, one_shot.visibility_map(s, grid)) for s in (build_scene(t) for t in tasks)]
    camera = plan.shot.camera_position
    lamps = [plan.shot.lamp_position] + [x.scene.center + t * (camera - x.scene.center)
                                         for x in lent[1:] for t in (0.3, 0.5, 0.7, 0.9)]
    hidden = shadowed = 0
    for lamp in lamps:
        shot = replace(plan.shot, lamp_position=np.asarray(lamp, float))
        e = shot.exposure
        scene, bounds = coverage.stacked(lent, shot.T_cell_cam)
        shared = evaluate.SharedLaunches(evaluate.gray_inputs(task, scene, task.part.material.scaled(1.0)),
                                         [end - start for start, end in bounds])
        whole = evaluate.build_problem(tasks[0], scene, None, focus_m=e.focus_m,
                                       gray=evaluate.Rows(shared, 0, len(scene.points)))
        for k, (t, x) in enumerate(zip(tasks, lent)):
            seen_by = replace(x.scene, T_cell_cam=shot.T_cell_cam)
            got = coverage.on_samples(t, x, seen_by, shot, shared.rows(k), whole)
            alone = evaluate.build_problem(t, seen_by, one_shot.build_maps(t, seen_by, settings, visible=x.visible),
                                           focus_m=e.focus_m)
            c = evaluate.at_exposure(alone, shot.lamp_position, e.shutter_s, e.f_number, joints=shot.joints,
                                     drive=shot.drive)
            assert got.values == requirements.judged(alone, c, requirements.ln_values(alone, c))
            assert [r.amount for r in got.values] == [r.amount for r in requirements.judged(alone, c, requirements.ln_values(alone, c))]
            assert np.array_equal(got.problem.camera_seen, alone.camera_seen)
            assert got.problem.camera_unseen == alone.camera_unseen
            lamps_at = np.vstack([shot.lamp_position[None], evaluate.moved_positions(alone, shot.joints)])
            for mine, own in ((evaluate.spot_blocked(got.problem, lamps_at), evaluate.spot_blocked(alone, lamps_at)),
                              (requirements.lamp_hides(got.problem, shot.lamp_position[None]),
                               requirements.lamp_hides(alone, shot.lamp_position[None])),
                              (requirements.problem_view_angles(got.problem), requirements.problem_view_angles(alone)),
                              (requirements.footprints(got.problem), requirements.footprints(alone))):
                assert mine.shape == own.shape and np.array_equal(mine, own)
            assert np.array_equal(got.gray, np.minimum(c.gray[0], 2.0 ** t.camera.sensor.bit_depth - 1))
            hidden += int(requirements.lamp_hides(alone, shot.lamp_position[None]).sum())
            shadowed += int(evaluate.spot_blocked(alone, lamps_at).sum())
    assert hidden > 0 and shadowed > 0
