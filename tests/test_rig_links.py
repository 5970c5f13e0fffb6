"""The pan-tilt's links as collision bodies (issue 26), their geometry as the task declares it
(`cell.collision.rig_reach_m`): the planner's bodies (cell.collision.scene.lamp_bodies: the tilt
servo, and with a declared reach the rig's arm) stand where docs/formats.md puts them (against
trimesh's boxes and cylinders built here from its words), a reach shorter than the rig's largest
radius plus the lamp's depth is refused with one line, the lamp and its own links may touch, a
body beside a link is refused naming both, the lamp's moves step by its links too (against a
dense sweep of the servo's solid), a long reach makes a pan over the robot's side that a compact
head is routed through a collision the run refuses before anything moves; and the simulated
cell's own check (sim.obstacles) stops a deliberately bad move of the arm or the pan-tilt into a
link."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from cell import cli
from cell.collision.bodies import SAMPLE_BOUND_M, distance
from cell.collision.paths import Stop, lamp_path, plan_transition
from cell.collision.scene import CollisionScene, reaching_joints
from cell.core import geometry
from cell.core.errors import DeviceFault, GoalNotReached
from cell.devices.rig import lamp_position
from cell.planning.scene import look_at
from cell.report.recorder import Recorder
from cell.run import motion
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.obstacles import Obstacles
from sim.pantilt import SimPanTilt

from simcell import variant
from test_motion import sim_devices, steps

ROOT = Path(__file__).resolve().parent.parent
HINGE = ROOT / "tasks" / "hinge.yaml"
SERVO_MM = (34.0, 46.5, 28.5)        # a Dynamixel XM430: across the aim (horizontal), across it, along it
LONG_M = 0.69                        # a long reach: the hinge's rig (0.6 m) and lamp (80 mm deep) plus 10 mm


@pytest.fixture(scope="module")
def hinge():
    task = load_task(HINGE)
    return task, CollisionScene.of(task)


def with_reach(task, reach_m):
    """The task with cell.collision.rig_reach_m set (None: not declared)."""
    return replace(task, cell=replace(task.cell, collision=replace(task.cell.collision, rig_reach_m=reach_m)))


def rig_solids(task, joints):
    """The lamp's box and the tilt servo's (trimesh boxes) and the rig's arm (a trimesh cylinder,
    or None) as docs/formats.md describes them: the lamp aims at the pivot, its x axis
    horizontal; the servo's front face at the lamp's back, or rig_reach_m from the pivot where
    the task declares it; then the arm, a 10 mm radius tube along the aim from the lamp's back to
    the servo's front face."""
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    p = lamp_position(pivot, *joints)
    aim = (pivot - p) / np.linalg.norm(pivot - p)
    x = np.cross((0.0, 0.0, 1.0), aim)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(aim, x), aim])
    depth = task.cell.collision.lamp_size_m[2]
    lamp = trimesh.creation.box(extents=task.cell.collision.lamp_size_m,
                                transform=geometry.transform(R, p - 0.5 * depth * aim))
    reach = task.cell.collision.rig_reach_m
    back = p - depth * aim
    front = back if reach is None else pivot - reach * aim
    servo = trimesh.creation.box(extents=np.array(SERVO_MM) * 1e-3,
                                 transform=geometry.transform(R, front - 0.5e-3 * SERVO_MM[2] * aim))
    arm = None if reach is None else trimesh.creation.cylinder(radius=0.010, segment=[back, front], sections=64)
    return lamp, servo, arm


def facing(task, scene, point, look):
    """T_cell_cam of the camera looking along `look` (unit) whose body's far end along it lies in
    the plane through `point` square to `look`, its axis through `point`."""
    look = np.asarray(look, float)
    T = look_at(np.asarray(point, float) - look, point)
    body = scene.camera_body(task.frames.T_cell_flange(T))
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    front = float((geometry.apply(body.T_cell_box, signs * body.half_m) @ look).max())
    T[:3, 3] += (float(np.asarray(point) @ look) - front) * look
    return T


def corners(box):
    return np.array(sorted(map(tuple, np.round(box.vertices, 12))))


def box_corners(body):
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    return corners(trimesh.Trimesh(geometry.apply(body.T_cell_box, signs * body.half_m)))


