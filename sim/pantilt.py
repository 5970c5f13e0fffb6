"""Simulated pan-tilt: Dynamixel-like servos in integer ticks (4096 a turn, 2048 the centre)
with position limits, so the read-back joints carry the real rig's quantization."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from cell.core.errors import DeviceFault
from cell.devices.rig import lamp_position
from cell.devices.operator import Operator
from cell.devices.servo import CENTRE_TICK, ServoRig, describe_hardware_error

if TYPE_CHECKING:
    from sim.obstacles import Obstacles
    from cell.task.device_config import PanTiltConfig
    from cell.task.types import LampRig as LampRigModel

FULL_RANGE = (0, 4095)


class SimPanTilt(ServoRig):
    """`limits` {id: (min, max) ticks} as the servos' Min/Max Position Limit (default the full
    turn). Fault injection: on move number `fail_on_move` servo `fail_servo` (default the tilt)
    reports Hardware Error Status `fail_bits` (default 0x04, overheating) and stops. In the sim
    the operator's manual radius is confirmed ("simulated: nothing to confirm") unless `yes` is False.
    A move longer than cell.pan_tilt.move_timeout_s is refused before moving, as the real
    servos', where the cell file states one (move_timeout_s)."""

    def __init__(self, rig: LampRigModel, config: PanTiltConfig, yes: bool = True,
                 operator: Operator | None = None, limits: Mapping[int, tuple[int, int]] | None = None,
                 fail_on_move: int | None = None, fail_servo: int | None = None, fail_bits: int = 0x04,
                 obstacles: Obstacles | None = None) -> None:
        super().__init__(rig, config, operator or Operator(simulated=yes))
        self.obstacles = obstacles
        self.limits = {i: (limits or {}).get(i, FULL_RANGE) for i in self.ids}
        self.present = {i: CENTRE_TICK for i in self.ids}
        self.torque = {i: True for i in self.ids}
        self.hardware_error = {i: 0 for i in self.ids}
        self.moves = 0
        self._fail = (fail_on_move, config.tilt_id if fail_servo is None else fail_servo, fail_bits)

    def move(self, pan_rad: float, tilt_rad: float, radius_m: float) -> None:
        """As the rig moves (ServoRig.move); given the cell's `obstacles` (sim.obstacles), the
        joints' path as the servos' ticks go straight from the present ticks to the goal ticks
        (the radius from the commanded one while none is known) is checked first: a move that
        would touch another body is a protective stop (DeviceFault), the lamp where it was."""
        if self.obstacles is not None and all(self.torque.values()):
            goals = self.goal_ticks(self._in_range(pan_rad, tilt_rad, radius_m), tilt_rad,
                                    None if self.manual_radius else radius_m)
            (pan0, tilt0, r0), (pan1, tilt1, r1) = self.joints_from_ticks(self.present), self.joints_from_ticks(goals)
            r0 = self._confirmed_radius if r0 is None else r0
            start = np.array([pan0, tilt0, r0 if np.isfinite(r0) else radius_m])
            end = np.array([pan1, tilt1, radius_m if r1 is None else r1])
            contact = self.obstacles.lamp_move(start, end, lambda j: lamp_position(self.rig.pivot_m, *j))
            if contact is not None:
                raise DeviceFault(self.device, f"protective stop: {contact} (the simulated cell's own "
                                               "collision check)")
            self.obstacles.lamp_position = lamp_position(self.rig.pivot_m, *end)
        super().move(pan_rad, tilt_rad, radius_m)

    @property
    def move_timeout_s(self) -> float | None:
        """The cell file's cell.pan_tilt.move_timeout_s where it states one, else None: no limit."""
        return self.config.move_timeout_s if self.config.move_timeout_given else None

    def _check_errors(self):
        for dxl_id, bits in self.hardware_error.items():
            if bits:
                raise DeviceFault(self.device, f"servo {dxl_id}: Hardware Error Status "
                                               f"{describe_hardware_error(bits)}")

    def _drive(self, goals):
        self.moves += 1
        on_move, dxl_id, bits = self._fail
        if self.moves == on_move:
            self.hardware_error[dxl_id], self.torque[dxl_id] = bits, False   # the servo's shutdown
        self._check_errors()
        for dxl_id, tick in goals.items():
            if self.torque[dxl_id]:
                self.present[dxl_id] = tick

    def _present_ticks(self):
        self._check_errors()
        return dict(self.present)

    def stop(self, fault_is_own: bool = False) -> None:
        if fault_is_own:
            self.torque = {i: False for i in self.ids}
