"""Simulated UR5e carrying the camera: the analytic kinematics of cell/devices/ur5e.py, the robot base at
the frames' T_cell_base and the camera at their hand-eye T_flange_cam."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.devices.interfaces import Arm
from cell.core.errors import DeviceFault
from cell.devices import ur5e
from cell.devices.ur5e import HOME_JOINTS
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from sim.obstacles import Obstacles
    from cell.core.frames import Frames
    from cell.task.device_config import ArmConfig



TRACK_M, TRACK_RAD = 0.01, 0.05       # a moveL's tracking steps
JUMP_RAD = 0.5                         # a joint turning more in one tracking step: a singularity


class SimArm(Arm):
    """Moves instantly along a moveL or a moveJ (move_joints: the joints linear). Along a moveL
    the flange's position on a straight line, its orientation by slerp, the joints tracked by the
    IK solution nearest the last (every TRACK_M and TRACK_RAD); where the tracking jumps (a
    singularity) the move is a joint move to the solution nearest the current joints. Given the
    cell's `obstacles` (sim.obstacles, its own collision check), a move that would touch another
    body stops before it, a protective stop (DeviceFault), the arm where it was. Fault
    injection: move number `fail_on_move` ends in a protective stop (DeviceFault). A command
    longer than cell.arm.move_timeout_s is refused before moving, as the real arm's, where the
    cell file states one (move_timeout_s)."""

    def __init__(self, config: ArmConfig, frames: Frames, joints: ArrayLike = HOME_JOINTS,
                 fail_on_move: int | None = None, obstacles: Obstacles | None = None) -> None:
        super().__init__(config, frames)
        self.joints = np.array(joints, float)
        self.moves = 0
        self.fail_on_move = fail_on_move
        self.obstacles = obstacles
        if obstacles is not None:
            obstacles.arm_joints = self.joints

    @property
    def move_timeout_s(self) -> float | None:
        """The cell file's cell.arm.move_timeout_s where it states one (the simulated controller
        has no watchdog of its own), else None: no limit."""
        return self.config.move_timeout_s if self.config.move_timeout_given else None

    def _move_tcp(self, T_base_cam, speed_m_s):
        self.moves += 1
        if self.moves == self.fail_on_move:
            raise DeviceFault(self.device, f"protective stop during move {self.moves} (injected)")
        try:
            path = self._path(self.frames.T_base_flange(T_base_cam))
        except ur5e.Unreachable as why:
            raise DeviceFault(self.device, f"camera pose unreachable for the UR5e: {why}") from None
        if self.obstacles is not None:
            contact = self.obstacles.arm_move(path)
            if contact is not None:
                raise DeviceFault(self.device, f"protective stop: {contact} (the simulated cell's own "
                                               "collision check)")
            self.obstacles.arm_joints = path[-1]
        self.joints = path[-1]

    def _move_joints(self, q, speed_rad_s, acceleration_rad_s2):
        """moveJ: the joints linear to q, checked by the cell's own collision check as a moveL's
        joint path (a protective stop before a contact, the arm where it was)."""
        self.moves += 1
        if self.moves == self.fail_on_move:
            raise DeviceFault(self.device, f"protective stop during move {self.moves} (injected)")
        if self.obstacles is not None:
            contact = self.obstacles.arm_move([self.joints, q])
            if contact is not None:
                raise DeviceFault(self.device, f"protective stop: {contact} (the simulated cell's own "
                                               "collision check)")
            self.obstacles.arm_joints = q
        self.joints = np.array(q, float)

    def _path(self, T_end: np.ndarray) -> list[np.ndarray]:
        """The joints along the moveL from the current flange pose to T_end (base frame)."""
        T0 = ur5e.forward(self.joints)
        turn = Rotation.from_matrix(T0[:3, :3].T @ T_end[:3, :3])
        n = max(1, int(np.ceil(max(np.linalg.norm(T_end[:3, 3] - T0[:3, 3]) / TRACK_M,
                                   turn.magnitude() / TRACK_RAD))))
        path = [self.joints]
        for s in np.linspace(0.0, 1.0, n + 1)[1:]:
            T = np.eye(4)
            T[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec(s * turn.as_rotvec()).as_matrix()
            T[:3, 3] = (1 - s) * T0[:3, 3] + s * T_end[:3, 3]
            try:
                q = ur5e.inverse(T, path[-1])
            except ur5e.Unreachable:
                break
            if np.abs(q - path[-1]).max() > JUMP_RAD:
                break
            path.append(q)
        else:
            return path
        return [self.joints, ur5e.inverse(T_end, self.joints)]

    def _unreachable(self, T_base_cam):
        """The UR5e's inverse kinematics from the current joints: why it has no solution, or None."""
        try:
            ur5e.inverse(self.frames.T_base_flange(T_base_cam), self.joints)
        except ur5e.Unreachable as why:
            return f"camera pose unreachable for the UR5e: {why}"
        return None

    def _joint_angles(self):
        return self.joints.copy()

    def _tcp_pose(self):
        return self.frames.T_base_cam_from_flange(ur5e.forward(self.joints))

    def stop(self) -> None:
        """Moves are instantaneous: nothing is ever in motion."""
