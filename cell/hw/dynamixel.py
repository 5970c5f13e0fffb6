"""The lamp's pan-tilt on Dynamixel X-series servos, Protocol 2.0 through dynamixel_sdk.

The X-series control table lives here and nowhere else (ROBOTIS e-Manual, XM430-W350); the
simulated pan-tilt and the servo emulator use it too. ServoRig maps the rig's joints to servo
ticks (4096 a turn, 2048 the centre) so the simulated and the real pan-tilt quantize alike.
"""
import time
from abc import abstractmethod
from collections import namedtuple

import numpy as np
import serial
from dynamixel_sdk import COMM_SUCCESS, GroupSyncWrite, PacketHandler, PortHandler

from cell.devices import LampRig
from cell.errors import DeviceFault

Item = namedtuple("Item", "address size")
MODEL_NUMBER = Item(0, 2)
FIRMWARE_VERSION = Item(6, 1)
ID = Item(7, 1)
OPERATING_MODE = Item(11, 1)
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
EEPROM_END = 64                         # addresses below are writable only with torque off

MODELS = {1020: "XM430-W350", 1030: "XM430-W210"}   # models with exactly this table
POSITION_MODE = 3
TICKS_PER_TURN = 4096
CENTRE_TICK = 2048
PROFILE_VELOCITY_RPM = 0.229            # Profile Velocity unit [rev/min]
ALERT = 0x80                            # status packet error byte: see Hardware Error Status
HARDWARE_ERRORS = {0: "input voltage", 2: "overheating", 3: "motor encoder",
                   4: "electrical shock", 5: "overload"}


def describe_hardware_error(bits):
    """Hardware Error Status (70) as text, e.g. '0x24 (overheating, overload)'."""
    names = [name for bit, name in HARDWARE_ERRORS.items() if bits >> bit & 1] or ["unknown bit"]
    return f"0x{bits:02X} ({', '.join(names)})"


def profile_velocity(speed_rad_s):
    """Profile Velocity (112) value for a joint speed; at least 1, as 0 means unlimited."""
    return max(1, round(speed_rad_s * 60 / (2 * np.pi) / PROFILE_VELOCITY_RPM))


class ServoRig(LampRig):
    """A LampRig on position-controlled servos: pan and tilt (and the radius when
    radius_axis is servo) as ticks, checked against each servo's position limits."""

    def __init__(self, rig, config, operator):
        super().__init__(rig, operator)
        self.config = config
        self.ids = [config.pan_id, config.tilt_id] + ([] if self.manual_radius else [config.radius_id])
        self.limits = {}                          # id -> (min tick, max tick), read from the servo

    def goal_ticks(self, pan, tilt, radius):
        """{id: tick} for the joints; pan wraps (it turns about z), tilt and radius do not."""
        c = self.config
        pan_rel = (pan - c.pan_offset_rad + np.pi) % (2 * np.pi) - np.pi
        goals = {c.pan_id: CENTRE_TICK + round(pan_rel * TICKS_PER_TURN / (2 * np.pi)),
                 c.tilt_id: CENTRE_TICK + round((tilt - c.tilt_offset_rad) * TICKS_PER_TURN / (2 * np.pi))}
        if radius is not None:
            (r0, r1), (t0, t1) = self.rig.radius_range_m, c.radius_ticks
            goals[c.radius_id] = round(t0 + (radius - r0) / (r1 - r0) * (t1 - t0))
        return goals

    def joints_from_ticks(self, ticks):
        """(pan, tilt, radius or None) from {id: tick}: the quantized joints the servos hold."""
        c = self.config
        pan = (ticks[c.pan_id] - CENTRE_TICK) * 2 * np.pi / TICKS_PER_TURN + c.pan_offset_rad
        tilt = (ticks[c.tilt_id] - CENTRE_TICK) * 2 * np.pi / TICKS_PER_TURN + c.tilt_offset_rad
        radius = None
        if c.radius_id in ticks:
            (r0, r1), (t0, t1) = self.rig.radius_range_m, c.radius_ticks
            radius = r0 + (ticks[c.radius_id] - t0) / (t1 - t0) * (r1 - r0)
        return (pan + np.pi) % (2 * np.pi) - np.pi, tilt, radius

    def _move_axes(self, pan, tilt, radius):
        goals = self.goal_ticks(pan, tilt, radius)
        for dxl_id, tick in goals.items():
            lo, hi = self.limits[dxl_id]
            if not lo <= tick <= hi:
                raise DeviceFault(self.device, f"servo {dxl_id}: goal tick {tick} outside its position "
                                               f"limits [{lo}, {hi}]: refused before moving")
        self._drive(goals)

    def _read_axes(self):
        return self.joints_from_ticks(self._present_ticks())

    @abstractmethod
    def _drive(self, goals):
        """Send the goal ticks and return once every servo holds its goal."""

    @abstractmethod
    def _present_ticks(self):
        """{id: Present Position}."""


