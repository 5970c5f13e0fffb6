"""The real arm: a UR through ur_rtde's RTDEControlInterface / RTDEReceiveInterface, run in a
device worker process (cell.devices.hw.ur_worker).

ur_rtde's constructors have no read timeout and hold the GIL while they block, so neither a thread
with a join timeout nor a signal can bound them in this process. `probe` first walks the first
steps with our own socket timeouts - the RTDE protocol-version handshake on 30004, the dashboard
server's greeting on 29999, a connect to the script port 30003 - for a precise message; then the
constructors and every later call run in the worker, each within connect_timeout_s (a command:
plus its own braking time), and a worker that does not answer in time is killed: a DeviceFault
naming the step. So a controller that answers the probe and then goes silent at any later step
of the connection cannot hang the run either.

Once connected, a command to a controller that has died or gone silent waits up to 300 s for its
"done" (and the getters return the last state forever; checked against sim/ur_controller.py). So
every command is sent only to a controller whose state is still arriving, and moveL (moveJ) is sent
asynchronously and watched here on the receive side against `move_timeout_s`, one batched round
trip to the worker per poll.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.devices import ur5e
from cell.devices.interfaces import Arm
from cell.core.errors import DeviceFault
from cell.core.geometry import from_ur_pose, rotation_angle, to_ur_pose
from cell.devices.hw.ur_worker import Remote, Worker

if TYPE_CHECKING:
    from cell.core.frames import Frames
    from cell.task.device_config import ArmConfig

PORTS = (30004, 29999, 30003)            # RTDE, dashboard, script: fixed by UR and ur_rtde
RTDE_REQUEST_PROTOCOL_VERSION = 86        # 'V' (RTDE guide); payload: uint16 version
RTDE_PROTOCOL_VERSION = 2
STOP_DECELERATION_M_S2 = 1.0
STOP_DECELERATION_RAD_S2 = 1.0            # stopJ's, after a moveJ: its leading joint turns at most speed_m_s / 1 m
PLAYING = 2                               # runtime_state: the control script runs
ARRIVED_M, ARRIVED_RAD = 0.5e-3, 5e-3     # TCP vs target when a move has arrived ...
STEADY_M_S = 1e-3                         # ... and stands still
POLL_S = 0.005
TCP_SETTLE_S = 0.02                       # controller time after setTcp before the TCP is read back
# getRobotMode / getSafetyMode (RTDE guide's robot_mode and safety_mode; UR's dashboard names)
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
ROBOT_MODE_RUNNING, SAFETY_MODES_TO_MOVE = 7, (1, 2)     # a run needs these: powered, brakes off, normal
DASHBOARD_QUERIES = {"polyscope_version": "PolyscopeVersion", "serial_number": "get serial number",
                     "remote_control": "is in remote control"}
# what the watcher reads per poll, in one round trip to the worker
WATCHED = (("receive", "isConnected"), ("control", "isConnected"), ("receive", "getTimestamp"),
           ("receive", "isEmergencyStopped"), ("receive", "isProtectiveStopped"),
           ("receive", "getRuntimeState"), ("receive", "getActualTCPPose"), ("receive", "getActualTCPSpeed"))


@dataclass(frozen=True)
class Watched:
    """The controller's state as one poll of WATCHED read it."""

    receive_connected: bool
    control_connected: bool
    timestamp: float
    emergency_stopped: bool
    protective_stopped: bool
    runtime_state: int
    tcp_pose: list[float]
    tcp_speed: list[float]

    @property
    def connected(self) -> bool:
        return self.receive_connected and self.control_connected

    def why_stopped(self) -> str:
        if self.emergency_stopped:
            return " (emergency stop)"
        if self.protective_stopped:
            return " (protective stop)"
        if self.runtime_state != PLAYING:
            return " (the control script is not running)"
        return ""


def _receive(sock, n):
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("connection closed")
        data += chunk
    return data


