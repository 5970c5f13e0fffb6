"""The moves of the closed loop after localization (issue 27): from where a further view left the
camera and the lamp back to the shot planned for where the part is. The order of the camera's and
the lamp's moves (cell.run.motion: the camera first, or the lamp first where the camera's path
with the lamp where it stands is not clear, logged), the re-plan for where the part is, which
takes the best lamp pose clear of the cell's bodies (cell.run.loop.follow, one_shot.plan), and its last resort where that shot cannot be taken (cell.run.loop.lamp_kept: the
plan carried along with the part). The independent judges are the simulated cell's own
collision check (sim.obstacles: other geometry, other distances), which stops a move that would
hit and lets the chosen one through, and the exact distance of its housings' boxes (box_gap)."""
import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.distance import cdist

from cell.collision.scene import reaching_joints
from cell.core.errors import DeviceFault, GoalNotReached
from cell.core.geometry import apply
from cell.devices import ur5e
from cell.devices.rig import lamp_frame, lamp_position
from cell.planning import evaluate
from cell.planning.one_shot import plan
from cell.planning.plan import PlannerSettings
from cell.planning.scene import look_at
from cell.planning.whole_part import assigned, cleared, feature_plan
from cell.report.recorder import Recorder
from cell.run import localization, motion
from cell.run.context import RunContext
from cell.run.inspection import run_shot
from cell.run.loop import (Aim, Corrected, LoopFeature, Split, follow, iterate, lamp_kept, viewpoint_replanned,
                           where_located, with_black_level)
from cell.run.measurement import BlackLevel
from cell.task.loader import load_task
from sim.obstacles import Obstacles
from dense import acceptance_failures, patch_surface, shade
from simcell import run_loop, variant
from test_bracket import bracket  # noqa: F401  (the fixture: the bracket and its plan)
from test_localization import error as localization_error
from test_mismatch import cases as mismatch_cases, run_job as mismatch_run
from test_motion import sim_devices

ROOT = Path(__file__).resolve().parent.parent
HINGE, CONROD = ROOT / "tasks" / "hinge.yaml", ROOT / "tasks" / "conrod.yaml"


def steps(folder):
    return [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]


def lamp_at(task, joints):
    """The lamp's position [m] at (pan, tilt, radius): pan -180 and 180 deg alike."""
    return lamp_position(task.lamp.rig.pivot_m, *joints)


def crossing(task):
    """Two stops of the hinge's cell (camera pose, its joints, lamp joints): A, the camera 0.35 m
    from the pivot up and aside, the lamp low at pan 0; B, the camera low at pan 0 where that
    lamp stands, the lamp at pan 180 deg, 45 deg up."""
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    T_a, T_b = look_at(pivot + (-0.1, 0.15, 0.3), pivot), look_at(pivot + (0.2, 0.0, 0.17), pivot)
    a = (T_a, np.asarray(reaching_joints(task.frames, T_a), float), (0.0, np.radians(30.0), 0.2))
    b = (T_b, np.asarray(reaching_joints(task.frames, T_b), float), (np.pi, np.radians(45.0), 0.2))
    return a, b


@pytest.mark.parametrize("lamp_first", [True, False], ids=["A to B: the lamp first", "B to A: the camera first"])
def test_the_order_of_the_camera_s_and_the_lamp_s_moves_is_the_one_the_simulator_lets_through(tmp_path, lamp_first):
    """crossing's A to B: the camera first would run into the lamp standing low (the
    simulator's own check stops it); the lamp first, then the camera, goes through, and a
    `move_order` step says so. B to A: the lamp first would swing into the camera standing low
    (the simulator stops it, its tilt servo passing the UR5e's upper arm first on the pan's way
    round through -90 deg); the camera first, then the lamp, goes through: the default order, no
    `move_order` step."""
    task = load_task(HINGE)
    (T_from, q_from, lamp_from), (T_to, _, lamp_to) = crossing(task)[::1 if lamp_first else -1]
    hit = sim_devices(task, q_from, lamp_from)
    with pytest.raises(DeviceFault, match="camera housing would hit the lamp" if lamp_first else
                       "(lamp housing|tilt servo) would hit the (camera|arm link)"):
        hit.arm.move_camera(T_to) if lamp_first else hit.lamp.move(*lamp_to)
    devices = sim_devices(task, q_from, lamp_from)
    with Recorder(tmp_path / "run") as recorder:
        move = motion.go(task, devices, recorder, T_to, lamp_to, to="the shot's poses")
    assert move.clear and move.lamp_first == lamp_first
    assert devices.arm.camera_pose() == pytest.approx(T_to, abs=1e-9)
    assert lamp_at(task, devices.lamp.joints()) == pytest.approx(lamp_at(task, lamp_to), abs=1e-3)
    orders = [s["message"] for s in steps(tmp_path / "run") if s["step"] == "move_order"]
    assert len(orders) == lamp_first and all(o.startswith("the lamp first, then the camera") for o in orders)


