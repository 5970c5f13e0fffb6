"""Dynamixel X-series servos without the SDK: the control table (ROBOTIS e-Manual, XM430-W350) and
ServoRig, which maps the rig's joints to servo ticks (4096 a turn, 2048 the centre) so the
simulated and the real pan-tilt quantize alike. The real SDK calls live in cell/devices/hw/dynamixel.py;
the simulated pan-tilt and the servo emulator use this table too, without loading the SDK.
"""

from __future__ import annotations

from abc import abstractmethod
from collections import namedtuple
from typing import TYPE_CHECKING

import numpy as np

from cell.devices.interfaces import LampRig
from cell.core.errors import DeviceFault

if TYPE_CHECKING:
    from cell.devices.operator import Operator
    from cell.task.device_config import PanTiltConfig
    from cell.task.types import LampRig as LampRigModel

Item = namedtuple("Item", "address size")
MODEL_NUMBER = Item(0, 2)
FIRMWARE_VERSION = Item(6, 1)
ID = Item(7, 1)
OPERATING_MODE = Item(11, 1)
TEMPERATURE_LIMIT = Item(31, 1)          # [deg C]
MAX_POSITION_LIMIT = Item(48, 4)
MIN_POSITION_LIMIT = Item(52, 4)
SHUTDOWN = Item(63, 1)
TORQUE_ENABLE = Item(64, 1)
LED = Item(65, 1)
HARDWARE_ERROR_STATUS = Item(70, 1)
PROFILE_ACCELERATION = Item(108, 4)
PROFILE_VELOCITY = Item(112, 4)
GOAL_POSITION = Item(116, 4)
MOVING = Item(122, 1)
PRESENT_POSITION = Item(132, 4)
PRESENT_INPUT_VOLTAGE = Item(144, 2)     # [0.1 V]
PRESENT_TEMPERATURE = Item(146, 1)       # [deg C]
EEPROM_END = 64                         # addresses below are writable only with torque off

MODELS = {1020: "XM430-W350", 1030: "XM430-W210"}   # models with exactly this table
POSITION_MODE = 3
TICKS_PER_TURN = 4096
CENTRE_TICK = 2048
PROFILE_VELOCITY_RPM = 0.229            # Profile Velocity unit [rev/min]
INPUT_VOLTAGE_UNIT_V = 0.1              # Present Input Voltage unit
ALERT = 0x80                            # status packet error byte: see Hardware Error Status
HARDWARE_ERRORS = {0: "input voltage", 2: "overheating", 3: "motor encoder",
                   4: "electrical shock", 5: "overload"}


def describe_hardware_error(bits: int) -> str:
    """Hardware Error Status (70) as text, e.g. '0x24 (overheating, overload)'."""
    names = [name for bit, name in HARDWARE_ERRORS.items() if bits >> bit & 1] or ["unknown bit"]
    return f"0x{bits:02X} ({', '.join(names)})"


def pan_turns(pan_rad: float, pan_offset_rad: float) -> int:
    """The whole turns k the pan servo's goal drops (goal_ticks): position mode holds one turn,
    ticks 0..4095, so the pan relative to pan_offset is wrapped into [-180, 180) deg as its tick,
    k = floor((round((pan - offset) N / 2 pi) + 2048) / N), N = 4096; +180 deg is tick 0 = -180 deg."""
    k = round((pan_rad - pan_offset_rad) * TICKS_PER_TURN / (2 * np.pi))
    return (k + CENTRE_TICK) // TICKS_PER_TURN


def held_pan(pan_rad: float, pan_offset_rad: float) -> float:
    """The pan the servo drives to for a commanded pan, not quantized: pan - 2 pi k (pan_turns),
    so a path checked from one held pan to another is the one the servo's ticks take."""
    return float(pan_rad - 2 * np.pi * pan_turns(pan_rad, pan_offset_rad))


def profile_velocity(speed_rad_s: float) -> int:
    """Profile Velocity (112) value for a joint speed; at least 1, as 0 means unlimited."""
    return max(1, round(speed_rad_s * 60 / (2 * np.pi) / PROFILE_VELOCITY_RPM))


def ticks_per_s(speed_rad_s: float) -> float:
    """How fast a servo turns [ticks/s] at the Profile Velocity set for a joint speed
    (profile_velocity, in units of PROFILE_VELOCITY_RPM)."""
    return profile_velocity(speed_rad_s) * PROFILE_VELOCITY_RPM * TICKS_PER_TURN / 60


