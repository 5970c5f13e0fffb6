"""The devices the closed loop drives, as small interfaces with simulated (sim/) and real
(cell/hw/) implementations side by side (built in cell.backends), and the task's `cell.arm`,
`cell.pan_tilt` and `cell.camera` settings (docs/devices.md).

Every motion is checked against the envelope and speed limits here, in the interface, before a
backend sees it, so no backend can skip the check. A refused or failed command raises
DeviceFault; state is read back from the device, never assumed.
"""
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell import geometry
from cell.errors import DeviceFault, TaskError
from cell.schema import Integer, Number, Pair, Section, Spec, Text, Vector, show
from cell.rig import lamp_aim, lamp_position
from cell.session import try_all

__all__ = ["Arm", "LampRig", "Camera", "Devices", "ArmConfig", "PanTiltConfig", "CameraConfig",
           "DevicesConfig", "devices_from_config", "check_arm_motion"]

MAX_SPEED_M_S = 0.25            # ur_rtde's default moveL speed: a hard cap for an inspection cell
MAX_ACCELERATION_M_S2 = 1.2     # ur_rtde's default moveL acceleration
MAX_SERVO_SPEED_DEG_S = 90.0
DXL_BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
                  1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000)  # the SDK's list


# ---------------------------------------------------------------------------------------------
# Settings (task keys cell.arm, cell.pan_tilt, cell.camera; docs/devices.md)

# Validated settings in SI units; the defaults live in the schemas below (devices_from_config({})).
@dataclass(frozen=True)
class ArmConfig:
    host: str | None                        # robot address; required for --backend hw only
    connect_timeout_s: float
    T_cell_base: np.ndarray                 # 4x4: robot base frame in the cell
    T_flange_cam: np.ndarray                # 4x4 hand-eye: camera frame in the flange frame
    workspace_min_m: np.ndarray             # cell frame box the camera and flange must stay in
    workspace_max_m: np.ndarray
    speed_m_s: float                        # what moves use, and the most any move may use
    acceleration_m_s2: float


@dataclass(frozen=True)
class PanTiltConfig:
    port: str | None                        # serial device; required for --backend hw only
    baud: int
    pan_id: int
    tilt_id: int
    radius_id: int                          # used when lamp.rig.radius_axis is servo
    pan_offset_rad: float                   # joint angle at the servo's centre tick 2048
    tilt_offset_rad: float
    radius_ticks: tuple                     # radius servo ticks at radius_range_m's ends
    speed_rad_s: float
    move_timeout_s: float
    tolerance_ticks: int


@dataclass(frozen=True)
class CameraConfig:
    source: int | str                       # cv2.VideoCapture index or path
    exposure_unit_s: float                  # CAP_PROP_EXPOSURE unit (V4L2: 100 us)
    discard_frames: int                     # frames still exposed the old way after a change


@dataclass(frozen=True)
class DevicesConfig:
    task_file: Path
    arm: ArmConfig
    pan_tilt: PanTiltConfig
    camera: CameraConfig


class _OptionalText(Text):
    default = None


class _Source(Spec):
    """A camera index (integer >= 0) or a device / video / image-sequence path."""

    expected = "a camera index (integer >= 0) or a path"
    default = 0

    def read(self, file, path, raw, to_si):
        if isinstance(raw, int) and not isinstance(raw, bool) and raw >= 0:
            return raw
        if isinstance(raw, str) and raw.strip():
            return raw.strip()
        raise TaskError(file, path, repr(raw), self.expected)


def _default(spec, value):
    """spec with a default (in SI units, as the parser returns values)."""
    spec.default = value
    return spec


