"""A lens without motor control (OpenCV and most GenICam cameras): the operator sets the f-number
and the focus distance when told, and is asked again only when they change."""

from __future__ import annotations

from typing import TYPE_CHECKING

from cell.devices.interfaces import Camera

if TYPE_CHECKING:
    from cell.devices.operator import Operator


class ManualLensCamera(Camera):
    def __init__(self, bit_depth: int, operator: Operator, why: str) -> None:
        super().__init__(bit_depth)
        self.operator = operator
        operator.require(self.device, f"the aperture and focus ({why})")

    def set_aperture(self, f_number: float) -> None:
        if self.f_number is None or abs(f_number / self.f_number - 1) > 0.01:
            self.operator.confirm(self.device, f"set the lens to f/{f_number:.1f}")
        self.f_number = float(f_number)

    def set_focus(self, focus_m: float) -> None:
        if self.focus_m is None or abs(focus_m - self.focus_m) > 1e-3:
            self.operator.confirm(self.device, f"focus the lens at {1e3 * focus_m:.0f} mm")
        self.focus_m = float(focus_m)