def housings_apart(task, located, shot):
    """The least distance [m] between the simulator's camera housing, the arm's flange where the
    located hand-eye puts the true camera at the shot's pose, and its lamp housing at the shot's
    joints (sim.obstacles' sampled boxes, every pair of samples)."""
    world = Obstacles(task)
    q = np.asarray(reaching_joints(located.frames, shot.T_cell_cam), float)
    lamp = world.lamp(lamp_position(task.lamp.rig.pivot_m, *shot.joints))
    return float(cdist(world.camera(q), lamp).min())


@pytest.fixture(scope="module")
def conrod_plan():
    """The conrod's task and its plan (planned once for the module)."""
    task = load_task(CONROD)
    return task, plan(task)


def conrod_further_view(conrod_plan):
    """The conrod planned, its camera found turned 2 deg about x (the mismatch matrix's case,
    seed 1: the estimate 1.91 deg), the arm where capture 1 stood (the plan's camera pose as the
    uncorrected hand-eye puts it), the lamp low at pan 0, 25 deg up, where the further view left
    it. (task, plan, pose error, located task, simulated devices)."""
    task, planned = conrod_plan
    zero = np.zeros(3)
    error = localization.PoseError(zero, zero, np.radians([1.91, -0.09, 0.02]), zero, zero, zero, zero, 3, 0, 0.0)
    further = (0.0, np.radians(24.96), planned.shot.joints[2])
    devices = sim_devices(task, np.asarray(reaching_joints(task.frames, planned.shot.T_cell_cam), float), further)
    return task, planned, error, localization.located_task(task, error), devices


# the run's re-plan by a search that did not know the cell's bodies (located-1/plan.json before
# the re-plans searched among the clear lamp poses)
REPLANNED_LAMP = (np.radians(63.95), np.radians(72.51), 0.22655)


def test_a_re_planned_shot_whose_move_is_refused_keeps_the_plan_s_lamp(tmp_path, conrod_plan):
    """The mismatch matrix's conrod, its camera turned 2 deg about x: localized with a further
    view (the lamp low), a re-planned shot whose move is refused (the lamp at pan 64 deg, 72.5 deg
    up, 0.2265 m, where a search without the cell's bodies put it: under the 10 mm padding from
    the camera body where the corrected hand-eye puts it, so no order of the moves reaches it).
    The simulator's own housings agree that that shot is under the padding. The loop's last
    resort: the plan carried along with the part (the lamp at the plan's joints, the camera at
    the plan's view of the part): its shot keeps the padding by the simulator's housings too, and
    its move from where the further view left the cell goes through the simulator's own check."""
    task, planned, error, located, devices = conrod_further_view(conrod_plan)
    padding = task.cell.collision.padding_m
    replanned = SimpleNamespace(T_cell_cam=error.T_part @ planned.shot.T_cell_cam, joints=REPLANNED_LAMP)
    assert housings_apart(task, located, replanned) < padding
    with Recorder(tmp_path / "run") as recorder:
        ctx = RunContext(located, devices, recorder, 6)
        refused = where_located(ctx, located, replanned, error)
        assert not refused.clear and set(refused.clearance.bodies) == {"camera_body", "lamp_body"}
        kept = lamp_kept(ctx, LoopFeature.planned(located, planned), error,
                         f"the move there is refused: {motion.refusal(refused)}")
        shot = kept.plan.shot
        assert shot.joints == planned.shot.joints
        assert shot.T_cell_cam == pytest.approx(error.T_part @ planned.shot.T_cell_cam, abs=1e-12)
        assert "the plan's lamp pose kept" in kept.why and "camera_body and lamp_body" in kept.why
        assert housings_apart(task, located, shot) >= padding
        assert devices.arm.moves == 0 and devices.lamp.moves == 0          # lamp_kept moves nothing
        corrected = localization.corrected(devices, error)
        motion.go(located, corrected, recorder, shot.T_cell_cam, shot.joints, to="the shot's poses")
    assert corrected.arm.camera_pose() == pytest.approx(shot.T_cell_cam, abs=1e-9)
    assert lamp_at(task, devices.lamp.joints()) == pytest.approx(lamp_at(task, shot.joints), abs=1e-3)


