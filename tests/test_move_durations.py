"""How long the arm's moves take against the controller's move_timeout_s (issue 27): the
trapezoid law distance / speed + speed / acceleration (cell.devices.interfaces.trapezoid_s, the
one the UR adapter refuses a command by), each planned move's time in plan.json (`duration_s`),
a move longer than the timeout made in several commands along the same path (line_commands,
joint_commands, driven by cell.run.motion.drive_arm), the simulated arm keeping a timeout the
cell file states, a timeout no command can keep refused as bad input, and a split shot's views'
moves checked before the first moves. Expectations are worked by hand (closed forms) or come
from the simulated arm's own read-back."""
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.cli import main
from cell.collision.paths import Stop, plan_transition
from cell.collision.scene import CollisionScene
from cell.core.errors import DeviceFault
from cell.core.geometry import transform
from cell.devices import ur5e
from cell.devices.interfaces import (CRUISE_SHARE, SPEED_SAMPLE_RAD, Devices, joint_commands, line_commands,
                                     trapezoid_s)
from cell.planning.scene import look_at
from cell.report.recorder import Recorder
from cell.run import motion
from cell.task.loader import load_task
from sim.arm import SimArm

from simcell import device_settings, variant
from test_bracket import bracket  # noqa: F401  (the fixture: the bracket and its plan)

ROOT = Path(__file__).resolve().parent.parent
HINGE = ROOT / "tasks" / "hinge.yaml"
SPEED, ACCELERATION = 0.1, 0.5              # the example cell's cell.arm: ramps 0.2 s


def arm_config(**arm):
    """The example cell's ArmConfig with `arm` (cell.arm keys) as a cell file states them."""
    return device_settings({"arm": {"speed_m_s": SPEED, "acceleration_m_s2": ACCELERATION, **arm}}).arm


def steps(folder):
    return [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]


def test_a_straight_move_s_time_is_the_trapezoid_and_a_longer_one_is_cut_into_equal_commands():
    """0.3 m along x while turning 0.2 rad about z: the longer of the two (0.3 m; a turn counts
    1 m per rad) at 0.1 m/s, 0.5 m/s^2 takes 0.3 / 0.1 + 0.1 / 0.5 = 3.2 s, one command under any
    timeout above that. Under 1.2 s: (3.2 - 0.2) / (0.99 (1.2 - 0.2)) = 3.03, so 4 commands of
    0.75 + 0.2 = 0.95 s, each a quarter of the line and of the turn (scipy's rotation)."""
    config = arm_config()
    a = transform(translation=(0.0, 0.0, 0.5))
    b = transform(Rotation.from_euler("z", 0.2).as_matrix(), (0.3, 0.0, 0.5))
    assert trapezoid_s(0.3, SPEED, ACCELERATION) == pytest.approx(3.2)
    for timeout in (None, 3.2, 30.0):
        [(T, seconds)] = line_commands(config, a, b, timeout)
        assert np.array_equal(T, b) and seconds == pytest.approx(3.2)
    commands = line_commands(config, a, b, 1.2)
    assert len(commands) == 4
    for k, (T, seconds) in enumerate(commands, 1):
        assert seconds == pytest.approx(0.95) and seconds <= 1.2
        assert T[:3, 3] == pytest.approx([0.075 * k, 0.0, 0.5], abs=1e-12)
        assert T[:3, :3] == pytest.approx(Rotation.from_euler("z", 0.05 * k).as_matrix(), abs=1e-12)
    with pytest.raises(DeviceFault, match=r"every move's ramps take 0.20 s .* over move_timeout_s 0.2 s"):
        line_commands(config, a, b, 0.2)