@pytest.mark.parametrize("reach_m", [None, LONG_M])
@pytest.mark.parametrize("joints", [(0.0, 0.35, 0.2), (2.1, 1.2, 0.45), (-2.8, 0.09, 0.6)])
def test_the_lamp_s_links_stand_where_the_formats_doc_puts_them(hinge, joints, reach_m):
    """The boxes' corners are trimesh's; the arm's capsule has the trimesh cylinder's axis (its cap
    centres at the capsule's ends, its rims on the capsule's surface). Without a declared reach the servo rides on
    the lamp's back (touching it) and there is no arm; with one, the servo's front is reach - r -
    depth from the lamp's back."""
    task = with_reach(hinge[0], reach_m)
    scene = CollisionScene.of(task)
    lamp, servo, arm = rig_solids(task, joints)
    bodies = scene.lamp_bodies(lamp_position(task.lamp.rig.pivot_m, *joints))
    names = ("lamp_body", "tilt_servo") if reach_m is None else ("lamp_body", "tilt_servo", "rig_arm")
    assert tuple(body.name for body in bodies) == names
    assert np.allclose(box_corners(bodies[0]), corners(lamp), atol=1e-9)
    assert np.allclose(box_corners(bodies[1]), corners(servo), atol=1e-9)
    gap = 0.0 if reach_m is None else reach_m - joints[2] - task.cell.collision.lamp_size_m[2]
    assert distance(bodies[0], bodies[1]) == pytest.approx(gap, abs=SAMPLE_BOUND_M + 1e-9)
    if reach_m is not None:
        capsule = bodies[2]
        on_axis = np.linalg.norm(np.cross(arm.vertices - capsule.a, capsule.b - capsule.a), axis=1) < 1e-12
        assert on_axis.sum() == 2 and np.allclose(sorted(map(tuple, arm.vertices[on_axis])),
                                                  sorted(map(tuple, [capsule.a, capsule.b])), atol=1e-12)
        assert capsule.radius_m == 0.010 and np.allclose(capsule.sdf(arm.vertices[~on_axis]), 0.0, atol=1e-12)


@pytest.mark.parametrize("reach_m", [None, LONG_M])
def test_the_lamp_and_its_links_may_touch_one_another_but_nothing_else(hinge, reach_m):
    """The lamp and its links touch (the servo on the lamp's back; or the arm both boxes), yet the
    cell is clear with the camera far; a camera 5 mm behind the servo's back face is refused
    naming it, the clearance within the boxes' sampling bound of the true 5 mm."""
    task = with_reach(hinge[0], reach_m)
    scene = CollisionScene.of(task)
    joints = (0.4, 0.5, 0.3 if reach_m is None else task.lamp.rig.radius_range_m[1])
    p = lamp_position(task.lamp.rig.pivot_m, *joints)
    box, servo, *arm = scene.lamp_bodies(p)
    assert distance(box, servo) <= 0.0 if reach_m is None else all(distance(a, b) <= 0.0 for a in arm
                                                                    for b in (box, servo))
    far = look_at(np.array([-0.3, 0.3, 0.4]), np.array([-0.3, 0.3, 0.0]))
    assert scene.clearance(far, lamp_position=p).ok
    R, gap = servo.T_cell_box[:3, :3], 0.005
    centre = servo.center - (servo.half_m[2] + gap + scene.camera_half_m[2]) * R[:, 2]     # behind its back
    T_cell_flange = geometry.transform(R, centre - scene.camera_offset_m * R[:, 2])
    T_cell_cam = T_cell_flange @ task.frames.T_flange_cam
    hit = scene.clearance(T_cell_cam, lamp_position=p)
    assert hit.bodies == ("camera_body", "tilt_servo") and not hit.ok
    assert gap - SAMPLE_BOUND_M - 1e-9 <= hit.distance_m <= gap + 1e-9
    assert "collision: camera_body and tilt_servo" in hit.reason()


