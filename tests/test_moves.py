"""The moves a run makes (issue 26): the simulated arm and pan-tilt's own collision check
(sim.obstacles) stops a deliberately bad move with a device fault and lets the planner's path
(cell.collision.paths, via points) through; a run whose move cannot be made clear is refused
before anything moves, exit 1, naming both bodies and where; the example's run goes through the
via points."""
import json
import re
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from cell.cli import main
from cell.collision.paths import plan_move
from cell.collision.scene import CollisionScene
from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.devices import ur5e
from cell.devices.rig import RIG_ARM_RADIUS_M, TILT_SERVO_SIZE_M
from cell.planning.scene import look_at
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.obstacles import Obstacles, light_housing
from sim.pantilt import SimPanTilt

from simcell import variant
from test_collision import stop, wall_task

ROOT = Path(__file__).resolve().parent.parent
HINGE, BEAM = ROOT / "tasks" / "hinge.yaml", ROOT / "tests" / "tasks" / "features" / "conrod_beam.yaml"
RING_LENS = ROOT / "tests" / "tasks" / "features" / "ring_lens.yaml"     # the camera down through a ring's hole
PLATE_DOME = ROOT / "tests" / "tasks" / "features" / "plate_dome.yaml"   # the camera in through a dome's hole


def sim_arm(task, joints):
    """The simulated arm with the cell's own collision check, at the joints given."""
    return SimArm(task.cell.devices.arm, task.frames, joints=joints, obstacles=Obstacles(task))


def test_the_simulated_arm_stops_a_move_through_a_wall_and_takes_the_planned_via_points(tmp_path):
    task = wall_task(tmp_path)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    arm = sim_arm(task, a.arm_joints)
    before = arm.joints.copy()
    with pytest.raises(DeviceFault) as fault:              # straight across: through the wall
        arm.move_camera(b.T_cell_cam)
    assert "protective stop" in fault.value.reason and "fixture" in fault.value.reason
    assert np.array_equal(arm.joints, before)              # stopped: nothing moved
    move = plan_move(CollisionScene.of(task), task.cell.devices.arm, 0, a, 1, b)
    assert move.clear and len(move.via) == 2
    for T in (*move.via, b.T_cell_cam):                    # the planner's path: the sim lets it through
        arm.move_camera(T)
    assert np.allclose(arm.camera_pose(), b.T_cell_cam, atol=1e-9)
    assert np.allclose(arm.joints, move.joints_end, atol=1e-6)   # arrived as the planner's path did


def test_the_simulated_pan_tilt_stops_before_the_lamp_hits_the_camera():
    task = load_task(HINGE)
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    obstacles = Obstacles(task)
    arm = SimArm(task.cell.devices.arm, task.frames, obstacles=obstacles)
    arm.move_camera(look_at(pivot + (0.0, 0.0, 0.25), pivot))   # the camera right over the pivot
    lamp = SimPanTilt(task.lamp.rig, task.cell.devices.pan_tilt, obstacles=obstacles)
    lamp.move(0.0, np.radians(30.0), 0.25)                       # 0.125 m beside the camera: clear
    with pytest.raises(DeviceFault) as fault:                    # up to 85 deg: into the camera
        lamp.move(0.0, np.radians(85.0), 0.25)
    assert "protective stop" in fault.value.reason
    assert "lamp housing" in fault.value.reason and "camera housing" in fault.value.reason
    assert np.degrees(lamp.joints()[1]) == pytest.approx(30.0, abs=0.1)    # it stayed where it was


