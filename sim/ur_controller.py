"""A UR e-Series controller on loopback for the unmodified ur_rtde client, so tests can run the
real RTDEReceiveInterface / RTDEControlInterface code path (and cell.devices.hw.ur.URArm) without a robot.

    python -m sim.ur_controller [--host 127.0.0.1] [--max-seconds N]
                                [--fault KIND [--fault-on-move N] [--fault-after-s S]]
                                [--mute STEP]

It must run in its own process (ur_rtde's constructors hold the GIL while they block). It prints
READY once it listens on UR's fixed ports - dashboard 29999, RTDE 30004, script 30003 - and ends
itself after --max-seconds. One process, one thread, a 500 Hz tick, standard-library sockets:
- RTDE (UR's RTDE guide): protocol version 2, controller version 5.11, output recipes streamed at
  their own frequency with the guide's types, input recipes numbered 1..N per connection (as
  ur_rtde counts them; it never reads the id), the client's data packages written into the
  controller's input registers.
- The control script ur_rtde uploads on 30003 (`def rtde_control():`) is recognised, and its
  register protocol is interpreted instead of its URScript (ur_rtde's scripts/rtde_control.script):
  the command in input_int_register_0 (moveL 3, moveJ 1, stopJ 34), arguments in input_double_register_0..,
  the async flag in input_int_register_1; output_int_register_0 is 1 (ready) or 2 (done),
  output_int_register_1 a query's answer, output_int_register_2 the async progress word.
- The arm: UR5e kinematics (cell/devices/ur5e.py). moveL follows the straight TCP line at the commanded
  speed with a trapezoidal profile of the commanded acceleration (a rotation counts as 1 m per
  rad, as movel's speed is rad/s for a pure rotation), the joints from the inverse nearest the
  current ones, every tick; moveJ turns every joint linearly, the leading one with that profile
  at the commanded speed and acceleration [rad/s, rad/s^2].
- Faults, from the command line or the dashboard (`emulator fault KIND [on move N after S]`):
  protective-stop, emergency-stop (the arm halts, the script stops, the safety bits rise), silent
  (the controller answers nothing more and streams nothing, connections stay open), drop (every
  connection closes and the controller leaves the network: it accepts no more).
- A connection step that never answers (`--mute STEP`, MUTE_STEPS): every client's connection
  goes silent at that step, as a listener that passes a connection check and then hangs.
"""

from __future__ import annotations

import argparse
import errno
import re
import selectors
import socket
import struct
import sys
import time
from collections.abc import Sequence
from typing import Any, TextIO, cast

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from cell.core.geometry import from_ur_pose, to_ur_pose
from cell.devices import ur5e
from sim.addresses import loopback

DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT = 29999, 30004, 30003   # fixed by UR and ur_rtde
TICK_S = 0.002                                                 # e-Series: 500 Hz
CONTROLLER_VERSION = (5, 11, 1, 108318)
POLYSCOPE = "URSoftware 5.11.1.108318 (Mar 22 2021)"
SERIAL_NUMBER = "20205500000"
JOINT_SPEED_MAX = np.radians([180.0, 180.0, 180.0, 180.0, 180.0, 180.0])  # UR5e, rad/s
FAULTS = ("protective-stop", "emergency-stop", "silent", "drop")
# --mute STEP: a controller that goes silent at one step of a client's connection (the connection
# stays open): after answering RTDE's protocol version request, at RTDE's start (the recipes set
# up, no state ever streamed), after the dashboard's greeting, or taking programs on the script
# port without ever starting them
MUTE_STEPS = ("rtde-version", "rtde-start", "dashboard", "script")
MAX_BACKLOG = 1 << 22                  # bytes queued for a client that does not read: drop it

# RTDE message types (RTDE guide)
REQUEST_PROTOCOL_VERSION, GET_URCONTROL_VERSION, TEXT_MESSAGE = ord("V"), ord("v"), ord("M")
DATA_PACKAGE, SETUP_OUTPUTS, SETUP_INPUTS = ord("U"), ord("O"), ord("I")
START, PAUSE = ord("S"), ord("P")

# runtime_state, robot_mode, safety_mode and the status bits (RTDE guide; ur_rtde's enums)
STOPPED, PLAYING = 1, 2
POWER_OFF, RUNNING = 3, 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
POWER_ON_BIT, PROGRAM_RUNNING_BIT = 1 << 0, 1 << 1                      # robot_status_bits
NORMAL_MODE_BIT, PROTECTIVE_STOPPED_BIT = 1 << 0, 1 << 2                # safety_status_bits
ROBOT_EMERGENCY_STOPPED_BIT, EMERGENCY_STOPPED_BIT, STOPPED_DUE_TO_SAFETY_BIT = 1 << 6, 1 << 7, 1 << 10
JOINT_RUNNING_MODE = 253