POSITIVE = dict(ok=lambda v: v > 0, expected="a positive number")
ANGLE = dict(ok=lambda v: abs(v) <= np.pi, expected="an angle within [-180, 180] deg")
# defaults: the example cell, a UR5e on the table beside the part, the camera 5 cm past the flange
ARM = Section({
    "host": _OptionalText(),
    "connect_timeout_s": Number(**POSITIVE, default=2.0),
    "base_position_m": _default(Vector(), (0.0, -0.40, 0.0)),
    "base_rpy_deg": _default(Vector(), (0.0, 0.0, 0.0)),
    "hand_eye_position_m": _default(Vector(), (0.0, 0.0, 0.05)),
    "hand_eye_rpy_deg": _default(Vector(), (0.0, 0.0, 0.0)),
    "workspace_min_m": _default(Vector(), (-0.60, -0.60, 0.10)),
    "workspace_max_m": _default(Vector(), (0.60, 0.60, 1.00)),
    "speed_m_s": Number(lambda v: 0 < v <= MAX_SPEED_M_S, f"a speed in (0, {MAX_SPEED_M_S}] m/s",
                        default=0.1),
    "acceleration_m_s2": Number(lambda v: 0 < v <= MAX_ACCELERATION_M_S2,
                                f"an acceleration in (0, {MAX_ACCELERATION_M_S2}] m/s^2", default=0.5),
}, required=False)

PAN_TILT = Section({
    "port": _OptionalText(),
    "baud": Integer(9600, 4_000_000, default=57600),
    "pan_id": Integer(0, 252, default=1),
    "tilt_id": Integer(0, 252, default=2),
    "radius_id": Integer(0, 252, default=3),
    "pan_offset_deg": Number(**ANGLE, default=0.0),
    "tilt_offset_deg": Number(**ANGLE, default=0.0),
    "radius_ticks": _default(Pair(lambda v: 0 <= v <= 4095 and v == int(v), "ticks in 0..4095",
                                  strict=True), (0, 4095)),
    "speed_deg_s": Number(lambda v: 0 < v <= MAX_SERVO_SPEED_DEG_S,
                          f"a speed in (0, {MAX_SERVO_SPEED_DEG_S}] deg/s", default=30.0),
    "move_timeout_s": Number(**POSITIVE, default=5.0),
    "tolerance_ticks": Integer(0, 100, default=3),
}, required=False)

CAMERA = Section({
    "source": _Source(),
    "exposure_unit_s": Number(**POSITIVE, default=1e-4),
    "discard_frames": Integer(0, 100, default=2),
}, required=False)


def _section(file, name, spec, raw):
    path = f"cell.{name}"
    return spec.absent(file, path) if raw is None else spec.read(file, path, raw, None)


