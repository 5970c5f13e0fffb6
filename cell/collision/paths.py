"""The moves between two shots checked along their paths, and via points around a collision.

The arm moves first, the lamp parked at the first shot's pose (cell.run.acquisition.move_to), by
moveL: the camera's position on a straight line and its orientation by slerp, the joints by the
inverse kinematics nearest the last step's (as the controller follows a Cartesian path). Then the
lamp moves in its joints (pan, tilt, radius linear together), the arm at the second shot.
Steps bound how far any point of a moving body travels between two checked poses below half the
padding: the camera body by |dp| + |dtheta| rho (rho its farthest point from the camera's
origin), the arm's links by sum_i |dq_i| R (R the arm's reach with the camera, from any joint
axis), the lamp body by (|dpan| + |dtilt|) (r + its diagonal) + |dr|. A direct move closer than
the padding gets via points: back along the camera's axis from the first shot, across at that
standoff, in along the second's axis; retreats of VIA_RETREATS_M are tried in turn.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation, Slerp

from cell.collision.scene import Clearance, CollisionScene
from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.devices import ur5e
from cell.devices.interfaces import check_arm_motion
from cell.devices.rig import lamp_position

if TYPE_CHECKING:
    from cell.task.device_config import ArmConfig

ARM_REACH_M = 0.85                       # the UR5e's reach from its shoulder (datasheet: 850 mm)
VIA_RETREATS_M = (0.10, 0.20, 0.30)      # back along the camera's axis, tried in turn
MIN_STEP_M = 0.001                       # a padding of 0 still checks every millimetre
MAX_STEPS = 5000                         # a longer path is refused, not checked for minutes
MAX_JOINT_STEP_RAD = 0.2                 # more in one step of a straight path: it meets a singularity


@dataclass(frozen=True)
class Move:
    """A move from shot `start` to shot `end` (plan indices): the smallest clearance along its
    path (via points included), and the via camera poses T_cell_cam (empty: direct); `clear`
    when that clearance is at least the padding."""

    start: int
    end: int
    clearance: Clearance
    via: tuple[np.ndarray, ...] = ()
    steps: int = 0                       # poses checked

    @property
    def clear(self) -> bool:
        return self.clearance.ok

    def reason(self) -> str:
        return f"the move from shot {self.start} to shot {self.end}: {self.clearance.reason()}"

    def to_json(self) -> dict[str, object]:
        return {"from": self.start, "to": self.end, "clearance_m": self.clearance.distance_m,
                "clearance_bodies": list(self.clearance.bodies), "via": [T.tolist() for T in self.via],
                "steps": self.steps}


def _least(clearances: list[Clearance], padding_m: float) -> Clearance:
    return min(clearances, key=lambda c: c.distance_m, default=Clearance(np.inf, ("", ""), padding_m))


def arm_path(scene: CollisionScene, T_from: np.ndarray, q_from: ArrayLike, T_to: np.ndarray,
             lamp: ArrayLike | None) -> tuple[Clearance, np.ndarray, int]:
    """(the smallest Clearance along the moveL from T_from (joints q_from) to T_to, the joints it
    ends at, the poses checked); raises ur5e.Unreachable where the inverse kinematics fail."""
    step = max(0.5 * scene.padding_m, MIN_STEP_M)
    corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3)).T.reshape(-1, 3) * scene.camera_half_m
    in_cam = geometry.apply(scene.frames.T_cam_flange @ geometry.transform(
        translation=(0.0, 0.0, scene.camera_offset_m)), corners)
    rho = float(np.linalg.norm(in_cam, axis=1).max())
    reach = ARM_REACH_M + scene.camera_offset_m + float(np.linalg.norm(scene.camera_half_m))
    turn = geometry.rotation_angle(T_from, T_to)
    n = max(1, int(np.ceil((np.linalg.norm(T_to[:3, 3] - T_from[:3, 3]) + turn * rho) / step)))
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix([T_from[:3, :3], T_to[:3, :3]]))
    q_start = np.asarray(q_from, float)
    for _ in range(4):                   # refine until the joints' sweep is within the step too
        s = np.linspace(0.0, 1.0, n + 1)
        poses = np.repeat(np.eye(4)[None], n + 1, axis=0)
        poses[:, :3, :3] = slerp(s).as_matrix()
        poses[:, :3, 3] = (1 - s)[:, None] * T_from[:3, 3] + s[:, None] * T_to[:3, 3]
        joints = [q_start]
        for T in poses[1:]:
            joints.append(ur5e.inverse(scene.frames.T_base_flange(scene.frames.T_base_cam(T)), joints[-1]))
        jumps = np.abs(np.diff(joints, axis=0))
        if jumps.max() > MAX_JOINT_STEP_RAD:
            raise ur5e.Unreachable(f"the straight path turns a joint {np.degrees(jumps.max()):.0f} deg in one "
                                   "step: a singularity or a change of configuration on the way")
        sweep = float(jumps.sum(axis=1).max()) * reach
        if sweep <= step:
            break
        n = int(np.ceil(n * sweep / step))
        if n > MAX_STEPS:
            raise ur5e.Unreachable(f"a path of more than {MAX_STEPS} steps of {step * 1e3:g} mm")
    found = [scene.clearance(T, q, lamp) for T, q in zip(poses, joints)]
    return _least(found, scene.padding_m), joints[-1], len(poses)


def lamp_path(scene: CollisionScene, T_cam: np.ndarray, q: ArrayLike, joints_from: ArrayLike,
              joints_to: ArrayLike) -> tuple[Clearance, int]:
    """The smallest Clearance as the lamp moves in its joints (pan, tilt, radius), the arm still."""
    a, b = np.asarray(joints_from, float), np.asarray(joints_to, float)
    step = max(0.5 * scene.padding_m, MIN_STEP_M)
    arm = max(a[2], b[2]) + 2 * float(np.linalg.norm(scene.lamp_half_m))
    n = max(1, int(np.ceil(((abs(b[0] - a[0]) + abs(b[1] - a[1])) * arm + abs(b[2] - a[2])) / step)))
    s = np.linspace(0.0, 1.0, n + 1)[:, None]
    pan, tilt, radius = ((1 - s) * a + s * b).T
    positions = lamp_position(scene.pivot_m, pan, tilt, radius)
    return _least([scene.clearance(T_cam, q, p) for p in positions], scene.padding_m), len(positions)


@dataclass(frozen=True)
class Stop:
    """What a move needs of a shot: the camera pose, the arm's joints there, the lamp's joints."""

    T_cell_cam: np.ndarray
    arm_joints: np.ndarray
    lamp_joints: tuple[float, float, float]


def plan_move(scene: CollisionScene, arm: ArmConfig, start: int, a: Stop, end: int, b: Stop) -> Move:
    """The Move from stop a to stop b: direct if clear, else through the first via points
    (VIA_RETREATS_M) whose path is clear; neither: the direct move, not clear, with its bodies."""
    lamp_a = lamp_position(scene.pivot_m, *a.lamp_joints)
    direct, steps = _through(scene, [a.T_cell_cam, b.T_cell_cam], a.arm_joints, lamp_a)
    if direct is not None and direct.ok:
        return _with_lamp(scene, Move(start, end, direct, (), steps), b, a.lamp_joints)
    for retreat in VIA_RETREATS_M:
        via = (_retreated(a.T_cell_cam, retreat), _retreated(b.T_cell_cam, retreat))
        try:
            for T in via:
                check_arm_motion(arm, scene.frames, T, arm.speed_m_s)
        except DeviceFault:
            continue
        found, n = _through(scene, [a.T_cell_cam, *via, b.T_cell_cam], a.arm_joints, lamp_a)
        steps += n
        if found is not None and found.ok:
            return _with_lamp(scene, Move(start, end, found, via, steps), b, a.lamp_joints)
    if direct is None:
        direct = Clearance(-np.inf, ("arm", "its reach"), scene.padding_m)
    return Move(start, end, direct, (), steps)


def _through(scene: CollisionScene, poses: list[np.ndarray], q: np.ndarray,
             lamp: np.ndarray) -> tuple[Clearance | None, int]:
    """The smallest Clearance of moveL's through the poses in turn (None: a pose the arm does not
    reach on the way), and the poses checked."""
    found, steps = [], 0
    try:
        for T_from, T_to in zip(poses, poses[1:]):
            c, q, n = arm_path(scene, T_from, q, T_to, lamp)
            found.append(c)
            steps += n
    except ur5e.Unreachable:
        return None, steps
    return _least(found, scene.padding_m), steps


def _with_lamp(scene: CollisionScene, move: Move, b: Stop, lamp_from: tuple[float, float, float]) -> Move:
    """The move with the lamp's own move after the arm's (the arm at stop b) counted in."""
    c, n = lamp_path(scene, b.T_cell_cam, b.arm_joints, lamp_from, b.lamp_joints)
    least = _least([move.clearance, c], scene.padding_m)
    return Move(move.start, move.end, least, move.via, move.steps + n)


def _retreated(T_cell_cam: np.ndarray, distance_m: float) -> np.ndarray:
    """The camera pose moved back along its optical axis (away from what it looks at)."""
    T = T_cell_cam.copy()
    T[:3, 3] -= distance_m * T[:3, 2]
    return T