def test_a_joint_move_s_time_is_the_leading_joint_s_trapezoid_at_the_camera_s_speed_limit():
    """The base joint alone turning 2 rad from home: the camera circles the base's axis at a
    constant distance rho, so joint_speed turns it at v = 0.1 m/s / (rho e^(2 / 200)) (its bound
    between its 200 samples 0.01 rad apart), the acceleration scaled alike: 2 / v + 0.2 s.
    Under a timeout of 60 % of that it takes ceil((D - 0.2) / (0.99 (T - 0.2))) equal commands,
    each a piece of the same line of joints."""
    task = load_task(HINGE)
    config, frames = arm_config(), task.frames
    q0 = np.array(ur5e.HOME_JOINTS, float)
    q1 = q0 + np.array([2.0, 0, 0, 0, 0, 0])
    tcp = (ur5e.forward(q0) @ frames.T_flange_cam)[:3, 3]              # base frame: the axis is z
    rho = float(np.hypot(tcp[0], tcp[1]))
    v = SPEED / (rho * np.exp(2.0 / np.ceil(2.0 / SPEED_SAMPLE_RAD)))
    whole = 2.0 / v + SPEED / ACCELERATION
    [(q, seconds)] = joint_commands(config, frames, q0, q1, None)
    assert np.array_equal(q, q1) and seconds == pytest.approx(whole, rel=1e-9)
    timeout = 0.6 * whole
    n = int(np.ceil((whole - 0.2) / (CRUISE_SHARE * (timeout - 0.2))))
    commands = joint_commands(config, frames, q0, q1, timeout)
    assert n == 2 and len(commands) == n
    for k, (q, seconds) in enumerate(commands, 1):
        assert q == pytest.approx(q0 + k / n * (q1 - q0), abs=1e-12)
        assert seconds == pytest.approx((whole - 0.2) / n + 0.2, rel=1e-9) and seconds <= timeout


def test_a_planned_move_carries_its_commands_time():
    """plan_transition's Move between two camera poses 0.1 m apart above the hinge's part, both
    looking straight down (the same orientation), the lamp where it is: a direct moveL of
    0.1 / 0.1 + 0.2 = 1.2 s, in plan.json's move as duration_s; the cell's move_timeout_s 0.7 s
    cuts it into ceil(1.0 / (0.99 x 0.5)) = 3 commands, 1.0 + 3 x 0.2 = 1.6 s."""
    task = load_task(HINGE)
    scene = CollisionScene.of(task)

    def at(x):
        T = look_at(np.array([x, 0.1, 0.40]), np.array([x, 0.1, 0.0]))
        return Stop(T, ur5e.inverse(task.frames.T_base_flange(task.frames.T_base_cam(T)), ur5e.HOME_JOINTS),
                    (np.radians(180.0), np.radians(45.0), 0.2))

    a, b = at(-0.05), at(0.05)
    move = plan_transition(scene, task.cell.devices.arm, a, b, 0, 1)
    assert move.clear and move.via == () and move.joint_legs == ()
    assert move.duration_s == pytest.approx(1.2) and move.to_json()["duration_s"] == pytest.approx(1.2)
    cut = plan_transition(scene, replace(task.cell.devices.arm, move_timeout_s=0.7), a, b, 0, 1)
    assert cut.duration_s == pytest.approx(1.6)


def test_the_simulated_arm_keeps_a_timeout_the_cell_file_states_and_the_run_cuts_a_longer_move(tmp_path):
    """A cell file stating move_timeout_s 1.2 s: the simulated arm refuses a single 0.3 m moveL
    (3.2 s) before moving, as the UR does, where without that key it has no limit; motion's
    drive_arm makes the same move in 4 commands (test above), which the arm takes, arriving at
    the target, logged as one `move_split`."""
    task = load_task(HINGE)
    home = task.frames.T_cell_cam_from_base(task.frames.T_base_cam_from_flange(ur5e.forward(ur5e.HOME_JOINTS)))
    target = home.copy()
    target[:3, 3] += [0.3, 0.0, 0.0]
    stated = SimArm(arm_config(move_timeout_s=1.2), task.frames)
    assert stated.move_timeout_s == 1.2
    with pytest.raises(DeviceFault, match=r"moveL of 0.300 m at 0.1 m/s takes 3.2 s, over move_timeout_s 1.2 s: "
                                          r"refused before moving"):
        stated.move_camera(target)
    assert stated.moves == 0 and np.allclose(stated.joints, ur5e.HOME_JOINTS)
    unstated = SimArm(arm_config(), task.frames)
    assert unstated.move_timeout_s is None and unstated.config.move_timeout_s == 30.0
    unstated.move_camera(target)
    assert unstated.moves == 1
    with Recorder(tmp_path / "run") as recorder:
        motion.drive_arm(Devices(stated, None, None), recorder, "the target", target)
    assert stated.moves == 4 and np.allclose(stated.camera_pose(), target, atol=1e-9)
    [split] = [s for s in steps(tmp_path / "run") if s["step"] == "move_split"]
    assert split["commands"] == 4 and split["duration_s"] == pytest.approx(3.8)
    assert "in 4 commands along the same path, each within the arm's move_timeout_s 1.2 s" in split["message"]


