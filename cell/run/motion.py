"""The one way the cell moves: every move of the arm and of the lamp, in a run and in the
calibration routines, starts from where the devices read back (the camera's pose and the arm's
joints, Arm.joint_angles; the lamp's joints, and the ones its axes will go to, LampRig.target),
is checked along its path as the devices follow it (cell.collision.paths.plan_transition: the
arm's moveL with via points around a collision, the lamp parked; then the lamp's route, via
joints around a collision, the arm at the target; or, where that is not clear, the lamp first;
where no moveL is clear, the same with a moveJ through the change of the arm's configuration)
and is then driven through its via points.
A move no clear path serves is refused before anything moves: GoalNotReached with cause
`collision` (exit 1), naming both bodies and where."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from cell.collision.paths import Move, Stop, joint_leg, plan_transition
from cell.collision.scene import CollisionScene, reaching_joints
from cell.core.errors import GoalNotReached
from cell.devices import ur5e
from cell.devices.interfaces import commands, joint_commands, line_commands, speaking_for

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.planning.plan import Shot
    from cell.report.recorder import Recorder
    from cell.task.types import Task

CAUSE = "collision"      # the run's cause of a refused move (cell.run.loop.CAUSES)


def check(task: Task, devices: Devices, T_cell_cam: np.ndarray | None = None,
          lamp_joints: tuple[float, ...] | None = None, to: str = "the target") -> Move:
    """The Move from where the devices read back to the camera pose T_cell_cam (None: the arm
    stays) and the lamp's joints (None: the lamp stays), checked along its path; moves nothing.
    Where the arm cannot tell its joints, the path starts at the inverse kinematics nearest home;
    a lamp whose (manual) radius is not known yet starts at the target's radius."""
    target = _lamp_target(devices, lamp_joints)
    a = standing(task, devices, np.nan if target is None else target[2])
    b = Stop(a.T_cell_cam if T_cell_cam is None else np.asarray(T_cell_cam, float), a.arm_joints, target)
    return plan_transition(CollisionScene.of(task), task.cell.devices.arm, a, b, "where the cell stands", to)


def standing(task: Task, devices: Devices, radius_m: float = np.nan) -> Stop:
    """Where the devices stand, read back, as a Stop: the camera's pose, the arm's joints (where
    the arm cannot tell them, the inverse kinematics nearest home), the lamp's joints (None where
    its manual radius is not known yet and radius_m does not stand in for it)."""
    with speaking_for(devices.arm):
        T_now, q = devices.arm.camera_pose(), devices.arm.joint_angles()
    with speaking_for(devices.lamp):
        pan, tilt, radius = devices.lamp.joints()
    if q is None:
        q = np.asarray(reaching_joints(task.frames, T_now) or ur5e.HOME_JOINTS, float)
    lamp_now = (float(pan), float(tilt), float(radius if np.isfinite(radius) else radius_m))
    return Stop(T_now, np.asarray(q, float), lamp_now if np.all(np.isfinite(lamp_now)) else None)


def check_back(task: Task, devices: Devices, there: Move, T_cell_cam: np.ndarray,
               lamp_joints: tuple[float, ...] | None, back: Stop, to: str, back_to: str) -> Move:
    """The Move back from where `there` (check's to T_cell_cam and lamp_joints, `to`) arrives to
    the camera pose and arm joints of `back` (a Stop read before, `back_to`), the lamp staying
    where `there` leaves it, checked along its path; moves nothing. A round trip is taken only
    with both ways clear: where the arm goes next is not known before it arrives."""
    target = _lamp_target(devices, lamp_joints)
    lamp = target if target is not None else standing(task, devices).lamp_joints
    a = Stop(np.asarray(T_cell_cam, float), np.asarray(there.joints_end, float), lamp)
    return plan_transition(CollisionScene.of(task), task.cell.devices.arm, a, replace(back, lamp_joints=None),
                           to, back_to)


