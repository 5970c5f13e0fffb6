"""The moves a run makes, checked before anything moves: the route of a plan's shots from the
arm's home pose with every move collision-checked along its path (cell.collision.paths: via
points around a collision, the route ordered by cell.run.route on the moves' true travel, each
move's time, Move.duration_s), the views a shot is split into likewise (`view_moves`), and the
arm and lamp driven through them (`follow`). A feasible plan whose route has a move that
cannot be made clear becomes infeasible, `collision` binding, naming both bodies and where."""
from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from cell.collision.paths import Move, Stop, checked_route, home_stop, plan_transition
from cell.collision.scene import CollisionScene, reaching_joints
from cell.devices import ur5e
from cell.devices.interfaces import speaking_for
from cell.devices.servo import held_pan
from cell.run import motion, route

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.planning.plan import Plan
    from cell.report.recorder import Recorder
    from cell.task.types import Task

HOME_TOLERANCE_M = 1e-3          # a start pose this close to home starts the plan's first move


def stops(task: Task, plan: Plan) -> list[Stop]:
    """The plan's shots as stops of the arm and the lamp: the joints the planner chose (or the
    inverse kinematics nearest the home joints), the lamp's joints with the pan the servo holds
    (held_pan: +180 deg is driven to -180 deg), so the lamp's moves are checked as driven."""
    out = []
    for shot in plan.shots:
        pan, tilt, radius = shot.joints
        pan = held_pan(pan, task.cell.devices.pan_tilt.pan_offset_rad)
        q = reaching_joints(task.frames, shot.T_cell_cam, shot.arm_joints)
        out.append(Stop(shot.T_cell_cam, np.asarray(q, float), (pan, tilt, radius)))
    return out


def with_moves(task: Task, plan: Plan) -> Plan:
    """The plan with its route's checked moves (Plan.moves: from the home pose through every
    shot, in the order a run visits them), their time in timing_s (`moves`, and in `total`). A
    move that cannot be made clear makes the plan infeasible, `collision` binding, its reason the
    hint. A plan already infeasible, or with a shot the arm does not reach, is returned as it is:
    the run refuses it before anything moves anyway."""
    if not plan.feasible or any(reaching_joints(task.frames, s.T_cell_cam, s.arm_joints) is None
                                for s in plan.shots):
        return plan
    start = time.perf_counter()
    scene = CollisionScene.of(task)
    _, moves = checked_route(scene, task.cell.devices.arm, [home_stop(scene), *stops(task, plan)],
                             route.shortest_order)
    took = time.perf_counter() - start
    timing = {**plan.timing_s, "moves": took, "total": plan.timing_s.get("total", 0.0) + took}
    planned = replace(plan, moves=tuple(moves), timing_s=timing)
    blocked = next((m for m in moves if not m.clear), None)
    if blocked is None:
        return planned
    return replace(planned, feasible=False, binding="collision", miss=float("inf"), hint=blocked.reason())


def order(plan: Plan) -> tuple[int, ...]:
    """The shots' order of the plan's checked route (Plan.moves)."""
    return tuple(int(m.end) for m in plan.moves)


def run_moves(task: Task, plan: Plan, devices: Devices) -> list[Move]:
    """The moves of the plan's route as the run makes them: the first checked again from where
    the devices read back (read_back), the rest the plan's unless the first arrives in other
    joints than the plan's did (then each is checked again from where the last arrives). Every
    move is checked before anything moves."""
    scene, arm = CollisionScene.of(task), task.cell.devices.arm
    at, at_home = read_back(task, devices, scene)
    targets, moves = stops(task, plan), list[Move]()
    for k, planned in enumerate(plan.moves):
        arrived, foreseen = (moves[-1].joints_end, plan.moves[k - 1].joints_end) if moves else (None, None)
        if arrived is not None and foreseen is not None and np.allclose(arrived, foreseen, atol=1e-6):
            moves.append(planned)
        else:
            move = plan_transition(scene, arm, at, targets[int(planned.end)],
                                   planned.start if moves or at_home else "start", planned.end)
            moves.append(move)
        if not moves[-1].clear or moves[-1].joints_end is None:
            break
        at = replace(targets[int(planned.end)], arm_joints=moves[-1].joints_end)
    return moves