class DynamixelPanTilt(ServoRig):
    """The real pan-tilt: dynamixel_sdk PortHandler/PacketHandler(2.0) on a serial port."""

    def __init__(self, rig, config, operator):
        super().__init__(rig, config, operator)
        self._port, self._packet = PortHandler(config.port), PacketHandler(2.0)
        try:
            self._port.openPort()
            self._port.setBaudRate(config.baud)
        except (OSError, serial.SerialException) as err:
            raise DeviceFault(self.device, f"cannot open {config.port}: {err}") from None
        try:
            for dxl_id in self.ids:
                self._connect(dxl_id)
        except DeviceFault:
            self._port.closePort()
            raise

    def _connect(self, dxl_id):
        model, comm, error = self._packet.ping(self._port, dxl_id)
        self._check(dxl_id, comm, error, "ping")
        if model not in MODELS:
            raise DeviceFault(self.device, f"servo {dxl_id} is model {model}; expected one with the "
                                           f"X-series table: {MODELS}")
        if self._read(dxl_id, OPERATING_MODE) != POSITION_MODE:
            raise DeviceFault(self.device, f"servo {dxl_id} is not in position control mode "
                                           f"(Operating Mode 11 = {POSITION_MODE})")
        self.limits[dxl_id] = (self._read(dxl_id, MIN_POSITION_LIMIT), self._read(dxl_id, MAX_POSITION_LIMIT))
        self._write(dxl_id, PROFILE_VELOCITY, profile_velocity(self.config.speed_rad_s))
        self._write(dxl_id, TORQUE_ENABLE, 1)

    def _check(self, dxl_id, comm, error, what, alert_ok=False):
        """Turn the SDK's (comm_result, error) into a DeviceFault naming the servo."""
        if comm != COMM_SUCCESS:
            raise DeviceFault(self.device, f"servo {dxl_id}: {what}: {self._packet.getTxRxResult(comm)}")
        if error & ALERT and not alert_ok:
            bits, comm, _ = self._packet.read1ByteTxRx(self._port, dxl_id, HARDWARE_ERROR_STATUS.address)
            status = describe_hardware_error(bits) if comm == COMM_SUCCESS else "(status unreadable)"
            raise DeviceFault(self.device, f"servo {dxl_id}: Hardware Error Status {status}")
        if error & ~ALERT:
            raise DeviceFault(self.device, f"servo {dxl_id}: {what}: {self._packet.getRxPacketError(error)}")

    def _read(self, dxl_id, item):
        read = {1: self._packet.read1ByteTxRx, 2: self._packet.read2ByteTxRx,
                4: self._packet.read4ByteTxRx}[item.size]
        value, comm, error = read(self._port, dxl_id, item.address)
        self._check(dxl_id, comm, error, f"read {item.address}")
        return value - (1 << 32) if item.size == 4 and value >= 1 << 31 else value   # int32

    def _write(self, dxl_id, item, value, alert_ok=False):
        write = {1: self._packet.write1ByteTxRx, 4: self._packet.write4ByteTxRx}[item.size]
        comm, error = write(self._port, dxl_id, item.address, int(value) & 0xFFFFFFFF)
        self._check(dxl_id, comm, error, f"write {item.address}", alert_ok)

    def _drive(self, goals):
        # one Sync Write so pan and tilt start together; errors surface in the reads that follow
        sync = GroupSyncWrite(self._port, self._packet, GOAL_POSITION.address, GOAL_POSITION.size)
        for dxl_id, tick in goals.items():
            sync.addParam(dxl_id, list(int(tick).to_bytes(4, "little", signed=True)))
        comm = sync.txPacket()
        if comm != COMM_SUCCESS:
            raise DeviceFault(self.device, f"goal positions not sent: {self._packet.getTxRxResult(comm)}")
        deadline = time.monotonic() + self.config.move_timeout_s
        while True:
            present = self._present_ticks()
            moving = [self._read(dxl_id, MOVING) for dxl_id in goals]
            if not any(moving) and all(abs(present[i] - t) <= self.config.tolerance_ticks
                                       for i, t in goals.items()):
                return
            if time.monotonic() > deadline:
                late = {i: (present[i], t) for i, t in goals.items()}
                raise DeviceFault(self.device, f"servos (id: (present, goal) ticks) {late} not at their "
                                               f"goals after {self.config.move_timeout_s} s")
            time.sleep(0.005)

    def _present_ticks(self):
        return {dxl_id: self._read(dxl_id, PRESENT_POSITION) for dxl_id in self.ids}

    def stop(self, fault_is_own=False):
        """Hold where each servo is (goal = present, torque on), or torque off for the servos'
        own fault. Every servo is tried; the first failure is raised afterwards."""
        failures = []
        for dxl_id in self.ids:
            try:
                if fault_is_own:       # a servo in alert still takes the write; its reply says alert
                    self._write(dxl_id, TORQUE_ENABLE, 0, alert_ok=True)
                else:
                    self._write(dxl_id, GOAL_POSITION, self._read(dxl_id, PRESENT_POSITION))
            except DeviceFault as fault:
                failures.append(fault)
        if failures:
            raise failures[0]

    def close(self):
        self._port.closePort()