def go_back(task: Task, devices: Devices, back: Stop, recorder: Recorder, to: str,
            iteration: int | None = None) -> np.ndarray:
    """The camera back to the Stop `back` (its pose, by the arm's joints there: check_back's
    target, not the inverse kinematics nearest where the arm stands, which may take another
    path), the lamp staying: checked from where the devices read back, refused unless clear
    (go). Returns the read-back camera pose (the caller logs it)."""
    move = plan_transition(CollisionScene.of(task), task.cell.devices.arm, standing(task, devices),
                           replace(back, lamp_joints=None), "where the cell stands", to)
    go(task, devices, recorder, back.T_cell_cam, None, to, iteration, checked=move)
    with speaking_for(devices.arm):
        return devices.arm.camera_pose()


def _lamp_target(devices: Devices, lamp_joints: tuple[float, ...] | None) -> tuple[float, float, float] | None:
    """The joints the lamp's axes go to for (pan, tilt, radius) (the pan as the servo holds it:
    LampRig.target); None: the lamp stays."""
    if lamp_joints is None:
        return None
    with speaking_for(devices.lamp):
        return devices.lamp.target(lamp_joints[0], lamp_joints[1], lamp_joints[2])


def how_apart(move: Move) -> str:
    """The clear move's nearest bodies in words: 'camera_body and lamp_body at least 31.4 mm
    apart', or 'nothing near' where no pair has a finite distance."""
    if not np.isfinite(move.clearance.distance_m):
        return "nothing near"
    return f"{' and '.join(move.clearance.bodies)} at least {1e3 * move.clearance.distance_m:.1f} mm apart"


def refusal(move: Move) -> GoalNotReached:
    """The refusal of a move that is not clear: the collision first, then the move, then that
    nothing moved."""
    c = move.clearance
    return GoalNotReached(f"{c.reason()}, on the move from {_end(move.start)} to {_end(move.end)}: "
                          "refused before anything moved", CAUSE)


def _end(end: object) -> str:
    return f"shot {end}" if isinstance(end, int) else str(end)


def go(task: Task, devices: Devices, recorder: Recorder, T_cell_cam: np.ndarray | None = None,
       lamp_joints: tuple[float, ...] | None = None, to: str = "the target",
       iteration: int | None = None, checked: Move | None = None,
       arrived: Callable[[], object] | None = None) -> Move:
    """Check the move (check; `checked`: the caller's check of it from where the devices stand,
    nothing moved since) and refuse it (refusal) unless clear; then drive it: the arm
    through its via points to T_cell_cam, the lamp through its via joints to lamp_joints (the
    lamp first where the move says so, Move.lamp_first, logged as `move_order`), each via logged
    as read back (`move_via`, `move_lamp_via`). The last legs are the caller's to
    log: `arrived()` is called when the arm is there, before the lamp moves. A leg the move makes
    by moveJ (Move.joint_legs: a change of the arm's configuration) goes to the joints the check
    planned. Returns the Move."""
    move = checked or check(task, devices, T_cell_cam, lamp_joints, to)
    if not move.clear:
        raise refusal(move)
    lamp_joints = _lamp_target(devices, lamp_joints)     # the joints check() checked
    apart = how_apart(move)

    def via(step: str, what: str, k: int, n: int, position: np.ndarray) -> None:
        recorder.step(step, f"{what} via point {k} of {n} on the way to {to}: at {np.round(position, 4).tolist()} m "
                            f"in the cell frame (collision-checked: {apart})", iteration=iteration, via=k, to=to,
                      position_m=position)

    def arm() -> None:
        for k, T in enumerate(move.via, 1):
            with speaking_for(devices.arm):
                leg(k - 1, T)
                position = devices.arm.camera_pose()[:3, 3]
            via("move_via", "the camera's", k, len(move.via), position)
        if T_cell_cam is not None:
            with speaking_for(devices.arm):
                leg(len(move.via), T_cell_cam)
            if arrived is not None:
                arrived()

    def leg(k: int, T: np.ndarray) -> None:
        """The arm's leg k to the camera pose T: a moveJ to the joints the check planned there
        where the move makes it one (Move.joint_legs), else a moveL (drive_arm)."""
        if k in move.joint_legs:
            q = move.via_joints[k] if k < len(move.via) else move.joints_end
            assert q is not None, "a clear move arrives somewhere"
            drive_arm(devices, recorder, to, q=q, iteration=iteration)
        else:
            drive_arm(devices, recorder, to, T, iteration=iteration)

    def lamp() -> None:
        for k, joints in enumerate(move.lamp_via, 1):
            with speaking_for(devices.lamp):
                drive_lamp(devices, recorder, f"the lamp's via point {k} on the way to {to}", joints, iteration)
                position = devices.lamp.lamp_pose()[0]
            via("move_lamp_via", "the lamp's", k, len(move.lamp_via), position)
        if lamp_joints is not None:
            with speaking_for(devices.lamp):
                drive_lamp(devices, recorder, to, lamp_joints, iteration)

    if move.lamp_first:
        recorder.step("move_order", f"the lamp first, then the camera, on the way to {to}: the camera's path with "
                                    "the lamp where it stands is not clear, the lamp's then the camera's is "
                                    f"(collision-checked: {apart})", iteration=iteration, to=to, lamp_first=True)
    for part in ((lamp, arm) if move.lamp_first else (arm, lamp)):
        part()
    return move


