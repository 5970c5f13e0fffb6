"""Protocol 2.0 on the wire, pymeasure-style: the e-Manual's example packets byte for byte
through the real dynamixel_sdk and the pty servo emulator, then the real DynamixelPanTilt on
that emulator (moves, read-back, hardware errors, absent servos, limits); the simulated cell
loads no SDK."""
import io
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest
import serial
from dynamixel_sdk import (COMM_RX_TIMEOUT, COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler,
                           PortHandler)

from cell.devices import servo
from cell.core.errors import DeviceFault
from cell.devices.hw import dynamixel
from cell.devices.hw.dynamixel import DynamixelPanTilt
from cell.devices.operator import Operator
from cell.task.types import LampRig
from sim.dxl_emulator import DxlEmulator, crc16, packet, stuff, unstuff
from loopback import BUSY_S
from simcell import device_settings

# e-Manual, Protocol 2.0, Ping example 1: ID 1 is an XM430-W210 (1030), firmware 38
PING_1 = bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")
PING_1_STATUS = bytes.fromhex("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")


def bus(**kwargs):
    return DxlEmulator(**{"model_number": 1030, "firmware": 0x26, **kwargs})


class PatientPort(PortHandler):
    """The SDK's port, waiting PATIENCE_S longer for each status packet than the SDK's own (2 x 16
    + 2 ms at 57600 baud): the emulator answers from a thread of this process, which a machine
    starved of cores may not run in time; these tests are of the bytes, not of the timing."""

    def setPacketTimeout(self, packet_length):
        super().setPacketTimeout(packet_length)
        self.packet_timeout += 1e3 * PATIENCE_S


PATIENCE_S = 1.0


def sdk(emulator, patient=True):
    """The SDK's port (patient: PatientPort, else the SDK's own timing) and packet handler."""
    port = (PatientPort if patient else PortHandler)(emulator.port)
    assert port.openPort() and port.setBaudRate(57600)
    return port, PacketHandler(2.0)


def test_the_simulated_cell_loads_no_servo_sdk():
    code = "import sys, sim.cell; assert 'dynamixel_sdk' not in sys.modules and 'serial' not in sys.modules"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_crc_and_packet_of_the_emanual_ping():
    assert crc16(PING_1[:-2]) == 0x4E19
    assert packet(1, 0x01) == PING_1
    assert packet(1, 0x55, bytes.fromhex("06 04 26"), error=0) == PING_1_STATUS


def test_byte_stuffing_inserts_fd_after_a_header_pattern_and_round_trips():
    body = bytes.fromhex("03 6C 00 FF FF FD 00")
    assert stuff(body) == bytes.fromhex("03 6C 00 FF FF FD FD 00")
    assert unstuff(stuff(body)) == body


def test_ping_read_write_bytes_match_the_emanual():
    with bus(ids=(1,)) as emulator:
        port, handler = sdk(emulator)
        assert handler.ping(port, 1) == (1030, COMM_SUCCESS, 0)
        assert emulator.received[-1] == PING_1 and emulator.sent[-1] == PING_1_STATUS

        emulator.servos[1].position = 166                # torque off: it stays there
        assert handler.read4ByteTxRx(port, 1, servo.PRESENT_POSITION.address) == (166, COMM_SUCCESS, 0)
        assert emulator.received[-1] == bytes.fromhex("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")
        assert emulator.sent[-1] == bytes.fromhex("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0")

        assert handler.write4ByteTxRx(port, 1, servo.GOAL_POSITION.address, 512) == (COMM_SUCCESS, 0)
        assert emulator.received[-1] == bytes.fromhex("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89")
        assert emulator.sent[-1] == bytes.fromhex("FF FF FD 00 01 04 00 55 00 A1 0C")
        port.closePort()


def test_sync_read_and_sync_write_bytes_match_the_emanual():
    with bus(ids=(1, 2)) as emulator:
        port, handler = sdk(emulator)
        emulator.servos[1].position, emulator.servos[2].position = 166, 2079
        time.sleep(0.01)                                   # the emulator publishes the positions
        group = GroupSyncRead(port, handler, servo.PRESENT_POSITION.address, 4)
        group.addParam(1), group.addParam(2)
        assert group.txRxPacket() == COMM_SUCCESS
        assert [group.getData(i, 132, 4) for i in (1, 2)] == [166, 2079]
        assert emulator.received[-1] == bytes.fromhex("FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA")
        assert emulator.sent[-2:] == [bytes.fromhex("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0"),
                                      bytes.fromhex("FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE")]

        write = GroupSyncWrite(port, handler, servo.GOAL_POSITION.address, 4)
        write.addParam(1, [0x96, 0, 0, 0]), write.addParam(2, [0xAA, 0, 0, 0])
        assert write.txPacket() == COMM_SUCCESS
        time.sleep(0.01)
        assert emulator.received[-1] == bytes.fromhex(
            "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87")
        assert [emulator.servos[i].get(servo.GOAL_POSITION) for i in (1, 2)] == [150, 170]
        port.closePort()


