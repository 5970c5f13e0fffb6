"""cell.run.motion, the one way the cell moves (issue 26): a move starts from where the devices
read back, takes via points where the direct path hits something, and is refused before
anything moves (cause `collision`, exit 1, both bodies named) where no path is clear. The
simulated cell's own check (sim.obstacles, the `collisions` effect: other geometry, other
distances) is the independent judge: it stops the direct moves, and lets the routes motion
chose through."""
from pathlib import Path

import numpy as np
import pytest

from cell.collision.scene import reaching_joints
from cell.core.errors import DeviceFault, GoalNotReached
from cell.devices.interfaces import Devices
from cell.devices.rig import lamp_position
from cell.planning.scene import look_at
from cell.report.recorder import Recorder
from cell.run import motion
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.obstacles import Obstacles
from sim.pantilt import SimPanTilt

from simcell import variant
from test_collision import stop, wall_task

HINGE = Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml"


def sim_devices(task, arm_joints, lamp_joints):
    """The simulated arm and pan-tilt sharing the cell's own collision check, the arm at
    arm_joints and the lamp at lamp_joints, placed there (no camera: nothing is captured). The
    lamp is placed, not driven: its servo's way there from the centre tick (e.g. to 180 deg
    through -90 deg) is no move under test."""
    obstacles = Obstacles(task)
    arm = SimArm(task.cell.devices.arm, task.frames, joints=arm_joints, obstacles=obstacles)
    lamp = SimPanTilt(task.lamp.rig, task.cell.devices.pan_tilt)
    lamp.move(*lamp_joints)
    lamp.obstacles, obstacles.lamp_position = obstacles, lamp_position(task.lamp.rig.pivot_m, *lamp.joints())
    lamp.moves = 0
    return Devices(arm, lamp, camera=None)


def steps(folder):
    import json
    return [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]


def test_a_move_whose_direct_path_hits_the_wall_takes_via_points_the_sim_lets_through(tmp_path):
    task = wall_task(tmp_path)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    devices = sim_devices(task, a.arm_joints, a.lamp_joints)
    with pytest.raises(DeviceFault, match="protective stop"):     # the sim's own check: straight through the wall
        devices.arm.move_camera(b.T_cell_cam)
    assert np.allclose(devices.arm.joints, a.arm_joints)         # stopped where it stood
    with Recorder(tmp_path / "run") as recorder:
        move = motion.go(task, devices, recorder, b.T_cell_cam, to="shot 1")
    assert len(move.via) == 2 and move.clear
    assert all(T[2, 3] > 0.42 for T in move.via)                  # over the wall's top
    assert np.allclose(devices.arm.camera_pose(), b.T_cell_cam, atol=1e-9)
    assert devices.arm.moves == 1 + 3                             # the stopped one, two via points, the target
    via = [s for s in steps(tmp_path / "run") if s["step"] == "move_via"]
    assert [np.allclose(s["position_m"], T[:3, 3], atol=1e-9) for s, T in zip(via, move.via)] == [True, True]


def test_the_path_starts_where_the_arm_reads_back_not_where_a_caller_thinks_it_is(tmp_path):
    """The same target from either side of the wall: already there, a lamp-only check and no
    via points; from the far side (the joints read back there), over the wall."""
    task = wall_task(tmp_path)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    here = sim_devices(task, a.arm_joints, a.lamp_joints)
    assert np.allclose(here.arm.joint_angles(), a.arm_joints)    # the read-back: the sim's joints
    stay = motion.check(task, here, a.T_cell_cam)
    assert stay.clear and stay.via == () and stay.travel_m == 0.0
    there = sim_devices(task, b.arm_joints, b.lamp_joints)
    across = motion.check(task, there, a.T_cell_cam)
    assert across.clear and len(across.via) == 2
    assert np.allclose(across.corners_m[0], b.T_cell_cam[:3, 3])  # it starts where the arm stands