def devices_from_config(task_cell_devices, task_file):
    """The task's raw `cell.arm`, `cell.pan_tilt`, `cell.camera` mappings -> DevicesConfig
    (SI units, defaults filled in). Raises TaskError naming the file and key path."""
    raw = dict(task_cell_devices or {})
    for name in raw:
        if name not in ("arm", "pan_tilt", "camera"):
            raise TaskError(task_file, f"cell.{name}", "an unknown device section",
                            "one of arm, pan_tilt, camera")
    a = {k: np.asarray(v, float) if isinstance(v, tuple) else v
         for k, v in _section(task_file, "arm", ARM, raw.get("arm")).items()}
    p = _section(task_file, "pan_tilt", PAN_TILT, raw.get("pan_tilt"))
    c = _section(task_file, "camera", CAMERA, raw.get("camera"))
    if not np.all(a["workspace_min_m"] < a["workspace_max_m"]):
        raise TaskError(task_file, "cell.arm.workspace_max_m", show(a["workspace_max_m"]),
                        f"above workspace_min_m {show(a['workspace_min_m'])} on every axis")
    if p["baud"] not in DXL_BAUD_RATES:
        raise TaskError(task_file, "cell.pan_tilt.baud", show(p["baud"]),
                        "one of the SDK's rates: " + ", ".join(map(str, DXL_BAUD_RATES)))
    ids = [p["pan_id"], p["tilt_id"], p["radius_id"]]
    if len(set(ids)) != 3:
        raise TaskError(task_file, "cell.pan_tilt.tilt_id", show(ids), "distinct pan, tilt and radius ids")
    arm = ArmConfig(
        host=a["host"], connect_timeout_s=a["connect_timeout_s"],
        T_cell_base=geometry.from_rpy(a["base_rpy_rad"], a["base_position_m"]),
        T_flange_cam=geometry.from_rpy(a["hand_eye_rpy_rad"], a["hand_eye_position_m"]),
        workspace_min_m=a["workspace_min_m"], workspace_max_m=a["workspace_max_m"],
        speed_m_s=a["speed_m_s"], acceleration_m_s2=a["acceleration_m_s2"])
    pan_tilt = PanTiltConfig(
        port=p["port"], baud=p["baud"], pan_id=p["pan_id"], tilt_id=p["tilt_id"],
        radius_id=p["radius_id"], pan_offset_rad=p["pan_offset_rad"],
        tilt_offset_rad=p["tilt_offset_rad"], radius_ticks=tuple(int(t) for t in p["radius_ticks"]),
        speed_rad_s=np.radians(p["speed_deg_s"]), move_timeout_s=p["move_timeout_s"],
        tolerance_ticks=p["tolerance_ticks"])
    camera = CameraConfig(source=c["source"], exposure_unit_s=c["exposure_unit_s"],
                          discard_frames=c["discard_frames"])
    return DevicesConfig(Path(task_file), arm, pan_tilt, camera)


# ---------------------------------------------------------------------------------------------
# Interfaces

def check_arm_motion(config, T_cell_cam, speed_m_s):
    """Refuse (DeviceFault) a camera pose whose camera or flange leaves the workspace box, a
    matrix that is not a rigid transform, or a speed above the limit - before anything moves."""
    T = np.asarray(T_cell_cam, float)
    R = T[:3, :3] if T.shape == (4, 4) else np.zeros((3, 3))
    if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        raise DeviceFault("arm", "camera pose is not a rigid transform: refused before moving")
    if not 0 < speed_m_s <= config.speed_m_s:
        raise DeviceFault("arm", f"speed {speed_m_s} m/s outside (0, {config.speed_m_s}] m/s: "
                                 "refused before moving")
    flange = T @ np.linalg.inv(config.T_flange_cam)
    lo, hi = config.workspace_min_m, config.workspace_max_m
    for name, p in (("camera", T[:3, 3]), ("flange", flange[:3, 3])):
        if np.any(p < lo) or np.any(p > hi):
            raise DeviceFault("arm", f"{name} at {np.round(p, 3).tolist()} m is outside the workspace "
                                     f"{lo.tolist()}..{hi.tolist()} m: refused before moving")