def test_a_run_whose_move_no_via_points_clear_is_refused_before_anything_moves(tmp_path, capsys):
    """conrod_beam.yaml's beam 50 mm taller (to z = 450 mm, clear of the wrist above either shot)
    and the workspace's top at 0.6 m: a retreat of 0.1 m does not clear the beam, one of 0.2 m
    takes the flange out of the workspace."""
    wall = trimesh.creation.box(extents=(10.0, 80.0, 200.0), transform=geometry.transform(translation=(-6, 0, 350)))
    (tmp_path / "tall.stl").write_bytes(wall.export(file_type="stl"))
    path = variant(tmp_path, BEAM, {"cell.collision.fixture_mesh": str(tmp_path / "tall.stl"),
                                    "cell.collision.fixture_mesh_unit": "mm",
                                    "cell.arm.workspace_max_m": [0.6, 0.6, 0.6]})
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.splitlines()[-1]
    plan = json.loads((out / "plan.json").read_text())
    assert not plan["feasible"] and plan["binding"] == "collision"
    blocked = plan["moves"][-1]
    assert (blocked["from"], blocked["to"]) == (0, 1) and blocked["clearance_m"] < 0.01
    a, b = blocked["clearance_bodies"]
    assert "fixture" in (a, b) and {a, b} & {"camera_body", "wrist_1", "wrist_2", "wrist_3"}
    assert "collision" in err and f"{a} and {b}" in err and "with the camera at" in err and "shot 0 to shot 1" in err
    steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert not {"move_camera", "move_lamp", "move_via", "capture"} & set(steps)


@pytest.mark.long          # 20-40 s: plans and runs two shots
def test_the_beam_example_runs_through_its_via_points_and_the_sim_never_stops_it(tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(BEAM), "--out", str(out)]) == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    via = [line for line in log if line["step"] == "move_via"]
    plan = json.loads((out / "plan.json").read_text())
    planned = [T for m in plan["moves"] for T in m["via"]]
    assert len(via) == len(planned) == 2
    for line, T in zip(via, planned):                     # at the planned via points, in turn
        assert np.allclose(line["position_m"], np.asarray(T)[:3, 3], atol=1e-9)
    assert not any(line["step"] == "fault" for line in log)


# --- the Done-when check: every planned path, densely sampled against the meshes ------------
# Shares no path or distance code with cell.collision: the camera's moveL re-interpolated by
# scipy's Slerp at steps of at most PATH_STEP_M for any point of the arm (joints by the UR5e's inverse
# kinematics nearest the last), the lamp's joints linearly; each body's surface sampled by trimesh
# (boxes as trimesh primitives, the fixed lights' housings as the simulator's own meshes,
# sim.obstacles.light_housing, the links as points along their axes every DENSE_M, less their
# radii; the pan-tilt's links as docs/formats.md places them: the tilt servo's box behind the
# lamp, its front face at the lamp's back or at cell.collision.rig_reach_m from the pivot, and with
# that key the rig's tube from the lamp's back to the servo's front), the nearest pairs by k-d
# trees. Sampled surfaces lie no nearer than the surfaces: a
# distance found below the padding is a contact the planner let through.

DENSE_M = 0.002             # the bodies' surface samples' spacing
PATH_STEP_M = 0.005         # the most any point of the arm travels between two poses checked (the
                            # planner's own steps: 20-25 mm where its clearance is 50 mm)
FAR_M = 0.05                # distances are searched up to this; farther pairs count as this far


def box_points(size):
    return trimesh.sample.sample_surface_even(trimesh.creation.box(extents=size), 4000, radius=0.6 * DENSE_M,
                                              seed=7)[0]


