"""`cell hw-check` as a user runs it, against the UR controller emulator process (the real
ur_rtde receive interface), the pty servo emulator (the real dynamixel_sdk) and a video file (the
real cv2.VideoCapture): every device's state as the emulators were set, nothing moved or written;
a silent or absent arm, a missing serial port, a stopped arm and a servo's hardware error are
exit 3 naming the device and its address, and the other devices are still read."""
import json
import socket
import subprocess
import sys
import time
from contextlib import contextmanager

import cv2
import numpy as np
import pytest

from cell.devices import servo
from cell.run.backends import check_hw_devices
from cell.core.geometry import to_ur_pose
from cell.task.loader import load_task
from cell.devices import ur5e
from sim.dxl_emulator import PING, READ, DxlEmulator
from sim.ur_controller import RTDE_PORT
from loopback import BUSY_S, dashboard, start_emulator, stop_emulator
from loopback import free_host as free_loopback
from simcell import variant

HOME_RAD = np.radians([-90.0, -90.0, 90.0, -90.0, -90.0, 0.0])   # the emulator after power-up
PAN_TICKS, TILT_TICKS = 2048 + 341, 2048 + 512                    # pan 29.97 deg, tilt 45 deg


@pytest.fixture(scope="module")
def ur_host(tmp_path_factory):
    """The UR controller emulator, its own process on its own loopback address."""
    host = free_loopback()
    process = start_emulator(host, (), 180, tmp_path_factory.mktemp("ur") / "ur_controller.log")
    yield host
    stop_emulator(process)


@contextmanager
def servos():
    """Pan (1) and tilt (2) on the pty bus, torque off, at known ticks and temperatures."""
    with DxlEmulator(ids=(1, 2), model_number=1020, firmware=45) as emulator:
        for dxl_id, ticks, celsius in ((1, PAN_TICKS, 41), (2, TILT_TICKS, 37)):
            emulator.servos[dxl_id].position = ticks
            emulator.servos[dxl_id].set(servo.PRESENT_TEMPERATURE, celsius)
        emulator.servos[2].set(servo.MAX_POSITION_LIMIT, 3000)
        time.sleep(0.01)                                  # the emulator publishes the positions
        yield emulator


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """Two frames of the hinge's sensor size (1032 x 776), MJPG."""
    path = tmp_path_factory.mktemp("camera") / "frames.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (1032, 776), isColor=True)
    for gray in (60, 90):
        writer.write(np.full((776, 1032, 3), gray, np.uint8))
    writer.release()
    return path


def task(tmp_path, host, port, source, timeout_s=2.0):
    return variant(tmp_path, "tasks/hinge.yaml", {
        "cell.arm.host": host, "cell.arm.connect_timeout_s": timeout_s,
        "cell.pan_tilt.port": port, "cell.camera.source": str(source)})


def hw_check(path, *options):
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "cell", "hw-check", str(path), *options],
                          capture_output=True, text=True, timeout=60)
    return done, time.monotonic() - start


