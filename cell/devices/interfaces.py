"""The devices the closed loop drives, as small interfaces with simulated (sim/) and real
(cell/devices/hw.py) implementations side by side, built in cell.run.backends from the task's settings
(cell.task.device_config, docs/devices.md).

Every motion is checked against the envelope and speed limits here, in the interface, before a
backend sees it, so no backend can skip the check. A refused or failed command raises
DeviceFault; state is read back from the device, never assumed.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.devices import ur5e
from cell.devices.rig import lamp_aim, lamp_position
from cell.devices.session import try_all

if TYPE_CHECKING:
    from cell.core.frames import Frames
    from cell.devices.operator import Operator
    from cell.task.device_config import ArmConfig
    from cell.task.types import LampRig as LampRigModel

__all__ = ["Arm", "LampRig", "Camera", "LightController", "Devices", "check_arm_motion", "check_joint_motion",
           "arm_accepts", "joint_speed", "trapezoid_s", "line_length", "line_commands", "joint_commands",
           "speaking_for"]

ENVELOPE_STEP_M = 0.001         # a joint move's camera and flange within this of the workspace's faces
SPEED_SAMPLE_RAD = 0.01         # joint_speed's samples: every joint together turns at most this between two
# a command of a split move cruises at most this share of what move_timeout_s leaves after its
# ramps: the run splits from the joints and pose it reads back, a hair from the plan's
CRUISE_SHARE = 0.99

# what device libraries raise: serial.SerialException and socket errors are OSErrors (an unplugged
# USB adapter, OSError 19 from a camera), ur_rtde raises RuntimeError
LIBRARY_ERRORS = (OSError, RuntimeError, EOFError)


@contextmanager
def speaking_for(device: Device | type[Device]) -> Iterator[None]:
    """Device calls inside this block: whatever the device's library raises becomes a DeviceFault
    naming the device (`device.device`; a device class while it opens), so the run stops safely and
    exits 3, never a traceback."""
    try:
        yield
    except LIBRARY_ERRORS as err:
        raise DeviceFault(device.device, f"{type(err).__name__}: {err}") from err


def check_arm_motion(config: ArmConfig, frames: Frames, T_cell_cam: ArrayLike, speed_m_s: float) -> None:
    """Refuse (DeviceFault) a camera pose whose camera or flange (by the frames' hand-eye) leaves
    the workspace box, a matrix that is not a rigid transform, or a speed above the limit -
    before anything moves."""
    T = np.asarray(T_cell_cam, float)
    R = T[:3, :3] if T.shape == (4, 4) else np.zeros((3, 3))
    if not _rigid(R[None])[0]:
        raise DeviceFault("arm", "camera pose is not a rigid transform: refused before moving")
    if not 0 < speed_m_s <= config.speed_m_s:
        raise DeviceFault("arm", f"speed {speed_m_s} m/s outside (0, {config.speed_m_s}] m/s: "
                                 "refused before moving")
    flange = frames.T_cell_flange(T)
    lo, hi = config.workspace_min_m, config.workspace_max_m
    for name, p in (("camera", T[:3, 3]), ("flange", flange[:3, 3])):
        if not _inside(config, p[None])[0]:
            raise DeviceFault("arm", f"{name} at {np.round(p, 3).tolist()} m is outside the workspace "
                                     f"{lo.tolist()}..{hi.tolist()} m: refused before moving")


def check_joint_motion(config: ArmConfig, frames: Frames, q_from: ArrayLike, q_to: ArrayLike) -> None:
    """Refuse (DeviceFault) a joint move (moveJ: every joint linear from q_from to q_to) whose
    target leaves the joint limits (ur5e.JOINT_LIMITS) or along which the camera's origin or the
    flange's leaves the workspace box, before anything moves. The path's poses are walked by
    conservative advancement: a point d inside the box, rho_i from joint i's axis, moves at most
    sum_i |dq_i| (rho_i + step) in a step that moves it at most `step` (its distance from an axis
    grows no faster than it moves), and each step keeps that at most max(d, ENVELOPE_STEP_M): the
    points stay inside, within ENVELOPE_STEP_M of the faces where they pass that close."""
    a, b = np.asarray(q_from, float), np.asarray(q_to, float)
    if b.shape != (6,) or not np.all(np.isfinite(b)) or np.any(np.abs(b) > ur5e.JOINT_LIMITS):
        raise DeviceFault("arm", f"joints {np.round(np.degrees(b), 1).tolist()} deg outside the UR5e's joint limits: "
                                 "refused before moving")
    lo, hi = config.workspace_min_m, config.workspace_max_m
    s = 0.0
    while True:
        q = a + s * (b - a)
        frames_q = ur5e.chain(frames.T_cell_base, q)
        flange = frames_q[6]
        points = np.array([(flange @ frames.T_flange_cam)[:3, 3], flange[:3, 3]])    # camera, flange
        for name, p in zip(("camera", "flange"), points):
            if not _inside(config, p[None])[0]:
                raise DeviceFault("arm", f"the joint move takes the {name} to {np.round(p, 3).tolist()} m, outside "
                                         f"the workspace {lo.tolist()}..{hi.tolist()} m: refused before moving")
        if s >= 1.0:
            return
        inset = np.maximum(np.minimum(points - lo, hi - points).min(axis=1), ENVELOPE_STEP_M)   # (2,)
        rel = points[:, None] - frames_q[None, :6, :3, 3]                                      # (2, 6, 3)
        axes = frames_q[None, :6, :3, 2]
        rho = np.linalg.norm(rel - np.sum(rel * axes, axis=-1, keepdims=True) * axes, axis=-1)  # (2, 6)
        sweep = np.sum(np.abs(b - a) * (rho + inset[:, None]), axis=1)                          # per unit s
        s = min(1.0, s + float(np.min(inset / np.maximum(sweep, 1e-300))))


def joint_speed(config: ArmConfig, frames: Frames, q_from: ArrayLike, q_to: ArrayLike) -> tuple[float, float]:
    """(the leading joint's speed [rad/s], its acceleration [rad/s^2]) of a moveJ from q_from to
    q_to that moves the camera's origin (the TCP) no faster than the arm's speed_m_s, a moveL's
    limit. Along q(s) = q_from + s dq the TCP moves |dp/ds| <= B(s) = sum_k |dq_k| rho_k(s), rho_k
    its distance from joint k's axis; rho_k changes no faster than the TCP moves relative to that
    axis, so |dB/ds| <= sum |dq| B and B between samples h apart is at most the nearer sample's
    times exp(sum |dq| h) (Gronwall). The leading joint at v moves s at v / max |dq|, so
    v = speed_m_s max |dq| / max B. The acceleration is scaled alike (the path's tangential part)."""
    a, dq = np.asarray(q_from, float), np.asarray(q_to, float) - np.asarray(q_from, float)
    total = float(np.abs(dq).sum())
    if total == 0.0:
        return config.speed_m_s, config.acceleration_m_s2
    n = max(1, int(np.ceil(total / SPEED_SAMPLE_RAD)))
    q = a + np.linspace(0.0, 1.0, n + 1)[:, None] * dq
    T = np.broadcast_to(np.eye(4), (n + 1, 4, 4))
    axes = []
    for k in range(6):
        axes.append((T[:, :3, 3], T[:, :3, 2]))      # joint k's axis: frame k's origin and z
        T = T @ ur5e.dh(k, q[:, k])
    tcp = (T @ frames.T_flange_cam)[:, :3, 3]
    rho = np.stack([np.linalg.norm(np.cross(tcp - o, z), axis=1) for o, z in axes], axis=1)   # (n + 1, 6)
    bound = float((rho @ np.abs(dq)).max()) * np.exp(total / n)
    scale = float(np.abs(dq).max()) / max(bound, 1e-300)
    return config.speed_m_s * scale, config.acceleration_m_s2 * scale


def trapezoid_s(distance: float, speed: float, acceleration: float) -> float:
    """How long a move of `distance` takes at `speed` and `acceleration` (a moveL's metres at
    m/s and m/s^2, a moveJ's leading joint in rad, rad/s, rad/s^2), the trapezoid law
    distance / speed + speed / acceleration: up to speed, cruise, down to rest. Exact where it
    reaches speed (distance >= speed^2 / acceleration); below, the triangle's
    2 sqrt(distance / acceleration), which this bounds from above."""
    return distance / speed + speed / acceleration


def line_length(T_from: ArrayLike, T_to: ArrayLike) -> float:
    """A moveL's length as the controller times it [m]: the larger of the position's travel and
    the orientation's turn, a turn counted as 1 m per rad (moveL's speed is rad/s where only the
    orientation changes). Frame-free: the same in the cell and the robot's base frame."""
    a, b = np.asarray(T_from, float), np.asarray(T_to, float)
    return max(float(np.linalg.norm(b[:3, 3] - a[:3, 3])), geometry.rotation_angle(a, b))


def line_commands(config: ArmConfig, T_from: np.ndarray, T_to: np.ndarray,
                  timeout_s: float | None) -> list[tuple[np.ndarray, float]]:
    """The moveLs (camera pose T_cell_cam, seconds) that make the straight move from T_from to
    T_to at the arm's speed_m_s and acceleration_m_s2, each within timeout_s (None: no limit):
    one where its trapezoid_s, D, is within; else the fewest n equal pieces of the same path
    (geometry.line_path: the same line, the same turn) whose time (D - r) / n + r (r = speed /
    acceleration, the ramps every command takes) keeps the cruise within CRUISE_SHARE of
    timeout_s - r (commands), n = ceil((D - r) / (CRUISE_SHARE (timeout_s - r)))."""
    v, a = config.speed_m_s, config.acceleration_m_s2
    whole = trapezoid_s(line_length(T_from, T_to), v, a)
    n = commands(whole, v / a, timeout_s)
    pose, _ = geometry.line_path(T_from, T_to)
    return [(pose(k / n) if k < n else np.asarray(T_to, float), (whole - v / a) / n + v / a) for k in range(1, n + 1)]


def joint_commands(config: ArmConfig, frames: Frames, q_from: ArrayLike, q_to: ArrayLike,
                   timeout_s: float | None) -> list[tuple[np.ndarray, float]]:
    """The moveJs (joints, seconds) that make the joint move from q_from to q_to (every joint
    linear), each within timeout_s (None: no limit): one where its time is within (trapezoid_s
    of the leading joint's turn at joint_speed's speed and acceleration); else equal pieces of
    the same line of joints, each timed at its own joint_speed (the camera's speed bound taken
    over the piece alone: its leading joint may turn faster than the whole's), from the whole's
    count (commands) up one at a time until each cruises within CRUISE_SHARE of timeout_s - r
    (r = speed_m_s / acceleration_m_s2: joint_speed scales both alike, so every piece's ramps)."""
    a, b = np.asarray(q_from, float), np.asarray(q_to, float)

    def timed(n: int) -> list[tuple[np.ndarray, float]]:
        ends = [a + k / n * (b - a) for k in range(n)] + [b]
        return [(q1, trapezoid_s(float(np.abs(q1 - q0).max()), *joint_speed(config, frames, q0, q1)))
                for q0, q1 in zip(ends, ends[1:])]

    whole = timed(1)
    ramp = config.speed_m_s / config.acceleration_m_s2
    n = commands(whole[0][1], ramp, timeout_s)
    if n == 1:
        return whole
    assert timeout_s is not None, "commands splits only under a limit"
    while True:
        pieces = timed(n)
        if all(t <= ramp + CRUISE_SHARE * (timeout_s - ramp) for _, t in pieces):
            return pieces
        n += 1


def commands(whole_s: float, ramp_s: float, timeout_s: float | None) -> int:
    """How many equal pieces a move of whole_s (trapezoid_s; ramp_s of it its ramps) is made in
    so that each command is within timeout_s: 1 where the whole is (or no limit, None), else
    ceil((whole_s - ramp_s) / (CRUISE_SHARE (timeout_s - ramp_s))). DeviceFault where the arm's
    ramps alone take timeout_s (cell.task.device_config refuses such a cell file; the lamp's
    moves have no ramps)."""
    if timeout_s is None or whole_s <= timeout_s:
        return 1
    if ramp_s >= timeout_s:
        raise DeviceFault("arm", f"every move's ramps take {ramp_s:.2f} s (speed_m_s / acceleration_m_s2), over "
                                 f"move_timeout_s {timeout_s} s: refused before moving")
    return int(np.ceil((whole_s - ramp_s) / (CRUISE_SHARE * (timeout_s - ramp_s))))


def arm_accepts(config: ArmConfig, frames: Frames, T_cell_cams: ArrayLike) -> np.ndarray:
    """(N,) whether check_arm_motion lets each of N camera poses (N, 4, 4) pass at the arm's own
    speed: its tests (rigid, camera and flange inside the workspace box) on all at once (a
    feature's view spheres ask thousands, cell.planning.viewpoints)."""
    T = np.asarray(T_cell_cams, float).reshape(-1, 4, 4)
    flange = frames.T_cell_flange(T)
    return _rigid(T[:, :3, :3]) & _inside(config, T[:, :3, 3]) & _inside(config, flange[:, :3, 3])


def _rigid(R: np.ndarray) -> np.ndarray:
    """(N,) of rotations (N, 3, 3): R^T R = I within np.allclose's tolerances (atol 1e-6) and
    det R > 0 (no mirror); NaN is not rigid."""
    gram = np.swapaxes(R, -1, -2) @ R
    close = np.abs(gram - np.eye(3)) <= 1e-6 + 1e-5 * np.eye(3)
    return np.all(close, axis=(-2, -1)) & (np.linalg.det(R) > 0)


def _inside(config: ArmConfig, p: np.ndarray) -> np.ndarray:
    """(N,) of points (N, 3): inside the workspace box, its faces included."""
    return ~(np.any(p < config.workspace_min_m, axis=-1) | np.any(p > config.workspace_max_m, axis=-1))


class Arm(ABC):
    """Carries the camera. Poses are T_cell_cam (camera frame in the cell frame); the robot base
    and the hand-eye are the task's frames (cell.core.frames.Frames)."""

    device = "arm"

    def __init__(self, config: ArmConfig, frames: Frames) -> None:
        self.config, self.frames = config, frames

    def move_camera(self, T_cell_cam: np.ndarray, speed_m_s: float | None = None) -> None:
        """Move so the camera frame is at T_cell_cam (one moveL); returns when there, raises
        DeviceFault on limits, a move longer than move_timeout_s (_within_timeout, the length
        from the pose read back), unreachable poses or a device error."""
        speed = self.config.speed_m_s if speed_m_s is None else speed_m_s
        check_arm_motion(self.config, self.frames, T_cell_cam, speed)
        if self.move_timeout_s is not None:
            length = line_length(self.camera_pose(), T_cell_cam)
            self._within_timeout(f"moveL of {length:.3f} m at {speed} m/s", length, speed,
                                 self.config.acceleration_m_s2)
        self._move_tcp(self.frames.T_base_cam(T_cell_cam), speed)

    def move_joints(self, q: ArrayLike) -> None:
        """moveJ: every joint linear to q [rad] (all starting and stopping together), the TCP no
        faster than a moveL at the arm's speed (joint_speed); returns when there, raises
        DeviceFault where check_joint_motion refuses it or it takes longer than move_timeout_s
        (_within_timeout; both before moving), where the arm cannot
        tell its joints (no path from them can be checked) or on a device error."""
        q_now = self.joint_angles()
        if q_now is None:
            raise DeviceFault(self.device, "a joint move needs the arm's joints read back, which this arm does not "
                                           "report: refused before moving")
        check_joint_motion(self.config, self.frames, q_now, q)
        speed, acceleration = joint_speed(self.config, self.frames, q_now, q)
        turn = float(np.abs(np.asarray(q, float) - q_now).max())
        self._within_timeout(f"moveJ of {np.degrees(turn):.1f} deg at {np.degrees(speed):.1f} deg/s", turn, speed,
                             acceleration)
        self._move_joints(np.asarray(q, float), speed, acceleration)

    @property
    def move_timeout_s(self) -> float | None:
        """The longest one command may take (cell.arm.move_timeout_s: the controller's watchdog
        stops a move not done by then), None: no limit."""
        return self.config.move_timeout_s

    def _within_timeout(self, move: str, distance: float, speed: float, acceleration: float) -> None:
        """Refuse `move` (in words) before moving where its trapezoid_s (the leading joint's for
        a moveJ) exceeds move_timeout_s: the run splits a longer move (line_commands,
        joint_commands), so this is the last guard, on every backend that keeps a limit."""
        limit, takes_s = self.move_timeout_s, trapezoid_s(distance, speed, acceleration)
        if limit is not None and takes_s > limit:
            raise DeviceFault(self.device, f"{move} takes {takes_s:.1f} s, over move_timeout_s {limit} s: "
                                           "refused before moving")

    def _move_joints(self, q, speed_rad_s, acceleration_rad_s2):
        """Move the joints to q (moveJ) at the leading joint's speed and acceleration."""
        raise DeviceFault(self.device, "this arm makes no joint move (moveJ): refused before moving")

    def refusal(self, T_cell_cam: np.ndarray, speed_m_s: float | None = None) -> str | None:
        """Why move_camera would refuse this pose (the envelope's check, then the backend's reach),
        or None; moves nothing. A backend without kinematics of its own finds out when it moves."""
        speed = self.config.speed_m_s if speed_m_s is None else speed_m_s
        try:
            check_arm_motion(self.config, self.frames, T_cell_cam, speed)
        except DeviceFault as refused:
            return refused.reason
        return self._unreachable(self.frames.T_base_cam(T_cell_cam))

    def _unreachable(self, T_base_cam):
        """Why the robot cannot put the camera at T_base_cam (None: it can, or cannot tell)."""
        return None

    def camera_pose(self) -> np.ndarray:
        """The actual T_cell_cam, read back from the device."""
        return self.frames.T_cell_cam_from_base(self._tcp_pose())

    def joint_angles(self) -> np.ndarray | None:
        """The arm's six joint angles [rad], read back from the device: which of the inverse
        kinematics' branches the arm stands on, where a path from here starts (cell.run.motion).
        None: a backend that cannot tell (the path then starts at the solution nearest home)."""
        q = self._joint_angles()
        return None if q is None else np.asarray(q, float)

    def _joint_angles(self):
        """The joints as the device reports them (None: it does not)."""
        return None

    @abstractmethod
    def _move_tcp(self, T_base_cam, speed_m_s):
        """Move the camera (the TCP) to T_base_cam in the robot's base frame."""

    @abstractmethod
    def _tcp_pose(self):
        """Actual T_base_cam."""

    @abstractmethod
    def stop(self) -> None:
        """Stop any motion now."""

    def state(self) -> dict[str, Any]:
        """What the arm reports, read back and JSON-ready (`cell hw-check`); reads only. A backend
        that knows more (modes, joints) says more; `problems`: what a run would stop on."""
        return {"camera_pose": self.camera_pose().tolist(), "problems": []}

    def close(self) -> None:
        """Release the connection (after stop)."""


def _check_range(device, name, value, bounds, degrees=False):
    lo, hi = bounds
    if not lo - 1e-9 <= value <= hi + 1e-9:
        show, unit = (np.degrees, "deg") if degrees else (float, "m")
        raise DeviceFault(device, f"{name} {show(value):.4g} {unit} outside the rig's range "
                                  f"[{show(lo):.4g}, {show(hi):.4g}] {unit}: refused before moving")


class LampRig(ABC):
    """Moves the lamp on its sphere around the pivot (task's lamp.rig): pan about the cell's z,
    tilt as elevation, radius by a servo or by the operator (radius_axis: manual)."""

    device = "pan-tilt"

    def __init__(self, rig: LampRigModel, operator: Operator) -> None:
        self.rig, self.operator = rig, operator
        self.manual_radius = rig.radius_axis == "manual"
        self._confirmed_radius = float("nan")      # manual radius: what the operator confirmed
        if self.manual_radius:
            operator.require(self.device, "the lamp radius (radius_axis: manual)")

    def move(self, pan_rad: float, tilt_rad: float, radius_m: float) -> None:
        """Move to the joints (checked against the rig's ranges first); a manual radius is then
        set by the operator."""
        pan = self._in_range(pan_rad, tilt_rad, radius_m)
        self._move_axes(pan, tilt_rad, None if self.manual_radius else radius_m)
        if self.manual_radius and not abs(radius_m - self._confirmed_radius) < 0.5e-3:
            self.operator.confirm(self.device, f"set the lamp radius (pivot to lamp) to "
                                               f"{radius_m * 1e3:.1f} mm")
            self._confirmed_radius = radius_m

    def _in_range(self, pan_rad, tilt_rad, radius_m):
        """The pan (+ 2 pi k) within the rig's range, or DeviceFault for joints outside it."""
        lo, hi = self.rig.pan_range_rad      # pan turns about z: pan + 2 pi k may be the one in range
        pan = next((p for p in pan_rad + 2 * np.pi * np.array([0.0, -1.0, 1.0])
                    if lo - 1e-9 <= p <= hi + 1e-9), pan_rad)
        _check_range(self.device, "pan", pan, self.rig.pan_range_rad, degrees=True)
        _check_range(self.device, "tilt", tilt_rad, self.rig.tilt_range_rad, degrees=True)
        _check_range(self.device, "radius", radius_m, self.rig.radius_range_m)
        return pan

    def target(self, pan_rad: float, tilt_rad: float, radius_m: float) -> tuple[float, float, float]:
        """The joints move(pan, tilt, radius) drives the axes to: the pan as the one in the rig's
        range (+ 2 pi k) as the axis holds it (`held`: a servo's goal wraps into one turn, +180 deg
        to -180 deg), so the lamp's route checked to these (cell.run.motion) is the one driven.
        DeviceFault for joints outside the ranges, as move."""
        pan = self.held(float(self._in_range(pan_rad, tilt_rad, radius_m)))
        return pan, float(tilt_rad), float(radius_m)

    def refusal(self, pan_rad: float, tilt_rad: float, radius_m: float) -> str | None:
        """Why move would refuse these joints (outside the rig's ranges), or None; moves nothing."""
        try:
            self._in_range(pan_rad, tilt_rad, radius_m)
        except DeviceFault as refused:
            return refused.reason
        return None

    def joints(self) -> tuple[float, float, float]:
        """(pan, tilt, radius) read back; a manual radius is the one the operator confirmed."""
        pan, tilt, radius = self._read_axes()
        return pan, tilt, self._confirmed_radius if self.manual_radius else radius

    def lamp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(position, aim) of the lamp in the cell frame from the read-back joints."""
        position = lamp_position(self.rig.pivot_m, *self.joints())
        return position, lamp_aim(self.rig.pivot_m, position)

    @abstractmethod
    def held(self, pan_rad: float) -> float:
        """The pan the axis drives to and reads back for a commanded pan, not quantized."""

    @property
    @abstractmethod
    def move_timeout_s(self) -> float | None:
        """The longest one move of the axes may take (None: no limit)."""

    @abstractmethod
    def move_s(self, start: tuple[float, float, float], end: tuple[float, float, float]) -> float:
        """How long the axes take from joints `start` to `end` (pan, tilt, radius) [s]."""

    @abstractmethod
    def _move_axes(self, pan_rad, tilt_rad, radius_m):
        """Drive the axes (radius_m is None when the operator sets it) and wait until there."""

    @abstractmethod
    def _read_axes(self):
        """(pan, tilt, radius or None) as the device reports them."""

    @abstractmethod
    def stop(self, fault_is_own: bool = False) -> None:
        """Hold position with torque on; torque off only if the fault is the servos' own."""

    def state(self) -> dict[str, Any]:
        """The read-back joints [rad, m], JSON-ready (`cell hw-check`); reads only. `problems`:
        what a run would stop on."""
        pan, tilt, radius = self.joints()
        return {"pan_rad": float(pan), "tilt_rad": float(tilt),
                "radius_m": None if radius is None or np.isnan(radius) else float(radius), "problems": []}

    def close(self) -> None:
        """Release the port (after stop)."""


class Camera(ABC):
    """Takes gray images (uint8 or uint16 by bit depth) with a set shutter time, f-number and
    focus distance."""

    device = "camera"

    def __init__(self, bit_depth: int) -> None:
        self.bit_depth = bit_depth
        self.shutter_s: float | None = None
        self.f_number: float | None = None
        self.focus_m: float | None = None

    @abstractmethod
    def set_exposure(self, shutter_s: float) -> float:
        """Set the shutter time; returns the one the camera actually uses [s]."""

    @abstractmethod
    def set_aperture(self, f_number: float) -> None:
        """Set the f-number (motorized, or by the operator)."""

    @abstractmethod
    def set_focus(self, focus_m: float) -> None:
        """Focus the lens at this distance along the optical axis [m] (motorized, or by the
        operator)."""

    @abstractmethod
    def capture(self) -> np.ndarray:
        """One gray image (H, W) as uint8 (bit depth <= 8) or uint16."""

    def state(self) -> dict[str, Any]:
        """What the camera reports, JSON-ready (`cell hw-check`); sets nothing. A backend that
        can ask the device (model, pixel format, exposure range) says more; `problems`: what a run
        would stop on."""
        return {"bit_depth": self.bit_depth, "shutter_s": self.shutter_s, "f_number": self.f_number,
                "focus_m": self.focus_m, "problems": []}

    def close(self) -> None:
        """Release the camera."""


class LightController(ABC):
    """A multi-channel LED lighting controller: channels 1..channels, each driven at a level, the
    fraction of its full output in [0, 1] (percent only on the wire). Levels outside [0, 1] and
    channels not configured are refused here, before the device sees them; every set is read
    back from the device."""

    device = "lighting"

    def __init__(self, channels: int, name: str) -> None:
        self.channels, self.name = channels, name       # name: the controller and its address

    def set_drive(self, channel: int, level: float) -> float:
        """Drive `channel` at `level` (0..1); returns the level read back from the device."""
        self._check_channel(channel)
        if not 0.0 <= level <= 1.0:
            raise DeviceFault(self.device, f"{self.name}: channel {channel} level {level:.4g} outside "
                                           "[0, 1]: refused before setting")
        return self._set_drive(channel, float(level))

    def drive(self, channel: int) -> float:
        """The level channel is driven at (0..1), read back from the device."""
        self._check_channel(channel)
        return self._read_drive(channel)

    def levels(self) -> dict[int, float]:
        """Every channel's level (0..1), read back from the device: {channel: level}."""
        return {channel: self.drive(channel) for channel in range(1, self.channels + 1)}

    def all_off(self) -> None:
        """Every channel to 0, each tried even if one fails; then the first failure is raised,
        naming the channels left as they were."""
        failures = {}
        for channel in range(1, self.channels + 1):
            try:
                self.set_drive(channel, 0.0)
            except DeviceFault as fault:
                failures[channel] = fault.reason
        if failures:
            first = next(iter(failures.values()))
            raise DeviceFault(self.device, f"{first}; channels {list(failures)} not turned off")

    def _check_channel(self, channel: int) -> None:
        if not (isinstance(channel, (int, np.integer)) and 1 <= channel <= self.channels):
            raise DeviceFault(self.device, f"{self.name}: channel {channel!r} is not one of the "
                                           f"configured 1..{self.channels}: refused before setting")

    @abstractmethod
    def _set_drive(self, channel: int, level: float) -> float:
        """Set the channel's level on the device and return it read back."""

    @abstractmethod
    def _read_drive(self, channel: int) -> float:
        """The channel's level as the device reports it."""

    def describe(self) -> dict:
        """What the controller is, JSON-ready: its name (and address) and channel count."""
        return {"name": self.name, "channels": self.channels}

    def state(self) -> dict:
        """Every channel's level read back, JSON-ready (`cell hw-check`); sets nothing. `problems`:
        what a run would stop on."""
        return {"levels": {str(c): level for c, level in self.levels().items()}, "problems": []}

    def close(self) -> None:
        """Release the connection (after all_off)."""


Device = Arm | LampRig | Camera | LightController     # one of the cell's devices (speaking_for names it)


@dataclass
class Devices:
    """The cell's three devices and, where the task has one, its lighting controller, with the
    safe stop every fault ends in (hardware notes)."""

    arm: Arm
    lamp: LampRig
    camera: Camera
    lights: LightController | None = None

    def safe_stop(self, fault: BaseException | None = None) -> list[str]:
        """Stop the arm, hold the servos (torque off only for their own fault), close the camera,
        turn every light channel off. Every step is tried; returns the messages of steps that
        failed, in turn."""
        lamp_faulted = isinstance(fault, DeviceFault) and fault.device == self.lamp.device
        steps = (self.arm.stop, lambda: self.lamp.stop(fault_is_own=lamp_faulted), self.camera.close)
        return try_all(steps + ((self.lights.all_off,) if self.lights else ()))

    def close(self) -> list[str]:
        """Release everything after a normal end (the lights turned off first)."""
        lights = (self.lights.all_off, self.lights.close) if self.lights else ()
        return try_all((self.arm.close, self.lamp.close, self.camera.close) + lights)

    def releases(self) -> tuple[Callable[[], object], ...]:
        """The connections to release after a safe stop: the arm's, the servos' and the lighting
        controller's."""
        return (self.arm.close, self.lamp.close) + ((self.lights.close,) if self.lights else ())