def test_a_value_that_looks_like_a_header_survives_the_round_trip_through_the_sdk():
    # (dynamixel_sdk 4.1.0 sends it unstuffed - txPacket drops addStuffing's result - and the
    # CRC still matches; the emulator's status packet is stuffed and the SDK removes it)
    with bus(ids=(1,)) as emulator:
        port, handler = sdk(emulator)
        value = 0x00FDFFFF                                  # little endian on the wire: FF FF FD 00
        assert handler.write4ByteTxRx(port, 1, servo.PROFILE_ACCELERATION.address, value) == (COMM_SUCCESS, 0)
        assert handler.read4ByteTxRx(port, 1, servo.PROFILE_ACCELERATION.address) == (value, COMM_SUCCESS, 0)
        assert emulator.sent[-1] == packet(1, 0x55, bytes.fromhex("FF FF FD 00"), error=0)
        assert b"\xff\xff\xfd\xfd\x00" in emulator.sent[-1]
        port.closePort()


def test_bad_crc_is_answered_with_a_crc_error_and_absent_ids_are_silent():
    with bus(ids=(1,)) as emulator:
        with serial.Serial(emulator.port, 57600, timeout=0.2) as line:
            line.write(PING_1[:-1] + b"\x00")
            assert line.read(11) == packet(1, 0x55, error=0x03)
        port, handler = sdk(emulator, patient=False)
        start = time.monotonic()
        assert handler.ping(port, 9)[1] == COMM_RX_TIMEOUT
        assert time.monotonic() - start < 0.2 + BUSY_S
        port.closePort()


# --- the real DynamixelPanTilt on the emulator ----------------------------------------------

RIG = LampRig(pivot_m=np.array([0.0, 0.0, 0.004]), pan_range_rad=(-np.pi, np.pi),
              tilt_range_rad=(np.radians(5.0), np.radians(85.0)), radius_range_m=(0.15, 0.60),
              radius_axis="manual")
SERVO_RIG = LampRig(RIG.pivot_m, RIG.pan_range_rad, RIG.tilt_range_rad, RIG.radius_range_m, "servo")


DEFAULTS = device_settings({}).pan_tilt


def pan_tilt(emulator, rig=RIG, **config):
    """The real pan-tilt on the emulator at 90 deg/s; its 3 s move timeout keeps a pan across
    the turn (200 deg below: 2.2 s on real servos, which the emulator turns 10 times faster)."""
    settings = dict(port=emulator.port, speed_rad_s=np.radians(90.0), move_timeout_s=3.0, **config)
    return DynamixelPanTilt(rig, replace(DEFAULTS, **settings), Operator(yes=True, stdout=io.StringIO()))


def test_moves_and_reads_back_the_quantized_joints():
    with bus(ids=(1, 2), speedup=10) as emulator:
        rig = pan_tilt(emulator)
        assert [emulator.servos[i].get(servo.TORQUE_ENABLE) for i in (1, 2)] == [1, 1]
        assert emulator.servos[1].get(servo.PROFILE_VELOCITY) == servo.profile_velocity(np.radians(90.0))
        rig.move(np.radians(30.0), np.radians(45.0), 0.30)
        assert emulator.servos[1].get(servo.GOAL_POSITION) == 2048 + round(4096 * 30 / 360)
        assert emulator.servos[2].get(servo.PRESENT_POSITION) == 2048 + 512
        pan, tilt, radius = rig.joints()
        assert np.degrees(pan) == pytest.approx(30.0, abs=360 / 4096 / 2)
        assert pan == (2048 + 341 - 2048) * 2 * np.pi / 4096            # the quantized angle
        assert np.degrees(tilt) == pytest.approx(45.0) and radius == 0.30
        rig.move(np.radians(-170.0), np.radians(10.0), 0.30)
        assert np.degrees(rig.joints()[0]) == pytest.approx(-170.0, abs=0.05)
        rig.stop()                                         # hold: torque stays on
        assert [emulator.servos[i].get(servo.TORQUE_ENABLE) for i in (1, 2)] == [1, 1]
        rig.close()


def test_servo_radius_axis_moves_the_third_servo():
    with bus(ids=(1, 2, 3), speedup=10) as emulator:
        rig = pan_tilt(emulator, rig=SERVO_RIG, radius_ticks=(100, 4000))
        rig.move(0.0, np.radians(45.0), 0.375)              # half way along the radius range
        assert emulator.servos[3].get(servo.PRESENT_POSITION) == 2050
        assert rig.joints()[2] == pytest.approx(0.375, abs=0.45 / 3900)
        rig.close()


def test_hardware_error_during_a_move_names_the_servo_and_the_bits():
    with bus(ids=(1, 2), speedup=10) as emulator:
        rig = pan_tilt(emulator)
        emulator.inject_hardware_error(2, 0x04)
        with pytest.raises(DeviceFault, match=r"servo 2: Hardware Error Status 0x04 \(overheating\)"):
            rig.move(np.radians(10.0), np.radians(45.0), 0.3)
        rig.stop(fault_is_own=True)                         # the servos' own fault: torque off
        assert [emulator.servos[i].get(servo.TORQUE_ENABLE) for i in (1, 2)] == [0, 0]
        rig.close()


