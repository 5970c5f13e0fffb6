"""The lamp's real pan-tilt: Dynamixel X-series servos, Protocol 2.0 through dynamixel_sdk, on the
control table and the tick mapping of cell.devices.servo.

A serial link that goes away (an unplugged USB adapter, a closed pty) fails inside the SDK with
pyserial's SerialException, an OSError, or termios.error (no OSError: tcdrain and tcflush on a
vanished tty, EIO), and leaves the SDK's port flagged in use, so that every later call would
report "Port is in use!". So each SDK call goes through `_sdk`: the first such failure is a
DeviceFault saying the link is lost, and so is every later call, unsent.

The SDK waits 2 latency timers + 2 ms for a status packet (36 ms), and its busy wait misses a
reply that came while the process was descheduled between reading nothing and checking the
clock (seen on a loaded 2-core machine), so the port (`_Port`) waits SLACK_MS longer. A ping,
read or write still without a status packet is sent again (ATTEMPTS in all): a ping or read
changes nothing and every write here sets an absolute value, and a bus loses a packet now and
then. Before it, a late reply is waited out and discarded (the line quiet for QUIET_S), so it
cannot be taken for the next question's answer.
"""

from __future__ import annotations

import termios
import time
from typing import TYPE_CHECKING, Any

import serial
from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, GroupSyncWrite, PacketHandler, PortHandler
from dynamixel_sdk.port_handler import LATENCY_TIMER

from cell.core.errors import DeviceFault
from cell.devices.servo import (ALERT, FIRMWARE_VERSION, GOAL_POSITION, HARDWARE_ERROR_STATUS, INPUT_VOLTAGE_UNIT_V,
                        MAX_POSITION_LIMIT, MIN_POSITION_LIMIT, MODELS, MOVING, OPERATING_MODE, POSITION_MODE,
                        PRESENT_INPUT_VOLTAGE, PRESENT_POSITION, PRESENT_TEMPERATURE, PROFILE_VELOCITY,
                        TEMPERATURE_LIMIT, TORQUE_ENABLE, ServoRig, describe_hardware_error, profile_velocity)

if TYPE_CHECKING:
    from cell.devices.operator import Operator
    from cell.task.device_config import PanTiltConfig
    from cell.task.types import LampRig as LampRigModel

ATTEMPTS = 3
SLACK_MS = 50.0
QUIET_S = (2 * LATENCY_TIMER + 2.0 + SLACK_MS) / 1e3


class _Port(PortHandler):
    """The SDK's port, waiting SLACK_MS longer for every status packet."""

    def setPacketTimeout(self, packet_length: int) -> None:
        super().setPacketTimeout(packet_length)
        self.packet_timeout += SLACK_MS


