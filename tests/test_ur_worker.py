"""URArm's connection through the ur_rtde worker process (cell.devices.hw.ur_worker): nothing listening, a
listener that accepts and never answers, and a controller that goes silent at each later step of
the connection - after RTDE's protocol version, at RTDE's start once the recipes are set up,
after the dashboard's greeting, on the script port - are each a DeviceFault naming the arm, the
host and the step within connect_timeout_s and a small margin, never a hang. The listeners run in
this test process as threads: possible only because ur_rtde no longer holds this process's GIL."""
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cell.core.errors import DeviceFault
from cell.devices.hw import ur
from cell.devices.hw.ur_worker import Worker
from cell.task.loader import load_task
from cell.planning.scene import look_at
from loopback import BUSY_S, free_host
from sim import ur_controller
from simcell import device_settings

TASK = "tasks/hinge.yaml"
FRAMES = load_task(TASK).frames
ARM = device_settings({}, TASK).arm
TIMEOUT_S = 1.0
MARGIN_S = 1.0 + BUSY_S  # the probe, spawning the worker (0.1 s idle), killing it


def arm_config(host, timeout_s=TIMEOUT_S):
    return replace(ARM, host=host, connect_timeout_s=timeout_s)


def no_worker_left():
    """No child of this process runs cell.devices.hw.ur_worker (zombies included: every worker is reaped)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            command = (stat.parent / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == os.getpid() and b"cell.devices.hw.ur_worker" in command:
            return False
    return True


def fails_in_time(host, match, timeout_s=TIMEOUT_S):
    began = time.monotonic()
    with pytest.raises(DeviceFault, match=match) as fault:
        ur.URArm(arm_config(host, timeout_s), FRAMES)
    took = time.monotonic() - began
    assert fault.value.device == "arm" and took < timeout_s + MARGIN_S, took
    assert no_worker_left()
    return took


@contextmanager
def controller_thread(**options):
    """The UR emulator's server in a thread of this process, on an address of its own."""
    host = free_host()
    server = ur_controller.Server(host, ur_controller.Controller(**options))
    thread = threading.Thread(target=server.run, args=(60.0,), daemon=True)
    thread.start()
    try:
        yield host
    finally:
        server.stopping = True
        thread.join(5.0)


@contextmanager
def listener_that_never_answers():
    """Accepts on all three of UR's ports and never sends a byte."""
    host = free_host()
    servers = [socket.create_server((host, port)) for port in (29999, 30003, 30004)]
    accepted = []

    def accept(server):
        try:
            while True:
                accepted.append(server.accept()[0])
        except OSError:
            return
    for server in servers:
        threading.Thread(target=accept, args=(server,), daemon=True).start()
    try:
        yield host
    finally:
        for sock in servers + accepted:
            sock.close()


def test_nothing_listening_fails_at_once_naming_arm_host_and_port():
    host = free_host()
    took = fails_in_time(host, rf"UR at {host}:30004: RTDE protocol version request failed within "
                               rf"{TIMEOUT_S} s: .*Connection refused")
    assert took < 0.5 + BUSY_S


def test_a_listener_that_accepts_and_never_answers_fails_within_the_timeout():
    with listener_that_never_answers() as host:
        took = fails_in_time(host, rf"UR at {host}:30004: RTDE protocol version request failed within "
                                   rf"{TIMEOUT_S} s: no answer")
        assert took > TIMEOUT_S - 0.05


@pytest.mark.parametrize("step, constructor", [
    ("rtde-version", "RTDEReceiveInterface"),
    ("rtde-start", "RTDEReceiveInterface"),
    ("dashboard", "RTDEControlInterface"),
    ("script", "RTDEControlInterface"),
])
def test_a_controller_silent_at_a_later_step_of_the_connection_is_a_fault_within_the_timeout(step, constructor):
    """The probe passes (version, greeting, script port all answer), then ur_rtde's constructor
    would wait forever (the script port: ur_rtde's own 5 s); the worker is killed in time."""
    with controller_thread(mute=step) as host:
        took = fails_in_time(host, rf"UR at {host}: {constructor} connect \(.*\): no answer within "
                                   rf"{TIMEOUT_S} s \(worker stopped\)")
        assert took > TIMEOUT_S - 0.05


def test_ur_rtdes_own_errors_become_device_faults(monkeypatch):
    host = free_host()
    monkeypatch.setattr(ur, "probe", lambda host, timeout_s: None)     # straight to ur_rtde
    fails_in_time(host, rf"UR at {host}: .*Could not connect to: {host}")


def test_the_move_watchers_round_trip_to_the_worker_stays_well_under_its_poll_period():
    with controller_thread() as host:
        arm = ur.URArm(arm_config(host), FRAMES)
        try:
            times = []
            for _ in range(100):
                began = time.perf_counter()
                state = arm._watched()
                times.append(time.perf_counter() - began)
            assert state.connected and state.runtime_state == ur.PLAYING and len(state.tcp_pose) == 6
            assert statistics.median(times) < 0.2 * ur.POLL_S, times
            assert arm._receive.getRobotMode() == ur_controller.RUNNING         # any getter, by name
            assert not no_worker_left()
        finally:
            arm.close()
        assert no_worker_left()


def test_the_worker_starts_from_any_main_even_a_script_without_a_main_guard():
    """(multiprocessing's spawn would re-run such a script in the child and fail)"""
    code = ("from cell.devices.hw.ur_worker import Worker\n"
            "worker = Worker('arm', 'UR at 127.0.0.9')\n"
            "print(worker.call([], 5.0, 'nothing'))\n"
            "worker.close()\n")
    done = subprocess.run([sys.executable, "-"], input=code, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr


def test_a_worker_that_died_is_a_fault_naming_the_step_and_later_calls_say_why():
    worker = Worker("arm", "UR at 127.0.0.9")
    worker._process.kill()
    worker._process.wait()
    with pytest.raises(DeviceFault, match=r"UR at 127.0.0.9: getActualQ: the ur_rtde worker process ended"):
        worker.call([("receive", "getActualQ", ())], 1.0, "getActualQ")
    with pytest.raises(DeviceFault, match=r"stopL not sent: the ur_rtde worker process ended"):
        worker.call([("control", "stopL", (1.0,))], 1.0, "stopL")
    worker.close()
    assert no_worker_left()


def test_a_pose_the_controller_cannot_reach_is_refused_by_asking_it_and_nothing_moves():
    """Arm.refusal on the real client: the controller's isPoseWithinSafetyLimits (the emulator's
    UR5e kinematics) says no to a pose beyond the reach and yes to one within it."""
    with controller_thread() as host:
        arm = ur.URArm(arm_config(host), FRAMES)
        try:
            before = arm.camera_pose()
            far = look_at(np.array([0.55, 0.55, 0.9]), np.array([0.6, 0.6, 0.0]))   # inside the workspace box
            why = arm.refusal(far)
            assert why is not None and "unreachable or outside the robot's safety limits" in why
            assert arm.refusal(before) is None
            assert np.allclose(arm.camera_pose(), before, atol=1e-9)
        finally:
            arm.stop()
            arm.close()