def drive_arm(devices: Devices, recorder: Recorder, to: str, T_cell_cam: np.ndarray | None = None,
              q: np.ndarray | None = None, iteration: int | None = None) -> None:
    """The arm to the camera pose T_cell_cam by moveL, or to the joints q by moveJ, from where it
    reads back, in the commands that keep each within its move_timeout_s (line_commands,
    joint_commands: pieces of the same path, so the path checked is the path driven, each
    stopping at its end); a move made in several logged (`move_split`). The caller speaks for the
    arm (speaking_for); an arm that cannot tell its joints gets the moveJ whole (it refuses it)."""
    arm = devices.arm
    if q is None:
        pieces = line_commands(arm.config, arm.camera_pose(), np.asarray(T_cell_cam, float), arm.move_timeout_s)
    elif (q_now := arm.joint_angles()) is None:
        arm.move_joints(q)
        return
    else:
        pieces = joint_commands(arm.config, arm.frames, q_now, q, arm.move_timeout_s)
    if len(pieces) > 1:
        kind, total = "straight move" if q is None else "joint move", sum(t for _, t in pieces)
        recorder.step("move_split", f"the {kind} to {to} in {len(pieces)} commands along the same path, each "
                                    f"within the arm's move_timeout_s {arm.move_timeout_s} s ({total:.1f} s in all)",
                      iteration=iteration, to=to, commands=len(pieces), duration_s=total)
    for target, _ in pieces:
        if q is None:
            arm.move_camera(target)
        else:
            arm.move_joints(target)


def drive_lamp(devices: Devices, recorder: Recorder, to: str, joints: tuple[float, ...],
               iteration: int | None = None) -> None:
    """The lamp to `joints` (pan, tilt, radius, as the axes hold them: LampRig.target) from where
    it reads back, in the fewest equal pieces of the same line of joints that keep each move
    within its move_timeout_s (LampRig.move_s; interfaces.commands, no ramps), a split logged
    (`move_split`). A radius the operator sets (manual) stays where it is until the last piece
    (the target's where it is not known yet), so it is asked for once. The caller speaks for
    the lamp (speaking_for)."""
    lamp = devices.lamp
    end = np.array(joints[:3], float)
    start = np.array(lamp.joints(), float)
    start[2] = start[2] if np.isfinite(start[2]) else end[2]
    whole = lamp.move_s((start[0], start[1], start[2]), (end[0], end[1], end[2]))
    n = commands(whole, 0.0, lamp.move_timeout_s)
    if n > 1:
        recorder.step("move_split", f"the lamp's move to {to} in {n} moves along the same line of its joints, each "
                                    f"within its move_timeout_s {lamp.move_timeout_s} s ({whole:.1f} s in all)",
                      iteration=iteration, to=to, commands=n, duration_s=whole)
    for k in range(1, n):
        along = start + k / n * (end - start)
        lamp.move(along[0], along[1], start[2] if lamp.manual_radius else along[2])
    lamp.move(*end)