def test_hardware_error_at_connect_is_a_fault():
    with bus(ids=(1, 2)) as emulator:
        emulator.inject_hardware_error(1, 0x21)
        with pytest.raises(DeviceFault, match=r"servo 1: .*0x21 \(input voltage, overload\)"):
            pan_tilt(emulator)


def test_absent_servo_is_a_fault_after_the_sdk_timeout():
    with bus(ids=(1, 2)) as emulator:
        start = time.monotonic()
        with pytest.raises(DeviceFault, match="servo 7: ping: .*There is no status packet") as fault:
            pan_tilt(emulator, tilt_id=7)
        assert fault.value.device == "pan-tilt"
        assert time.monotonic() - start < 1.0 + BUSY_S


def test_goal_outside_the_servos_position_limits_is_refused_before_moving():
    with bus(ids=(1, 2), speedup=10) as emulator:
        emulator.servos[1].set(servo.MAX_POSITION_LIMIT, 3000)   # EEPROM, set before the torque is on
        rig = pan_tilt(emulator)
        with pytest.raises(DeviceFault, match=r"servo 1: goal tick 3755 outside its position limits \[0, 3000"):
            rig.move(np.radians(150.0), np.radians(45.0), 0.3)
        assert emulator.servos[1].get(servo.GOAL_POSITION) == 2048
        rig.close()


def test_a_lost_status_packet_is_sent_again_and_only_a_servo_that_never_answers_is_a_fault():
    with bus(ids=(1, 2), speedup=10) as emulator:
        rig = pan_tilt(emulator)
        rig.move(np.radians(30.0), np.radians(45.0), 0.30)
        emulator.lose(2)                         # two replies lost: the third attempt answers
        assert np.degrees(rig.joints()[0]) == pytest.approx(30.0, abs=0.05)
        assert np.degrees(rig.joints()[1]) == pytest.approx(45.0, abs=0.05)   # nothing stale left over
        emulator.lose(dynamixel.ATTEMPTS - 1)      # a write too: it sets an absolute value
        rig._write(1, servo.PROFILE_VELOCITY, 77)
        assert emulator.servos[1].get(servo.PROFILE_VELOCITY) == 77
        assert sum(raw[7] == 0x03 for raw in emulator.received[-dynamixel.ATTEMPTS:]) == dynamixel.ATTEMPTS
        emulator.lose(dynamixel.ATTEMPTS)
        with pytest.raises(DeviceFault, match="servo 1: read 132: .*There is no status packet"):
            rig.joints()
        rig.close()


def test_a_reply_that_comes_after_the_sdk_gave_up_is_never_taken_for_the_next_answer():
    """Replies later than the wait: taken for the next question's answer, a position would pass
    for the Max Position Limit. The line is waited out before each repeat, so the position's
    reads end in a fault instead."""
    with bus(ids=(1, 2), speedup=10) as emulator:
        rig = pan_tilt(emulator)
        rig.move(np.radians(30.0), np.radians(45.0), 0.30)
        timeout_s = (2 * 16 + 2.0 + dynamixel.SLACK_MS) / 1e3       # the SDK's wait and ours
        emulator.late(3, 1.2 * timeout_s)
        with pytest.raises(DeviceFault, match="servo 1: read 132: .*There is no status packet"):
            rig._read(1, servo.PRESENT_POSITION)
            pytest.fail(f"Max Position Limit read as {rig._read(1, servo.MAX_POSITION_LIMIT)}")
        time.sleep(2 * timeout_s)
        assert rig._read(1, servo.MAX_POSITION_LIMIT) == 4095
        rig.close()


def test_a_serial_link_that_goes_away_is_a_fault_now_and_for_every_later_call():
    """The pty closes, as an unplugged adapter: the SDK's termios.error (EIO) on its next call is a
    DeviceFault saying the link is lost, and the stop after it says so too, not 'Port is in use!'
    (the SDK's flag stays set after the error)."""
    with bus(ids=(1, 2), speedup=10) as emulator:
        rig = pan_tilt(emulator)
        emulator.close()
        lost = rf"serial link {emulator.port} lost \(\[Errno 5\] Input/output error\)"
        with pytest.raises(DeviceFault, match=lost) as fault:
            rig.move(np.radians(10.0), np.radians(45.0), 0.3)
        assert fault.value.device == "pan-tilt"
        with pytest.raises(DeviceFault, match=lost + ": not sent"):
            rig.stop(fault_is_own=True)
        rig.close()                                        # nothing left to release: no error


def test_missing_serial_port_is_a_fault():
    config = replace(DEFAULTS, port="/nonexistent/ttyDXL")
    with pytest.raises(DeviceFault, match="cannot open /nonexistent/ttyDXL"):
        DynamixelPanTilt(RIG, config, Operator(yes=True))