def test_a_round_trip_is_checked_both_ways_before_it_leaves_and_comes_back_by_the_way_checked(tmp_path):
    """From the near side of the wall to the far side and back: the way back, checked from where
    the way there arrives (check_back) before anything moves, goes over the wall too, from the
    far stop to the near one; driven (go_back, checked again from where the arm reads back), the
    arm passes the same via points and stands where it started, at the joints it read there."""
    task = wall_task(tmp_path)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    devices = sim_devices(task, a.arm_joints, a.lamp_joints)
    start = motion.standing(task, devices)
    there = motion.check(task, devices, b.T_cell_cam, to="the far side")
    back = motion.check_back(task, devices, there, b.T_cell_cam, None, start, "the far side", "the near side")
    assert there.clear and back.clear and len(back.via) == 2
    assert all(T[2, 3] > 0.42 for T in back.via)                  # over the wall's top
    assert np.allclose(back.corners_m[0], b.T_cell_cam[:3, 3]) and np.allclose(back.corners_m[-1], a.T_cell_cam[:3, 3])
    with Recorder(tmp_path / "run") as recorder:
        motion.go(task, devices, recorder, b.T_cell_cam, to="the far side", checked=there)
        read = motion.go_back(task, devices, start, recorder, "the near side")
    assert np.allclose(read, a.T_cell_cam, atol=1e-9) and np.allclose(devices.arm.joints, a.arm_joints, atol=1e-9)
    via = [s["position_m"] for s in steps(tmp_path / "run") if s["step"] == "move_via" and s["to"] == "the near side"]
    assert np.allclose(via, [T[:3, 3] for T in back.via], atol=1e-6)


def walled_in(tmp_path):
    """The wall, and the workspace's top at 0.5 m: the flange stands at 0.45 m at either end, and
    every via point (a retreat of at least 0.1 m up the camera's axis) takes it out of the box.
    (task, the stop on the near side, the one on the far side, the devices at the near one)."""
    wall_task(tmp_path)
    task = load_task(variant(tmp_path, HINGE, {"cell.collision.fixture_mesh": str(tmp_path / "wall.stl"),
                                               "cell.arm.workspace_max_m": [0.6, 0.6, 0.5]}))
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    return task, a, b, sim_devices(task, a.arm_joints, a.lamp_joints)


def test_a_move_no_path_clears_is_refused_with_both_bodies_and_nothing_moves(tmp_path):
    """walled_in: no path from one side of the wall to the other."""
    task, a, b, devices = walled_in(tmp_path)
    before = devices.arm.joints.copy()
    with Recorder(tmp_path / "run") as recorder, pytest.raises(GoalNotReached) as refused:
        motion.go(task, devices, recorder, b.T_cell_cam, b.lamp_joints, to="shot 1")
    error = refused.value
    assert error.cause == "collision" and error.exit_code == 1
    said = str(error)
    assert said.startswith("collision: ") and "fixture and " in said and "shot 1" in said
    assert "before anything moved" in said
    assert devices.arm.moves == 0 and devices.lamp.moves == 0     # the sim recorded no motion
    assert np.array_equal(devices.arm.joints, before)
    assert not {"move_via", "move_lamp_via"} & {s["step"] for s in steps(tmp_path / "run")}


def test_a_lamp_move_that_would_sweep_through_the_camera_goes_around_it(tmp_path):
    """The camera 0.19 m from the pivot at 39 deg of elevation; the lamp at 0.2 m and 35 deg
    panned from -60 to 60 deg passes through it or its tilt servo through the arm (the sim stops
    that); motion's route goes
    through via joints at another tilt, which the sim lets through."""
    task = load_task(HINGE)
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    T = look_at(pivot + (0.15, 0.0, 0.12), pivot)
    q = reaching_joints(task.frames, T)
    start, end = (np.radians(-60.0), np.radians(35.0), 0.2), (np.radians(60.0), np.radians(35.0), 0.2)
    blocked = sim_devices(task, q, start)
    with pytest.raises(DeviceFault, match="(lamp housing|rig arm|tilt servo) would hit"):
        blocked.lamp.move(*end)           # the lamp or a link of its rig into the camera or the arm
    devices = sim_devices(task, q, start)
    with Recorder(tmp_path / "run") as recorder:
        move = motion.go(task, devices, recorder, None, end, to="the probe")
    assert move.clear and len(move.lamp_via) == 2 and move.via == ()
    assert all(abs(tilt - np.radians(35.0)) > np.radians(5.0) for _, tilt, _ in move.lamp_via)
    assert np.allclose(devices.lamp.joints()[:2], end[:2], atol=np.radians(0.2))
    assert np.allclose(devices.arm.joints, q)                      # the arm stayed
    lamp_via = [s for s in steps(tmp_path / "run") if s["step"] == "move_lamp_via"]
    at = [lamp_position(pivot, *j) for j in move.lamp_via]
    assert [np.allclose(s["position_m"], p, atol=2e-3) for s, p in zip(lamp_via, at)] == [True, True]