class Arm(ABC):
    """Carries the camera. Poses are T_cell_cam (camera frame in the cell frame)."""

    device = "arm"

    def __init__(self, config):
        self.config = config

    def move_camera(self, T_cell_cam, speed_m_s=None):
        """Move so the camera frame is at T_cell_cam; returns when there, raises DeviceFault on
        limits, unreachable poses or a device error."""
        speed = self.config.speed_m_s if speed_m_s is None else speed_m_s
        check_arm_motion(self.config, T_cell_cam, speed)
        self._move_tcp(np.linalg.inv(self.config.T_cell_base) @ T_cell_cam, speed)

    def camera_pose(self):
        """The actual T_cell_cam, read back from the device."""
        return self.config.T_cell_base @ self._tcp_pose()

    @abstractmethod
    def _move_tcp(self, T_base_cam, speed_m_s):
        """Move the camera (the TCP) to T_base_cam in the robot's base frame."""

    @abstractmethod
    def _tcp_pose(self):
        """Actual T_base_cam."""

    @abstractmethod
    def stop(self):
        """Stop any motion now."""

    def close(self):
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

    def __init__(self, rig, operator):
        self.rig, self.operator = rig, operator
        self.manual_radius = rig.radius_axis == "manual"
        self._confirmed_radius = float("nan")      # manual radius: what the operator confirmed
        if self.manual_radius:
            operator.require(self.device, "the lamp radius (radius_axis: manual)")

    def move(self, pan_rad, tilt_rad, radius_m):
        """Move to the joints (checked against the rig's ranges first); a manual radius is then
        set by the operator."""
        lo, hi = self.rig.pan_range_rad      # pan turns about z: pan + 2 pi k may be the one in range
        pan = next((p for p in pan_rad + 2 * np.pi * np.array([0.0, -1.0, 1.0])
                    if lo - 1e-9 <= p <= hi + 1e-9), pan_rad)
        _check_range(self.device, "pan", pan, self.rig.pan_range_rad, degrees=True)
        _check_range(self.device, "tilt", tilt_rad, self.rig.tilt_range_rad, degrees=True)
        _check_range(self.device, "radius", radius_m, self.rig.radius_range_m)
        self._move_axes(pan, tilt_rad, None if self.manual_radius else radius_m)
        if self.manual_radius and not abs(radius_m - self._confirmed_radius) < 0.5e-3:
            self.operator.confirm(self.device, f"set the lamp radius (pivot to lamp) to "
                                               f"{radius_m * 1e3:.1f} mm")
            self._confirmed_radius = radius_m

    def joints(self):
        """(pan, tilt, radius) read back; a manual radius is the one the operator confirmed."""
        pan, tilt, radius = self._read_axes()
        return pan, tilt, self._confirmed_radius if self.manual_radius else radius

    def lamp_pose(self):
        """(position, aim) of the lamp in the cell frame from the read-back joints."""
        position = lamp_position(self.rig.pivot_m, *self.joints())
        return position, lamp_aim(self.rig.pivot_m, position)

    @abstractmethod
    def _move_axes(self, pan_rad, tilt_rad, radius_m):
        """Drive the axes (radius_m is None when the operator sets it) and wait until there."""

    @abstractmethod
    def _read_axes(self):
        """(pan, tilt, radius or None) as the device reports them."""

    @abstractmethod
    def stop(self, fault_is_own=False):
        """Hold position with torque on; torque off only if the fault is the servos' own."""

    def close(self):
        """Release the port (after stop)."""


class Camera(ABC):
    """Takes gray images (uint8 or uint16 by bit depth) with a set shutter time, f-number and
    focus distance."""

    device = "camera"

    def __init__(self, bit_depth):
        self.bit_depth = bit_depth
        self.shutter_s = None
        self.f_number = None
        self.focus_m = None

    @abstractmethod
    def set_exposure(self, shutter_s):
        """Set the shutter time; returns the one the camera actually uses [s]."""

    @abstractmethod
    def set_aperture(self, f_number):
        """Set the f-number (motorized, or by the operator)."""

    @abstractmethod
    def set_focus(self, focus_m):
        """Focus the lens at this distance along the optical axis [m] (motorized, or by the
        operator)."""

    @abstractmethod
    def capture(self):
        """One gray image (H, W) as uint8 (bit depth <= 8) or uint16."""

    def close(self):
        """Release the camera."""


@dataclass
class Devices:
    """The cell's three devices, with the safe stop every fault ends in (hardware notes)."""

    arm: Arm
    lamp: LampRig
    camera: Camera

    def safe_stop(self, fault=None):
        """Stop the arm, hold the servos (torque off only for their own fault), close the camera.
        Every step is tried; returns the messages of steps that failed, in turn."""
        lamp_faulted = isinstance(fault, DeviceFault) and fault.device == self.lamp.device
        steps = (self.arm.stop, lambda: self.lamp.stop(fault_is_own=lamp_faulted), self.camera.close)
        return try_all(steps)

    def close(self):
        """Release everything after a normal end."""
        return try_all((self.arm.close, self.lamp.close, self.camera.close))