def test_hw_check_prints_every_devices_state_and_moves_nothing(tmp_path, ur_host, video):
    with servos() as emulator:
        done, _ = hw_check(task(tmp_path, ur_host, emulator.port, video), "--json")
        assert done.returncode == 0, done.stderr
        report = json.loads(done.stdout)
        arm, pan_tilt, camera = report["devices"]
        assert report["ready"] and [d["device"] for d in report["devices"]] == ["arm", "pan-tilt", "camera"]

        assert arm["address"] == ur_host and arm["answered"]
        state = arm["state"]
        assert (state["robot_mode"], state["safety_mode"], state["remote_control"]) == ("RUNNING", "NORMAL", True)
        assert state["joints_rad"] == pytest.approx(HOME_RAD, abs=1e-12)
        # no TCP offset set: the TCP is the flange, by the UR5e's forward kinematics at home
        assert state["tcp_pose"] == pytest.approx(to_ur_pose(ur5e.forward(HOME_RAD)), abs=1e-9)
        assert state["polyscope_version"].startswith("URSoftware 5.11")

        s1, s2 = pan_tilt["state"]["servos"]["1"], pan_tilt["state"]["servos"]["2"]
        assert pan_tilt["address"] == emulator.port and pan_tilt["state"]["baud"] == 57600
        assert (s1["role"], s1["model"], s1["model_number"], s1["firmware"]) == ("pan", "XM430-W350", 1020, 45)
        assert (s1["present_position_ticks"], s2["present_position_ticks"]) == (PAN_TICKS, TILT_TICKS)
        assert s1["joint_rad"] == pytest.approx(341 * 2 * np.pi / 4096)     # pan offset 0: centre 2048
        assert s2["joint_rad"] == pytest.approx(np.pi / 4)
        assert (s1["temperature_c"], s2["temperature_c"], s1["temperature_limit_c"]) == (41, 37, 80)
        assert (s2["min_position_limit_ticks"], s2["max_position_limit_ticks"]) == (0, 3000)
        assert s1["hardware_error"] == "none" and s1["input_voltage_v"] == pytest.approx(12.0)
        assert not s1["torque_enabled"] and s1["operating_mode"] == 3

        state = camera["state"]
        assert (state["width_px"], state["height_px"], state["bit_depth"]) == (1032, 776, 8)
        assert state["pixel_format"] == "MJPG" and state["exposure_range_s"] is None

        # read only: pings and reads on the bus, nothing written, nothing moved
        assert {raw[7] for raw in emulator.received} == {PING, READ}
        assert [emulator.servos[i].get(servo.PRESENT_POSITION) for i in (1, 2)] == [PAN_TICKS, TILT_TICKS]
        assert [emulator.servos[i].get(servo.TORQUE_ENABLE) for i in (1, 2)] == [0, 0]
        status = dashboard(ur_host, "emulator status")
        assert status.startswith("moves 0 runtime_state 1 ")            # no program uploaded, no moveL
        assert json.loads(status.split(" q ")[1]) == pytest.approx(HOME_RAD, abs=1e-6)

        done, _ = hw_check(task(tmp_path, ur_host, emulator.port, video))
        assert done.returncode == 0, done.stderr
        out = done.stdout
        assert f"arm       {ur_host}: answered" in out
        assert "robot mode RUNNING, safety mode NORMAL, remote control yes" in out
        assert "joints [-90.0, -90.0, 90.0, -90.0, -90.0, 0.0] deg" in out
        assert ("servo 1 (pan): XM430-W350 (model 1020, firmware 45), operating mode 3, torque off, "
                "position 2389 ticks = 29.97 deg, limits 0..4095 ticks, hardware error none, 41 C") in out
        assert "1032 x 776 px, 3 channel(s), 8 bit, pixel format MJPG" in out
        assert out.strip().endswith("hw-check: all 3 devices answered; nothing was moved or set")


def test_nothing_listening_and_a_missing_port_are_exit_3_and_the_camera_is_still_read(tmp_path, video):
    host = free_loopback()                                            # nothing listens there
    done, elapsed = hw_check(task(tmp_path, host, "/nonexistent/ttyDXL", video, timeout_s=1.0), "--json")
    assert done.returncode == 3, done.stderr
    assert f"cell hw-check: arm at {host} did not answer: UR at {host}:30004: RTDE protocol " in done.stderr
    assert "cell hw-check: pan-tilt at /nonexistent/ttyDXL did not answer: cannot open /nonexistent/ttyDXL" \
        in done.stderr
    assert "Traceback" not in done.stderr and elapsed < 20
    arm, pan_tilt, camera = json.loads(done.stdout)["devices"]
    assert not arm["answered"] and not pan_tilt["answered"]
    assert camera["ready"] and camera["state"]["width_px"] == 1032


def test_a_silent_arm_is_a_fault_within_the_connect_timeout(tmp_path, video):
    host = free_loopback()
    # accepts (the backlog) and never answers; SO_REUSEADDR (create_server's) as the emulators bind:
    # the address is reserved for this process (loopback.free_host)
    with socket.create_server((host, RTDE_PORT), backlog=4):
        with servos() as emulator:
            start = time.monotonic()
            arm, pan_tilt, camera = check_hw_devices(load_task(task(tmp_path, host, emulator.port, video, 1.5)))
            elapsed = time.monotonic() - start
    assert arm.fault == f"UR at {host}:30004: RTDE protocol version request failed within 1.5 s: no answer"
    assert 1.5 <= elapsed < 3.0 + BUSY_S
    assert pan_tilt.ready and camera.ready


def test_a_protective_stop_and_a_servo_hardware_error_are_reported_and_exit_3(tmp_path, ur_host, video):
    assert dashboard(ur_host, "emulator fault protective-stop") == "fault protective-stop injected"
    try:
        with servos() as emulator:
            emulator.inject_hardware_error(2, 0x24)
            done, _ = hw_check(task(tmp_path, ur_host, emulator.port, video))
    finally:
        dashboard(ur_host, "emulator reset")
    assert done.returncode == 3
    assert "robot mode RUNNING, safety mode PROTECTIVE_STOP" in done.stdout
    assert "servo 2 (tilt): XM430-W350" in done.stdout and "hardware error 0x24 (overheating, overload)" in done.stdout
    assert (f"cell hw-check: arm at {ur_host} not ready: safety mode PROTECTIVE_STOP: a run needs NORMAL "
            "or REDUCED") in done.stderr
    assert "cell hw-check: pan-tilt at /dev/pts/" in done.stderr
    assert "servo 2: Hardware Error Status 0x24 (overheating, overload)" in done.stderr