class Dense:
    """A task's bodies for the dense check."""

    def __init__(self, task, step=PATH_STEP_M):
        from cell.collision.scene import MAY_TOUCH
        c, self.task, self.may_touch, self.step = task.cell.collision, task, MAY_TOUCH, step
        fixed = [("part", task.part.mesh.copy().apply_transform(task.frames.T_cell_part))]
        if c.fixture is not None:
            fixed.append(("fixture", c.fixture))
        fixed += [(light.name, light_housing(light)) for light in task.lights if light.mount == "fixed"]
        self.fixed = [(name, cKDTree(trimesh.sample.sample_surface_even(
            m, int(m.area / DENSE_M ** 2), radius=0.5 * DENSE_M, seed=5)[0])) for name, m in fixed]
        self.camera = box_points(c.camera_size_m) + (0.0, 0.0, c.camera_offset_m)
        self.lamp_size = np.asarray(c.lamp_size_m, float)
        self.lamp_local = box_points(c.lamp_size_m)
        self.servo_size = np.asarray(TILT_SERVO_SIZE_M, float)
        self.servo_local = box_points(self.servo_size)

    def lamp(self, joints):
        """[(name, points, radius)] of the lamp's box and the pan-tilt's links at the lamp's joints."""
        from cell.devices.rig import lamp_position
        pivot = np.asarray(self.task.lamp.rig.pivot_m, float)
        p = lamp_position(pivot, *joints)
        z = (pivot - p) / np.linalg.norm(pivot - p)
        x = np.cross((0.0, 0.0, 1.0), z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
        R = np.column_stack([x, np.cross(z, x), z])
        back = p - self.lamp_size[2] * z
        reach = self.task.cell.collision.rig_reach_m
        front = back if reach is None else pivot - reach * z
        bodies = [("lamp_body", self.lamp_local @ R.T + back + 0.5 * self.lamp_size[2] * z, 0.0),
                  ("tilt_servo", self.servo_local @ R.T + front - 0.5 * self.servo_size[2] * z, 0.0)]
        if reach is None:
            return bodies
        n = int(np.ceil(np.linalg.norm(front - back) / DENSE_M)) + 1
        return [*bodies, ("rig_arm", back + np.linspace(0, 1, n)[:, None] * (front - back), RIG_ARM_RADIUS_M)]

    def nearest(self, q, lamp_joints):
        """(the smallest distance between bodies that may not touch, which two) at joints q and
        the lamp's joints (None: no lamp)."""
        from cell.collision.scene import arm_links
        flange = self.task.frames.T_cell_base @ ur5e.forward(q)
        bodies = [("camera_body", self.camera @ flange[:3, :3].T + flange[:3, 3], 0.0)]
        for link in arm_links(self.task.frames.T_cell_base, q):
            n = int(np.ceil(np.linalg.norm(link.b - link.a) / DENSE_M)) + 1
            bodies.append((link.name, link.a + np.linspace(0, 1, n)[:, None] * (link.b - link.a), link.radius_m))
        if lamp_joints is not None:
            bodies += self.lamp(lamp_joints)
        best = (np.inf, ("", ""))
        trees = [(name, cKDTree(p), r) for name, p, r in bodies]
        for i, (a, pa, ra) in enumerate(bodies):
            others = [(b, t, 0.0) for b, t in self.fixed] + [(b, t, rb) for b, t, rb in trees[i + 1:]]
            for b, tree, rb in others:
                if frozenset((a, b)) in self.may_touch:
                    continue
                d = min(float(tree.query(pa, distance_upper_bound=FAR_M + ra + rb)[0].min()) - ra - rb, FAR_M)
                best = min(best, (d, (a, b)))
        return best

    def path(self, T_a, T_b, q):
        """The joints along the moveL from T_a (joints q) to T_b, no point of the arm moving more
        than self.step between two (each joint's sweep times the arm's 1.3 m reach with a camera)."""
        from scipy.spatial.transform import Rotation, Slerp
        frames = self.task.frames
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix([T_a[:3, :3], T_b[:3, :3]]))
        n = max(2, int(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]) / self.step))
        while True:
            s = np.linspace(0.0, 1.0, n + 1)
            joints = [np.asarray(q, float)]
            for k in range(1, n + 1):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = slerp(s[k]).as_matrix(), (1 - s[k]) * T_a[:3, 3] + s[k] * T_b[:3, 3]
                joints.append(ur5e.inverse(frames.T_base_flange(frames.T_base_cam(T)), joints[-1]))
            sweep = float(np.abs(np.diff(joints, axis=0)).sum(axis=1).max()) * 1.3
            if sweep <= self.step:
                return joints
            n = int(np.ceil(n * sweep / self.step))


    def joint_path(self, q_a, q_b):
        """The joints along the moveJ from q_a to q_b (linear), no point of the arm moving more
        than self.step between two: each joint's turn times the farthest any point beyond it lies
        from its axis (the DH table's lengths beyond joint k, |a_k| + sum over j > k of |a_j| +
        |d_j|, plus the camera's farthest sample from the flange)."""
        q_a, q_b = np.asarray(q_a, float), np.asarray(q_b, float)
        tool = float(np.linalg.norm(self.camera, axis=1).max())
        beyond = [abs(ur5e.A[k]) + sum(abs(ur5e.A[j]) + abs(ur5e.D[j]) for j in range(k + 1, 6)) + tool
                  for k in range(6)]
        n = max(1, int(np.ceil(np.abs(q_b - q_a) @ np.array(beyond) / self.step)))
        return [(1 - s) * q_a + s * q_b for s in np.linspace(0.0, 1.0, n + 1)]