def test_where_the_plan_carried_along_is_refused_too_the_run_stops_pose_naming_both(tmp_path, conrod_plan):
    """The loop's plan with its lamp where the re-plan put it: carried along, it is refused as
    the re-plan was; cause `pose`, the pose found and both refusals named, nothing moved."""
    task, planned, error, located, devices = conrod_further_view(conrod_plan)
    replanned = SimpleNamespace(T_cell_cam=error.T_part @ planned.shot.T_cell_cam, joints=REPLANNED_LAMP)
    feature = LoopFeature.planned(located, planned)
    lamp_there = replace(planned, shots=(replace(planned.shot, joints=REPLANNED_LAMP),))
    with Recorder(tmp_path / "run") as recorder, pytest.raises(GoalNotReached) as stop:
        ctx = RunContext(located, devices, recorder, 6)
        refused = where_located(ctx, located, replanned, error)
        lamp_kept(ctx, replace(feature, model=replace(feature.model, plan=lamp_there)), error,
                  f"the move there is refused: {motion.refusal(refused)}")
    assert stop.value.cause == "pose"
    said = str(stop.value)
    assert said.startswith("the part is off by") and "with the lamp kept at the plan's pose: collision: " in said
    assert said.count("camera_body and lamp_body") == 2
    assert devices.arm.moves == 0 and devices.lamp.moves == 0