class DynamixelPanTilt(ServoRig):
    """The real pan-tilt: dynamixel_sdk PortHandler/PacketHandler(2.0) on a serial port.

    read_only (`cell hw-check`): the port opened and nothing written - no Profile Velocity, the
    torque left as it is - so only state() works; the servos are pinged and read there."""

    def __init__(self, rig: LampRigModel, config: PanTiltConfig, operator: Operator,
                 read_only: bool = False) -> None:
        super().__init__(rig, config, operator)
        self._port, self._packet = _Port(config.port), PacketHandler(2.0)
        self._lost = None                    # why the serial link is gone, once it is
        try:
            self._port.openPort()
            self._port.setBaudRate(config.baud)
        except (OSError, serial.SerialException) as err:
            raise DeviceFault(self.device, f"cannot open {config.port}: {err}") from None
        if read_only:
            return
        try:
            for dxl_id in self.ids:
                self._connect(dxl_id)
        except DeviceFault:
            self._port.closePort()
            raise

    def _sdk(self, call, *args):
        """call(*args), an SDK function; a lost serial link is a DeviceFault, now and from then on."""
        if self._lost:
            raise DeviceFault(self.device, f"{self._lost}: not sent")
        try:
            return call(*args)
        except (OSError, termios.error) as err:          # SerialException is an OSError
            if isinstance(err, termios.error):
                err = OSError(*err.args)                  # (errno, text) shown as an OSError's
            self._lost = f"serial link {self.config.port} lost ({err})"
            raise DeviceFault(self.device, self._lost) from None

    def _ask(self, call, dxl_id, *args):
        """A ping, read or write, call(port, dxl_id, *args) -> (..., comm, error), sent again while
        no status packet comes, the input drained of a late one first."""
        for attempt in range(ATTEMPTS):
            if attempt:
                self._sdk(self._drain)
            *value, comm, error = self._sdk(call, self._port, dxl_id, *args)
            if comm != COMM_RX_TIMEOUT:
                break
        return (*value, comm, error)

    def _drain(self):
        """Discard what arrives until the line is quiet for QUIET_S (at most 10 times)."""
        for _ in range(10):
            time.sleep(QUIET_S)
            if not self._port.ser.in_waiting:
                return
            self._port.ser.reset_input_buffer()

    def _connect(self, dxl_id):
        model, comm, error = self._ask(self._packet.ping, dxl_id)
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
            bits, comm, _ = self._ask(self._packet.read1ByteTxRx, dxl_id, HARDWARE_ERROR_STATUS.address)
            status = describe_hardware_error(bits) if comm == COMM_SUCCESS else "(status unreadable)"
            raise DeviceFault(self.device, f"servo {dxl_id}: Hardware Error Status {status}")
        if error & ~ALERT:
            raise DeviceFault(self.device, f"servo {dxl_id}: {what}: {self._packet.getRxPacketError(error)}")

    def _read(self, dxl_id, item, alert_ok=False):
        read = {1: self._packet.read1ByteTxRx, 2: self._packet.read2ByteTxRx,
                4: self._packet.read4ByteTxRx}[item.size]
        value, comm, error = self._ask(read, dxl_id, item.address)
        self._check(dxl_id, comm, error, f"read {item.address}", alert_ok)
        return value - (1 << 32) if item.size == 4 and value >= 1 << 31 else value   # int32

    def _write(self, dxl_id, item, value, alert_ok=False):
        write = {1: self._packet.write1ByteTxRx, 4: self._packet.write4ByteTxRx}[item.size]
        comm, error = self._ask(write, dxl_id, item.address, int(value) & 0xFFFFFFFF)
        self._check(dxl_id, comm, error, f"write {item.address}", alert_ok)

    def _drive(self, goals):
        # one Sync Write so pan and tilt start together; errors surface in the reads that follow
        sync = GroupSyncWrite(self._port, self._packet, GOAL_POSITION.address, GOAL_POSITION.size)
        for dxl_id, tick in goals.items():
            sync.addParam(dxl_id, list(int(tick).to_bytes(4, "little", signed=True)))
        comm = self._sdk(sync.txPacket)
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

    def state(self) -> dict[str, Any]:
        """Per servo (pan, tilt and the radius servo, by id): model, firmware, operating mode,
        torque, Present Position in ticks and as its joint [rad or m], Min/Max Position Limit,
        Hardware Error Status decoded, temperature and its limit [deg C], input voltage [V]; pings
        and reads only. A servo that does not answer is recorded and the others are still read.
        `problems`: what a run would stop on (an absent servo, another model or operating mode, a
        hardware error, a position outside the limits)."""
        roles = {self.config.pan_id: "pan", self.config.tilt_id: "tilt", self.config.radius_id: "radius"}
        servos, problems, ticks = {}, [], {}
        for dxl_id in self.ids:
            try:
                servos[dxl_id] = self._servo_state(dxl_id, roles[dxl_id])
            except DeviceFault as fault:
                servos[dxl_id] = {"role": roles[dxl_id], "error": fault.reason}
                problems.append(fault.reason)
                continue
            s = servos[dxl_id]
            ticks[dxl_id] = s["present_position_ticks"]
            problems += [f"servo {dxl_id}: {p}" for p in s.pop("problems")]
        if len(ticks) == len(self.ids):
            joints = self.joints_from_ticks(ticks)
            for dxl_id, joint in zip((self.config.pan_id, self.config.tilt_id, self.config.radius_id), joints):
                if dxl_id in servos and joint is not None:
                    servos[dxl_id]["joint_m" if dxl_id == self.config.radius_id else "joint_rad"] = float(joint)
        return {"port": self.config.port, "baud": self.config.baud,
                "servos": {str(i): s for i, s in servos.items()}, "problems": problems}

    def _servo_state(self, dxl_id, role):
        model, comm, error = self._ask(self._packet.ping, dxl_id)
        self._check(dxl_id, comm, error, "ping", alert_ok=True)
        read = {item: self._read(dxl_id, item, alert_ok=True) for item in (
            FIRMWARE_VERSION, OPERATING_MODE, TORQUE_ENABLE, PRESENT_POSITION, MIN_POSITION_LIMIT,
            MAX_POSITION_LIMIT, HARDWARE_ERROR_STATUS, PRESENT_TEMPERATURE, TEMPERATURE_LIMIT,
            PRESENT_INPUT_VOLTAGE)}
        position, lo, hi = read[PRESENT_POSITION], read[MIN_POSITION_LIMIT], read[MAX_POSITION_LIMIT]
        bits = read[HARDWARE_ERROR_STATUS]
        problems = []
        if model not in MODELS:
            problems.append(f"model {model}; a run needs one with the X-series table: {MODELS}")
        if read[OPERATING_MODE] != POSITION_MODE:
            problems.append(f"Operating Mode {read[OPERATING_MODE]}; a run needs position control "
                            f"({POSITION_MODE})")
        if bits:
            problems.append(f"Hardware Error Status {describe_hardware_error(bits)}")
        if not lo <= position <= hi:
            problems.append(f"Present Position {position} outside its position limits [{lo}, {hi}]")
        return {"role": role, "model_number": model, "model": MODELS.get(model, "unknown"),
                "firmware": read[FIRMWARE_VERSION], "operating_mode": read[OPERATING_MODE],
                "torque_enabled": bool(read[TORQUE_ENABLE]), "present_position_ticks": position,
                "min_position_limit_ticks": lo, "max_position_limit_ticks": hi,
                "hardware_error_status": bits,
                "hardware_error": describe_hardware_error(bits) if bits else "none",
                "temperature_c": read[PRESENT_TEMPERATURE], "temperature_limit_c": read[TEMPERATURE_LIMIT],
                "input_voltage_v": round(read[PRESENT_INPUT_VOLTAGE] * INPUT_VOLTAGE_UNIT_V, 3),
                "problems": problems}

    def stop(self, fault_is_own: bool = False) -> None:
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

    def close(self) -> None:
        try:
            self._port.closePort()
        except (OSError, termios.error):
            pass                              # a lost link: nothing left to release