def view_moves(task: Task, plan: Plan, devices: Devices) -> list[Move]:
    """The moves from where the devices read back (read_back) through plan.shots in their order
    (the views a shot is split into, cell.run.inspection.split_views), each checked from where
    the last arrives (plan_transition: the arm's reach, collisions along the path, the time its
    commands take, Move.duration_s), the start and end named `view j of n`; a move not clear
    ends the list. Moves nothing: the run checks every view's move before the first moves."""
    scene, arm, n = CollisionScene.of(task), task.cell.devices.arm, len(plan.shots)
    at, _ = read_back(task, devices, scene)
    moves = list[Move]()
    for j, target in enumerate(stops(task, plan)):
        moves.append(plan_transition(scene, arm, at, target, f"view {j} of {n}" if j else "where the cell stands",
                                     f"view {j + 1} of {n}"))
        if not moves[-1].clear or moves[-1].joints_end is None:
            break
        at = replace(target, arm_joints=moves[-1].joints_end)
    return moves


def read_back(task: Task, devices: Devices, scene: CollisionScene) -> tuple[Stop, bool]:
    """(where the devices stand as a Stop: the camera's pose and the arm's joints read back
    (Arm.joint_angles; where the arm cannot tell them, home's when its camera is at home's pose,
    else the inverse kinematics nearest home), the lamp's joints (None where its radius is not
    known); whether the camera is at home's pose)."""
    with speaking_for(devices.arm):
        T, read = devices.arm.camera_pose(), devices.arm.joint_angles()
    with speaking_for(devices.lamp):
        pan, tilt, radius = devices.lamp.joints()
    lamp = (float(pan), float(tilt), float(radius))
    home = home_stop(scene)
    at_home = bool(np.linalg.norm(T[:3, 3] - home.T_cell_cam[:3, 3]) <= HOME_TOLERANCE_M
                   and np.allclose(T[:3, :3], home.T_cell_cam[:3, :3], atol=1e-4))
    q = read if read is not None else home.arm_joints if at_home else reaching_joints(task.frames, T)
    return Stop(T, np.asarray(ur5e.HOME_JOINTS if q is None else q, float),
                lamp if np.all(np.isfinite(lamp)) else None), at_home


def follow(task: Task, devices: Devices, move: Move, recorder: Recorder,
           lamp_joints: tuple[float, ...] | None = None) -> None:
    """The arm through the move's via points (each a moveL the planner checked, and
    cell.run.motion checks again from where the arm reads back; a leg the planner made a moveJ,
    Move.joint_legs, to the joints it planned there, motion.move_joints), logged as read back,
    the lamp first to the shot's lamp_joints where the planner moved it first (Move.lamp_first:
    the path was checked with it there); a last leg that is a moveJ too, to the shot's planned
    joints (a moveL's recheck could not follow the change of configuration). Then
    motion.move_to takes the camera and the lamp to the shot."""
    if (move.via or move.joint_legs) and move.lamp_first and lamp_joints is not None:
        motion.go(task, devices, recorder, None, lamp_joints, f"shot {move.end}'s lamp pose, before the via points")
    for k, T in enumerate(move.via, 1):
        to = f"via point {k} to shot {move.end}"
        if k - 1 in move.joint_legs:
            position = motion.move_joints(task, devices, move.via_joints[k - 1], recorder, to)[:3, 3]
        else:
            position = motion.move_camera(task, devices, T, recorder, to)[:3, 3]
        recorder.step("move_via", f"via point {k} of {len(move.via)} on the way to shot {move.end}: camera at "
                                  f"{np.round(position, 4).tolist()} m in the cell frame (the path collision-checked: "
                                  f"{' and '.join(move.clearance.bodies)} at least "
                                  f"{1e3 * move.clearance.distance_m:.1f} mm apart)",
                      via=k, to_shot=move.end, position_m=position)
    if len(move.via) in move.joint_legs and move.joints_end is not None:
        motion.move_joints(task, devices, move.joints_end, recorder, f"shot {move.end}")
