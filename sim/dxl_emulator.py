"""Dynamixel X-series servos speaking Protocol 2.0 on a pseudo-terminal, so tests can run the
real dynamixel_sdk code path (and DynamixelPanTilt) without hardware, pymeasure-style.

The SDK opens `emulator.port` (the pty's slave, put in raw mode); a thread answers on the
master side: PING, READ, WRITE, SYNC_READ, SYNC_WRITE, with CRC-16 and byte stuffing checked and
produced, Present Position moving toward Goal Position at the profile velocity while the torque
is on, and ids not on the bus silent. Every packet in and out is kept for byte-exact asserts.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time
import tty
from collections.abc import Iterable
from types import TracebackType

from cell.devices.servo import (ALERT, CENTRE_TICK, EEPROM_END, FIRMWARE_VERSION, GOAL_POSITION,
                        HARDWARE_ERROR_STATUS, ID, MAX_POSITION_LIMIT, MIN_POSITION_LIMIT, MODEL_NUMBER,
                        MOVING, OPERATING_MODE, POSITION_MODE, PRESENT_INPUT_VOLTAGE, PRESENT_POSITION,
                        PRESENT_TEMPERATURE, PROFILE_VELOCITY, PROFILE_VELOCITY_RPM, SHUTDOWN,
                        TEMPERATURE_LIMIT, TICKS_PER_TURN, TORQUE_ENABLE)
from cell.devices.servo import Item

HEADER = b"\xff\xff\xfd\x00"
PING, READ, WRITE, SYNC_READ, SYNC_WRITE, STATUS = 0x01, 0x02, 0x03, 0x82, 0x83, 0x55
BROADCAST = 0xFE
ERROR_INSTRUCTION, ERROR_CRC, ERROR_DATA_LIMIT, ERROR_ACCESS = 0x02, 0x03, 0x06, 0x07
TABLE_SIZE = 147                                   # through Present Temperature (146)
WRITABLE = set(range(ID.address, EEPROM_END)) | {64, 65, 68} | set(range(108, 120))
MAX_VELOCITY = 265                                 # Profile Velocity 0 (no limit) moves at this


def crc16(data: bytes) -> int:
    """Protocol 2.0 CRC-16: polynomial 0x8005, initial value 0, no reflection."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = (crc << 1 ^ 0x8005 if crc & 0x8000 else crc << 1) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """FF FF FD inside a packet goes out as FF FF FD FD, so it cannot look like a header."""
    out = bytearray()
    for byte in body:
        out.append(byte)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    out, i = bytearray(), 0
    while i < len(body):
        out.append(body[i])
        if out[-3:] == b"\xff\xff\xfd" and body[i + 1:i + 2] == b"\xfd":
            i += 1
        i += 1
    return bytes(out)


def packet(dxl_id: int, instruction: int, params: bytes | Iterable[int] = b"", error: int | None = None) -> bytes:
    """A complete packet: header, id, length, instruction (and a status packet's error byte),
    stuffed parameters, CRC over everything before it."""
    body = stuff(bytes([instruction]) + (b"" if error is None else bytes([error])) + bytes(params))
    head = HEADER + bytes([dxl_id]) + (len(body) + 2).to_bytes(2, "little")
    return head + body + crc16(head + body).to_bytes(2, "little")


def _word(params, i):
    return int.from_bytes(params[i:i + 2], "little")


class Servo:
    """One servo's control table (X-series addresses from cell.devices.servo), at the e-Manual's initial
    values; powered at 12.0 V and at 30 deg C unless a test sets Present Input Voltage (144) or
    Present Temperature (146)."""

    def __init__(self, dxl_id: int, model_number: int, firmware: int) -> None:
        self.table = bytearray(TABLE_SIZE)
        for item, value in ((MODEL_NUMBER, model_number), (FIRMWARE_VERSION, firmware), (ID, dxl_id),
                            (OPERATING_MODE, POSITION_MODE), (MAX_POSITION_LIMIT, TICKS_PER_TURN - 1),
                            (MIN_POSITION_LIMIT, 0), (TEMPERATURE_LIMIT, 80), (SHUTDOWN, 0x34),
                            (GOAL_POSITION, CENTRE_TICK), (PRESENT_POSITION, CENTRE_TICK),
                            (PRESENT_INPUT_VOLTAGE, 120), (PRESENT_TEMPERATURE, 30)):
            self.set(item, value)
        self.position = float(CENTRE_TICK)

    def get(self, item: Item) -> int:
        raw = self.table[item.address:item.address + item.size]
        return int.from_bytes(raw, "little", signed=item.size == 4)

    def set(self, item: Item, value: int) -> None:
        self.table[item.address:item.address + item.size] = int(value).to_bytes(
            item.size, "little", signed=item.size == 4)

    def write(self, address: int, data: bytes) -> int:
        """Apply a WRITE; returns the status error number (0 = done)."""
        span = range(address, address + len(data))
        if not set(span) <= WRITABLE or (address < EEPROM_END and self.get(TORQUE_ENABLE)):
            return ERROR_ACCESS
        new = bytearray(self.table)
        new[address:address + len(data)] = data
        goal = int.from_bytes(new[GOAL_POSITION.address:GOAL_POSITION.address + 4], "little", signed=True)
        if not self.get(MIN_POSITION_LIMIT) <= goal <= self.get(MAX_POSITION_LIMIT):
            return ERROR_DATA_LIMIT
        self.table = new
        return 0

    def step(self, dt: float, speedup: float) -> None:
        """Move Present Position toward Goal Position at the profile velocity (torque on, no
        hardware error)."""
        goal = self.get(GOAL_POSITION)
        if self.get(TORQUE_ENABLE) and not self.get(HARDWARE_ERROR_STATUS):
            rpm = (self.get(PROFILE_VELOCITY) or MAX_VELOCITY) * PROFILE_VELOCITY_RPM
            reach = rpm / 60 * TICKS_PER_TURN * dt * speedup
            self.position += max(-reach, min(reach, goal - self.position))
        self.set(PRESENT_POSITION, round(self.position))
        self.set(MOVING, int(self.get(TORQUE_ENABLE) and round(self.position) != goal))


class DxlEmulator:
    """A bus of servos at `ids` on a pseudo-terminal; use as a context manager. `speedup`
    scales the motion so tests need not wait for real servo speeds."""

    def __init__(self, ids: Iterable[int] = (1, 2), model_number: int = 1020, firmware: int = 45,
                 speedup: float = 1.0) -> None:
        self.servos = {i: Servo(i, model_number, firmware) for i in ids}
        self.speedup = speedup
        self.received: list[bytes] = []             # raw packets, as on the wire
        self.sent: list[bytes] = []
        self.lose_replies = 0                        # status packets still to lose (lose())
        self.late_replies = (0, 0.0)                 # (how many, by how long): late()
        self.synced = threading.Event()              # set when a Sync Write (goal positions) came
        self.lock = threading.Lock()
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._buffer = bytearray()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dxl-emulator", daemon=True)

    def __enter__(self) -> DxlEmulator:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """The bus goes away, as an unplugged adapter: the pty closes, and the SDK's next read or
        write on it fails (EIO). Idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        os.close(self._master)
        os.close(self._slave)

    def lose(self, replies: int) -> None:
        """The next `replies` status packets are lost on the bus (noise): never sent."""
        with self.lock:
            self.lose_replies = replies

    def late(self, replies: int, delay_s: float) -> None:
        """The next `replies` status packets are sent `delay_s` late (a reply the SDK gave up on)."""
        with self.lock:
            self.late_replies = (replies, delay_s)

    def inject_hardware_error(self, dxl_id: int, bits: int) -> None:
        """Set Hardware Error Status; like the real servo's shutdown, the torque goes off."""
        with self.lock:
            servo = self.servos[dxl_id]
            servo.set(HARDWARE_ERROR_STATUS, bits)
            servo.set(TORQUE_ENABLE, 0)

    def _run(self):
        last = time.monotonic()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.001)
            with self.lock:
                now = time.monotonic()
                for servo in self.servos.values():
                    servo.step(now - last, self.speedup)
                last = now
                if ready:
                    self._buffer += os.read(self._master, 4096)
                    self._parse()

    def _parse(self):
        while True:
            start = self._buffer.find(HEADER)
            if start < 0:
                del self._buffer[:-3]                   # keep what may begin a header
                return
            del self._buffer[:start]
            if len(self._buffer) < 7:
                return
            total = 7 + int.from_bytes(self._buffer[5:7], "little")
            if len(self._buffer) < total:
                return
            raw = bytes(self._buffer[:total])
            del self._buffer[:total]
            self.received.append(raw)
            self._handle(raw)

    def _reply(self, dxl_id, error=0, params=b""):
        servo = self.servos[dxl_id]
        alert = ALERT if servo.get(HARDWARE_ERROR_STATUS) else 0
        raw = packet(dxl_id, STATUS, params, error | alert)
        if self.lose_replies:
            self.lose_replies -= 1
            return
        self.sent.append(raw)
        late, delay_s = self.late_replies
        if late:
            self.late_replies = (late - 1, delay_s)
            threading.Timer(delay_s, os.write, (self._master, raw)).start()
            return
        os.write(self._master, raw)

    def _handle(self, raw):
        dxl_id, instruction = raw[4], raw[7]
        unicast = dxl_id in self.servos
        if crc16(raw[:-2]) != int.from_bytes(raw[-2:], "little"):
            if unicast:
                self._reply(dxl_id, ERROR_CRC)
            return
        params = unstuff(raw[8:-2])
        address, length = _word(params, 0), _word(params, 2)      # READ, SYNC_READ, SYNC_WRITE
        if instruction == PING:
            for i in (self.servos if dxl_id == BROADCAST else [dxl_id] if unicast else []):
                model, firmware = self.servos[i].get(MODEL_NUMBER), self.servos[i].get(FIRMWARE_VERSION)
                self._reply(i, params=model.to_bytes(2, "little") + bytes([firmware]))
        elif instruction in (READ, SYNC_READ):
            ids = params[4:] if instruction == SYNC_READ else [dxl_id] if unicast else []
            for i in (i for i in ids if i in self.servos):
                if address + length > TABLE_SIZE:
                    self._reply(i, ERROR_ACCESS)
                else:
                    self._reply(i, params=self.servos[i].table[address:address + length])
        elif instruction == WRITE:
            for i in (self.servos if dxl_id == BROADCAST else [dxl_id] if unicast else []):
                error = self.servos[i].write(address, params[2:])
                if unicast:
                    self._reply(i, error)
        elif instruction == SYNC_WRITE:
            self.synced.set()
            for k in range(4, len(params), length + 1):
                if params[k] in self.servos:
                    self.servos[params[k]].write(address, params[k + 1:k + 1 + length])
        elif unicast:
            self._reply(dxl_id, ERROR_INSTRUCTION)
