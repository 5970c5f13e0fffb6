"""Simulated camera: the renderer draws what the camera sees from the arm's and the lamp's
read-back poses with the set shutter time, f-number and focus (motorized lens in the sim)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cell.devices.interfaces import Camera
from cell.core.errors import DeviceFault
from cell.devices.interfaces import Arm, LampRig, LightController


class SimCamera(Camera):
    """`render(T_cell_cam, lamp_pos, lamp_aim, shutter_s, f_number, focus_m) -> image` is the
    renderer (sim.world.Renderer); focus_m is None until set_focus (the renderer's default).
    With a lighting controller (`lights`), the renderer is also given `drives`, every channel's
    level as the controller reads it back at the capture. Fault injection: capture number
    `fail_on_capture` times out (DeviceFault)."""

    def __init__(self, render: Callable[..., np.ndarray], arm: Arm, lamp: LampRig, bit_depth: int = 8,
                 fail_on_capture: int | None = None, timeout_s: float = 1.0,
                 lights: LightController | None = None) -> None:
        super().__init__(bit_depth)
        self.render, self.arm, self.lamp, self.lights = render, arm, lamp, lights
        self.fail_on_capture, self.timeout_s = fail_on_capture, timeout_s
        self.captures = 0

    def set_exposure(self, shutter_s: float) -> float:
        if not shutter_s > 0:
            raise DeviceFault(self.device, f"shutter time {shutter_s} s is not positive")
        self.shutter_s = float(shutter_s)
        return self.shutter_s

    def set_aperture(self, f_number: float) -> None:
        if not f_number > 0:
            raise DeviceFault(self.device, f"f-number {f_number} is not positive")
        self.f_number = float(f_number)

    def set_focus(self, focus_m: float) -> None:
        """Focus distance along the optical axis [m] (motorized focus in the sim)."""
        if not focus_m > 0:
            raise DeviceFault(self.device, f"focus distance {focus_m} m is not positive")
        self.focus_m = float(focus_m)

    def state(self) -> dict[str, Any]:
        """The interface's state, and with a renderer of a frame size (sim.world.Renderer) what a
        real camera reports besides (`cell hw-check` of cell.camera.driver: simulated)."""
        state = super().state()
        shape = getattr(self.render, "shape", None)
        if shape is not None:
            state.update(model="simulated", backend="sim.world.Renderer (the task's scene)",
                         width_px=shape[1], height_px=shape[0], channels=1, pixel_format=None,
                         exposure_s=self.shutter_s, exposure_range_s=None)
        return state

    def capture(self) -> np.ndarray:
        self.captures += 1
        if self.captures == self.fail_on_capture:
            raise DeviceFault(self.device, f"capture timed out after {self.timeout_s} s "
                                           f"(capture {self.captures}, injected)")
        if self.shutter_s is None or self.f_number is None:
            raise DeviceFault(self.device, "capture before the shutter time and f-number were set")
        lamp_pos, lamp_aim = self.lamp.lamp_pose()
        drives = {} if self.lights is None else {"drives": self.lights.levels()}
        image = self.render(self.arm.camera_pose(), lamp_pos, lamp_aim, self.shutter_s, self.f_number,
                            self.focus_m, **drives)
        return np.asarray(image)
