"""What every step of a run works with and none of them changes: the task, the devices, the
recorder, the iteration limit, a black level found earlier, the camera pose re-plans keep and the
pose error of the part and the camera an earlier shot found. A run of several shots gives each
shot its own (its sub-recorder, the black level and the pose error the shots before it found, the
shot's camera pose) by dataclasses.replace."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from cell.devices.interfaces import Devices
    from cell.report.recorder import Recorder
    from cell.run.localization import PoseError
    from cell.run.measurement import BlackLevel
    from cell.task.types import Task


@dataclass(frozen=True)
class RunContext:
    """The run's task as given (a shot's features are its one-feature tasks), the cell's devices,
    the run folder's recorder and the most captures a loop takes (max_iterations); `black` a
    black level an earlier shot found (None: the loop finds it), `T_cell_cam` the camera pose a
    re-plan keeps (a planned shot's; None: the task's camera rule places it), `pose_error` the
    part's and the camera's pose error an earlier shot found (cell.run.localization; None: the
    loop localizes the part at its first capture)."""

    task: Task
    devices: Devices
    recorder: Recorder
    max_iterations: int
    black: BlackLevel | None = None
    T_cell_cam: np.ndarray | None = None
    pose_error: PoseError | None = None