@pytest.mark.long
def test_the_conrod_with_its_camera_turned_2_deg_converges_from_its_further_view(tmp_path):
    """The mismatch matrix's case end to end (conrod, sim.truth.camera_rpy_deg [2, 0, 0], seed 1,
    every effect; about 5 minutes): localized from a further view with the lamp low, the shot
    re-planned there with its lamp clear of the cell's bodies (a search without them put it
    under the padding from the camera body), no lamp kept; the run converges within the
    matrix's 6 captures, the hand-eye's turn found within 0.3 deg and the part within 1 mm of
    where it is (the truth: not moved)."""
    keys = {"sim.effects": ["shadows", "cone_falloff", "vignetting", "defocus", "noise", "black_level", "quantization"],
            "sim.seed": 1, "sim.truth.camera_rpy_deg": [2.0, 0.0, 0.0]}
    cell = run_loop(variant(tmp_path, CONROD, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    captures = len(cell.report["iterations"]) + sum(line["step"] == "capture" and line["message"].startswith("locate-")
                                                    for line in cell.log)
    assert captures <= 6
    found = cell.report["localization"]
    assert found["followed"] and found["hand_eye_rpy_deg"] == pytest.approx([2.0, 0.0, 0.0], abs=0.3)
    assert found["part_offset_m"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert not any(line["step"] == "correct" and "lamp_kept" in line for line in cell.log)
    (located,) = [r["plan"] for r in cell.report["replans"] if r["iteration"] == found["iteration"]]
    assert located["feasible"] and located["clearance_m"] >= 0.01


def box_gap(a, b):
    """The exact distance [m] between two solid boxes, each (centre (3,), rotation (3, 3), half
    sizes (3,)): the least |x - y| over x = c_a + R_a (h_a u), y = c_b + R_b (h_b v), u and v in
    [-1, 1]^3, a convex problem that L-BFGS-B solves to its global minimum (0 where they overlap)."""
    (ca, Ra, ha), (cb, Rb, hb) = a, b

    def squared(z):
        d = ca + Ra @ (ha * z[:3]) - cb - Rb @ (hb * z[3:])
        return d @ d, np.concatenate([2 * ha * (Ra.T @ d), -2 * hb * (Rb.T @ d)])
    best = minimize(squared, np.zeros(6), jac=True, method="L-BFGS-B", bounds=[(-1, 1)] * 6,
                    options={"ftol": 1e-15, "gtol": 1e-12})
    return float(np.sqrt(max(best.fun, 0.0)))


def sim_housings(task, arm_joints, lamp_joints):
    """The simulator's camera and lamp housings (sim.obstacles.Obstacles' boxes of the task's
    `cell.collision` sizes: the camera's centred offset_m along the flange's z at the arm's
    joints, the lamp's front face at its position, its z the aim at the pivot) as box_gap's
    (centre, rotation, half sizes)."""
    c = task.cell.collision
    flange = task.frames.T_cell_base @ ur5e.forward(np.asarray(arm_joints, float))
    camera = (flange[:3, :3] @ [0.0, 0.0, c.camera_offset_m] + flange[:3, 3], flange[:3, :3],
              0.5 * np.asarray(c.camera_size_m, float))
    position = lamp_at(task, lamp_joints)
    R = lamp_frame(np.asarray(task.lamp.rig.pivot_m, float), position)
    half = 0.5 * np.asarray(c.lamp_size_m, float)
    return camera, (position - half[2] * R[:, 2], R, half)


# the run's estimate where it re-planned (conrod, sim.truth.camera_rpy_deg [2, 0, 0], seed 1, every
# effect; 3 views) and the black level its dark frame found, which every re-plan knows
RUN_ESTIMATE = localization.PoseError(np.array([-0.56, -0.52, 0.28]) * 1e-3, np.radians([-0.09, 0.05, -0.02]),
                                      np.radians([1.91, -0.09, 0.02]), *np.zeros((4, 3)), 3, 0, 0.0)
RUN_BLACK = 5.0


def followed(tmp_path, conrod_plan, task=None):
    """loop.follow on the conrod's RUN_ESTIMATE after its further view (conrod_further_view's
    cell; `task`: the conrod's as the loop knows it, by default with RUN_BLACK): (its events, the
    Aim it returns or the GoalNotReached it raised, the located task, the devices)."""
    conrod, planned, _, _, devices = conrod_further_view(conrod_plan)
    task = task or with_black_level(conrod, RUN_BLACK)
    feature = LoopFeature.planned(task, planned)
    aim = Aim((feature,), BlackLevel(RUN_BLACK, 0.0, "task"), planned.shot.exposure.shutter_s,
              planned.shot.exposure.f_number)
    events = []
    with Recorder(tmp_path / "run") as recorder:
        steps = follow(RunContext(task, devices, recorder, 6), aim, 1, RUN_ESTIMATE)
        try:
            while True:
                events.append(next(steps))
        except StopIteration as end:
            result = end.value
        except GoalNotReached as stop:
            result = stop
    return events, result, localization.located_task(task, RUN_ESTIMATE), devices


def test_the_re_plan_for_where_the_part_is_takes_the_best_lamp_pose_clear_of_the_cell(tmp_path, conrod_plan):
    """The conrod's run above, re-planned for where it localized the part and the camera: the
    best lamp pose of a search that does not know the cell's bodies stands under the 10 mm
    padding from the camera body where the corrected hand-eye puts it (by the planner's check, a
    lower bound of the distance: 8.0 mm; the simulator's housings' exact distance is 9.95 mm);
    loop.follow's re-plan takes the best pose clear of them instead,
    feasible, its clearance at least the padding, no lamp kept. The simulator's own check lets
    the move there through, and its housings where the arm and the lamp then stand keep the
    padding (their boxes' exact distance, and the lamp's sampled gap to every other body)."""
    events, aim, located, devices = followed(tmp_path, conrod_plan)
    padding = located.cell.collision.padding_m
    blind = cleared(located, plan(located, PlannerSettings(collisions=False)))
    assert blind.binding == "collision" and set(blind.shot.clearance.bodies) == {"camera_body", "lamp_body"}

    assert isinstance(aim, Aim) and aim.located
    replanned = aim.shot
    assert aim.features[0].model.plan.feasible and replanned.clearance.distance_m >= padding
    assert not any(isinstance(e, Corrected) and "lamp_kept" in e.correction for e in events)
    assert any("lamp poses the search tried refused" in note for note in aim.features[0].model.plan.notes)
    assert replanned.joints != pytest.approx(blind.shot.joints, abs=1e-6)

    corrected = localization.corrected(devices, RUN_ESTIMATE)
    with Recorder(tmp_path / "move") as recorder:
        motion.go(located, corrected, recorder, replanned.T_cell_cam, replanned.joints, to="the shot's poses")
    arm, lamp = devices.arm.joint_angles(), devices.lamp.joints()
    assert corrected.arm.camera_pose() == pytest.approx(replanned.T_cell_cam, abs=1e-9)
    assert box_gap(*sim_housings(located, arm, lamp)) >= padding
    assert Obstacles(located).gap(arm, lamp_at(located, lamp), lamp_moves=True)[0] >= padding


def test_where_no_clear_lamp_pose_meets_the_requirements_nor_the_plan_s_the_loop_stops_pose_naming_both(
        tmp_path, conrod_plan):
    """The same re-plan with a lamp housing 0.8 m across (its front face 0.8 x 0.8 m): the lamp
    poses that keep it 10 mm from every other body all miss a requirement, so the re-plan is the
    search's without the bodies, whose shot meets them and collides (`collision`, the lamp's body
    named); the plan's lamp kept is refused too: the run stops, cause `pose`, the pose found and
    both refusals named, nothing moved."""
    conrod = with_black_level(conrod_plan[0], RUN_BLACK)
    wide = replace(conrod, cell=replace(conrod.cell, collision=replace(conrod.cell.collision,
                                                                       lamp_size_m=(0.8, 0.8, 0.05))))
    events, stop, _, devices = followed(tmp_path, conrod_plan, wide)
    assert isinstance(stop, GoalNotReached) and stop.cause == "pose"
    replan = [e.plan for e in events if type(e).__name__ == "Replan"]
    assert len(replan) == 1 and replan[0]["binding"] == "collision" and "lamp_body" in replan[0]["hint"]
    said = str(stop)
    assert said.startswith("the part is off by")
    assert "re-planned for where the part is, no lamp pose clear of the cell's bodies meets every requirement" in said
    assert "with the lamp kept at the plan's pose: collision: " in said and said.count("lamp_body") == 2
    assert devices.arm.moves == 0 and devices.lamp.moves == 0


def test_the_lamp_s_clearance_at_a_re_plan_s_camera_is_every_pair_of_the_lamp_s_kept_apart(conrod_plan):
    """CollisionScene.lamp_clear, the re-plan's question of each lamp pose, at RUN_ESTIMATE's
    camera on a grid of lamp poses about the one a search without the cell's bodies takes (both
    answers occur): the same as every pair of the lamp's bodies (its box, the pan-tilt's links)
    with another body (bodies.distance of each, no pruning) at least the padding apart; where it says clear, the simulator's lamp
    and camera housings' exact distance (box_gap) keeps the padding too."""
    from itertools import product

    from cell.collision.bodies import distance
    from cell.collision.scene import CollisionScene
    located = localization.located_task(with_black_level(conrod_plan[0], RUN_BLACK), RUN_ESTIMATE)
    padding, pivot = located.cell.collision.padding_m, located.lamp.rig.pivot_m
    T = RUN_ESTIMATE.T_part @ conrod_plan[1].shot.T_cell_cam
    q = reaching_joints(located.frames, T)
    scene = CollisionScene.of(located)
    joints = [(np.radians(p), np.radians(t), r) for p, t, r in product(range(50, 80, 3), range(64, 80, 2), (0.2, 0.23))]
    clear = scene.lamp_clear(T, q, [lamp_position(pivot, *j) for j in joints])
    others = scene.bodies(T, q)
    for j, ok in zip(joints, clear):
        lamp = scene.lamp_bodies(lamp_position(pivot, *j))
        assert ok == all(distance(body, other) >= padding for body in lamp for other in others)
        if ok:
            assert box_gap(*sim_housings(located, q, j)) >= padding
    assert clear.any() and not clear.all()



def bracket_carried(tmp_path, bracket, offset_m):
    """The bracket's plan, the part found offset_m off (cell frame): the shot of the bevel and
    web_outer carried along with it (LoopFeatures of the located tasks and moved plans), the
    simulated devices where that shot was planned, its RunContext's Recorder and the error."""
    task, plan = bracket
    (s,) = [s for s in range(len(plan.shots)) if set(assigned(plan, s)) == {"bevel", "web_outer"}]
    found = localization_error(offset_m=offset_m)
    names = [f.name for f in plan.features]
    features = [LoopFeature.planned(localization.located_task(task.with_feature(i), found),
                                    localization.moved_plan(feature_plan(plan, s, i), found.T_part))
                for i in (names.index(n) for n in assigned(plan, s))]
    devices = sim_devices(task, plan.shots[s].arm_joints, plan.shots[s].joints)
    return features, devices, found


def assert_serves(task, shot):
    """The shot (its camera pose, its lamp's position, its exposure) serves the feature of the
    one-feature task, the part where the task puts it: the UR5e's forward kinematics of its
    joints (`shot.arm_joints`, where given) gives its camera back, and tests/dense.py's NumPy
    shading of the true patch finds every point in band, lit, seen and in focus, inside the image
    by the pinhole u = f/p x/z + (W - 1)/2."""
    frames, sensor, lens = task.frames, task.camera.sensor, task.camera.lens
    if getattr(shot, "arm_joints", None) is not None:
        np.testing.assert_allclose(frames.T_cell_base @ ur5e.forward(shot.arm_joints) @ frames.T_flange_cam,
                                   shot.T_cell_cam, atol=1e-9)
    points, normals = patch_surface(task, 3000)
    assert acceptance_failures(SimpleNamespace(feasible=True), shade(task, shot, points, normals)) == [], \
        task.feature.name
    f_px = lens.focal_length_m / sensor.pixel_pitch_m
    local = (points - shot.T_cell_cam[:3, 3]) @ shot.T_cell_cam[:3, :3]
    u = f_px * local[:, 0] / local[:, 2] + (sensor.width_px - 1) / 2
    v = f_px * local[:, 1] / local[:, 2] + (sensor.height_px - 1) / 2
    assert u.min() > -0.5 and u.max() < sensor.width_px - 0.5 and v.min() > -0.5 and v.max() < sensor.height_px - 0.5


def test_a_bracket_shot_carried_out_of_the_arm_s_reach_is_re_planned_at_a_viewpoint_that_serves_its_features(
        tmp_path, bracket):
    """The bracket 30 mm along -x: the shot of the bevel and web_outer carried along with the part
    leaves the UR5e's reach (the closed-form inverse has no joints for it).
    The loop re-plans that shot's viewpoint for where the part is (loop.viewpoint_replanned, the
    whole-part planner on those two features): one shot that serves both (assert_serves);
    nothing moved."""
    features, devices, found = bracket_carried(tmp_path, bracket, (-0.03, 0.0, 0.0))
    carried = features[0].model.plan.shot
    assert reaching_joints(features[0].task.frames, carried.T_cell_cam) is None
    with Recorder(tmp_path / "run") as recorder:
        ctx = RunContext(features[0].task, devices, recorder, 6)
        located = viewpoint_replanned(ctx, features, found, "the carried shot's move is refused")
    assert [f.name for f in located] == [f.name for f in features]
    shot = located[0].model.plan.shot
    assert all(f.model.plan.shot.T_cell_cam == pytest.approx(shot.T_cell_cam, abs=1e-12) for f in located)
    for feature in located:
        assert_serves(feature.task, shot)
    assert devices.arm.moves == 0 and devices.lamp.moves == 0


def test_where_no_one_viewpoint_serves_the_carried_shot_s_features_they_are_split_into_shots_that_do(
        tmp_path, bracket):
    """The mismatch matrix's bracket 10 mm along -x: the carried shot of the bevel and web_outer
    is out of reach (the refusal names the wrist's distance against the arm's span, a2 + a3) and,
    the part there, the planner needs a shot for each of the two features (no one viewpoint
    serves both): loop.Split, its plan's shots each one feature's and serving it, the part where
    it is (assert_serves); nothing moved."""
    task = bracket[0]
    features, devices, found = bracket_carried(tmp_path, bracket, (-0.01, 0.0, 0.0))
    carried = features[0].model.plan.shot
    span = 1e3 * (abs(ur5e.A[1]) + abs(ur5e.A[2]))
    with Recorder(tmp_path / "run") as recorder, pytest.raises(Split) as split:
        ctx = RunContext(features[0].task, devices, recorder, 6)
        move = where_located(ctx, features[0].task, carried, found)
        assert not move.clear
        refused = str(motion.refusal(move))
        assert "mm from the shoulder, the arm spans" in refused and f"-{span:.1f} mm" in refused
        viewpoint_replanned(ctx, features, found, refused)
    plan = split.value.plan
    assert split.value.error is found and len(plan.shots) == 2
    assert sorted(assigned(plan, j) for j in range(2)) == [("bevel",), ("web_outer",)]
    for j, shot in enumerate(plan.shots):
        (name,) = assigned(plan, j)
        one = split.value.task.with_feature([f.name for f in plan.features].index(name))
        assert one.frames.T_cell_part == pytest.approx(found.T_part @ task.frames.T_cell_part, abs=1e-12)
        assert_serves(one, shot)
    assert devices.arm.moves == 0 and devices.lamp.moves == 0


class CaptureStops:
    """A camera that takes the f-number, focus and shutter it is set to and stops the run at its
    first capture (a DeviceFault): what the loop would capture, where the arm and the lamp stand."""

    device = "camera"

    def __init__(self, bit_depth):
        self.bit_depth, self.settings = bit_depth, {}

    def set_aperture(self, f_number):
        self.settings["f_number"] = f_number

    def set_focus(self, focus_m):
        self.settings["focus_m"] = focus_m

    def set_exposure(self, shutter_s):
        self.settings["shutter_s"] = shutter_s
        return shutter_s

    def capture(self):
        raise DeviceFault("camera", "the test stops at the first capture")


def later_shot(tmp_path, bracket, found, names=("bevel", "web_outer")):
    """inspection.run_shot of the bracket's shot of the features `names` with the pose error
    `found` from an earlier shot (the black level the task's), the simulated arm and lamp where
    that shot was planned, a CaptureStops camera: (its ShotRun, the DeviceFault it raised or
    None, its log's steps, the devices)."""
    task, plan = bracket
    (s,) = [s for s in range(len(plan.shots)) if set(assigned(plan, s)) == set(names)]
    devices = replace(sim_devices(task, plan.shots[s].arm_joints, plan.shots[s].joints),
                      camera=CaptureStops(task.camera.sensor.bit_depth))
    black = BlackLevel(evaluate.black_level(task), 0.0, "task")
    done: list = []
    fault = None
    with Recorder(tmp_path / "run") as recorder:
        try:
            run_shot(RunContext(task, devices, recorder, 6, black=black, pose_error=found), plan, s, done)
        except DeviceFault as err:
            fault = err
    return done[0], fault, steps(tmp_path / "run"), devices


@pytest.mark.parametrize("names, offset, replanned, seen", [
    (("bevel", "web_outer"), (-0.03, 0.0, 0.0), "2 features re-planned at a new viewpoint", ["bevel", "web_outer"]),
    (("bevel", "web_outer"), (-0.01, 0.0, 0.0), "the shot's features re-planned for where the part is need 2 shots",
     ["bevel"]),
    (("base_top",), (0.0, 0.0, 0.3), "1 feature re-planned at a new viewpoint", ["base_top"])],
    ids=["30 mm along -x: one viewpoint", "10 mm along -x: a view each", "300 mm up: one feature's"])
def test_a_later_shot_whose_carried_move_is_refused_is_re_planned_where_the_part_is(tmp_path, bracket, names, offset,
                                                                                    replanned, seen):
    """The bracket found off by an earlier shot (inspection.run_shot applies the pose before the
    shot moves): 30 or 10 mm along -x, the shot of the bevel and web_outer carried along with the
    part is out of the UR5e's reach (its closed-form inverse has no joints for it), and so is
    base_top's with the part 300 mm up; its viewpoint is re-planned for where the part is, as a
    shot localized in itself is (loop.carried_viewpoint: at 30 mm one viewpoint serves the bevel
    and web_outer, at 10 mm each needs its own, loop.Split, the bevel's visited first). The arm
    and the lamp go there and the camera is set for its first capture: the camera pose the UR5e's
    forward kinematics gives for the joints the simulated arm reads back (its own collision check
    let the move through), the lamp where its read-back joints put it and the exposure the camera
    was set to serve the view's features (assert_serves: the true patch, the part where it is, in
    band, lit, seen, in focus and inside the image)."""
    task, plan = bracket
    found = localization_error(offset_m=offset)
    (s,) = [s for s in range(len(plan.shots)) if set(assigned(plan, s)) == set(names)]
    assert reaching_joints(task.frames, found.T_part @ plan.shots[s].T_cell_cam) is None
    result, fault, log, devices = later_shot(tmp_path, bracket, found, names)
    assert fault is not None and "the test stops at the first capture" in str(fault) and not result.success
    (why,) = [line for line in log if line["step"] == "correct" and line.get("viewpoint")]
    assert why["message"].startswith("the part is off by [" + ", ".join(f"{1e3 * v:+.2f}" for v in offset) + "] mm")
    assert "the carried shot's move is refused" in why["message"] and "mm from the shoulder" in why["message"]
    assert why["message"].endswith(replanned)
    views = [line for line in log if line["step"] == "correct" and "view" in line]
    assert [v["features"] for v in views[:1]] == ([seen] if "need 2 shots" in replanned else [])
    frames, camera = task.frames, devices.camera.settings
    T_cell_cam = frames.T_cell_base @ ur5e.forward(devices.arm.joint_angles()) @ frames.T_flange_cam
    shot = SimpleNamespace(T_cell_cam=T_cell_cam, lamp_position=lamp_at(task, devices.lamp.joints()),
                           exposure=SimpleNamespace(**camera))
    assert np.linalg.norm(shot.T_cell_cam[:3, 3] - (found.T_part @ plan.shots[s].T_cell_cam)[:3, 3]) > 0.01
    located = localization.located_task(task, found)
    index = [f.name for f in task.features]
    for name in seen:
        assert_serves(located.with_feature(index.index(name)), shot)


def test_a_later_shot_no_viewpoint_serves_stops_pose_naming_the_refusal_and_the_re_plan(tmp_path, bracket):
    """The bracket found 300 mm along -x by an earlier shot (no fixture is that far off; the
    case where no viewpoint serves): the move to its shot of the bevel and web_outer carried there
    is refused (the part itself within the padding of the lamp's tilt servo), and re-planned for
    where the part is no viewpoint serves them (every camera pose that sees web_outer is outside
    the arm's workspace): the shot stops with cause `pose`, the pose found first, then the carried
    shot's refusal and the re-plan's cause; nothing moved."""
    found = localization_error(offset_m=(-0.3, 0.0, 0.0))
    result, fault, _, devices = later_shot(tmp_path, bracket, found)
    assert fault is None and not result.success and result.cause == "pose"
    said = result.message
    assert said.startswith("the part is off by [-300.00, +0.00, +0.00] mm")
    refusal, replan = said.split("the carried shot's move is refused: ")[1].split("; the shot's viewpoint re-planned: ")
    assert refusal.startswith("collision: ") and "no shot covers it" in replan
    assert devices.arm.moves == 0 and devices.lamp.moves == 0


def test_a_view_of_a_split_shot_with_no_capture_left_stops_before_it_moves(tmp_path, bracket):
    """The views a shot is split into share its captures (loop.iterate numbers them on): a view
    whose first capture would be past the shot's max_iterations stops with cause `iterations`,
    naming its features, before anything moves (it is never reported in band unmeasured)."""
    features, devices, _ = bracket_carried(tmp_path, bracket, (0.0, 0.0, 0.0))
    with Recorder(tmp_path / "run") as recorder, pytest.raises(GoalNotReached) as stop:
        next(iterate(RunContext(features[0].task, devices, recorder, 2), features, first_capture=3))
    assert stop.value.cause == "iterations"
    assert str(stop.value) == "bevel, web_outer not captured: none of the shot's 2 captures is left for their view"
    assert devices.arm.moves == 0 and devices.lamp.moves == 0


@pytest.mark.long
def test_the_bracket_10_mm_along_minus_x_converges_in_the_views_its_located_part_needs(tmp_path):
    """The mismatch matrix's bracket 10 mm along -x, every effect on (seed 1): the first shot
    visited (the bevel's and web_outer's) localizes the part; its shot carried along is out of
    the arm's reach and no one viewpoint serves both features there, so each gets its own view
    (loop.Split, inspection.split_views). The run converges, every feature in band, the
    estimate within the issue's 1 mm and 0.3 deg of the simulator's truth key, the located
    shot's three captures its first (there, localized) and one in each view."""
    (case,) = [c for c in mismatch_cases(seeds=(1,), tasks=("bracket",), kinds=["part offset"])
               if c.world["sim.truth.part_offset_m"] == [-0.01, 0.0, 0.0]]
    outcome = mismatch_run(case.task, case.world, case.materials, case.seed, tmp_path)
    assert outcome["converged"], outcome["reason"]
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    found = report["localization"]
    assert found["part_offset_m"] == pytest.approx([-0.01, 0.0, 0.0], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx([0.0, 0.0, 0.0], abs=0.3)
    (located,) = [s for s in report["shots"] if set(s["features"]) == {"bevel", "web_outer"}]
    shot = json.loads((tmp_path / "run" / located["folder"] / "report.json").read_text())
    assert shot["converged"] and len(shot["captures"]) == 3
    assert all(f["converged"] for f in report["features"])


@pytest.mark.long
def test_the_bracket_turned_5_deg_about_y_and_z_re_plans_its_last_shot_where_the_part_is_and_converges(
        tmp_path, bracket):
    """The bracket turned 5 deg about y and 5 deg about z (the simulator's truth key, about its
    first feature's centre; every effect on, seed 1; about 2 minutes): the first shot visited
    (the bevel's and web_outer's) localizes the part; the last (the chamfer's and web_inner's),
    carried along with the part, is out of the UR5e's reach (its closed-form inverse has no joints
    for the truth-moved camera pose), so its viewpoint is re-planned where the part is before it
    moves (loop.carried_viewpoint in inspection.run_shot). The run converges, every
    feature in band and registered, within the matrix's 6 captures a shot, the estimate within the
    issue's 1 mm and 0.3 deg of the truth key; the last shot captured from a camera at least
    10 mm from the carried pose, in one capture."""
    task, plan = bracket
    truth = {"sim.truth.part_rpy_deg": [0.0, 5.0, 5.0]}
    center = apply(task.frames.T_cell_part, task.features[0].center_m)
    E = localization_error(part_rpy_deg=(0.0, 5.0, 5.0), center=center).T_part
    (s,) = [s for s in range(len(plan.shots)) if set(assigned(plan, s)) == {"chamfer", "web_inner"}]
    carried = E @ plan.shots[s].T_cell_cam
    assert reaching_joints(task.frames, carried) is None
    outcome = mismatch_run("bracket", truth, (), 1, tmp_path)
    assert outcome["converged"], outcome["reason"]
    assert outcome["captures"] <= 6 * outcome["shots"]
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    found = report["localization"]
    assert found["part_offset_m"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx([0.0, 5.0, 5.0], abs=0.3)
    assert [r["features"] for r in report["shots"]][0] == ["bevel", "web_outer"] and found["iteration"] == 1
    assert all(f["converged"] and f["in_band"] for f in report["features"])
    log = steps(tmp_path / "run" / f"shot-{s}")
    (why,) = [line for line in log if line["step"] == "correct"]
    assert why["viewpoint"] and "the carried shot's move is refused: the arm cannot follow" in why["message"]
    (moved,) = [line for line in log if line["step"] == "move_camera"]
    assert np.linalg.norm(np.asarray(moved["position_m"]) - carried[:3, 3]) > 0.01
    last = json.loads((tmp_path / "run" / f"shot-{s}" / "report.json").read_text())
    assert last["converged"] and len(last["captures"]) == 1
    assert all(it["registration"]["trusted"] and it["in_band"] for it in last["iterations"])