def probe(host: str, timeout_s: float) -> None:
    """Raise DeviceFault unless the controller at `host` answers each step ur_rtde blocks on
    within timeout_s: RTDE handshake, dashboard greeting, script port connect."""
    rtde_port, dashboard_port, script_port = PORTS
    steps = [(rtde_port, "RTDE protocol version request"), (dashboard_port, "dashboard greeting"),
             (script_port, "script port connect")]
    for port, what in steps:
        try:
            with socket.create_connection((host, port), timeout=timeout_s) as sock:
                if port == rtde_port:
                    sock.sendall(struct.pack(">HBH", 5, RTDE_REQUEST_PROTOCOL_VERSION, RTDE_PROTOCOL_VERSION))
                    size, kind = struct.unpack(">HB", _receive(sock, 3))
                    accepted = _receive(sock, size - 3)[:1]
                    if kind != RTDE_REQUEST_PROTOCOL_VERSION or accepted != b"\x01":
                        raise ConnectionError(f"RTDE protocol version {RTDE_PROTOCOL_VERSION} refused")
                elif port == dashboard_port:
                    _receive(sock, 1)
        except (OSError, struct.error) as err:      # ConnectionError and TimeoutError too
            reason = "no answer" if isinstance(err, TimeoutError) else str(err) or type(err).__name__
            raise DeviceFault("arm", f"UR at {host}:{port}: {what} failed within {timeout_s} s: "
                                     f"{reason}") from None


def dashboard(host: str, timeout_s: float) -> dict[str, Any]:
    """The controller's identity and whether it is in Remote Control (which ur_rtde's control
    interface needs on a real robot), asked on the dashboard server: queries only. An answer
    other than true/false (a CB3 has no `is in remote control`) is None for unknown."""
    port = PORTS[1]
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            lines = sock.makefile("rb")
            lines.readline()                                            # the greeting
            answers: dict[str, Any] = {}
            for key, query in DASHBOARD_QUERIES.items():
                sock.sendall(query.encode() + b"\n")
                answers[key] = lines.readline().decode(errors="replace").strip()
    except OSError as err:
        reason = "no answer" if isinstance(err, TimeoutError) else str(err) or type(err).__name__
        raise DeviceFault("arm", f"UR at {host}:{port}: dashboard query failed within {timeout_s} s: "
                                 f"{reason}") from None
    answers["remote_control"] = {"true": True, "false": False}.get(answers["remote_control"].lower())
    return answers