def move_to(task: Task, devices: Devices, shot: Shot, recorder: Recorder, iteration: int | None = None) -> None:
    """Camera and lamp to the shot's poses along a checked path (go), each logged as read back
    from the device."""
    def arrived() -> None:
        with speaking_for(devices.arm):
            position = devices.arm.camera_pose()[:3, 3]
        off = float(np.linalg.norm(position - shot.camera_position))
        recorder.step("move_camera", f"camera at {np.round(position, 4).tolist()} m in the cell frame "
                                     f"({1e3 * off:.2f} mm from the plan)", iteration=iteration, position_m=position,
                      error_m=off)

    go(task, devices, recorder, shot.T_cell_cam, shot.joints, "the shot's poses", iteration, arrived=arrived)
    _log_lamp(devices, recorder, iteration, "")


def move_joints(task: Task, devices: Devices, q: np.ndarray, recorder: Recorder, to: str) -> np.ndarray:
    """The arm by moveJ to the joints q (a route's leg through a change of configuration,
    cell.run.moves.follow), the path checked from where the arm reads back (joint_path, the lamp
    where it stands) and refused (refusal) unless clear; logged as `move_joints`. Returns the
    read-back camera pose."""
    with speaking_for(devices.arm):
        q_now = devices.arm.joint_angles()
    with speaking_for(devices.lamp):
        lamp = devices.lamp.lamp_pose()[0]
    if q_now is None:
        raise GoalNotReached(f"the joint move to {to} needs the arm's joints read back, which it does not report: "
                             "refused before anything moved", CAUSE)
    found, _, steps = joint_leg(CollisionScene.of(task), task.cell.devices.arm, q_now, q,
                                lamp if np.all(np.isfinite(lamp)) else None)
    move = Move("where the cell stands", to, found, steps=steps, joints_end=np.asarray(q, float), joint_legs=(0,))
    if not move.clear:
        raise refusal(move)
    with speaking_for(devices.arm):
        drive_arm(devices, recorder, to, q=q)
        T = devices.arm.camera_pose()
    recorder.step("move_joints", f"the arm's joints to {np.round(np.degrees(q), 1).tolist()} deg on the way to {to} "
                                 f"(a joint move: its configuration changes; collision-checked: {how_apart(move)}), "
                                 f"the camera at {np.round(T[:3, 3], 4).tolist()} m in the cell frame",
                  to=to, joints_deg=np.degrees(q), position_m=T[:3, 3])
    return T


def move_camera(task: Task, devices: Devices, T_cell_cam: np.ndarray, recorder: Recorder, to: str,
                iteration: int | None = None, checked: Move | None = None,
                lamp_joints: tuple[float, ...] | None = None) -> np.ndarray:
    """The camera to T_cell_cam along a checked path (go), the lamp where it is or to lamp_joints
    (then logged as read back); returns the read-back camera pose (the caller logs it)."""
    go(task, devices, recorder, T_cell_cam, lamp_joints, to, iteration, checked)
    if lamp_joints is not None:
        _log_lamp(devices, recorder, iteration, f"{to}: ")
    with speaking_for(devices.arm):
        return devices.arm.camera_pose()


def move_lamp(task: Task, devices: Devices, joints: tuple[float, ...], recorder: Recorder,
              iteration: int | None = None, why: str = "") -> tuple[float, float, float]:
    """The lamp to (pan, tilt, radius) [rad, rad, m] along a checked route (go), the arm where
    it is, logged as read back (after `why`, if given). Returns the read-back joints."""
    go(task, devices, recorder, None, joints, why.rstrip(": ") or "the lamp's pose", iteration)
    return _log_lamp(devices, recorder, iteration, why)


def _log_lamp(devices: Devices, recorder: Recorder, iteration: int | None, why: str) -> tuple[float, float, float]:
    with speaking_for(devices.lamp):
        pan, tilt, radius = devices.lamp.joints()
    recorder.step("move_lamp", f"{why}pan {np.degrees(pan):.2f} deg, tilt {np.degrees(tilt):.2f} deg, "
                               f"radius {1e3 * radius:.1f} mm", iteration=iteration,
                  joints={"pan_deg": np.degrees(pan), "tilt_deg": np.degrees(tilt), "radius_m": radius})
    return pan, tilt, radius