def across_the_base(task):
    """Two camera poses 0.35 m above the cell's floor looking down, 0.3 m either side of the
    arm's base axis (x = 0, y = -0.4 m): the straight path between them takes the wrist centre
    through the shoulder's singular cylinder, the far one's joints nearest the near one's are
    another configuration (the shoulder turned 65 deg further over)."""
    from cell.collision.paths import Stop
    from cell.devices import ur5e

    def at(x, q_near):
        T = look_at(np.array([x, -0.4, 0.35]), np.array([x, -0.4, -0.05]))
        return Stop(T, ur5e.inverse(task.frames.T_base_flange(task.frames.T_base_cam(T)), q_near), (0.0, 0.5, 0.2))

    a = at(-0.3, ur5e.HOME_JOINTS)
    return a, at(0.3, a.arm_joints)


def test_a_move_whose_straight_path_crosses_a_singularity_is_a_joint_move_the_sim_lets_through(tmp_path):
    from cell.collision.paths import arm_path
    from cell.collision.scene import CollisionScene
    from cell.devices import ur5e
    task = load_task(HINGE)
    a, b = across_the_base(task)
    with pytest.raises(ur5e.Unreachable, match="shoulder cylinder"):
        arm_path(CollisionScene.of(task), a.T_cell_cam, a.arm_joints, b.T_cell_cam, None)
    devices = sim_devices(task, a.arm_joints, a.lamp_joints)
    with Recorder(tmp_path / "run") as recorder:
        move = motion.go(task, devices, recorder, b.T_cell_cam, to="shot 1")
    assert move.clear and move.joint_legs == (0,) and move.via == ()
    assert np.allclose(devices.arm.joints, move.joints_end) and np.allclose(move.joints_end, b.arm_joints)
    assert np.allclose(devices.arm.camera_pose(), b.T_cell_cam, atol=1e-9)
    assert devices.arm.moves == 1                                 # one moveJ, the sim's check passed it
    assert move.to_json()["joint_legs"] == [0]


def test_a_joint_move_through_the_wall_is_refused_before_anything_moves_and_a_clear_one_is_driven(tmp_path):
    """motion.move_joints (a route's moveJ leg): from the near side of the wall to two of the far
    pose's configurations, one whose joint path sweeps the forearm through the wall (the sim's own
    check finds that contact), one clear of it (test_moves's dense check)."""
    from cell.devices import ur5e
    task = wall_task(tmp_path)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)
    devices = sim_devices(task, a.arm_joints, a.lamp_joints)
    solutions = ur5e.inverse_all(task.frames.T_base_flange(task.frames.T_base_cam(b.T_cell_cam)))
    blocked, clear = solutions[1], solutions[3]
    assert Obstacles(task).arm_move([a.arm_joints, blocked]) is not None
    with Recorder(tmp_path / "run") as recorder:
        with pytest.raises(GoalNotReached) as refused:
            motion.move_joints(task, devices, blocked, recorder, "shot 1")
        assert refused.value.cause == "collision" and "fixture and wrist_3" in str(refused.value)
        assert "before anything moved" in str(refused.value) and devices.arm.moves == 0
        T = motion.move_joints(task, devices, clear, recorder, "shot 1")
    assert np.allclose(devices.arm.joints, clear) and np.allclose(T, b.T_cell_cam, atol=1e-9)
    [logged] = [s for s in steps(tmp_path / "run") if s["step"] == "move_joints"]
    assert np.allclose(logged["joints_deg"], np.degrees(clear)) and "collision-checked" in logged["message"]
