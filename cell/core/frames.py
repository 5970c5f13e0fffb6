"""The cell's named transforms, in one registry that every pose composition reads and a
calibration writes (in the spirit of pytransform3d's TransformManager).

T_a_b maps b coordinates into a (4x4, metres); compose like algebra: T_a_c = T_a_b @ T_b_c.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class Frames:
    T_cell_part: np.ndarray        # the part in the cell: task part.position_m / rpy_deg
    T_cell_base: np.ndarray        # the robot base (UR "Base") in the cell: cell.arm.base_*
    T_flange_cam: np.ndarray       # hand-eye, the camera in the tool flange: cell.arm.hand_eye_*

    def with_transform(self, name: str, T: ArrayLike) -> Frames:
        """These frames with transform `name` (e.g. "T_flange_cam") replaced, as a calibration
        writes it; the others are kept."""
        if name not in {f.name for f in fields(self)}:
            raise ValueError(f"no transform {name!r}: one of {', '.join(f.name for f in fields(self))}")
        return replace(self, **{name: np.asarray(T, float)})

    @property
    def T_base_cell(self) -> np.ndarray:
        return np.linalg.inv(self.T_cell_base)

    @property
    def T_cam_flange(self) -> np.ndarray:
        return np.linalg.inv(self.T_flange_cam)

    def T_base_cam(self, T_cell_cam: np.ndarray) -> np.ndarray:
        """The camera pose the robot is sent (its TCP is the camera)."""
        return self.T_base_cell @ T_cell_cam

    def T_cell_cam_from_base(self, T_base_cam: np.ndarray) -> np.ndarray:
        """The camera pose in the cell from the robot's reported TCP pose."""
        return self.T_cell_base @ T_base_cam

    def T_cell_flange(self, T_cell_cam: np.ndarray) -> np.ndarray:
        """Where the flange is when the camera is at T_cell_cam (the workspace check)."""
        return T_cell_cam @ self.T_cam_flange

    def T_base_flange(self, T_base_cam: np.ndarray) -> np.ndarray:
        """The flange pose the arm's kinematics solve for, from the camera's."""
        return T_base_cam @ self.T_cam_flange

    def T_base_cam_from_flange(self, T_base_flange: np.ndarray) -> np.ndarray:
        """The camera pose from the flange pose of the arm's forward kinematics."""
        return T_base_flange @ self.T_flange_cam