def densely_checked(task, plan, moves):
    """The smallest distance over every move's path as cell.run makes it: the arm's through its
    via points, the lamp where it stands (none from home, where the plan does not know it); then
    the lamp's joints linearly through its via joints to the shot's, its pan as the servo holds it
    (servo.held_pan), the arm at the shot; the lamp first where the move says so; a leg the move
    makes by moveJ with the joints linear:
    [(distance, bodies, move)]."""
    from cell.collision.paths import home_stop
    from cell.devices.servo import held_pan
    dense, found = Dense(task), []
    home = home_stop(CollisionScene.of(task))
    q, T, lamp = home.arm_joints, home.T_cell_cam, None
    # the lamp and its links lie within this of the pivot
    reach = max(task.lamp.rig.radius_range_m[1], task.cell.collision.rig_reach_m or 0.0) + 0.15

    def lamp_legs(q, start, legs):
        for end in legs:
            end = np.asarray(end, float)
            sweep = np.abs(end[:2] - start[:2]).sum() * reach + abs(end[2] - start[2])
            for s in np.linspace(0.0, 1.0, max(2, int(np.ceil(sweep / dense.step)) + 1)):
                found.append((*dense.nearest(q, (1 - s) * start + s * end), move.end))
            start = end
        return start

    for move in moves:
        shot = plan.shots[move.end]
        pan, tilt, radius = shot.joints
        arrives = np.array([held_pan(pan, task.cell.devices.pan_tilt.pan_offset_rad), tilt, radius])
        known = lamp is not None           # from home the lamp is not known: the arm's path without it, as
        lamp = arrives if lamp is None else lamp   # planned (the run checks it itself)
        if move.lamp_first:
            lamp = lamp_legs(q, lamp, [*move.lamp_via, arrives])
        corners = [T, *move.via, shot.T_cell_cam]
        for k, (T_a, T_b) in enumerate(zip(corners, corners[1:])):
            if k in move.joint_legs:                  # a moveJ: the joints linear to the leg's end's
                joints = dense.joint_path(q, move.via_joints[k] if k < len(move.via) else move.joints_end)
            else:
                joints = dense.path(T_a, T_b, q)
            found += [(*dense.nearest(j, lamp if known else None), move.end) for j in joints]
            q = joints[-1]
        if not move.lamp_first:
            lamp = lamp_legs(q, lamp, [*move.lamp_via, arrives])
        T = shot.T_cell_cam
    return found


def assert_every_path_keeps_the_padding(task, plan):
    from cell.run.moves import with_moves
    planned = with_moves(task, plan)
    assert planned.moves and all(m.clear for m in planned.moves)
    found = densely_checked(task, planned, planned.moves)
    d, bodies, shot = min(found, key=lambda f: f[0])
    assert d >= task.cell.collision.padding_m, f"{bodies} {d * 1e3:.1f} mm apart on the way to shot {shot}"


@pytest.mark.long
def test_the_wall_moves_keep_the_padding_along_their_whole_path_by_a_dense_check(tmp_path):
    """The wall of test_collision between two shots: the planner's via path at every 5 mm a point
    of the arm travels, 4-5x denser than its own steps."""
    task = wall_task(tmp_path)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    move = plan_move(CollisionScene.of(task), task.cell.devices.arm, 0, a, 1, b)
    dense = Dense(task)
    found, q, corners = [], a.arm_joints, [a.T_cell_cam, *move.via, b.T_cell_cam]
    for T_a, T_b in zip(corners, corners[1:]):
        joints = dense.path(T_a, T_b, q)
        found += [dense.nearest(j, a.lamp_joints) for j in joints]
        q = joints[-1]
    assert len(move.via) == 2 and len(found) > 5 * move.steps
    assert min(found)[0] >= task.cell.collision.padding_m


@pytest.mark.long          # 1-7 min: the examples' plans and their paths densely
@pytest.mark.parametrize("example", [ROOT / "tasks" / "bracket.yaml", BEAM, RING_LENS, PLATE_DOME, "yawed"],
                         ids=["bracket", "conrod_beam", "ring_lens", "plate_dome", "bracket_yawed_5_deg"])