class ServoRig(LampRig):
    """A LampRig on position-controlled servos: pan and tilt (and the radius when
    radius_axis is servo) as ticks, checked against each servo's position limits."""

    def __init__(self, rig: LampRigModel, config: PanTiltConfig, operator: Operator) -> None:
        super().__init__(rig, operator)
        self.config = config
        self.ids = [config.pan_id, config.tilt_id] + ([] if self.manual_radius else [config.radius_id])
        self.limits: dict[int, tuple[int, int]] = {}      # id -> (min tick, max tick), read from the servo

    def goal_ticks(self, pan: float, tilt: float, radius: float | None) -> dict[int, int]:
        """{id: tick} for the joints; pan wraps into one turn (pan_turns: it turns about z), tilt
        and radius do not."""
        c = self.config
        pan_rel = pan - c.pan_offset_rad - 2 * np.pi * pan_turns(pan, c.pan_offset_rad)
        goals = {c.pan_id: CENTRE_TICK + round(pan_rel * TICKS_PER_TURN / (2 * np.pi)),
                 c.tilt_id: CENTRE_TICK + round((tilt - c.tilt_offset_rad) * TICKS_PER_TURN / (2 * np.pi))}
        if radius is not None:
            (r0, r1), (t0, t1) = self.rig.radius_range_m, c.radius_ticks
            goals[c.radius_id] = round(t0 + (radius - r0) / (r1 - r0) * (t1 - t0))
        return goals

    def joints_from_ticks(self, ticks: dict[int, int]) -> tuple[float, float, float | None]:
        """(pan, tilt, radius or None) from {id: tick}: the quantized joints the servos hold, the
        pan within [-180, 180) deg of pan_offset as its ticks turn (held_pan), linear in them."""
        c = self.config
        pan = (ticks[c.pan_id] - CENTRE_TICK) * 2 * np.pi / TICKS_PER_TURN + c.pan_offset_rad
        tilt = (ticks[c.tilt_id] - CENTRE_TICK) * 2 * np.pi / TICKS_PER_TURN + c.tilt_offset_rad
        radius = None
        if c.radius_id in ticks:
            (r0, r1), (t0, t1) = self.rig.radius_range_m, c.radius_ticks
            radius = r0 + (ticks[c.radius_id] - t0) / (t1 - t0) * (r1 - r0)
        return pan, tilt, radius

    def held(self, pan_rad: float) -> float:
        return held_pan(pan_rad, self.config.pan_offset_rad)

    @property
    def move_timeout_s(self) -> float | None:
        """cell.pan_tilt.move_timeout_s: servos not at their goals by then are a fault."""
        return self.config.move_timeout_s

    def move_s(self, start: tuple[float, float, float], end: tuple[float, float, float]) -> float:
        """The servos' time from joints `start` to `end`: ticks_s of their goal ticks (the
        radius's only where a servo sets it)."""
        radius = (None, None) if self.manual_radius else (start[2], end[2])
        return self.ticks_s(self.goal_ticks(start[0], start[1], radius[0]), self.goal_ticks(end[0], end[1], radius[1]))

    def ticks_s(self, start: dict[int, int], goals: dict[int, int]) -> float:
        """How long the servos take from ticks `start` to `goals` [s]: the farthest one's ticks at
        ticks_per_s (every servo at the Profile Velocity set; Profile Acceleration left at the
        X-series' 0, a step in velocity, so no ramps)."""
        return max(abs(goals[i] - start[i]) for i in goals) / ticks_per_s(self.config.speed_rad_s)

    def _move_axes(self, pan, tilt, radius):
        goals = self.goal_ticks(pan, tilt, radius)
        for dxl_id, tick in goals.items():
            lo, hi = self.limits[dxl_id]
            if not lo <= tick <= hi:
                raise DeviceFault(self.device, f"servo {dxl_id}: goal tick {tick} outside its position "
                                               f"limits [{lo}, {hi}]: refused before moving")
        limit = self.move_timeout_s
        if limit is not None and (takes_s := self.ticks_s(self._present_ticks(), goals)) > limit:
            raise DeviceFault(self.device, f"the servos' move to {goals} ticks takes {takes_s:.1f} s at "
                                           f"{np.degrees(self.config.speed_rad_s):.0f} deg/s, over move_timeout_s "
                                           f"{limit} s: refused before moving")
        self._drive(goals)

    def _read_axes(self):
        return self.joints_from_ticks(self._present_ticks())

    @abstractmethod
    def _drive(self, goals):
        """Send the goal ticks and return once every servo holds its goal."""

    @abstractmethod
    def _present_ticks(self):
        """{id: Present Position}."""
