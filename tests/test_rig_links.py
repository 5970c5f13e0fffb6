"""The pan-tilt's links as collision bodies (issue 26): the planner's (cell.collision.scene:
lamp_bodies, the rig's arm and tilt servo) stand where the hardware notes put them (against
trimesh's boxes built here from the notes' words), the lamp and its own links may touch, a body
beside a link is refused naming both, the lamp's moves step by its links too (against a dense
sweep of the servo's solid), a move the other way round in pan where the direct one sweeps the
links through something; and the simulated cell's own check (sim.obstacles) stops a deliberately
bad move of the arm or the pan-tilt into a link."""
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from cell.collision.bodies import SAMPLE_BOUND_M, distance
from cell.collision.paths import Stop, lamp_path, lamp_route, plan_transition
from cell.collision.scene import CollisionScene, reaching_joints
from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.devices.rig import lamp_position
from cell.planning.scene import look_at
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.obstacles import Obstacles
from sim.pantilt import SimPanTilt

ROOT = Path(__file__).resolve().parent.parent
HINGE = ROOT / "tasks" / "hinge.yaml"
SERVO_MM = (34.0, 46.5, 28.5)        # a Dynamixel XM430: across the aim (horizontal), across it, along it


@pytest.fixture(scope="module")
def hinge():
    task = load_task(HINGE)
    return task, CollisionScene.of(task)


def rig_solids(task, joints):
    """The lamp's box and the tilt servo's (trimesh boxes) and the rig's arm (its axis' ends, its
    radius) as the hardware notes describe them: the lamp aims at the pivot, its x axis
    horizontal; the servo's front face a lamp's depth beyond the rig's largest radius; the arm, a
    10 mm radius tube along the aim from the lamp's back to the servo's centre."""
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    p = lamp_position(pivot, *joints)
    aim = (pivot - p) / np.linalg.norm(pivot - p)
    x = np.cross((0.0, 0.0, 1.0), aim)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(aim, x), aim])
    depth = task.cell.collision.lamp_size_m[2]
    lamp = trimesh.creation.box(extents=task.cell.collision.lamp_size_m,
                                transform=geometry.transform(R, p - 0.5 * depth * aim))
    servo_centre = pivot - (task.lamp.rig.radius_range_m[1] + depth + 0.5e-3 * SERVO_MM[2]) * aim
    servo = trimesh.creation.box(extents=np.array(SERVO_MM) * 1e-3, transform=geometry.transform(R, servo_centre))
    return lamp, servo, (p - depth * aim, servo_centre, 0.010)


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


@pytest.mark.parametrize("joints", [(0.0, 0.35, 0.2), (2.1, 1.2, 0.45), (-2.8, 0.09, 0.6)])
def test_the_lamp_s_links_stand_where_the_hardware_notes_put_them(hinge, joints):
    task, scene = hinge
    lamp, servo, (a, b, r) = rig_solids(task, joints)
    box, arm, held = scene.lamp_bodies(lamp_position(task.lamp.rig.pivot_m, *joints))
    assert (box.name, arm.name, held.name) == ("lamp_body", "rig_arm", "tilt_servo")
    for body, solid in ((box, lamp), (held, servo)):
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        assert np.allclose(corners(trimesh.Trimesh(geometry.apply(body.T_cell_box, signs * body.half_m))),
                           corners(solid), atol=1e-9)
    assert np.allclose(arm.a, a, atol=1e-12) and np.allclose(arm.b, b, atol=1e-12) and arm.radius_m == r
    # the servo meets the lamp's back only with the lamp at the rig's largest radius
    gap = task.lamp.rig.radius_range_m[1] - joints[2]
    assert distance(box, held) == pytest.approx(gap, abs=SAMPLE_BOUND_M + 1e-9) or distance(box, held) <= gap


