"""Simulated UR5e carrying the camera: the analytic kinematics of cell/devices/ur5e.py, the robot base at
the frames' T_cell_base and the camera at their hand-eye T_flange_cam."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.devices.interfaces import Arm
from cell.core.errors import DeviceFault
from cell.devices import ur5e

if TYPE_CHECKING:
    from cell.core.frames import Frames
    from cell.task.device_config import ArmConfig

# elbow up, wrist down: the flange points at the table in front of the base
HOME_JOINTS = np.radians([-90.0, -90.0, 90.0, -90.0, -90.0, 0.0])


class SimArm(Arm):
    """Moves instantly to the IK solution nearest the current joints. Fault injection:
    move number `fail_on_move` ends in a protective stop (DeviceFault)."""

    def __init__(self, config: ArmConfig, frames: Frames, joints: ArrayLike = HOME_JOINTS,
                 fail_on_move: int | None = None) -> None:
        super().__init__(config, frames)
        self.joints = np.array(joints, float)
        self.moves = 0
        self.fail_on_move = fail_on_move

    def _move_tcp(self, T_base_cam, speed_m_s):
        self.moves += 1
        if self.moves == self.fail_on_move:
            raise DeviceFault(self.device, f"protective stop during move {self.moves} (injected)")
        try:
            self.joints = ur5e.inverse(self.frames.T_base_flange(T_base_cam), self.joints)
        except ur5e.Unreachable as why:
            raise DeviceFault(self.device, f"camera pose unreachable for the UR5e: {why}") from None

    def _unreachable(self, T_base_cam):
        """The UR5e's inverse kinematics from the current joints: why it has no solution, or None."""
        try:
            ur5e.inverse(self.frames.T_base_flange(T_base_cam), self.joints)
        except ur5e.Unreachable as why:
            return f"camera pose unreachable for the UR5e: {why}"
        return None

    def _tcp_pose(self):
        return self.frames.T_base_cam_from_flange(ur5e.forward(self.joints))

    def stop(self) -> None:
        """Moves are instantaneous: nothing is ever in motion."""
