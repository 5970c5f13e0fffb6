"""The moves a run makes (issue 26): the simulated arm and pan-tilt's own collision check
(sim.obstacles) stops a deliberately bad move with a device fault and lets the planner's path
(cell.collision.paths, via points) through; a run whose move cannot be made clear is refused
before anything moves, exit 1, naming both bodies and where; the example's run goes through the
via points."""
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.cli import main
from cell.collision.paths import plan_move
from cell.collision.scene import CollisionScene
from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.planning.scene import look_at
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.obstacles import Obstacles
from sim.pantilt import SimPanTilt

from simcell import variant
from test_collision import stop, wall_task

ROOT = Path(__file__).resolve().parent.parent
HINGE, BEAM = ROOT / "tasks" / "hinge.yaml", ROOT / "tasks" / "conrod-beam.yaml"


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
    """conrod-beam.yaml's beam 50 mm taller (to z = 450 mm, clear of the wrist above either shot)
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
