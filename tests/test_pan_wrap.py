"""The lamp's pan as the servo drives it (issue 26): in position mode the pan servo holds one turn,
ticks 0..4095, its goal wrapped into [-180, 180) deg of pan_offset (cell.devices.servo.goal_ticks),
so a lamp commanded to +180 deg from +90 deg is driven to tick 0 (-180 deg) the long way, through
0 and -90 deg. The checked path must be that one: the controller's (cell.run.motion, the planner's
lamp_path/lamp_route to the held pan) and the simulator's own (its ticks from present to goal).
The independent judge: the servo's ticks stepped one by one from the present tick to the goal
tick, the lamp's housing at each against the camera's (sim.obstacles' sampled boxes, every pair)."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from cell.collision.paths import lamp_path
from cell.collision.scene import CollisionScene, reaching_joints
from cell.core.errors import DeviceFault
from cell.devices.rig import lamp_position
from cell.devices.servo import CENTRE_TICK, TICKS_PER_TURN, held_pan
from cell.planning.scene import look_at
from cell.report.recorder import Recorder
from cell.run import motion
from cell.task.loader import load_task
from sim.obstacles import CONTACT_M, Obstacles
from test_motion import sim_devices

HINGE = Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml"
TILT, RADIUS = np.radians(30.0), 0.2            # the lamp low, as it sweeps in pan
START = (np.radians(90.0), TILT, RADIUS)


def camera_at(task, pan_deg):
    """The camera's pose and joints 0.2 m out from the pivot at pan_deg, 0.17 m up, looking at
    the pivot: where the lamp at (pan_deg, 30 deg up, 0.2 m) stands."""
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    a = np.radians(pan_deg)
    T = look_at(pivot + (0.2 * np.cos(a), 0.2 * np.sin(a), 0.17), pivot)
    return T, np.asarray(reaching_joints(task.frames, T), float)


def servo_sweep_gap(task, q, pan_from, pan_to):
    """The least distance [m] between the simulator's camera housing (arm at q) and its lamp
    housing as the pan servo's tick goes one by one from pan_from's tick to pan_to's (each
    wrapped into 0..4095 by hand here: tick = 2048 + round(pan N / 2 pi) mod N, offset 0)."""
    assert task.cell.devices.pan_tilt.pan_offset_rad == 0.0
    tick = [(CENTRE_TICK + round(p * TICKS_PER_TURN / (2 * np.pi))) % TICKS_PER_TURN for p in (pan_from, pan_to)]
    world = Obstacles(task)
    camera = world.camera(q)
    step = 1 if tick[1] >= tick[0] else -1
    pans = [(t - CENTRE_TICK) * 2 * np.pi / TICKS_PER_TURN for t in range(tick[0], tick[1] + step, step * 8)]
    pivot = task.lamp.rig.pivot_m
    return min(float(cdist(camera, world.lamp(lamp_position(pivot, p, TILT, RADIUS))).min()) for p in pans)


def test_held_pan_is_the_goal_tick_s_pan():
    """held_pan against the tick by hand for pans across three turns and offsets: the servo's
    goal tick's pan (offset + (tick - 2048) 2 pi / N) within half a tick, and +180 deg held as -180."""
    rng = np.random.default_rng(3)
    for pan, offset in zip(rng.uniform(-3 * np.pi, 3 * np.pi, 500), rng.uniform(-np.pi, np.pi, 500)):
        k = round((pan - offset) * TICKS_PER_TURN / (2 * np.pi))
        tick = (CENTRE_TICK + k) % TICKS_PER_TURN
        held = held_pan(pan, offset)
        assert abs(held - (offset + (tick - CENTRE_TICK) * 2 * np.pi / TICKS_PER_TURN)) <= np.pi / TICKS_PER_TURN + 1e-12
        assert np.isclose(np.cos(held), np.cos(pan)) and np.isclose(np.sin(held), np.sin(pan))
    assert held_pan(np.pi, 0.0) == pytest.approx(-np.pi)
    assert held_pan(-np.pi, 0.0) == pytest.approx(-np.pi)
    assert held_pan(np.radians(179.9), 0.0) == pytest.approx(np.radians(179.9))


@pytest.mark.parametrize("pan_to", [np.pi, -np.pi], ids=["to +180 deg", "to -180 deg"])
def test_a_pan_move_to_180_deg_is_checked_the_way_the_servo_drives_it(tmp_path, pan_to):
    """From pan +90 deg to +/-180 deg (30 deg up, 0.2 m) the servo's ticks go through 0 deg, the
    camera standing where the lamp passes at 0 deg: the tick-by-tick judge finds contact there
    (and none on the short way 90 -> 180 deg, the one checked before), the simulator's own check
    stops the direct servo move, the controller's direct lamp_path from the read-back joints to
    LampRig.target (-180 deg) is under the padding naming the lamp and the camera, and the move
    the controller drives (via joints, or refused) never trips the simulator."""
    task = load_task(HINGE)
    _, q = camera_at(task, 0.0)
    assert servo_sweep_gap(task, q, START[0], pan_to) < CONTACT_M
    short = [lamp_position(task.lamp.rig.pivot_m, p, TILT, RADIUS) for p in np.linspace(START[0], np.pi, 60)]
    world = Obstacles(task)
    assert min(cdist(world.camera(q), world.lamp(x)).min() for x in short) > CONTACT_M

    hit = sim_devices(task, q, START)
    with pytest.raises(DeviceFault, match="protective stop"):
        hit.lamp.move(pan_to, TILT, RADIUS)

    devices = sim_devices(task, q, START)
    target = devices.lamp.target(pan_to, TILT, RADIUS)
    assert target[0] == pytest.approx(-np.pi)
    direct, _ = lamp_path(CollisionScene.of(task), devices.arm.camera_pose(), q, devices.lamp.joints(), target)
    assert not direct.ok and "lamp" in direct.reason() and "camera" in direct.reason()
    move = motion.check(task, devices, None, (pan_to, TILT, RADIUS))
    assert move.lamp_via or not move.clear
    if move.clear:
        with Recorder(tmp_path / "run") as recorder:
            motion.go(task, devices, recorder, None, (pan_to, TILT, RADIUS), to="the lamp's pose")
        assert devices.lamp.joints()[0] == pytest.approx(-np.pi, abs=1e-3)