def test_the_rig_s_reach_is_read_in_any_length_unit_and_one_too_short_is_refused_in_one_line(tmp_path, capsys):
    """cell.collision.rig_reach_mm: 700 is 0.7 m; the hinge's rig reaches 0.6 m and its lamp is
    80 mm deep, so 0.68 m is the least reach (the servo on the lamp's back there) and 0.65 m is
    refused by `cell check`: exit 2, one line naming the key, the value and the least, in mm too."""
    assert load_task(variant(tmp_path, HINGE, {"cell.collision.rig_reach_mm": 700})).cell.collision.rig_reach_m \
        == pytest.approx(0.7)
    assert load_task(variant(tmp_path, HINGE, {"cell.collision.rig_reach_m": 0.68})).cell.collision.rig_reach_m == 0.68
    assert load_task(HINGE).cell.collision.rig_reach_m is None
    capsys.readouterr()
    assert cli.main(["check", str(variant(tmp_path, HINGE, {"cell.collision.rig_reach_m": 0.65}))]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "cell.collision.rig_reach_m" in lines[0]
    assert "0.65 m (650 mm)" in lines[0] and "at least 0.68 m (680 mm)" in lines[0]


def swept_servo(task, camera, start, end, n=400):
    """The least distance [m] between the camera body's solid (trimesh, densely sampled) and
    the tilt servo's solid at n poses of the lamp's joints from start to end (rig_solids)."""
    surface = cKDTree(trimesh.sample.sample_surface_even(camera, 20000, seed=3)[0])
    least = np.inf
    for s in np.linspace(0.0, 1.0, n):
        _, servo, _ = rig_solids(task, (1 - s) * np.asarray(start) + s * np.asarray(end))
        points = trimesh.sample.sample_surface_even(servo, 3000, seed=4)[0]
        least = min(least, float(surface.query(points)[0].min()))
    return least


@pytest.mark.parametrize("beyond, clear", [(0.016, True), (0.004, False)])
def test_a_lamp_move_steps_by_its_links_the_servo_swung_past_a_camera(hinge, beyond, clear):
    """A long reach: the camera (no arm) looking at the pivot from beyond the servo at pan 0, its
    face `beyond` farther out than the servo's farthest corner; the lamp, 0.2 m from the pivot
    (its box 0.4 m inside), pans from -30 to 30 deg: the servo passes the camera. The planner's
    lamp path is clear exactly where a dense sweep of the servo's solid keeps the padding."""
    task = with_reach(hinge[0], LONG_M)
    scene = CollisionScene.of(task)
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    tilt = np.radians(20.0)
    u = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    servo_far = LONG_M + 1e-3 * SERVO_MM[2]
    face = float(np.linalg.norm([servo_far, 0.5e-3 * SERVO_MM[0], 0.5e-3 * SERVO_MM[1]])) + beyond
    T = facing(task, scene, pivot + face * u, -u)
    box = scene.camera_body(task.frames.T_cell_flange(T))
    camera = trimesh.creation.box(extents=2 * box.half_m, transform=box.T_cell_box)
    start, end = (np.radians(-30.0), tilt, 0.2), (np.radians(30.0), tilt, 0.2)
    found, steps_ = lamp_path(scene, T, None, start, end)
    dense = swept_servo(task, camera, start, end)
    padding = task.cell.collision.padding_m
    assert found.ok is clear and (dense >= padding) is clear
    if not clear:
        assert set(found.bodies) in ({"camera_body", "tilt_servo"}, {"camera_body", "rig_arm"})
    else:
        assert found.distance_m <= dense + 1e-9 and steps_ > 2
    box_far = min(distance(box, scene.lamp_bodies(lamp_position(pivot, *j))[0]) for j in (start, end))
    assert box_far > 0.3                                         # the lamp's box alone: far from it


def test_a_long_reach_refuses_the_pan_over_the_robot_s_side_a_compact_head_makes(tmp_path):
    """The arm at home, the lamp 0.2 m out at 10 deg of tilt panned from -45 to -135 deg, over the
    UR5e's base (the robot stands at y = -0.4 m). The compact head (no reach declared) pans
    straight past it, which the simulator lets through. With the reach declared long
    (0.69 m) the rig's arm sweeps through the base the direct way and meets the arm at every via
    tilt: the run refuses the move naming rig_arm before anything moves, and the simulator's own
    check stops the direct move as the rig's arm would hit the base."""
    compact = load_task(HINGE)
    long = load_task(variant(tmp_path, HINGE, {"cell.collision.rig_reach_m": LONG_M}))
    home = np.radians([-90.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    start, end = (np.radians(-45.0), np.radians(10.0), 0.2), (np.radians(-135.0), np.radians(10.0), 0.2)
    devices = sim_devices(compact, home, start)
    with Recorder(tmp_path / "compact") as recorder:
        move = motion.go(compact, devices, recorder, None, end, to="the probe")
    assert move.clear and move.lamp_via == () and set(move.clearance.bodies) == {"base", "tilt_servo"}
    assert np.allclose(devices.lamp.joints()[:2], end[:2], atol=np.radians(0.2))
    devices = sim_devices(long, home, start)
    with Recorder(tmp_path / "long") as recorder, pytest.raises(GoalNotReached) as refused:
        motion.go(long, devices, recorder, None, end, to="the probe")
    said = str(refused.value)
    assert said.startswith("collision: ") and "rig_arm" in said and "before anything moved" in said
    assert devices.lamp.moves == 0 and not {"move_lamp_via"} & {s["step"] for s in steps(tmp_path / "long")}
    with pytest.raises(DeviceFault) as fault:
        devices.lamp.move(*end)
    assert "the rig arm would hit the arm link 1" in fault.value.reason
    assert np.degrees(devices.lamp.joints()[0]) > -90.0                  # stopped before the base


# -- the simulated cell's own check -------------------------------------------------------------

def sim_cell(task, lamp_joints, T_cell_cam):
    """The simulated arm at T_cell_cam and pan-tilt at lamp_joints with the cell's own check."""
    obstacles = Obstacles(task)
    arm = SimArm(task.cell.devices.arm, task.frames, obstacles=obstacles)
    lamp = SimPanTilt(task.lamp.rig, task.cell.devices.pan_tilt, obstacles=obstacles)
    lamp.move(*lamp_joints)
    arm.move_camera(T_cell_cam)
    return arm, lamp


def above_servo(task, scene, joints, height):
    """The camera looking straight down at the tilt servo's centre, its body's bottom `height`
    above the servo's highest point (below 0: into it)."""
    servo = scene.lamp_bodies(lamp_position(task.lamp.rig.pivot_m, *joints))[1]
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    top = geometry.apply(servo.T_cell_box, signs * servo.half_m)[:, 2].max()
    return facing(task, scene, (*servo.center[:2], top + height), (0.0, 0.0, -1.0))


def test_the_simulated_arm_stops_before_the_camera_hits_the_tilt_servo(hinge):
    """The lamp at pan 0, 45 deg, 0.3 m, its servo on its back; the camera 40 mm above the servo
    comes down 10 mm into it: the planner refuses the move naming both, the simulator's own check
    stops it, the arm where it was."""
    task, scene = hinge
    joints = (0.0, np.radians(45.0), 0.3)
    high, low = above_servo(task, scene, joints, 0.04), above_servo(task, scene, joints, -0.01)
    arm, lamp = sim_cell(task, joints, high)
    q = reaching_joints(task.frames, high, arm.joints)
    move = plan_transition(scene, task.cell.devices.arm, Stop(high, np.asarray(q), joints), Stop(low, q, joints))
    assert not move.clear and "tilt_servo" in move.clearance.bodies
    before = arm.joints.copy()
    with pytest.raises(DeviceFault) as fault:
        arm.move_camera(low)
    assert "protective stop" in fault.value.reason and "camera housing would hit the tilt servo" in fault.value.reason
    assert np.array_equal(arm.joints, before)


@pytest.mark.parametrize("reach_m", [None, LONG_M])
def test_the_simulated_pan_tilt_stops_before_its_links_swing_into_the_camera(hinge, reach_m):
    """The camera's body 5 mm into where the servo stands at pan 0 (45 deg, 0.3 m); the lamp at
    pan -40 deg is clear of it, and panned to 0 its servo (or, the reach declared, the rig's arm)
    would hit it: the simulator stops the pan-tilt, which stays short of 0 deg."""
    task = with_reach(hinge[0], reach_m)
    scene = CollisionScene.of(task)
    tilt = np.radians(45.0)
    T = above_servo(task, scene, (0.0, tilt, 0.3), -0.005)
    arm, lamp = sim_cell(task, (np.radians(-40.0), tilt, 0.3), T)
    with pytest.raises(DeviceFault) as fault:
        lamp.move(0.0, tilt, 0.3)
    assert "protective stop" in fault.value.reason and "camera housing" in fault.value.reason
    hit = ("the tilt servo would hit",) if reach_m is None else ("the tilt servo would hit", "the rig arm would hit")
    assert any(words in fault.value.reason for words in hit)
    assert np.degrees(lamp.joints()[0]) < -1.0