# the control script's command codes (ur_rtde RTDE::RobotCommand::Type) and register values
MOVEJ, MOVEL, SET_TCP, PROTECTIVE_STOP, STOPL, STOPJ = 1, 3, 29, 31, 33, 34
IS_POSE_WITHIN_SAFETY_LIMITS, IS_STEADY = 36, 47
STOP_SCRIPT = 255
REALTIME_COMMANDS = {6, 9, 10, 11, 24, 25, 26, 27, 38, 58}   # the script answers them "ready", not "done"
READY_FOR_COMMAND, DONE_WITH_COMMAND = 1, 2

# RTDE types: struct format of one value
FORMATS = {"BOOL": "?", "UINT8": "B", "INT32": "i", "UINT32": "I", "UINT64": "Q", "DOUBLE": "d",
           "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}
_TYPE_GROUPS = {
    "VECTOR6D": "target_q target_qd target_qdd target_current target_moment actual_q actual_qd "
                "actual_qdd actual_current actual_moment joint_control_output actual_TCP_pose "
                "actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed joint_temperatures "
                "actual_joint_voltage ft_raw_wrench payload_inertia external_force_torque "
                "actual_current_window",
    "VECTOR3D": "actual_tool_accelerometer elbow_position elbow_velocity payload_cog",
    "VECTOR6INT32": "joint_mode",
    "DOUBLE": "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum "
              "actual_main_voltage actual_robot_voltage actual_robot_current standard_analog_input0 "
              "standard_analog_input1 standard_analog_output0 standard_analog_output1 io_current "
              "tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature "
              "tcp_force_scalar payload joint_position_deviation_ratio collision_detection_ratio "
              "speed_slider_fraction standard_analog_output_0 standard_analog_output_1",
    "INT32": "robot_mode safety_mode safety_status tool_output_voltage time_scale_source",
    "UINT32": "runtime_state robot_status_bits safety_status_bits analog_io_types tool_mode "
              "tool_analog_input_types script_control_line speed_slider_mask euromap67_input_bits "
              "euromap67_output_bits output_bit_registers0_to_31 output_bit_registers32_to_63 "
              "input_bit_registers0_to_31 input_bit_registers32_to_63",
    "UINT64": "actual_digital_input_bits actual_digital_output_bits",
    "UINT8": "tool_output_mode tool_digital_output0_mode tool_digital_output1_mode "
             "standard_digital_output_mask standard_digital_output configurable_digital_output_mask "
             "configurable_digital_output tool_digital_output_mask tool_digital_output "
             "standard_analog_output_mask standard_analog_output_type",
}
TYPES = {name: kind for kind, names in _TYPE_GROUPS.items() for name in names.split()}
REGISTER = re.compile(r"(?:input|output)_(int|double|bit)_register_(\d+)$")


def rtde_type(name: str) -> str:
    """The RTDE guide's type of a variable, or NOT_FOUND."""
    register = REGISTER.match(name)
    if register:
        return {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}[register.group(1)]
    return TYPES.get(name, "NOT_FOUND")


def message(kind: int, payload: bytes = b"") -> bytes:
    """An RTDE message: uint16 size counting the 3 header bytes, uint8 type, payload."""
    return struct.pack(">HB", len(payload) + 3, kind) + payload


class Profile:
    """A path of `length` followed with a trapezoidal profile of the commanded speed and
    acceleration started at t0; `brake` replaces the profile by a stop at a deceleration from
    wherever it is."""

    def __init__(self, length: float, speed: float, acceleration: float, t0: float) -> None:
        self.length, self.t0 = length, t0
        v, a = speed, acceleration
        t_ramp = v / a
        if v * t_ramp >= self.length:                  # triangular: never reaches the speed
            t_ramp = np.sqrt(self.length / a)
            self.phases = [(t_ramp, a), (t_ramp, -a)]  # (duration, acceleration)
        else:
            self.phases = [(t_ramp, a), (self.length / v - t_ramp, 0.0), (t_ramp, -a)]
        self.s0, self.v0, self.end = 0.0, 0.0, self.length

    def state(self, t: float) -> tuple[float, float, bool]:
        """(path position s, speed ds/dt, finished) at time t."""
        s, v, tau = self.s0, self.v0, t - self.t0
        for duration, a in self.phases:
            step = min(max(tau, 0.0), duration)
            s, v = s + v * step + 0.5 * a * step * step, v + a * step
            tau -= duration
            if tau < 0:
                return min(s, self.end), max(v, 0.0), False
        return self.end, 0.0, True

    def brake(self, deceleration: float, t: float) -> None:
        s, v, _ = self.state(t)
        self.s0, self.v0, self.t0 = s, v, t
        if deceleration > 0:
            self.phases = [(v / deceleration, -deceleration)]
            self.end = min(self.length, s + v * v / (2 * deceleration))
        else:
            self.phases, self.end = [], s


class Line(Profile):
    """A moveL: the straight TCP line from T0 to T1 (base frame), its length in metres (+ 1 m per
    rad of rotation)."""

    def __init__(self, T0: np.ndarray, T1: np.ndarray, speed: float, acceleration: float, t0: float) -> None:
        self.T0, self.T1 = T0, T1
        self.dp = T1[:3, 3] - T0[:3, 3]
        self.w = Rotation.from_matrix(T0[:3, :3].T @ T1[:3, :3]).as_rotvec()
        super().__init__(float(max(np.linalg.norm(self.dp), np.linalg.norm(self.w))), speed, acceleration, t0)

    def velocity(self, ds_dt: float) -> np.ndarray:
        """The TCP's [vx, vy, vz, wx, wy, wz] (base frame) at path speed ds/dt."""
        if self.length == 0:
            return np.zeros(6)
        return np.concatenate([self.dp, self.T0[:3, :3] @ self.w]) * ds_dt / self.length

    def pose(self, s: float) -> np.ndarray:
        f = s / self.length if self.length > 0 else 1.0
        T = np.eye(4)
        T[:3, :3] = self.T0[:3, :3] @ Rotation.from_rotvec(self.w * f).as_matrix()
        T[:3, 3] = self.T0[:3, 3] + self.dp * f
        return T


class Joints(Profile):
    """A moveJ: every joint linear from q0 to q1, the leading joint's angle [rad] the path's
    length (the others scaled to it: all start and stop together)."""

    def __init__(self, q0: np.ndarray, q1: np.ndarray, speed: float, acceleration: float, t0: float) -> None:
        self.q0, self.dq = q0, q1 - q0
        super().__init__(float(np.abs(self.dq).max()), speed, acceleration, t0)

    def joints(self, s: float) -> np.ndarray:
        return self.q0 + self.dq * (s / self.length if self.length > 0 else 1.0)


class Arm:
    """The UR5e: joints, the TCP offset (setTcp) and the line or joint move it follows, if any."""

    def __init__(self, joints: ArrayLike = ur5e.HOME_JOINTS) -> None:
        self.q = np.array(joints, float)
        self.qd, self.tcp_speed = np.zeros(6), np.zeros(6)
        self.T_flange_tcp = np.eye(4)
        self.line: Line | Joints | None = None
        self.t = time.monotonic()                # of the last step
        self._pose: tuple[bytes, np.ndarray] | None = None   # (key, wire pose): the stream's every tick

    def tcp(self) -> np.ndarray:
        return ur5e.forward(self.q) @ self.T_flange_tcp

    def tcp_pose(self) -> np.ndarray:
        """getActualTCPPose's [x, y, z, rx, ry, rz], computed again only when the arm moved."""
        key = self.q.tobytes() + self.T_flange_tcp.tobytes()
        if self._pose is None or self._pose[0] != key:
            self._pose = (key, to_ur_pose(self.tcp()))
        return self._pose[1]

    def reachable(self, T_base_tcp: np.ndarray) -> bool:
        try:
            ur5e.inverse(T_base_tcp @ np.linalg.inv(self.T_flange_tcp), self.q)
            return True
        except ur5e.Unreachable:
            return False

    def move_line(self, pose: ArrayLike, speed: float, acceleration: float, now: float) -> None:
        self.line = Line(self.tcp(), from_ur_pose(pose), speed, acceleration, now)

    def move_joints(self, q: ArrayLike, speed: float, acceleration: float, now: float) -> None:
        self.line = Joints(self.q.copy(), np.asarray(q, float), speed, acceleration, now)

    def halt(self) -> None:
        self.line, self.qd, self.tcp_speed = None, np.zeros(6), np.zeros(6)

    def step(self, now: float) -> str | None:
        """Follow the line to `now`; returns an error saying why the arm stopped, or None."""
        dt, self.t = now - self.t, now
        if self.line is None:
            self.qd, self.tcp_speed = np.zeros(6), np.zeros(6)
            return None
        s, ds_dt, finished = self.line.state(now)
        if isinstance(self.line, Joints):
            q = self.line.joints(s)
            T0, T1 = self.tcp(), ur5e.forward(q) @ self.T_flange_tcp
            turn = Rotation.from_matrix(T1[:3, :3] @ T0[:3, :3].T).as_rotvec()
            self.qd = (q - self.q) / max(dt, 1e-6)
            self.tcp_speed = np.concatenate([T1[:3, 3] - T0[:3, 3], turn]) / max(dt, 1e-6)
            self.q = q
            if finished:
                self.line = None
            return None
        T_base_flange = self.line.pose(s) @ np.linalg.inv(self.T_flange_tcp)
        try:
            q = ur5e.inverse(T_base_flange, self.q)
        except ur5e.Unreachable as why:
            self.halt()
            return f"movel: no inverse kinematics on the line: {why}"
        qd = (q - self.q) / max(dt, 1e-6)
        if np.any(np.abs(qd) > JOINT_SPEED_MAX):
            self.halt()
            return (f"movel: joint speeds {np.round(qd, 2).tolist()} rad/s over the limit "
                    "(a singularity or a configuration change on the line)")
        self.q, self.qd, self.tcp_speed = q, qd, self.line.velocity(ds_dt)
        if finished:
            self.line = None
        return None


class ControlScript:
    """ur_rtde's rtde_control program, its main loop and process_cmd interpreted on the registers
    instead of run as URScript. `blocked` is what a synchronous command waits for."""

    def __init__(self, text: str) -> None:
        offset = re.search(r"reg_offset_int\s*=\s*(\d+)", text)
        self.offset = int(offset.group(1)) if offset else 0
        self.executing = False
        self.blocked: str | None = None     # "move" or "stop": a sync movel / stopl in progress
        self.async_move = self.async_stop = False
        self.write_count = self.operation_id = 0

    def started(self, c: Controller) -> None:
        self.async_progress(c, -1)
        self.write_int(c, 0, READY_FOR_COMMAND)

    # registers, with the script's register offset
    def read_int(self, c: Controller, i: int) -> int:
        return c.inputs.get(f"input_int_register_{i + self.offset}", 0)

    def read_double(self, c: Controller, i: int) -> float:
        return c.inputs.get(f"input_double_register_{i + self.offset}", 0.0)

    def read_pose(self, c: Controller) -> list[float]:
        return [self.read_double(c, i) for i in range(6)]

    def write_int(self, c: Controller, i: int, value: int) -> None:
        c.outputs[f"output_int_register_{i + self.offset}"] = int(value)

    def async_progress(self, c: Controller, value: int) -> None:
        """write_async_progress_register: bit 15 running + 15-bit progress, bits 16-23 a write
        count, bits 24-30 the operation id (a new one when an operation starts, value 0)."""
        self.write_count = (self.write_count + 1) % 128
        if value == 0:
            self.operation_id = (self.operation_id + 1) % 128
        word = self.write_count << 16 | self.operation_id << 24
        if value >= 0:
            word += min(value, 32767) + 32768
        self.write_int(c, 2, word)

    def tick(self, c: Controller, now: float) -> None:
        """One pass of the script's `while keep_running:` loop (it syncs every tick)."""
        if self.async_move and c.arm.line is None:
            self.async_move = False
            self.async_progress(c, -1)
        if self.async_stop and c.arm.line is None:
            self.async_stop = False
            self.async_progress(c, -1)
        if self.blocked:
            if c.arm.line is not None:
                return
            self.blocked = None
            self.write_int(c, 0, DONE_WITH_COMMAND)
            self.executing = True
            return
        command = self.read_int(c, 0)
        if command == 0:
            self.executing = False
            self.write_int(c, 0, READY_FOR_COMMAND)
        elif not self.executing:
            self.executing = True
            self.process(c, command, now)

    def process(self, c: Controller, command: int, now: float) -> None:
        c.trace(f"command {command} async {self.read_int(c, 1)} "
                f"doubles {[round(self.read_double(c, i), 6) for i in range(8)]}")
        if command in (MOVEL, MOVEJ):
            target = self.read_pose(c)               # a pose, or moveJ's six joints [rad]
            speed, acceleration = self.read_double(c, 6), self.read_double(c, 7)
            name = "movel" if command == MOVEL else "movej"
            if not (speed > 0 and acceleration > 0):
                return c.script_error(f"{name}: speed {speed} and acceleration {acceleration} must be > 0")
            self.stop_async_move(c)
            (c.arm.move_line if command == MOVEL else c.arm.move_joints)(target, speed, acceleration, now)
            c.move_started(now)
            if self.read_int(c, 1) == 1:
                self.async_move = True
                self.async_progress(c, 0)
            else:
                self.blocked = "move"
                return
        elif command in (STOPL, STOPJ):
            deceleration, asynchronous = self.read_double(c, 0), self.read_int(c, 1)
            if self.async_stop:                    # restart a running async stop with these values
                self.async_stop = False
                self.async_progress(c, -1)
            self.stop_async_move(c)
            if c.arm.line is not None:
                c.arm.line.brake(deceleration, now)
            if asynchronous == 1:
                self.async_stop = True
                self.async_progress(c, 0)
            else:
                self.blocked = "stop"
                return
        elif command == SET_TCP:
            c.arm.T_flange_tcp = from_ur_pose(self.read_pose(c))
        elif command == IS_POSE_WITHIN_SAFETY_LIMITS:
            self.write_int(c, 1, int(c.arm.reachable(from_ur_pose(self.read_pose(c)))))
        elif command == IS_STEADY:
            self.write_int(c, 1, int(c.arm.line is None))
        elif command == PROTECTIVE_STOP:
            return c.fault("protective-stop", "triggerProtectiveStop")
        elif command == STOP_SCRIPT:
            return c.stop_program("stopScript")
        else:
            what = "a realtime command" if command in REALTIME_COMMANDS else "command"
            return c.script_error(f"{what} {command} is not emulated")
        self.write_int(c, 0, DONE_WITH_COMMAND)

    def stop_async_move(self, c: Controller) -> None:
        """Kill the move thread: its operation ends here (the arm brakes from where it is)."""
        if self.async_move:
            self.async_move = False
            self.async_progress(c, -1)


class Controller:
    """The controller's state: arm, program, safety, registers, and the armed fault."""

    def __init__(self, fault: str | None = None, fault_on_move: int = 1, fault_after_s: float = 0.0,
                 verbose: bool = False, log: TextIO = sys.stderr, mute: str | None = None) -> None:
        self.start = time.monotonic()
        self.log, self.verbose, self.mute = log, verbose, mute
        self.reset()
        # (kind, move, after [s]): a fault to fire that long after that move starts
        self.armed: tuple[str, int, float] | None = (fault, fault_on_move, fault_after_s) if fault else None

    def reset(self) -> None:
        """As after power-up: home joints, no TCP offset, no program, no fault armed."""
        self.arm = Arm()
        self.program: ControlScript | None = None
        self.inputs: dict[str, Any] = {}
        self.outputs: dict[str, Any] = {}
        self.robot_mode, self.safety_mode = RUNNING, SAFETY_NORMAL
        self.safety_bits = NORMAL_MODE_BIT
        self.moves = 0
        self.armed = None
        self.fault_at: tuple[float, str] | None = None       # (time, kind): a fault that fires then
        self.pending: list[str] = []                         # faults the server carries out (silent, drop)

    def say(self, text: str) -> None:
        print(f"ur_controller {time.monotonic() - self.start:7.3f} s: {text}", file=self.log, flush=True)

    def trace(self, text: str) -> None:
        if self.verbose:
            self.say(text)

    @property
    def runtime_state(self) -> int:
        return PLAYING if self.program else STOPPED

    def run_program(self, text: str) -> None:
        if not re.search(r"^def rtde_control\(\):", text, re.M):
            self.say("a program other than ur_rtde's rtde_control arrived on the script port: not run")
            return
        if self.safety_bits != NORMAL_MODE_BIT or self.robot_mode != RUNNING:
            self.say("program not started: the robot is stopped by its safety system")
            return
        self.arm.halt()
        self.program = ControlScript(text)
        self.program.started(self)
        self.say("rtde_control program started")

    def stop_program(self, why: str) -> None:
        if self.program:
            self.program = None
            self.arm.halt()
            self.say(f"program stopped ({why})")

    def script_error(self, why: str) -> None:
        self.say(f"runtime error: {why}")
        self.stop_program("runtime error")

    def move_started(self, now: float) -> None:
        self.moves += 1
        if self.armed and self.armed[1] == self.moves:
            kind, _, after_s = self.armed
            self.fault_at, self.armed = (now + after_s, kind), None

    def fault(self, kind: str, why: str = "injected") -> None:
        self.say(f"fault: {kind} ({why})")
        if kind == "protective-stop":
            self.safety_mode = SAFETY_PROTECTIVE_STOP
            self.safety_bits = PROTECTIVE_STOPPED_BIT | STOPPED_DUE_TO_SAFETY_BIT
        elif kind == "emergency-stop":
            self.safety_mode, self.robot_mode = SAFETY_ROBOT_EMERGENCY_STOP, POWER_OFF
            self.safety_bits = ROBOT_EMERGENCY_STOPPED_BIT | EMERGENCY_STOPPED_BIT | STOPPED_DUE_TO_SAFETY_BIT
        else:
            self.pending.append(kind)              # silent, drop: the server's to carry out
            return
        self.arm.halt()
        self.stop_program(kind)

    def unlock_protective_stop(self) -> bool:
        if self.safety_mode != SAFETY_PROTECTIVE_STOP:
            return False
        self.safety_mode, self.safety_bits = SAFETY_NORMAL, NORMAL_MODE_BIT
        return True

    def tick(self, now: float) -> None:
        if self.fault_at and now >= self.fault_at[0]:
            kind, self.fault_at = self.fault_at[1], None
            self.fault(kind, "armed")
        error = self.arm.step(now)
        if error:
            self.script_error(error)
        if self.program:
            self.program.tick(self, now)

    def values(self) -> dict[str, Any]:
        """The state as RTDE variables (names the guide defines; others are zero)."""
        pose = self.arm.tcp_pose()
        running = self.program is not None
        return {
            "timestamp": time.monotonic() - self.start,
            "target_q": self.arm.q, "actual_q": self.arm.q,
            "target_qd": self.arm.qd, "actual_qd": self.arm.qd,
            "actual_TCP_pose": pose, "target_TCP_pose": pose,
            "actual_TCP_speed": self.arm.tcp_speed, "target_TCP_speed": self.arm.tcp_speed,
            "joint_mode": [JOINT_RUNNING_MODE] * 6, "joint_temperatures": [30.0] * 6,
            "robot_mode": self.robot_mode, "safety_mode": self.safety_mode, "safety_status": self.safety_mode,
            "runtime_state": self.runtime_state,
            "robot_status_bits": (POWER_ON_BIT if self.robot_mode == RUNNING else 0)
                                 | (PROGRAM_RUNNING_BIT if running else 0),
            "safety_status_bits": self.safety_bits,
            "speed_scaling": 1.0, "target_speed_fraction": 1.0,
            "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0,
            "actual_execution_time": 0.1,
            **self.outputs, **{k: v for k, v in self.inputs.items() if k.startswith("input_")},
        }


class Connection:
    """A client socket with its input buffer and unsent output."""

    def __init__(self, sock: socket.socket, kind: str) -> None:
        self.sock, self.kind = sock, kind
        self.inbox, self.outbox = bytearray(), bytearray()

    def send(self, data: bytes) -> None:
        self.outbox += data

    def receive(self, c: Controller) -> bool:
        """Act on what arrived in the inbox; False when the client is to be dropped."""
        raise NotImplementedError

    def flush(self) -> bool:
        """Send what the socket takes; False when the client is gone or does not read."""
        try:
            while self.outbox:
                sent = self.sock.send(self.outbox)
                del self.outbox[:sent]
        except BlockingIOError:
            pass
        except OSError:
            return False
        return len(self.outbox) < MAX_BACKLOG


class Rtde(Connection):
    """One RTDE client: its output recipe (streamed once started) and its input recipes."""

    def __init__(self, sock: socket.socket) -> None:
        super().__init__(sock, "rtde")
        # ([(name, width)], format, period_s) of the output recipe
        self.output: tuple[list[tuple[str, int]], struct.Struct, float] | None = None
        self.inputs: list[list[tuple[str, str | None]]] = []     # per recipe id - 1: [(name, format)]
        self.started, self.next_send = False, 0.0

    def handle(self, c: Controller, kind: int, payload: bytes) -> None:
        if (c.mute == "rtde-version" and kind != REQUEST_PROTOCOL_VERSION) or (c.mute == "rtde-start"
                                                                             and kind == START):
            return c.trace(f"muted at {c.mute}: RTDE message {chr(kind)!r} not answered")
        if kind == REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 0
            self.send(message(kind, bytes([version == 2])))
        elif kind == GET_URCONTROL_VERSION:
            self.send(message(kind, struct.pack(">IIII", *CONTROLLER_VERSION)))
        elif kind == SETUP_OUTPUTS:
            frequency = struct.unpack(">d", payload[:8])[0]
            names = [n for n in payload[8:].decode().split(",") if n]
            types = [rtde_type(n) for n in names]
            c.trace(f"output recipe at {frequency:g} Hz: {len(names)} variables: {','.join(names)}")
            if "NOT_FOUND" in types:
                c.say(f"output recipe asks for unknown variables: "
                      f"{[n for n, t in zip(names, types) if t == 'NOT_FOUND']}")
            else:
                recipe_format = ">B" + "".join(FORMATS[t] for t in types)
                widths = [int(FORMATS[t][0]) if FORMATS[t][0].isdigit() else 1 for t in types]
                self.output = (list(zip(names, widths)), struct.Struct(recipe_format),
                               1.0 / min(max(frequency, 1.0), 500.0))
            self.send(message(kind, bytes([1]) + ",".join(types).encode()))
        elif kind == SETUP_INPUTS:
            names = [n for n in payload.decode().split(",") if n]
            types = [rtde_type(n) for n in names]
            self.inputs.append([(n, FORMATS.get(t)) for n, t in zip(names, types)])
            c.trace(f"input recipe {len(self.inputs)}: {','.join(names)}")
            self.send(message(kind, bytes([len(self.inputs)]) + ",".join(types).encode()))
        elif kind == START:
            self.started = self.output is not None
            self.send(message(kind, bytes([self.started])))
        elif kind == PAUSE:
            self.started = False
            self.send(message(kind, bytes([1])))
        elif kind == DATA_PACKAGE and payload:
            recipe = payload[0]
            if not 1 <= recipe <= len(self.inputs):
                c.say(f"data package for unknown input recipe {recipe}")
                return
            offset = 1
            for name, fmt in self.inputs[recipe - 1]:
                if fmt is None or offset + struct.calcsize(">" + fmt) > len(payload):
                    break
                value = struct.unpack_from(">" + fmt, payload, offset)
                c.inputs[name] = value[0] if len(value) == 1 else list(value)
                offset += struct.calcsize(">" + fmt)

    def receive(self, c: Controller) -> bool:
        while len(self.inbox) >= 3:
            size, kind = struct.unpack_from(">HB", self.inbox)
            if size < 3:
                return False
            if len(self.inbox) < size:
                return True
            payload = bytes(self.inbox[3:size])
            del self.inbox[:size]
            self.handle(c, kind, payload)
        return True

    def stream(self, c: Controller, values: dict[str, Any], now: float) -> None:
        if not self.started or self.output is None or now < self.next_send:
            return
        fields, packer, period = self.output
        self.next_send = max(self.next_send + period, now - period)
        flat = [1]                                       # the output recipe's id
        for name, width in fields:
            value = values.get(name, 0)
            if width == 1:
                flat.append(value)
            else:
                flat.extend(np.broadcast_to(value, (width,)).tolist())
        self.send(message(DATA_PACKAGE, packer.pack(*flat)))


class Dashboard(Connection):
    """The dashboard server: the lines ur_rtde and an operator use, plus `emulator ...`."""

    def __init__(self, sock: socket.socket) -> None:
        super().__init__(sock, "dashboard")
        self.send(b"Connected: Universal Robots Dashboard Server\n")

    def receive(self, c: Controller) -> bool:
        if c.mute == "dashboard":
            self.inbox.clear()
            return True
        while b"\n" in self.inbox:
            line, _, rest = bytes(self.inbox).partition(b"\n")
            self.inbox[:] = rest
            answer = self.answer(c, line.decode(errors="replace").strip())
            if answer is None:
                return False
            self.send(answer.encode() + b"\n")
        return True

    def answer(self, c: Controller, command: str) -> str | None:
        lower = command.lower()
        safety = {SAFETY_NORMAL: "NORMAL", SAFETY_PROTECTIVE_STOP: "PROTECTIVE_STOP",
                  SAFETY_ROBOT_EMERGENCY_STOP: "ROBOT_EMERGENCY_STOP"}[c.safety_mode]
        if lower == "polyscopeversion":
            return POLYSCOPE
        if lower == "get serial number":
            return SERIAL_NUMBER
        if lower == "is in remote control":
            return "true"
        if lower == "robotmode":
            return "Robotmode: " + ("RUNNING" if c.robot_mode == RUNNING else "POWER_OFF")
        if lower in ("safetystatus", "safetymode"):
            return f"{'Safetystatus' if lower == 'safetystatus' else 'Safetymode'}: {safety}"
        if lower == "programstate":
            return ("PLAYING" if c.program else "STOPPED") + " rtde_control"
        if lower == "running":
            return f"Program running: {'true' if c.program else 'false'}"
        if lower == "stop":
            c.stop_program("dashboard stop")
            return "Stopped"
        if lower == "unlock protective stop":
            return "Protective stop releasing" if c.unlock_protective_stop() else \
                "Cannot unlock protective stop: the robot is not protective stopped"
        if lower == "close safety popup":
            return "closing safety popup"
        if lower == "quit":
            self.send(b"Disconnected\n")
            return None
        if lower.startswith("emulator"):
            return self.emulator(c, lower.split()[1:])
        return f"could not understand: '{command}'"

    def emulator(self, c: Controller, words: Sequence[str]) -> str:
        """`emulator fault KIND [on move N after S]`, `emulator reset`, `emulator status`."""
        if words == ["reset"]:
            c.reset()
            return "reset: home joints, no TCP offset, no program, no fault"
        if words[:1] == ["status"]:
            return (f"moves {c.moves} runtime_state {c.runtime_state} safety_mode {c.safety_mode} "
                    f"moving {c.arm.line is not None} q {np.round(c.arm.q, 6).tolist()}")
        if len(words) >= 2 and words[0] == "fault" and words[1] in FAULTS:
            if len(words) == 2:
                c.fault(words[1], "dashboard")
                return f"fault {words[1]} injected"
            if len(words) == 7 and words[2:4] == ["on", "move"] and words[5] == "after":
                c.armed = (words[1], int(words[4]), float(words[6]))
                return f"fault {words[1]} armed for move {words[4]} after {words[6]} s"
        return f"could not understand: 'emulator {' '.join(words)}' (emulator fault {'|'.join(FAULTS)} " \
               "[on move N after S], emulator reset, emulator status)"


class ScriptPort(Connection):
    """Port 30003: URScript programs arrive as text, one top-level `def ...:` ... `end`."""

    def __init__(self, sock: socket.socket) -> None:
        super().__init__(sock, "script")

    def receive(self, c: Controller) -> bool:
        if c.mute == "script":
            self.inbox.clear()
            return True
        text = self.inbox.decode(errors="replace")
        end = re.search(r"^end[ \t]*\r?\n", text, re.M)
        while end:
            program, text = text[:end.end()], text[end.end():]
            c.run_program(program)
            end = re.search(r"^end[ \t]*\r?\n", text, re.M)
        self.inbox[:] = text.encode()
        return True


class Server:
    """The three listening ports and their clients, ticked at 500 Hz on one thread; `run` ends
    after max_seconds or once `stopping` is set (a test running it in a thread of its own, now
    that ur_rtde runs in cell.devices.hw.ur_worker's process and no longer holds this one's GIL)."""

    KINDS = {RTDE_PORT: Rtde, DASHBOARD_PORT: Dashboard, SCRIPT_PORT: ScriptPort}

    def __init__(self, host: str, controller: Controller) -> None:
        self.controller = controller
        self.selector = selectors.DefaultSelector()
        self.listeners: list[socket.socket] = []
        self.clients: dict[socket.socket, Connection] = {}
        self.silent = self.stopping = False
        for port, what in ((DASHBOARD_PORT, "dashboard"), (RTDE_PORT, "RTDE"), (SCRIPT_PORT, "script")):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((host, port))
            except OSError as err:
                sock.close()
                self.close()
                busy = err.errno == errno.EADDRINUSE
                raise SystemExit(f"ur_controller: cannot listen on {host}:{port} ({what}): "
                                 f"{'address already in use - another UR emulator or controller on this host?' if busy else err}")
            sock.listen(8)
            sock.setblocking(False)
            self.selector.register(sock, selectors.EVENT_READ, port)
            self.listeners.append(sock)

    def close(self) -> None:
        for conn in list(self.clients.values()):
            self.drop(conn)
        for sock in self.listeners:
            self.selector.unregister(sock)
            sock.close()
        self.listeners = []

    def drop(self, conn: Connection) -> None:
        self.clients.pop(conn.sock, None)
        try:
            self.selector.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        conn.sock.close()

    def accept(self, listener: socket.socket, port: int) -> None:
        try:
            sock, _ = listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = self.KINDS[port](sock)
        self.clients[sock] = conn
        self.selector.register(sock, selectors.EVENT_READ, conn)

    def read(self, conn: Connection) -> None:
        try:
            data = conn.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            return self.drop(conn)
        conn.inbox += data
        if not conn.receive(self.controller):
            conn.flush()
            self.drop(conn)

    def carry_out(self, kind: str) -> None:
        if kind == "silent":
            for conn in self.clients.values():          # the dashboard's answer still goes out
                conn.flush()
            self.silent = True
        elif kind == "drop":
            self.close()

    def run(self, max_seconds: float) -> None:
        c = self.controller
        deadline = time.monotonic() + max_seconds
        next_tick = time.monotonic()
        while True:
            now = time.monotonic()
            if now >= deadline or self.stopping:
                break
            if self.silent:                         # answers nothing, streams nothing, until the end
                time.sleep(min(0.05, deadline - now))
                continue
            for key, _ in self.selector.select(max(0.0, next_tick - now)):
                if isinstance(key.data, int):
                    self.accept(cast(socket.socket, key.fileobj), key.data)     # a listener's port
                elif key.fileobj in self.clients:
                    self.read(key.data)
            now = time.monotonic()
            if now < next_tick:
                continue
            next_tick = max(next_tick + TICK_S, now - 0.1)
            c.tick(now)
            while c.pending:
                self.carry_out(c.pending.pop(0))
            if self.silent:
                continue
            values = c.values()
            for conn in list(self.clients.values()):
                if isinstance(conn, Rtde):
                    conn.stream(c, values, now)
                if not conn.flush():
                    c.say(f"{conn.kind} client not reading: dropped")
                    self.drop(conn)
        self.close()


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sim.ur_controller", description=__doc__.split("\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to listen on")
    parser.add_argument("--max-seconds", type=float, default=600.0, help="end after this long")
    parser.add_argument("--fault", choices=FAULTS, help="inject this fault during a move")
    parser.add_argument("--fault-on-move", type=int, default=1, help="the move (moveL or moveJ) it fires in (1 = first)")
    parser.add_argument("--fault-after-s", type=float, default=0.0, help="seconds after that move starts")
    parser.add_argument("--mute", choices=MUTE_STEPS, help="answer nothing from this step of a connection on")
    parser.add_argument("--verbose", action="store_true", help="log recipes and commands on stderr")
    args = parser.parse_args(argv)
    host = loopback(args.host, "ur_controller")
    controller = Controller(args.fault, args.fault_on_move, args.fault_after_s, args.verbose, mute=args.mute)
    server = Server(host, controller)
    print("READY", flush=True)
    try:
        server.run(args.max_seconds)
    except KeyboardInterrupt:
        server.close()


if __name__ == "__main__":
    main()
