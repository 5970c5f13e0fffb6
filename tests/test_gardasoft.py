"""The Gardasoft RT lighting controller on the wire, pymeasure-style: the emulator
(sim/gardasoft_emulator.py) answers the manual's commands byte for byte; the real adapter
(cell.devices.hw.gardasoft) writes exactly the manual's command lines, reads every set back,
and turns each fault a controller shows (no reply, an error event, a dropped connection, a
refused one) into a DeviceFault naming the controller and its address; the session's safe stop
turns every channel off; `cell hw-check` reports the controller; bad `cell.lighting` keys are
bad input. Everything on 127.0.0.1, the emulator on a free port."""
import json
import math
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from cell.cli import main
from cell.core.errors import DeviceFault
from cell.devices.hw.gardasoft import GardasoftController
from cell.devices.interfaces import Devices
from cell.devices.session import Session
from cell.task.device_config import LightingConfig
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.camera import SimCamera
from sim.gardasoft_emulator import GardasoftEmulator
from sim.pantilt import SimPanTilt
from loopback import refusing_port
from simcell import device_settings, variant
from test_hw_check import hw_check, servos, ur_host, video  # noqa: F401 (ur_host, video: fixtures)
from test_hw_check import task as hw_task

# the controller's reply timeout: the emulator answers in a millisecond idle, but a thread of a
# busy machine (the suite on both cores, other test runs) may wait far longer for its turn
TIMEOUT_S = 2.0
SILENT_TIMEOUT_S = 0.3      # the one test that waits for the timeout to pass


@pytest.fixture
def emulator():
    with GardasoftEmulator(channels=4) as running:
        yield running


def settings(emulator, channels=4, timeout_s=TIMEOUT_S):
    host, port = emulator.address
    return LightingConfig(driver="gardasoft", host=host, port=port, channels=channels, timeout_s=timeout_s)


def controller(emulator, **kwargs):
    return GardasoftController(settings(emulator, **kwargs))


def exchange(emulator, line):
    """One raw command line to the emulator and the reply through its `>`."""
    with socket.create_connection(emulator.address, timeout=10.0) as sock:
        sock.sendall(line)
        reply = b""
        while not reply.endswith(b">"):
            reply += sock.recv(4096)
        return reply


# the emulator speaks the manual (12.3, 13.3, 13.5)

def test_the_emulator_answers_the_manuals_commands_byte_for_byte(emulator):
    assert exchange(emulator, b"VR\r") == b"RT420-20 (HW02) V031\r\n>"
    assert exchange(emulator, b"ST1\r") == b"CH 1, MD OFF, S 0.0%\r\n>"          # at power-up
    assert exchange(emulator, b"RS2,42.5\r") == b">"                            # a set says only >
    assert exchange(emulator, b"RS 3, 7 ; ST2;ST3\r") == b"CH 2, MD CONT, S 42.5%\r\nCH 3, MD CONT, S 7.0%\r\n>"
    assert exchange(emulator, b"ST0\r") == b"TM 0, TP 20.00ms\r\n>"
    assert exchange(emulator, b"XX1\r") == b"Err 2\r\n>"                        # not recognised
    assert exchange(emulator, b"RS5,10\r") == b"Err 1\r\n>"                     # a 4-channel model
    assert exchange(emulator, b"RS1,101\r") == b"Err 1\r\n>"
    assert exchange(emulator, b"RS1,1x\r") == b"Err 3\r\n>"
    assert exchange(emulator, b"RS1\r") == b"Err 4\r\n>"
    assert emulator.controller.setting_pct == {1: 0.0, 2: 42.5, 3: 7.0, 4: 0.0}


def test_the_emulator_sends_error_events_only_after_gt1(emulator):
    with socket.create_connection(emulator.address, timeout=10.0) as sock:
        sock.sendall(b"GT1\r")
        assert sock.recv(64) == b">"
        emulator.inject((2, 131))
        assert sock.recv(64) == b"Evt2,131;"
    assert exchange(emulator, b"GR\r") == b"Evt2,131;\r\n>"                     # the last event, then cleared
    assert exchange(emulator, b"GR\r") == b">"