def test_every_example_path_keeps_the_padding_by_a_dense_check(example, tmp_path):
    """The examples, and the bracket yawed 5 deg (its route has moveJs: bracket_yawed)."""
    from cell.planning.whole_part import plan_features
    task = load_task(bracket_yawed(tmp_path) if example == "yawed" else example)
    assert_every_path_keeps_the_padding(task, plan_features(task))


@pytest.mark.long          # 1-2 min a part
@pytest.mark.parametrize("part", ["sphere_cap", "lying_cylinder", "filleted_block"])
def test_generated_parts_with_random_features_keep_the_padding_on_every_path(tmp_path, part):
    """A part of tasks/make_parts.py with two random features (centres of triangles facing up
    within 37 deg, at least 6 mm from any steeper than 60 deg, 10-35 mm apart), a random camera direction within 30 deg
    of vertical, the lamp's pivot 10 mm above the part's top between them."""
    from cell.planning.whole_part import plan_features
    rng = np.random.default_rng(zlib.crc32(part.encode()))
    mesh = trimesh.load(ROOT / "tasks" / "parts" / f"{part}.stl")
    up, side = mesh.face_normals[:, 2] > 0.8, mesh.face_normals[:, 2] < 0.5
    edges = cKDTree(np.vstack([mesh.triangles[side].reshape(-1, 3), mesh.triangles_center[side]]))
    centres = mesh.triangles_center[up]
    centres = centres[edges.query(centres)[0] > 6.0]
    first = centres[rng.integers(len(centres))]
    apart = np.linalg.norm(centres - first, axis=1)
    near = centres[(apart > 10.0) & (apart < 35.0)]
    second = near[rng.integers(len(near))]
    tilt, pan = np.radians(rng.uniform(0, 30)), rng.uniform(0, 2 * np.pi)
    direction = [float(np.sin(tilt) * np.cos(pan)), float(np.sin(tilt) * np.sin(pan)), float(np.cos(tilt))]
    features = [{"name": f"f{k}", "center_mm": np.round(c, 3).tolist(), "radius_mm": 2.0, "samples": 16}
                for k, c in enumerate((first, second))]
    pivot = [*(0.5e-3 * (first[:2] + second[:2])).tolist(), 1e-3 * float(mesh.bounds[1, 2] + 10.0)]
    path = variant(tmp_path, BEAM, {"part.mesh": str(ROOT / "tasks" / "parts" / f"{part}.stl"),
                                    "features": features, "camera.view_direction": direction,
                                    "cell.collision": {}, "requirements.gray_band": [10, 250],
                                    "requirements.depth_of_field_m": 0.002,
                                    "lamp.rig.pivot_m": pivot})
    task = load_task(path)
    plan = plan_features(task)
    assert plan.feasible, plan.message
    assert_every_path_keeps_the_padding(task, plan)


def test_a_feature_whose_only_shot_collides_is_refused_naming_both_bodies(tmp_path, capsys):
    """tests/tasks/features/conrod_beam_blocked.yaml: the shank's camera lands in the beam."""
    out = tmp_path / "plan"
    assert main(["plan", str(ROOT / "tests" / "tasks" / "features" / "conrod_beam_blocked.yaml"),
                 "--out", str(out)]) == 1
    said, err = capsys.readouterr()
    err = err.splitlines()[-1]
    plan = json.loads((out / "plan.json").read_text())
    shank = next(f for f in plan["features"] if f["name"] == "shank")
    assert shank["covered_by"] is None and shank["binding"] == "collision"
    a, b = re.search(r"collision: (\w+) and (\w+) ", shank["hint"]).groups()
    assert "fixture" in (a, b) and {a, b} & {"camera_body", "wrist_1", "wrist_2", "wrist_3"}
    assert "collision" in err and "shank" in err and f"{a} and {b}" in err
    headline = said.splitlines()[0]           # its cause follows the count: the collision, not "collision fails"
    assert f"PARTIAL: 1 shot covers 1 of 2 features (chosen from 2 candidate shots); feature shank: no shot " \
           f"covers it: collision: {a} and {b} " in headline, headline
    assert "moves" not in plan                       # a partial plan: nothing to move along


