"""The real arm: a UR through ur_rtde's RTDEControlInterface / RTDEReceiveInterface.

ur_rtde's constructors have no read timeout and hold the GIL while they block (checked: a
constructor in a worker thread froze the whole interpreter), so neither a thread with a join
timeout nor a signal can bound them. Instead `probe` first walks the same steps with our own
socket timeouts - the RTDE protocol-version handshake on 30004, the dashboard server's greeting
on 29999, a connect to the script port 30003 - and the constructors run only when all answered.
"""
import socket
import struct

import rtde_control
import rtde_receive

from cell.devices import Arm
from cell.errors import DeviceFault
from cell.geometry import from_ur_pose, to_ur_pose

PORTS = (30004, 29999, 30003)            # RTDE, dashboard, script: fixed by UR and ur_rtde
RTDE_REQUEST_PROTOCOL_VERSION = 86        # 'V' (RTDE guide); payload: uint16 version
RTDE_PROTOCOL_VERSION = 2
STOP_DECELERATION_M_S2 = 1.0


def _receive(sock, n):
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("connection closed")
        data += chunk
    return data


def probe(host, timeout_s):
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


class URArm(Arm):
    """moveL of the camera frame: the frames' hand-eye is set as the TCP, so poses on the wire are
    T_base_cam; read back with getActualTCPPose."""

    def __init__(self, config, frames):
        super().__init__(config, frames)
        host = config.host
        probe(host, config.connect_timeout_s)
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(host)
            self._control = rtde_control.RTDEControlInterface(host)
            if not self._control.setTcp(list(to_ur_pose(frames.T_flange_cam))):
                raise RuntimeError("setTcp(hand-eye) refused")
        except RuntimeError as err:
            raise DeviceFault(self.device, f"UR at {host}: {err}") from None

    def _move_tcp(self, T_base_cam, speed_m_s):
        pose = list(to_ur_pose(T_base_cam))
        host = self.config.host
        try:
            if not self._control.isPoseWithinSafetyLimits(pose):
                raise DeviceFault(self.device, f"UR at {host}: pose {pose} unreachable or outside the "
                                               "robot's safety limits: refused before moving")
            done = self._control.moveL(pose, speed_m_s, self.config.acceleration_m_s2)
            stopped = self._receive.isProtectiveStopped() or self._receive.isEmergencyStopped()
        except RuntimeError as err:
            raise DeviceFault(self.device, f"UR at {host}: {err}") from None
        if not done or stopped:
            raise DeviceFault(self.device, f"UR at {host}: moveL did not complete"
                                           + (" (protective or emergency stop)" if stopped else ""))

    def _tcp_pose(self):
        try:
            return from_ur_pose(self._receive.getActualTCPPose())
        except RuntimeError as err:
            raise DeviceFault(self.device, f"UR at {self.config.host}: {err}") from None

    def stop(self):
        try:
            self._control.stopL(STOP_DECELERATION_M_S2)
        except RuntimeError as err:
            raise DeviceFault(self.device, f"UR at {self.config.host}: stopL failed: {err}") from None

    def close(self):
        self._control.stopScript()
        self._control.disconnect()
        self._receive.disconnect()