class URArm(Arm):
    """moveL of the camera frame (the frames' hand-eye is set as the TCP, so poses on the wire are
    T_base_cam; read back with getActualTCPPose), and moveJ of the joints where a move changes the
    arm's configuration (Arm.move_joints). A controller whose state stops arriving for
    connect_timeout_s, a lost connection, a protective or emergency stop, a stopped control
    script, a move not done within move_timeout_s and a ur_rtde call that does not return in
    time are each a DeviceFault. `self._receive.<getter>()` and `self._control.<command>()` call
    the worker's interfaces.

    read_only (`cell hw-check`): the receive interface alone - no control script uploaded, no TCP
    set, nothing commanded - so only state() and the read-back work; a move is refused."""

    def __init__(self, config: ArmConfig, frames: Frames, read_only: bool = False) -> None:
        super().__init__(config, frames)
        host, timeout_s = config.host, config.connect_timeout_s
        if host is None:
            raise DeviceFault(self.device, "no address to connect to (cell.arm.host)")
        self._host = host
        probe(host, timeout_s)
        self._worker = Worker(self.device, f"UR at {host}")
        # stopL brakes from up to speed_m_s before it answers
        stop_s = timeout_s + config.speed_m_s / STOP_DECELERATION_M_S2
        self._receive = Remote(self._worker, "receive", timeout_s)
        control = Remote(self._worker, "control", timeout_s, {"stopL": stop_s, "stopJ": stop_s})
        self._joint_move = False          # the last move a moveJ: stop() sends stopJ
        self._control = None if read_only else control
        try:
            self._worker.call([("receive", "__init__", (host,))], timeout_s,
                              "RTDEReceiveInterface connect (RTDE setup and the first state)")
            if read_only:
                return
            self._worker.call([("control", "__init__", (host,))], timeout_s,
                              "RTDEControlInterface connect (RTDE setup, dashboard, control script "
                              "upload and start)")
            self._alive("setTcp")
            if not control.setTcp(list(to_ur_pose(frames.T_flange_cam))):
                raise RuntimeError("setTcp(hand-eye) refused")
            # the receive interface's own stream may lag the control's "done" by a few ticks:
            # read nothing back until a state well after it carries the new TCP
            self._alive("getActualTCPPose after setTcp", after_s=TCP_SETTLE_S)
        except RuntimeError as err:
            self._worker.kill()
            raise self._fault(str(err)) from None
        except DeviceFault:
            self._worker.kill()
            raise

    def _fault(self, reason):
        return DeviceFault(self.device, f"UR at {self.config.host}: {reason}")

    def _watched(self):
        """The controller's state, one round trip (Watched); read-only, no control interface to ask."""
        calls = [(name, method, ()) for name, method in WATCHED if self._control or name == "receive"]
        values = self._worker.call(calls, self.config.connect_timeout_s, "reading the state")
        if self._control is None:
            values.insert(1, True)
        return Watched(*values)

    def _alive(self, command, after_s=0.0):
        """Return once a new controller state arrived (a tick, 2 ms on an e-Series), or one stamped
        `after_s` later than the last seen; DeviceFault naming `command`, unsent, if the connection
        is lost or none comes in connect_timeout_s."""
        timeout_s = self.config.connect_timeout_s
        seen, deadline = self._watched().timestamp, time.monotonic() + timeout_s
        while True:
            state = self._watched()
            if state.timestamp > seen + after_s or (not after_s and state.timestamp != seen):
                return
            if not state.connected:
                raise self._fault(f"connection to the controller lost: {command} not sent")
            if time.monotonic() > deadline:
                raise self._fault(f"controller silent (no state for {timeout_s} s): {command} not sent")
            time.sleep(POLL_S / 5)

    def _unreachable(self, T_base_cam):
        """The controller's isPoseWithinSafetyLimits (its kinematics and safety limits): why it
        would refuse the pose, or None; moves nothing. Read-only (no control side): None."""
        if self._control is None:
            return None
        pose = list(to_ur_pose(T_base_cam))
        try:
            self._alive("isPoseWithinSafetyLimits")
            within = self._control.isPoseWithinSafetyLimits(pose)
        except RuntimeError as err:
            raise self._fault(str(err)) from None
        return None if within else (f"pose {np.round(pose, 4).tolist()} unreachable or outside the robot's "
                                    "safety limits (isPoseWithinSafetyLimits)")

    def _move_tcp(self, T_base_cam, speed_m_s):
        if self._control is None:
            raise self._fault("opened read-only (cell hw-check): moveL refused")
        pose = list(to_ur_pose(T_base_cam))
        a, timeout_s = self.config.acceleration_m_s2, self.config.move_timeout_s
        try:
            self._alive("isPoseWithinSafetyLimits")
            if not self._control.isPoseWithinSafetyLimits(pose):
                raise self._fault(f"pose {pose} unreachable or outside the robot's safety limits: "
                                  "refused before moving")
            self._alive("moveL")
            self._joint_move = False
            if not self._control.moveL(pose, speed_m_s, a, True):
                raise self._fault("moveL refused" + self._watched().why_stopped())
        except RuntimeError as err:
            raise self._fault(str(err)) from None
        self._watch(T_base_cam, time.monotonic() + timeout_s)

    def _move_joints(self, q, speed_rad_s, acceleration_rad_s2):
        """moveJ, asynchronous and watched as moveL is (the TCP at the target joints' pose)."""
        if self._control is None:
            raise self._fault("opened read-only (cell hw-check): moveJ refused")
        timeout_s = self.config.move_timeout_s
        try:
            self._alive("moveJ")
            self._joint_move = True
            if not self._control.moveJ([float(x) for x in q], speed_rad_s, acceleration_rad_s2, True):
                raise self._fault("moveJ refused" + self._watched().why_stopped())
        except RuntimeError as err:
            raise self._fault(str(err)) from None
        self._watch(self.frames.T_base_cam_from_flange(ur5e.forward(q)), time.monotonic() + timeout_s, "moveJ")

    def _watch(self, T_target, deadline, command="moveL"):
        """Poll the receive side until the TCP stands at T_target; DeviceFault on the way."""
        timeout_s = self.config.connect_timeout_s
        seen, seen_at = None, time.monotonic()
        while True:
            state, now = self._watched(), time.monotonic()
            if not state.connected:
                raise self._fault(f"connection to the controller lost during {command}: {self._stop_name} not sent")
            if state.timestamp != seen:
                seen, seen_at = state.timestamp, now
            elif now - seen_at > timeout_s:
                raise self._fault(f"controller silent during {command} (no state for {timeout_s} s): "
                                  f"{self._stop_name} not sent")
            why = state.why_stopped()
            if why:
                raise self._fault(f"{command} did not complete" + why)
            T = from_ur_pose(state.tcp_pose)
            error_m = np.linalg.norm(T[:3, 3] - T_target[:3, 3])
            if (error_m < ARRIVED_M and rotation_angle(T, T_target) < ARRIVED_RAD
                    and np.linalg.norm(state.tcp_speed[:3]) < STEADY_M_S):
                return
            if now > deadline:
                try:
                    self.stop()
                    stopped = "stopped"
                except DeviceFault as fault:
                    stopped = fault.reason.removeprefix(f"UR at {self.config.host}: ")
                raise self._fault(f"{command} not done within move_timeout_s {self.config.move_timeout_s} s "
                                  f"({error_m * 1e3:.1f} mm from the target): {stopped}")
            time.sleep(POLL_S)

    def _tcp_pose(self):
        connected, pose = self._worker.call([("receive", "isConnected", ()), ("receive", "getActualTCPPose", ())],
                                            self.config.connect_timeout_s, "getActualTCPPose")
        if not connected:
            raise self._fault("connection to the controller lost")
        return from_ur_pose(pose)

    def _joint_angles(self):
        connected, q = self._worker.call([("receive", "isConnected", ()), ("receive", "getActualQ", ())],
                                         self.config.connect_timeout_s, "getActualQ")
        if not connected:
            raise self._fault("connection to the controller lost")
        return np.asarray(q, float)

    def state(self) -> dict[str, Any]:
        """Robot and safety mode by name, the TCP pose ([x, y, z, rx, ry, rz] in m and rad, base
        frame, of the controller's active TCP: a run sets the hand-eye as TCP) and the joints [rad],
        read once a fresh state arrived; the dashboard's identity and Remote Control. `problems`:
        what keeps a run from moving."""
        try:
            self._alive("state read")
            robot_mode, safety_mode = self._receive.getRobotMode(), self._receive.getSafetyMode()
            state = {"host": self.config.host,
                     "robot_mode": ROBOT_MODES.get(robot_mode, f"unknown ({robot_mode})"),
                     "safety_mode": SAFETY_MODES.get(safety_mode, f"unknown ({safety_mode})"),
                     "tcp_pose": list(self._receive.getActualTCPPose()),
                     "joints_rad": list(self._receive.getActualQ())}
        except RuntimeError as err:
            raise self._fault(str(err)) from None
        state.update(dashboard(self._host, self.config.connect_timeout_s))
        problems = []
        if robot_mode != ROBOT_MODE_RUNNING:
            problems.append(f"robot mode {state['robot_mode']}: a run needs RUNNING (power on, brakes "
                            "released)")
        if safety_mode not in SAFETY_MODES_TO_MOVE:
            problems.append(f"safety mode {state['safety_mode']}: a run needs NORMAL or REDUCED")
        if state["remote_control"] is False:
            problems.append("not in Remote Control: set it on the teach pendant (ur_rtde's control "
                            "interface needs it)")
        return {**state, "problems": problems}

    def stop(self) -> None:
        """stopL (stopJ after a moveJ), sent only to a controller that still answers (to any other it would wait 300 s
        for the done): then the stop could not be commanded, and that is a DeviceFault. A
        read-only arm commanded nothing: nothing to stop."""
        if self._control is None:
            return
        self._alive(self._stop_name)
        try:
            if self._joint_move:
                self._control.stopJ(STOP_DECELERATION_RAD_S2)
            else:
                self._control.stopL(STOP_DECELERATION_M_S2)
        except RuntimeError as err:
            raise self._fault(f"{self._stop_name} failed: {err}") from None

    @property
    def _stop_name(self) -> str:
        """The stop the last move needs: stopJ after a moveJ, else stopL."""
        return "stopJ" if self._joint_move else "stopL"

    def close(self) -> None:
        """stopScript and disconnect both interfaces (within 2 connect timeouts + 1 s) when the
        controller still answers; a gone or silent one gets neither (stopScript would wait 300 s,
        ur_rtde's disconnect 5 s for its reconnecting threads): the worker is ended at once, which
        closes its sockets."""
        disconnects = []
        try:
            if self._control is None:               # read-only: no script, no control interface
                self._alive("disconnect")
            else:
                self._alive("stopScript")
                self._control.stopScript()
                disconnects.append(("control", "disconnect", ()))
            disconnects.append(("receive", "disconnect", ()))
        except (DeviceFault, RuntimeError):
            disconnects = []
        finally:
            self._worker.close(disconnects, 2 * self.config.connect_timeout_s + 1.0)