def test_the_lamp_and_its_links_may_touch_one_another_but_nothing_else(hinge):
    """The arm enters both boxes (their distance <= 0), yet the cell is clear with the camera
    far; a camera 5 mm beside the servo's side face is refused naming it, the clearance within
    the boxes' sampling bound of the true 5 mm."""
    task, scene = hinge
    joints = (0.4, 0.5, 0.3)
    p = lamp_position(task.lamp.rig.pivot_m, *joints)
    box, arm, servo = scene.lamp_bodies(p)
    assert distance(box, arm) <= 0.0 and distance(arm, servo) <= 0.0
    far = look_at(np.array([-0.3, 0.3, 0.4]), np.array([-0.3, 0.3, 0.0]))
    assert scene.clearance(far, lamp_position=p).ok
    R, gap = servo.T_cell_box[:3, :3], 0.005
    centre = servo.center + (servo.half_m[0] + gap + scene.camera_half_m[0]) * R[:, 0]     # beside its x face
    T_cell_flange = geometry.transform(R, centre - scene.camera_offset_m * R[:, 2])
    T_cell_cam = T_cell_flange @ task.frames.T_flange_cam
    hit = scene.clearance(T_cell_cam, lamp_position=p)
    assert hit.bodies == ("camera_body", "tilt_servo") and not hit.ok
    assert gap - SAMPLE_BOUND_M - 1e-9 <= hit.distance_m <= gap + 1e-9
    assert "collision: camera_body and tilt_servo" in hit.reason()


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
    """The camera (no arm) looking at the pivot from beyond the servo's reach at pan 0, its face
    `beyond` farther out than the servo's farthest corner; the lamp, 0.2 m from the pivot (its
    box 0.4 m inside), pans from -30 to 30 deg: the servo passes the camera. The planner's lamp
    path is clear exactly where a dense sweep of the servo's solid keeps the padding."""
    task, scene = hinge
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    tilt = np.radians(20.0)
    u = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    servo_far = task.lamp.rig.radius_range_m[1] + task.cell.collision.lamp_size_m[2] + 1e-3 * SERVO_MM[2]
    face = float(np.linalg.norm([servo_far, 0.5e-3 * SERVO_MM[0], 0.5e-3 * SERVO_MM[1]])) + beyond
    T = facing(task, scene, pivot + face * u, -u)
    box = scene.camera_body(task.frames.T_cell_flange(T))
    camera = trimesh.creation.box(extents=2 * box.half_m, transform=box.T_cell_box)
    start, end = (np.radians(-30.0), tilt, 0.2), (np.radians(30.0), tilt, 0.2)
    found, steps = lamp_path(scene, T, None, start, end)
    dense = swept_servo(task, camera, start, end)
    padding = task.cell.collision.padding_m
    assert found.ok is clear and (dense >= padding) is clear
    if not clear:
        assert set(found.bodies) in ({"camera_body", "tilt_servo"}, {"camera_body", "rig_arm"})
    else:
        assert found.distance_m <= dense + 1e-9 and steps > 2
    box_far = min(distance(box, scene.lamp_bodies(lamp_position(pivot, *j))[0]) for j in (start, end))
    assert box_far > 0.3                                         # the lamp's box alone: far from it


def test_a_lamp_move_goes_the_other_way_round_in_pan_when_the_direct_one_meets_a_body(hinge):
    """The camera (no arm) in the links' way at pan -90 deg; the lamp from pan 0 to -180 deg
    directly sweeps through -90: the route arrives at +180 instead (the same pose, the other
    way round through +90; the rig's range is -180 to 180), clear, and says so (lamp_end)."""
    task, scene = hinge
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    tilt = np.radians(20.0)
    u = np.array([0.0, -np.cos(tilt), np.sin(tilt)])              # pan -90
    T = facing(task, scene, pivot + 0.5 * u + (0.0, 0.0, 0.005), (0.0, 0.0, -1.0))     # 5 mm into the arm's tube
    hit = scene.clearance(T, lamp_position=lamp_position(pivot, -0.5 * np.pi, tilt, 0.2))
    assert not hit.ok and "rig_arm" in hit.bodies
    start, end = (0.0, tilt, 0.2), (-np.pi, tilt, 0.2)
    direct, _ = lamp_path(scene, T, None, start, end)
    assert not direct.ok
    found, via, arrives, _ = lamp_route(scene, T, None, start, end)
    assert found.ok and via == () and arrives == pytest.approx((np.pi, tilt, 0.2))
    assert lamp_path(scene, T, None, start, arrives)[0].ok


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
    _, _, servo = scene.lamp_bodies(lamp_position(task.lamp.rig.pivot_m, *joints))
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    top = geometry.apply(servo.T_cell_box, signs * servo.half_m)[:, 2].max()
    return facing(task, scene, (*servo.center[:2], top + height), (0.0, 0.0, -1.0))