def test_the_cell_s_own_check_is_the_collisions_effect_off_unless_listed():
    """make_sim_devices gives the arm and the pan-tilt the cell's own check only with
    `collisions` in sim.effects: the hinge's lamp driven into the camera stops with it, and
    without it the simulated lamp goes there (the effect alone decides)."""
    from dataclasses import replace
    from cell.planning.scene import build_scene
    from sim.cell import make_sim_devices
    base = load_task(HINGE)
    scene = build_scene(base)
    pivot = np.asarray(base.lamp.rig.pivot_m, float)
    others = tuple(e for e in base.sim.effects if e != "collisions")
    for effects, stops in ((others, False), (others + ("collisions",), True)):
        devices = make_sim_devices(replace(base, sim=replace(base.sim, effects=effects)), scene)
        assert (devices.arm.obstacles is not None) is stops
        devices.arm.move_camera(look_at(pivot + (0.0, 0.0, 0.25), pivot))
        devices.lamp.move(0.0, np.radians(30.0), 0.25)
        if stops:
            with pytest.raises(DeviceFault, match="protective stop"):
                devices.lamp.move(0.0, np.radians(85.0), 0.25)
        else:
            devices.lamp.move(0.0, np.radians(85.0), 0.25)
            assert np.degrees(devices.lamp.joints()[1]) == pytest.approx(85.0, abs=0.1)


# --- moves through a change of the arm's configuration: moveJ, checked along its path ---------

BRACKET = ROOT / "tasks" / "bracket.yaml"


def bracket_yawed(tmp_path):
    """tasks/bracket.yaml turned 5 deg about z about its first feature's centre (the mismatch
    matrix's correct model of that row, test_mismatch._part_pose): its route needs moves through
    a change of the arm's configuration (a joint turns 165 deg on the moveL from shot 2 to 1)."""
    from test_mismatch import _part_pose
    return variant(tmp_path, BRACKET, _part_pose("bracket", rpy_deg=(0.0, 0.0, 5.0)))


@pytest.mark.long          # 15 s CPU: the sim's check of 7 paths, the dense check of one
def test_a_joint_move_the_planner_refuses_hits_in_the_simulated_cell_and_one_it_accepts_keeps_the_padding(tmp_path):
    """The wall of test_collision between two camera poses: from the first's joints by moveJ
    (the joints linear) to each of the 8 inverse kinematics solutions of the second. Each one
    joint_path refuses, the simulated cell's own check (sim.obstacles, the joints linear) stops
    with a contact; along each it accepts the dense check (trimesh's samples, every 20 mm any
    point of the arm travels) finds at least the padding, the least within 2 mm of the
    planner's (test_motion drives the accepted one through the sim)."""
    from cell.collision.paths import joint_path
    task = wall_task(tmp_path)
    scene, padding = CollisionScene.of(task), task.cell.collision.padding_m
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    dense = Dense(task, step=0.02)
    verdicts = []
    for q in ur5e.inverse_all(task.frames.T_base_flange(task.frames.T_base_cam(b.T_cell_cam))):
        found, end, steps = joint_path(scene, a.arm_joints, q, None)
        verdicts.append(found.ok)
        if found.ok:
            assert np.allclose(end, q)
            nearest = min(dense.nearest(j, None)[0] for j in dense.joint_path(a.arm_joints, q))
            assert nearest >= padding and found.distance_m == pytest.approx(nearest, abs=2e-3)
        else:
            assert Obstacles(task).arm_move([a.arm_joints, q]) is not None, np.degrees(q).round(1)
            assert found.distance_m < padding and "with the camera at" in found.reason()
    assert any(verdicts) and not all(verdicts)


def forward(q):
    """(N, 4, 4) T_base_flange of N joint vectors (N, 6): the DH table's product, all at once."""
    T = np.eye(4)
    for i in range(6):
        T = T @ ur5e.dh(i, q[:, i])
    return T