def test_hw_check_without_the_robots_address_is_bad_input(tmp_path, video):
    path = variant(tmp_path, "tasks/hinge.yaml", {"cell.pan_tilt.port": "/dev/ttyUSB0"})
    done, _ = hw_check(path)
    assert done.returncode == 2
    assert done.stderr.strip().endswith("cell.arm.host: found nothing, expected the robot's address "
                                        "(required for --backend hw; there is no default)")


def test_the_interfaces_default_state_is_the_read_back_of_the_simulated_devices():
    from cell.planning.scene import look_at
    from sim.arm import SimArm
    from sim.camera import SimCamera
    from sim.pantilt import SimPanTilt
    from simcell import device_settings

    hinge = load_task("tasks/hinge.yaml")
    settings = device_settings({})
    arm = SimArm(settings.arm, hinge.frames)
    T = look_at(np.array([-0.019, 0.0, 0.503]), np.array([0.006, 0.0, 0.004]))
    arm.move_camera(T)
    assert np.array(arm.state()["camera_pose"]) == pytest.approx(T, abs=1e-9)
    lamp = SimPanTilt(hinge.lamp.rig, settings.pan_tilt)
    lamp.move(np.radians(30.0), np.radians(45.0), 0.25)
    state = lamp.state()
    assert state["pan_rad"] == 341 * 2 * np.pi / 4096 and state["tilt_rad"] == np.pi / 4   # 4096 ticks a turn
    assert state["radius_m"] == 0.25 and state["problems"] == []                          # as confirmed (manual)
    camera = SimCamera(lambda *a: None, arm, lamp)
    camera.set_exposure(0.004)
    assert camera.state() == {"bit_depth": 8, "shutter_s": 0.004, "f_number": None, "focus_m": None,
                              "problems": []}


def test_an_absent_servo_is_named_and_the_other_servo_and_devices_still_read(tmp_path, video):
    host = free_loopback()                                            # nothing listens there
    with servos() as emulator:
        path = variant(tmp_path, "tasks/hinge.yaml", {
            "cell.arm.host": host, "cell.pan_tilt.port": emulator.port, "cell.pan_tilt.tilt_id": 7,
            "cell.camera.source": str(video)})
        arm, pan_tilt, camera = check_hw_devices(load_task(path))
    assert arm.fault.startswith(f"UR at {host}:30004: ") and camera.ready
    assert pan_tilt.state["problems"] == ["servo 7: ping: [TxRxResult] There is no status packet!"]
    assert pan_tilt.state["servos"]["1"]["present_position_ticks"] == PAN_TICKS
    assert pan_tilt.state["servos"]["7"] == {"role": "tilt", "error": pan_tilt.state["problems"][0]}


def test_a_read_only_arm_refuses_to_move_and_has_nothing_to_stop(ur_host):
    from cell.core.errors import DeviceFault
    from cell.devices.hw.ur import URArm
    from cell.planning.scene import look_at
    from simcell import device_settings

    hinge = load_task("tasks/hinge.yaml")
    arm = URArm(device_settings({"arm": {"host": ur_host}}).arm, hinge.frames, read_only=True)
    try:
        T = look_at(np.array([-0.019, 0.0, 0.503]), np.array([0.006, 0.0, 0.004]))
        with pytest.raises(DeviceFault, match=rf"UR at {ur_host}: opened read-only \(cell hw-check\): moveL refused"):
            arm.move_camera(T)
        arm.stop()                                                  # nothing was commanded
        assert arm.state()["joints_rad"] == pytest.approx(HOME_RAD, abs=1e-12)
    finally:
        arm.close()
    assert dashboard(ur_host, "emulator status").startswith("moves 0 runtime_state 1 ")


def test_a_camera_that_does_not_open_is_one_line_and_no_opencv_log_reaches_the_terminal(tmp_path):
    host = free_loopback()                                            # nothing listens there
    path = variant(tmp_path, "tasks/hinge.yaml", {"cell.arm.host": host, "cell.arm.connect_timeout_s": 1.0,
                                                  "cell.pan_tilt.port": "/nonexistent/ttyDXL",
                                                  "cell.camera.source": 97})    # no /dev/video97
    done, _ = hw_check(path)
    assert done.returncode == 3, done.stderr
    assert "cell hw-check: camera" in done.stderr and "97" in done.stderr
    assert "[ WARN" not in done.stderr + done.stdout and ".cpp" not in done.stderr + done.stdout
