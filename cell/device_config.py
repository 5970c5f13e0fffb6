"""The task's device settings, `cell.arm`, `cell.pan_tilt` and `cell.camera` (docs/devices.md):
their schemas, read by load_task with the rest of the task, and the typed, SI values the
backends are built from. The defaults describe the example cell and reach no network or bus.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell.errors import TaskError
from cell.schema import POSITIVE, Choice, Integer, Invalid, Number, Pair, Section, Spec, Text, Vector, show

MAX_SPEED_M_S = 0.25            # ur_rtde's default moveL speed: a hard cap for an inspection cell
MAX_ACCELERATION_M_S2 = 1.2     # ur_rtde's default moveL acceleration
MAX_SERVO_SPEED_DEG_S = 90.0
# opencv: cv2.VideoCapture; simulated: frames rendered by the simulator from the real arm's and
# pan-tilt's read-back poses, a dry run of a real arm and lamp rig without a camera
CAMERA_DRIVERS = ("opencv", "simulated")
DXL_BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
                  1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000)  # the SDK's list


# Validated settings in SI units; the defaults live in the schemas below.
@dataclass(frozen=True)
class ArmConfig:
    host: str | None                        # robot address; required for --backend hw only
    connect_timeout_s: float
    workspace_min_m: np.ndarray             # cell frame box the camera and flange must stay in
    workspace_max_m: np.ndarray
    speed_m_s: float                        # what moves use, and the most any move may use
    acceleration_m_s2: float
    move_timeout_s: float                   # a move not done by then is a fault


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
    driver: str                             # CAMERA_DRIVERS
    source: int | str                       # cv2.VideoCapture index or path
    exposure_unit_s: float                  # CAP_PROP_EXPOSURE unit (V4L2: 100 us)
    discard_frames: int                     # frames still exposed the old way after a change


@dataclass(frozen=True)
class DevicesConfig:
    task_file: Path
    arm: ArmConfig
    pan_tilt: PanTiltConfig
    camera: CameraConfig
    given: tuple                            # the sections the task set, e.g. ("arm",)


class _Source(Spec):
    """A camera index (integer >= 0) or a device / video / image-sequence path."""

    expected = "a camera index (integer >= 0) or a path"
    default = 0

    def convert(self, raw, to_si):
        if isinstance(raw, int) and not isinstance(raw, bool) and raw >= 0:
            return raw
        if isinstance(raw, str) and raw.strip():
            return raw.strip()
        raise Invalid(raw, self.expected)


ANGLE = dict(ok=lambda v: abs(v) <= np.pi, expected="an angle within [-180, 180] deg")
# defaults: the example cell, a UR5e on the table beside the part, the camera 5 cm past the flange
ARM = Section({
    "host": Text(default=None),
    "connect_timeout_s": Number(**POSITIVE, default=2.0),
    "base_position_m": Vector(default=(0.0, -0.40, 0.0)),
    "base_rpy_deg": Vector(default=(0.0, 0.0, 0.0)),
    "hand_eye_position_m": Vector(default=(0.0, 0.0, 0.05)),
    "hand_eye_rpy_deg": Vector(default=(0.0, 0.0, 0.0)),
    "workspace_min_m": Vector(default=(-0.60, -0.60, 0.10)),
    "workspace_max_m": Vector(default=(0.60, 0.60, 1.00)),
    "speed_m_s": Number(lambda v: 0 < v <= MAX_SPEED_M_S, f"a speed in (0, {MAX_SPEED_M_S}] m/s",
                        default=0.1),
    "acceleration_m_s2": Number(lambda v: 0 < v <= MAX_ACCELERATION_M_S2,
                                f"an acceleration in (0, {MAX_ACCELERATION_M_S2}] m/s^2", default=0.5),
    "move_timeout_s": Number(**POSITIVE, default=30.0),
}, required=False)

PAN_TILT = Section({
    "port": Text(default=None),
    "baud": Integer(9600, 4_000_000, default=57600),
    "pan_id": Integer(0, 252, default=1),
    "tilt_id": Integer(0, 252, default=2),
    "radius_id": Integer(0, 252, default=3),
    "pan_offset_deg": Number(**ANGLE, default=0.0),
    "tilt_offset_deg": Number(**ANGLE, default=0.0),
    "radius_ticks": Pair(lambda v: 0 <= v <= 4095 and v == int(v), "ticks in 0..4095", strict=True,
                         default=(0, 4095)),
    "speed_deg_s": Number(lambda v: 0 < v <= MAX_SERVO_SPEED_DEG_S,
                          f"a speed in (0, {MAX_SERVO_SPEED_DEG_S}] deg/s", default=30.0),
    "move_timeout_s": Number(**POSITIVE, default=5.0),
    "tolerance_ticks": Integer(0, 100, default=3),
}, required=False)

CAMERA = Section({
    "driver": Choice(*CAMERA_DRIVERS, default="opencv"),
    "source": _Source(),
    "exposure_unit_s": Number(**POSITIVE, default=1e-4),
    "discard_frames": Integer(0, 100, default=2),
}, required=False)

SECTIONS = {"arm": ARM, "pan_tilt": PAN_TILT, "camera": CAMERA}     # the task's cell.<name>


def devices_config(file, cell, written):
    """The parsed `cell` section's arm, pan_tilt and camera values -> DevicesConfig, after the
    checks one key alone cannot make (TaskError naming the file and key). `written`: the section
    as the file wrote it, whose non-empty device sections are recorded as `given`. The base and
    hand-eye poses go to the task's Frames."""
    given = tuple(name for name in SECTIONS if (written or {}).get(name))
    a, p, c = cell["arm"], cell["pan_tilt"], cell["camera"]
    if not np.all(a["workspace_min_m"] < a["workspace_max_m"]):
        raise TaskError(file, "cell.arm.workspace_max_m", show(a["workspace_max_m"]),
                        f"above workspace_min_m {show(a['workspace_min_m'])} on every axis")
    if p["baud"] not in DXL_BAUD_RATES:
        raise TaskError(file, "cell.pan_tilt.baud", show(p["baud"]),
                        "one of the SDK's rates: " + ", ".join(map(str, DXL_BAUD_RATES)))
    ids = [p["pan_id"], p["tilt_id"], p["radius_id"]]
    if len(set(ids)) != 3:
        raise TaskError(file, "cell.pan_tilt.tilt_id", show(ids), "distinct pan, tilt and radius ids")
    arm = ArmConfig(
        host=a["host"], connect_timeout_s=a["connect_timeout_s"], workspace_min_m=a["workspace_min_m"], workspace_max_m=a["workspace_max_m"],
        speed_m_s=a["speed_m_s"], acceleration_m_s2=a["acceleration_m_s2"],
        move_timeout_s=a["move_timeout_s"])
    pan_tilt = PanTiltConfig(
        port=p["port"], baud=p["baud"], pan_id=p["pan_id"], tilt_id=p["tilt_id"],
        radius_id=p["radius_id"], pan_offset_rad=p["pan_offset_rad"],
        tilt_offset_rad=p["tilt_offset_rad"], radius_ticks=tuple(int(t) for t in p["radius_ticks"]),
        speed_rad_s=np.radians(p["speed_deg_s"]), move_timeout_s=p["move_timeout_s"],
        tolerance_ticks=p["tolerance_ticks"])
    camera = CameraConfig(driver=c["driver"], source=c["source"], exposure_unit_s=c["exposure_unit_s"],
                          discard_frames=c["discard_frames"])
    return DevicesConfig(Path(file), arm, pan_tilt, camera, tuple(given))