def test_a_joint_move_whose_camera_or_flange_leaves_the_workspace_on_the_way_is_refused():
    """check_joint_motion against the forward kinematics sampled densely (every 0.5 mm a point
    of the arm travels): random joint moves of the hinge's arm with both ends inside the
    workspace box and within the joint limits; each whose camera or flange passes more than 1 mm
    outside on the way is refused, each that stays more than 1 mm inside is not."""
    from cell.devices.interfaces import check_joint_motion
    task = load_task(HINGE)
    config, frames = task.cell.devices.arm, task.frames
    lo, hi = config.workspace_min_m, config.workspace_max_m
    rng = np.random.default_rng(3)

    def inset(q):
        """(N,) the least distance inside the box of the camera's and the flange's origins (< 0: out)."""
        flange = frames.T_cell_base @ forward(q)
        points = np.stack([(flange @ frames.T_flange_cam)[..., :3, 3], flange[..., :3, 3]], axis=1)
        return np.minimum(points - lo, hi - points).min(axis=(1, 2))

    judged = {True: 0, False: 0}
    while min(judged.values()) < 8:
        q0 = ur5e.HOME_JOINTS + rng.uniform(-1.0, 1.0, 6)
        q1 = ur5e.HOME_JOINTS + rng.uniform(-2.0, 2.0, 6)
        if np.any(np.abs(q1) > ur5e.JOINT_LIMITS) or min(inset(np.array([q0, q1]))) < 0.0:
            continue
        n = int(np.ceil(np.abs(q1 - q0).sum() * 1.3 / 5e-4))
        least = inset(q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0)).min()
        if abs(least) <= 1e-3:
            continue
        if least < 0:
            with pytest.raises(DeviceFault, match="outside the workspace"):
                check_joint_motion(config, frames, q0, q1)
        else:
            check_joint_motion(config, frames, q0, q1)
        judged[bool(least > 0)] += 1


def test_a_joint_move_at_joint_speed_moves_the_camera_no_faster_than_the_arm_s_speed():
    """joint_speed's leading joint's speed: the camera's origin (the TCP) along random moveJs,
    its speed by finite differences of the forward kinematics, never above the arm's speed_m_s."""
    from cell.devices.interfaces import joint_speed
    task = load_task(HINGE)
    config, frames = task.cell.devices.arm, task.frames
    rng = np.random.default_rng(5)
    fastest = 0.0
    for _ in range(20):
        q0, q1 = ur5e.HOME_JOINTS + rng.uniform(-2.0, 2.0, (2, 6))
        v, _ = joint_speed(config, frames, q0, q1)
        s = np.linspace(0.0, 1.0, 20001)
        tcp = (forward(q0 + s[:, None] * (q1 - q0)) @ frames.T_flange_cam)[:, :3, 3]
        ds_dt = v / np.abs(q1 - q0).max()                   # the leading joint at v
        speed = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / np.diff(s) * ds_dt
        fastest = max(fastest, float(speed.max()) / config.speed_m_s)
    assert 0.5 < fastest <= 1.0


@pytest.mark.long          # 30-60 s: plans the bracket and runs its three shots
def test_the_bracket_yawed_5_deg_plans_its_route_with_joint_moves_and_runs_it_on_the_simulator(tmp_path):
    """The mismatch matrix's correct model of the bracket yawed 5 deg: its route's moves between
    shots whose moveL crosses a change of configuration are moveJs (plan.json's joint_legs), and
    `cell run` on the simulated cell (its own collision check on) drives them to the planned
    joints and converges."""
    task = bracket_yawed(tmp_path)
    out = tmp_path / "run"
    assert main(["run", str(task), "--out", str(out)]) == 0
    plan = json.loads((out / "plan.json").read_text())
    joint = [m for m in plan["moves"] if m.get("joint_legs")]
    assert joint and all(m["clearance_m"] >= plan_padding(task) for m in plan["moves"])
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    driven = [line for line in log if line["step"] == "move_joints"]
    assert len(driven) == sum(len(m["joint_legs"]) for m in joint)
    for line, move in zip(driven, joint):                  # each to the joints the plan's route planned
        assert line["to"] == f"shot {move['to']}" and np.allclose(line["joints_deg"], move["arm_joints_deg"])
    assert not any(line["step"] == "fault" for line in log)
    assert json.loads((out / "report.json").read_text())["converged"]


def plan_padding(task_path):
    return load_task(task_path).cell.collision.padding_m