def test_a_timeout_no_command_can_keep_is_bad_input(tmp_path, capsys):
    """move_timeout_s 0.15 s with the ramps taking 0.1 / 0.5 = 0.2 s: no move of the arm can keep
    it, on any backend: exit 2, one line naming the key, before anything is planned."""
    task = variant(tmp_path, HINGE, {"cell.arm.move_timeout_s": 0.15})
    assert main(["run", str(task), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cell.arm.move_timeout_s" in err[0] and "0.2 s every move of the arm takes" in err[0]
    assert not (tmp_path / "run").exists()


def test_a_run_under_a_short_stated_timeout_cuts_its_moves_and_the_simulator_refuses_one_not_cut(
        tmp_path, monkeypatch, capsys):
    """`cell run` of the hinge on the simulated cell with move_timeout_s 1.0 s stated: the move
    from home to the shot (2 s as one command) is made in commands within it (`move_split`),
    and the run converges; the same run with the move driven as one command (line_commands
    never cutting) is refused by the simulated arm before that move (a device fault, exit 3),
    as the UR refuses it."""
    task = variant(tmp_path, HINGE, {"cell.arm.move_timeout_s": 1.0})
    assert main(["run", str(task), "--out", str(tmp_path / "cut")]) == 0
    [split] = [s for s in steps(tmp_path / "cut") if s["step"] == "move_split"]
    assert split["commands"] >= 2 and split["duration_s"] <= split["commands"] * 1.0
    monkeypatch.setattr(motion, "line_commands", lambda config, T_from, T_to, timeout_s: [(T_to, 0.0)])
    assert main(["run", str(task), "--out", str(tmp_path / "whole")]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "over move_timeout_s 1.0 s: refused before moving" in last


@pytest.mark.long          # 30-60 s: plans the yawed bracket and runs its three shots
def test_the_yawed_bracket_s_joint_moves_over_the_default_timeout_are_cut_and_the_run_converges(tmp_path):
    """The bracket turned 5 deg about z (test_moves.bracket_yawed) on the simulated cell stating
    the UR's default move_timeout_s 30 s: its route's two moveJs through a change of the arm's
    configuration take over 30 s as one command (plan.json's duration_s counts them cut: above
    30 s, below 60), each is made in commands the simulated arm takes within 30 s (it refuses a
    longer one), logged with the plan's time, and the run converges."""
    from test_moves import bracket_yawed
    task = variant(tmp_path, bracket_yawed(tmp_path), {"cell.arm.move_timeout_s": 30.0})
    out = tmp_path / "run"
    assert main(["run", str(task), "--out", str(out)]) == 0
    plan = json.loads((out / "plan.json").read_text())
    long_moves = [m for m in plan["moves"] if m["duration_s"] > 30.0]
    assert long_moves and all(m.get("joint_legs") == [0] and m["duration_s"] < 60.0 for m in long_moves)
    cut = [s for s in steps(out) if s["step"] == "move_split"]
    assert [s["to"] for s in cut] == [f"shot {m['to']}" for m in long_moves]
    for line, move in zip(cut, long_moves):
        assert line["commands"] == 2 and line["duration_s"] == pytest.approx(move["duration_s"], rel=1e-6)


def split_shot(tmp_path, bracket, monkeypatch, view_2=None):
    """The bracket found 10 mm along -x by an earlier shot: its shot of the bevel and web_outer,
    carried out of reach, re-planned into two views (loop.Split; test_located_moves), run by
    inspection.run_shot up to its first capture (later_shot); `view_2(task, shot) -> T_cell_cam`
    moves the second view's camera first. (ShotRun, its fault, its log's steps, the devices)."""
    from cell.planning import whole_part
    from test_located_moves import later_shot
    from test_localization import error
    planner = whole_part.plan_features

    def planned(task, *args, **kwargs):
        plan = planner(task, *args, **kwargs)
        if view_2 is None or len(plan.shots) != 2:
            return plan
        second = replace(plan.shots[1], T_cell_cam=view_2(task, plan.shots[1]))
        return replace(plan, shots=(plan.shots[0], second))

    monkeypatch.setattr(whole_part, "plan_features", planned)
    return later_shot(tmp_path, bracket, error(offset_m=(-0.01, 0.0, 0.0)))


def test_a_split_shot_checks_every_view_s_move_before_the_first_moves(tmp_path, bracket, monkeypatch):
    """The two views' moves (from where the cell stands to view 1, on to view 2) are checked and
    logged (`views`, each move's duration_s) before the first move of the shot; untouched, the
    arm then moves to view 1 and the shot goes on to its first capture. With the second view's
    camera put 5 mm in front of the bevel's centre (its body through the part), the shot stops at
    that check, cause `pose`, the first contact of the camera's body on the move from view 1 to
    view 2 named, and nothing moved (the simulated arm's and lamp's own move counts)."""
    result, fault, log, devices = split_shot(tmp_path / "clear", bracket, monkeypatch)
    [views] = [line for line in log if line["step"] == "views"]
    assert len(views["moves"]) == 2 and all(m["duration_s"] > 0 for m in views["moves"])
    assert [m["to"] for m in views["moves"]] == ["view 1 of 2", "view 2 of 2"]
    first_move = next(k for k, line in enumerate(log) if line["step"].startswith("move_"))
    assert log.index(views) < first_move and devices.arm.moves >= 1
    assert fault is not None and "the test stops at the first capture" in str(fault)

    def into_the_part(task, shot):
        T = shot.T_cell_cam.copy()
        centre = task.frames.T_cell_part @ np.append(task.features[0].center_m, 1.0)
        T[:3, 3] = centre[:3] - 0.005 * T[:3, 2]                # 5 mm in front of the bevel's centre
        return T

    result, fault, log, devices = split_shot(tmp_path / "blocked", bracket, monkeypatch, into_the_part)
    assert fault is None and not result.success and result.cause == "pose"
    assert result.message.startswith("the part is off by [-10.00, +0.00, +0.00] mm")
    assert "on the move from view 1 of 2 to view 2 of 2: refused before anything moved" in result.message
    assert "; carried there, collision: camera_body and " in result.message
    assert devices.arm.moves == 0 and devices.lamp.moves == 0
    assert not any(line["step"] == "views" for line in log)


def test_the_lamp_s_move_is_timed_as_its_servos_turn_and_a_longer_one_is_cut(tmp_path):
    """The bracket's route from shot 2 to shot 0 pans the lamp from -180 to 122.8 deg: the pan
    servo turns 3446 of its 4096 ticks a turn (position mode holds one turn: through 0) at the
    Profile Velocity for 30 deg/s, round(5 rpm / 0.229) = 22 units = 5.038 rpm, 343.9 ticks/s:
    10.02 s, over the default move_timeout_s 5 s. The simulated rig stating that timeout refuses
    it before moving; motion's drive_lamp makes it in ceil(10.02 / (0.99 x 5)) = 3 moves along
    the same line of joints, which the rig takes, logged as one `move_split`."""
    from sim.pantilt import SimPanTilt
    task = load_task(HINGE)
    config = device_settings({"pan_tilt": {"speed_deg_s": 30.0, "move_timeout_s": 5.0}}).pan_tilt
    lamp = SimPanTilt(task.lamp.rig, config)
    tilt = 2048 + round(5.0 / 360 * 4096)
    lamp.present = {config.pan_id: 0, config.tilt_id: tilt}                # pan -180 deg, tilt 5 deg
    start, end = (-np.pi, np.radians(5.0), 0.15), (np.radians(122.83), np.radians(5.0), 0.15)
    ticks = 2048 + round(122.83 / 360 * 4096)
    rate = round(5.0 / 0.229) * 0.229 * 4096 / 60
    assert ticks == 3446 and lamp.move_s(start, end) == pytest.approx(ticks / rate, rel=1e-12)
    assert ticks / rate == pytest.approx(10.02, abs=0.005)
    with pytest.raises(DeviceFault, match=r"takes 10.0 s at 30 deg/s, over move_timeout_s 5.0 s: refused before "
                                          r"moving"):
        lamp.move(*end)
    assert lamp.present[config.pan_id] == 0 and lamp.moves == 0
    unstated = SimPanTilt(task.lamp.rig, device_settings({"pan_tilt": {"speed_deg_s": 30.0}}).pan_tilt)
    assert unstated.move_timeout_s is None
    with Recorder(tmp_path / "run") as recorder:
        motion.drive_lamp(Devices(None, lamp, None), recorder, "shot 0", end)
    assert lamp.moves == 3 and lamp.present[config.pan_id] == ticks and lamp.present[config.tilt_id] == tilt
    [split] = [s for s in steps(tmp_path / "run") if s["step"] == "move_split"]
    assert split["commands"] == 3 and split["duration_s"] == pytest.approx(ticks / rate)