def test_the_simulated_arm_stops_before_the_camera_hits_the_tilt_servo(hinge):
    """The lamp at pan 0; the camera 40 mm above its servo comes down 10 mm into it: the planner
    refuses the move naming both, the simulator's own check stops it, the arm where it was."""
    task, scene = hinge
    joints = (0.0, np.radians(45.0), 0.2)                     # the servo inside the arm's workspace
    high, low = above_servo(task, scene, joints, 0.04), above_servo(task, scene, joints, -0.01)
    arm, lamp = sim_cell(task, joints, high)
    q = reaching_joints(task.frames, high, arm.joints)
    move = plan_transition(scene, task.cell.devices.arm, Stop(high, np.asarray(q), joints), Stop(low, q, joints))
    assert not move.clear and set(move.clearance.bodies) & {"tilt_servo", "rig_arm"}
    before = arm.joints.copy()
    with pytest.raises(DeviceFault) as fault:
        arm.move_camera(low)
    assert "protective stop" in fault.value.reason and "camera housing would hit the tilt servo" in fault.value.reason
    assert np.array_equal(arm.joints, before)


def test_the_simulated_pan_tilt_stops_before_its_servo_swings_into_the_camera(hinge):
    """The camera's body 5 mm into where the servo stands at pan 0; the lamp at pan -40 deg is
    clear of it, and panned to 0 the servo (or the arm) would hit it: the simulator stops the
    pan-tilt, which stays at -40 deg."""
    task, scene = hinge
    tilt = np.radians(45.0)                                   # the servo inside the arm's workspace
    T = above_servo(task, scene, (0.0, tilt, 0.2), -0.005)
    arm, lamp = sim_cell(task, (np.radians(-40.0), tilt, 0.2), T)
    with pytest.raises(DeviceFault) as fault:
        lamp.move(0.0, tilt, 0.2)
    assert "protective stop" in fault.value.reason and "camera housing" in fault.value.reason
    assert "the tilt servo would hit" in fault.value.reason or "the rig arm would hit" in fault.value.reason
    assert np.degrees(lamp.joints()[0]) == pytest.approx(-40.0, abs=0.1)


def test_the_lamp_waits_at_a_parking_pose_when_its_links_bar_the_arm_s_path_either_way(hinge):
    """The camera looking down, its body's bottom 20 mm under where the rig's arm passes at
    x = 0.35 m with the lamp at pan 0 or 5 deg and tilt 45 deg, moves from y = -0.15 to 0.15 m
    across it; the workspace's top 0.1 m above the camera forbids via points over it. Neither
    the arm first nor the lamp first is clear; the lamp parked at its lowest tilt is, and the
    move says where (lamp_park), its clearance the padding at least."""
    from dataclasses import replace
    task, scene = hinge
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    tilt = np.radians(45.0)
    x = 0.35
    height = pivot[2] + (x - pivot[0]) * np.tan(tilt) + 0.010 - 0.020       # the tube's top less 20 mm
    A, B = (facing(task, scene, (x, y, height), (0.0, 0.0, -1.0)) for y in (-0.15, 0.15))
    qa = reaching_joints(task.frames, A)
    qb = reaching_joints(task.frames, B, qa)
    arm = replace(task.cell.devices.arm, workspace_max_m=np.array([0.6, 0.6, A[2, 3] + 0.1]))
    a, b = Stop(A, np.asarray(qa), (0.0, tilt, 0.2)), Stop(B, np.asarray(qb), (np.radians(5.0), tilt, 0.2))
    assert scene.clearance(A, qa, lamp_position(pivot, *a.lamp_joints)).ok
    assert scene.clearance(B, qb, lamp_position(pivot, *b.lamp_joints)).ok
    move = plan_transition(scene, arm, a, b)
    assert move.clear and move.lamp_park is not None and not move.lamp_first and move.via == ()
    assert move.lamp_park[1] < tilt and move.clearance.distance_m >= task.cell.collision.padding_m
    assert move.to_json()["lamp_park"] == pytest.approx(list(move.lamp_park))
    from cell.collision.paths import plan_move
    assert not plan_move(scene, arm, 0, a, 1, b).clear                          # the arm first
    assert not plan_move(scene, arm, 0, replace(a, lamp_joints=b.lamp_joints), 1, b).clear   # the lamp first