def test_the_emulator_runs_as_a_module_and_refuses_a_non_loopback_host():
    process = subprocess.Popen([sys.executable, "-m", "sim.gardasoft_emulator", "--port", "0", "--max-seconds", "20",
                                "--channels", "2", "--fault", "drop", "--fault-on-command", "2"],
                               stdout=subprocess.PIPE, text=True)
    try:
        ready, _, address = process.stdout.readline().strip().partition(" ")
        host, _, port = address.partition(":")
        assert ready == "READY" and host == "127.0.0.1"
        with socket.create_connection((host, int(port)), timeout=10.0) as sock:
            sock.sendall(b"VR\r")
            assert sock.recv(64) == b"RT220-20 (HW02) V031\r\n>"
            sock.sendall(b"ST1\r")
            assert sock.recv(64) == b""                                 # dropped at the second command
    finally:
        process.kill()
        process.wait(timeout=10)
        process.stdout.close()
    refused = subprocess.run([sys.executable, "-m", "sim.gardasoft_emulator", "--host", "10.0.0.1", "--port", "0"],
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0 and "loopback only" in refused.stderr


# the adapter: exact bytes and the round trip

def test_the_adapter_writes_exactly_the_manuals_command_lines(emulator):
    lights = controller(emulator)
    assert emulator.received == [b"GT1\r", b"VR\r"]                 # events on, the model read
    lights.set_drive(1, 0.5)
    lights.set_drive(3, 0.123)
    lights.set_drive(2, 1.0)
    lights.set_drive(4, 0.0)
    assert emulator.received[2:] == [b"RS1,50\r", b"ST1\r", b"RS3,12.3\r", b"ST3\r",
                                     b"RS2,100\r", b"ST2\r", b"RS4,0\r", b"ST4\r"]
    del emulator.received[:]
    lights.all_off()
    assert emulator.received == [line for c in (1, 2, 3, 4) for line in (b"RS%d,0\r" % c, b"ST%d\r" % c)]
    lights.close()


def test_round_trip_set_read_back_and_all_off(emulator):
    lights = controller(emulator)
    assert lights.set_drive(1, 0.25) == pytest.approx(0.25, abs=1e-12)
    assert lights.set_drive(2, 0.8766) == pytest.approx(0.877, abs=1e-12)     # sent in 0.1 % steps
    assert [lights.drive(c) for c in (1, 2, 3, 4)] == pytest.approx([0.25, 0.877, 0.0, 0.0], abs=1e-12)
    assert emulator.controller.setting_pct == {1: 25.0, 2: 87.7, 3: 0.0, 4: 0.0}
    assert emulator.controller.mode == {1: "CONT", 2: "CONT", 3: "OFF", 4: "OFF"}
    assert lights.state() == {"firmware": "RT420-20 (HW02) V031",
                              "levels": {"1": 0.25, "2": pytest.approx(0.877), "3": 0.0, "4": 0.0}, "problems": []}
    assert lights.describe() == {"name": f"Gardasoft controller at {emulator.address[0]}:{emulator.address[1]}",
                                 "channels": 4, "driver": "gardasoft", "firmware": "RT420-20 (HW02) V031"}
    lights.all_off()
    assert emulator.controller.setting_pct == {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0}
    assert [lights.drive(c) for c in (1, 2, 3, 4)] == [0.0, 0.0, 0.0, 0.0]
    lights.close()


@pytest.mark.parametrize("channel, level, reason", [
    (0, 0.5, r"channel 0 is not one of the configured 1\.\.4: refused before setting"),
    (5, 0.5, r"channel 5 is not one of the configured 1\.\.4"),
    (1.0, 0.5, r"channel 1\.0 is not one of the configured"),
    (1, -0.01, r"channel 1 level -0\.01 outside \[0, 1\]: refused before setting"),
    (1, 1.2, r"channel 1 level 1\.2 outside \[0, 1\]"),
    (1, math.nan, r"channel 1 level nan outside \[0, 1\]"),
])
def test_a_channel_or_level_out_of_range_is_refused_before_anything_is_sent(emulator, channel, level, reason):
    lights = controller(emulator)
    sent = len(emulator.received)
    with pytest.raises(DeviceFault, match=rf"^lighting: Gardasoft controller at 127\.0\.0\.1:\d+: {reason}") as fault:
        lights.set_drive(channel, level)
    assert fault.value.device == "lighting" and len(emulator.received) == sent
    lights.close()


# each fault a controller shows -> a DeviceFault naming the controller and its address

def test_no_reply_within_the_timeout_is_a_fault_and_later_commands_are_not_sent(emulator):
    lights = controller(emulator, timeout_s=SILENT_TIMEOUT_S)
    emulator.inject("silent")
    name = f"Gardasoft controller at {emulator.address[0]}:{emulator.address[1]}"
    start = time.monotonic()
    with pytest.raises(DeviceFault) as fault:
        lights.set_drive(1, 0.5)
    assert SILENT_TIMEOUT_S <= time.monotonic() - start < SILENT_TIMEOUT_S + 10.0    # waited for it; no hang
    assert str(fault.value) == f"lighting: {name}: no reply ending in '>' to RS1,50 within 0.3 s"
    sent = len(emulator.received)
    with pytest.raises(DeviceFault, match=r"no reply .*: ST1 not sent$"):
        lights.drive(1)
    assert len(emulator.received) == sent
    lights.close()


def test_an_error_event_is_a_fault_naming_the_channel_and_the_event(emulator):
    lights = controller(emulator)
    emulator.inject((3, 131))                                   # over current on channel 3
    with pytest.raises(DeviceFault, match=r"^lighting: Gardasoft controller at 127\.0\.0\.1:\d+: "
                                          r"channel 3: event 131: over current$"):
        lights.set_drive(1, 0.5)
    emulator.inject((0, 128), on_command=len(emulator.received) + 1)     # a light connected: no error
    assert lights.drive(1) == 0.5
    lights.close()


def test_an_err_reply_is_a_fault_naming_the_command(emulator):
    lights = controller(emulator)
    with pytest.raises(DeviceFault, match=r"127\.0\.0\.1:\d+: XX answered Err 2 \(command not recognised\)$"):
        lights.command("XX")
    lights.close()


def test_a_dropped_connection_is_a_fault_and_all_off_connects_again(emulator):
    lights = controller(emulator)
    lights.set_drive(2, 0.6)
    emulator.inject("drop", on_command=len(emulator.received) + 1)      # at the next command line
    with pytest.raises(DeviceFault, match=r"^lighting: Gardasoft controller at 127\.0\.0\.1:\d+: connection "
                                          r"closed by the controller \(after RS1,40\)$"):
        lights.set_drive(1, 0.4)
    assert emulator.controller.setting_pct[2] == 60.0
    lights.all_off()                                             # a new connection
    assert emulator.controller.setting_pct == {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0}
    lights.close()


def test_a_refused_connection_is_a_fault_naming_the_address():
    port = refusing_port()
    config = LightingConfig("gardasoft", "127.0.0.1", port, 4, TIMEOUT_S)
    with pytest.raises(DeviceFault, match=rf"^lighting: Gardasoft controller at 127\.0\.0\.1:{port}: cannot "
                                          r"connect \(ConnectionRefusedError: "):
        GardasoftController(config)


def test_a_model_with_other_channels_than_configured_is_a_fault():
    with GardasoftEmulator(channels=8) as eight:
        with pytest.raises(DeviceFault, match=r"firmware 'RT820F-20 \(HW02\) V031' is a 8-channel model, "
                                              r"cell.lighting.channels is 4$"):
            controller(eight)


# the session's safe stop

def sim_devices(lights):
    task = load_task("tasks/hinge.yaml")
    config = device_settings({})
    arm = SimArm(config.arm, task.frames)
    rig = SimPanTilt(task.lamp.rig, config.pan_tilt)
    return Devices(arm, rig, SimCamera(lambda *a: np.zeros((4, 4), np.uint8), arm, rig), lights)


@pytest.mark.parametrize("fault", ["another device's", "the controller's dropped connection"])
def test_the_sessions_safe_stop_turns_every_channel_off(emulator, fault):
    faults = []
    with pytest.raises(DeviceFault, match="motion stopped$") as ended:
        with Session(on_fault=faults.append) as session:
            session.devices = sim_devices(controller(emulator))
            for channel, level in ((1, 0.3), (2, 0.9), (4, 1.0)):
                session.devices.lights.set_drive(channel, level)
            if fault == "another device's":
                raise DeviceFault("arm", "protective stop")
            emulator.inject("drop", on_command=len(emulator.received) + 1)
            session.devices.lights.set_drive(3, 0.5)
    assert emulator.controller.setting_pct == {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0}
    assert faults[0]["stop_failures"] == [] and faults[0]["release_failures"] == []
    assert ended.value.device == ("arm" if fault == "another device's" else "lighting")


def test_a_silent_controller_is_a_failed_stop_naming_the_channels_left_on(emulator):
    faults = []
    with pytest.raises(DeviceFault, match=r"STOP FAILED, check the cell: lighting: Gardasoft controller at "
                                          r"127\.0\.0\.1:\d+: no reply ending in '>' to RS1,0 within 0\.3 s; "
                                          r"channels \[1, 2, 3, 4\] not turned off$"):
        with Session(on_fault=faults.append) as session:
            session.devices = sim_devices(controller(emulator, timeout_s=SILENT_TIMEOUT_S))
            session.devices.lights.set_drive(2, 0.9)
            emulator.inject("silent")
            raise DeviceFault("arm", "protective stop")
    assert len(faults[0]["stop_failures"]) == 1 and emulator.controller.setting_pct[2] == 90.0


def test_a_normal_end_turns_the_lights_off_and_closes_them(emulator):
    with Session() as session:
        session.devices = sim_devices(controller(emulator))
        session.devices.lights.set_drive(1, 0.7)
    assert emulator.controller.setting_pct[1] == 0.0
    assert session.devices.lights._sock is None


def test_devices_without_a_controller_stop_as_before():
    devices = sim_devices(None)
    assert devices.lights is None and devices.safe_stop() == [] and devices.close() == []


# cell hw-check and the task keys

def lighting_task(tmp_path, ur_host, port, video, lighting):
    path = hw_task(tmp_path, ur_host, port, video)
    return variant(tmp_path, path, {"cell.lighting": lighting})


def test_hw_check_reports_the_controller_and_sets_nothing(tmp_path, ur_host, video, emulator):
    emulator.controller.setting_pct[2] = 35.0
    host, port = emulator.address
    with servos() as bus:
        path = lighting_task(tmp_path, ur_host, bus.port, video, {"host": host, "port": port, "timeout_ms": 500})
        done, _ = hw_check(path, "--json")
        assert done.returncode == 0, done.stderr
        lighting = json.loads(done.stdout)["devices"][3]
        assert lighting == {"device": "lighting", "address": f"{host}:{port}", "answered": True, "ready": True,
                            "fault": None, "state": {"firmware": "RT420-20 (HW02) V031",
                                                     "levels": {"1": 0.0, "2": 0.35, "3": 0.0, "4": 0.0},
                                                     "problems": []}}
        assert emulator.received == [b"VR\r", b"ST1\r", b"ST2\r", b"ST3\r", b"ST4\r"]   # asked, nothing set
        done, _ = hw_check(path)
    assert done.returncode == 0, done.stderr
    assert f"lighting  {host}:{port}: answered\n" in done.stdout
    assert "drive levels (0..1) by channel: 1: 0.000, 2: 0.350, 3: 0.000, 4: 0.000" in done.stdout
    assert done.stdout.strip().endswith("hw-check: all 4 devices answered; nothing was moved or set")


def test_hw_check_with_nothing_listening_is_exit_3_naming_the_controller(tmp_path, ur_host, video):
    port = refusing_port()
    with servos() as bus:
        done, _ = hw_check(lighting_task(tmp_path, ur_host, bus.port, video, {"host": "127.0.0.1", "port": port}))
    assert done.returncode == 3
    assert done.stderr.strip() == (f"cell hw-check: lighting at 127.0.0.1:{port} did not answer: Gardasoft "
                                   f"controller at 127.0.0.1:{port}: cannot connect (ConnectionRefusedError: "
                                   "[Errno 111] Connection refused)")


@pytest.mark.parametrize("lighting, line", [
    ({"channels": 3}, "cell.lighting.channels: found 3, expected 2, 4 or 8 (the controller model's channels)"),
    ({"port": 0}, "cell.lighting.port: found 0, expected an integer in 1..65535"),
    ({"timeout_s": -1}, "cell.lighting.timeout_s: found -1, expected a positive number (plausible: 50 ms to 600 s)"),
    ({"driver": "dmx"}, "cell.lighting.driver: found 'dmx', expected one of gardasoft"),
])
def test_bad_lighting_keys_exit_2_with_one_line(tmp_path, capsys, lighting, line):
    path = variant(tmp_path, "tasks/hinge.yaml", {"cell.lighting": lighting})
    assert main(["check", str(path)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and error.endswith(line)


def test_hw_without_the_controllers_address_is_bad_input(tmp_path):
    path = variant(tmp_path, "tasks/hinge.yaml", {"cell.arm.host": "127.0.0.1", "cell.pan_tilt.port": "/dev/null",
                                                  "cell.lighting": {"channels": 8}})
    done, _ = hw_check(path)
    assert done.returncode == 2
    assert done.stderr.strip().endswith("cell.lighting.host: found nothing, expected the lighting controller's "
                                        "address (required for --backend hw; there is no default)")
