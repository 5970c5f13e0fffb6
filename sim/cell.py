"""The simulated cell: SimArm, SimPanTilt, a SimLightController when the task has lights on
channels, and a SimCamera rendering the task's scene (sim.world.Renderer) at the controller's
levels, with the task's `cell.arm` / `cell.pan_tilt` / `cell.lighting` settings
(docs/devices.md) and optional injected faults. The arm and the lamp check each move against
the cell's bodies themselves (sim.obstacles) and stop before a collision."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.devices.interfaces import Devices
from sim.arm import SimArm
from sim.board import BoardView
from sim.camera import SimCamera
from sim.laser import LaserSpot
from sim.lighting import SimLightController
from sim.obstacles import Obstacles
from sim.pantilt import SimPanTilt
from sim.world import Renderer
from cell.devices.operator import Operator
from sim.laser import Beam

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.types import Task


@dataclass(frozen=True)
class SimFaults:
    """Faults to inject (None: none). The arm's move number `arm_fail_on_move` ends in a
    protective stop; on the lamp's move number `lamp_fail_on_move` servo `servo_id` (None: the
    tilt) reports Hardware Error Status `servo_bits` (0x04 overheating) and its torque goes off;
    capture number `camera_fail_on_capture` times out; the lighting controller's set number
    `lights_fail_on_set` reports over-current. All raise DeviceFault."""

    arm_fail_on_move: int | None = None
    lamp_fail_on_move: int | None = None
    servo_id: int | None = None
    servo_bits: int = 0x04
    camera_fail_on_capture: int | None = None
    lights_fail_on_set: int | None = None


def make_sim_devices(task: Task, scene: Scene | None, operator: Operator | None = None, yes: bool = True,
                     faults: SimFaults | dict[str, Any] | None = None, laser: Beam | None = None,
                     board: bool = False) -> Devices:
    """Devices of the simulated cell for a task and its scene (cell.planning.scene.build_scene); the
    operator (default Operator(yes=yes)) sets a manual lamp radius. faults: SimFaults, a dict of
    its fields, or None. The settings are the task's, checked when it was loaded. Given a laser
    aimed at the sensor (cell.calibration.camera_constant.Laser), the camera sees its spot (sim.laser), not
    the scene (which may then be None); given board, the ChArUco board of calibration.board
    (sim.board)."""
    faults = SimFaults(**faults) if isinstance(faults, dict) else faults or SimFaults()
    config = task.cell.devices
    obstacles = Obstacles(task) if "collisions" in task.sim.effects else None
    arm = SimArm(config.arm, task.frames, fail_on_move=faults.arm_fail_on_move, obstacles=obstacles)
    lamp = SimPanTilt(task.lamp.rig, config.pan_tilt, yes=yes, operator=operator,
                      fail_on_move=faults.lamp_fail_on_move, fail_servo=faults.servo_id,
                      fail_bits=faults.servo_bits, obstacles=obstacles)
    render: Callable[..., np.ndarray]
    if board:
        render = BoardView(task)
    elif laser:
        render = LaserSpot(task, laser)
    elif scene is not None:
        render = Renderer(task, scene)
    else:
        raise ValueError("the simulated camera needs a scene to render (or a laser, or the board)")
    lights = None
    if task.channels:             # cell.lighting's channel count, else as many as the lights need
        count = config.lighting.channels if config.lighting else max(task.channels)
        lights = SimLightController(count, fail_on_set=faults.lights_fail_on_set)
    camera = SimCamera(render, arm, lamp, task.camera.sensor.bit_depth,
                       fail_on_capture=faults.camera_fail_on_capture,
                       lights=lights if isinstance(render, Renderer) else None)
    return Devices(arm, lamp, camera, lights)
