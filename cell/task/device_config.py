"""The task's device settings, `cell.arm`, `cell.pan_tilt`, `cell.camera` and `cell.lighting`
(docs/devices.md):
their schemas, read by load_task with the rest of the task, and the typed, SI values the
backends are built from. The defaults describe the example cell and reach no network or bus.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from cell.core import geometry
from cell.core.errors import TaskError
from cell.core.inputs import checked_file
from cell.task.schema import (POSITIVE, Choice, Integer, Invalid, Number, Pair, Rule, Section, Spec, Text, Vector,
                         ToSI, _unit, parse, read_yaml, show)

MAX_SPEED_M_S = 0.25            # ur_rtde's default moveL speed: a hard cap for an inspection cell
MAX_ACCELERATION_M_S2 = 1.2     # ur_rtde's default moveL acceleration
MAX_SERVO_SPEED_DEG_S = 90.0
# opencv: cv2.VideoCapture; genicam: harvesters and a GenTL producer; simulated: frames rendered by
# the simulator from the real arm's and pan-tilt's read-back poses, a dry run of a real arm and
# lamp rig without a camera
CAMERA_DRIVERS = ("opencv", "genicam", "simulated")
LIGHTING_DRIVERS = ("gardasoft",)           # Gardasoft RT-series command set over TCP
GARDASOFT_PORT = 30313                      # RT manual 12.1: TCP commands go to this port
LIGHTING_CHANNELS = (2, 4, 8)               # RT220, RT420, RT820F
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
    hand_eye_file: Path | None = None       # where T_flange_cam came from (cell.arm.hand_eye), or the task
    move_timeout_given: bool = False        # the task states move_timeout_s (the simulated arm keeps it then)


@dataclass(frozen=True)
class PanTiltConfig:
    port: str | None                        # serial device; required for --backend hw only
    baud: int
    pan_id: int
    tilt_id: int
    radius_id: int                          # used when lamp.rig.radius_axis is servo
    pan_offset_rad: float                   # joint angle at the servo's centre tick 2048
    tilt_offset_rad: float
    radius_ticks: tuple[int, int]           # radius servo ticks at radius_range_m's ends
    speed_rad_s: float
    move_timeout_s: float
    tolerance_ticks: int
    move_timeout_given: bool = False        # the task states move_timeout_s (the simulated rig keeps it then)


@dataclass(frozen=True)
class CameraConfig:
    driver: str                             # CAMERA_DRIVERS: which backend class
    source: int | str                       # opencv: cv2.VideoCapture index or path
    exposure_unit_s: float                  # opencv: CAP_PROP_EXPOSURE unit (V4L2: 100 us)
    discard_frames: int                     # opencv: frames still exposed the old way after a change
    cti: Path | None                        # genicam: the GenTL producer (a .cti file)
    serial_number: str | None               # genicam: the device, by serial number ...
    device_index: int                       #   ... or by its place in the producer's list
    pixel_format: str | None                # genicam: Mono8 | Mono12 | Mono16, None: by bit depth
    gain: float | None                      # genicam: the Gain node's value, None: left as is
    frame_timeout_s: float                  # genicam: a frame later than shutter + this is a fault


@dataclass(frozen=True)
class LightingConfig:
    driver: str                             # LIGHTING_DRIVERS: which backend class
    host: str | None                        # controller address; required for --backend hw only
    port: int
    channels: int                           # the model's channels: 2, 4 or 8
    timeout_s: float                        # a reply (ending in ">") later than this is a fault


@dataclass(frozen=True)
class DevicesConfig:
    task_file: Path
    arm: ArmConfig
    pan_tilt: PanTiltConfig
    camera: CameraConfig
    given: tuple[str, ...]                  # the sections the task set, e.g. ("arm",)
    lighting: LightingConfig | None = None  # the lighting controller, if the task has cell.lighting


GENICAM_SDK = ("harvesters", "genicam")    # what cell.devices.hw.genicam_camera imports (the `genicam` extra)


def for_hw(config: DevicesConfig, channels: dict[int, str] | None = None) -> DevicesConfig:
    """The settings, once they name everything --backend hw reaches (bad input otherwise): the
    robot's address, the servos' serial port, the lighting controller's address if the task has
    one or has lights on channels (`channels`, Task.channels: {channel: its key}; no default
    reaches a network or a bus), every such channel one of the controller's (check_channels) and,
    for a GenICam camera, its SDK installed (looked up, not imported). The one check of the cell
    section for the real cell: `cell check` of a task whose cell.backend is hw, every command with
    --backend hw before any planning or folder (cell.cli.backend_of), `cell hw-check` and the
    backends before they connect."""
    file = config.task_file
    if not config.arm.host:
        raise TaskError(file, "cell.arm.host", "nothing",
                        "the robot's address (required for --backend hw; there is no default)")
    if not config.pan_tilt.port:
        raise TaskError(file, "cell.pan_tilt.port", "nothing",
                        "the servos' serial port, e.g. /dev/ttyUSB0 (required for --backend hw)")
    if channels and not config.lighting:
        raise TaskError(file, "cell.lighting.host", "nothing (no cell.lighting section)",
                        f"the lighting controller's address: the task's lights are on channels "
                        f"{', '.join(map(str, sorted(channels)))} (required for --backend hw)")
    if config.lighting and not config.lighting.host:
        raise TaskError(file, "cell.lighting.host", "nothing",
                        "the lighting controller's address (required for --backend hw; there is no default)")
    check_channels(config, channels or {})
    if config.camera.driver == "genicam":
        missing = next((name for name in GENICAM_SDK if importlib.util.find_spec(name) is None), None)
        if missing:
            raise genicam_sdk_missing(file, missing)
    return config


def check_channels(config: DevicesConfig, channels: dict[int, str]) -> None:
    """Every channel a light is on ({channel: its key}) one of the configured controller's,
    1..cell.lighting.channels (bad input otherwise, naming the light); nothing to check without
    cell.lighting (the simulated cell's controller has as many channels as the lights need)."""
    if config.lighting is None:
        return
    beyond = sorted(c for c in channels if c > config.lighting.channels)
    if beyond:
        raise TaskError(config.task_file, channels[beyond[0]], str(beyond[0]),
                        f"a channel of the lighting controller, 1..{config.lighting.channels} "
                        "(cell.lighting.channels)")


def genicam_sdk_missing(file: str | PathLike[str], name: str) -> TaskError:
    """The refusal of a GenICam camera whose SDK module `name` cannot be imported."""
    return TaskError(file, "cell.camera.driver", f"genicam, but {name} cannot be imported",
                     "the GenICam SDK installed: pip install 'lightplan-cell[genicam]'")


class _Source(Spec):
    """A camera index (integer >= 0) or a device / video / image-sequence path."""

    expected = "a camera index (integer >= 0) or a path"
    default = 0

    def convert(self, raw: Any, to_si: ToSI) -> int | str:
        if isinstance(raw, int) and not isinstance(raw, bool) and raw >= 0:
            return raw
        if isinstance(raw, str) and raw.strip():
            return raw.strip()
        raise Invalid(raw, self.expected)


class _SerialNumber(Spec):
    """A serial number as text; YAML reads an all-digit one as an integer, which is the same."""

    expected = "a serial number (text or digits)"
    default = None

    def convert(self, raw: Any, to_si: ToSI) -> str:
        if isinstance(raw, int) and not isinstance(raw, bool) and raw >= 0:
            return str(raw)
        if isinstance(raw, str) and raw.strip():
            return raw.strip()
        raise Invalid(raw, self.expected)


class _ChannelCount(Spec):
    """How many channels the controller model has."""

    expected = "2, 4 or 8 (the controller model's channels)"
    default = 4

    def convert(self, raw: Any, to_si: ToSI) -> int:
        if isinstance(raw, bool) or raw not in LIGHTING_CHANNELS:
            raise Invalid(raw, self.expected)
        return int(raw)


# what a hand-eye file holds: the task's own keys, in their place (`cell calibrate hand-eye` writes one)
HAND_EYE_FILE = {"cell": Section({"arm": Section({"hand_eye_position_m": Vector(), "hand_eye_rpy_deg": Vector()})})}
HAND_EYE_KEYS = ("hand_eye_position", "hand_eye_rpy")      # the keys' bases, in any unit


class _HandEyeFile(Spec):
    """`cell.arm.hand_eye`: a hand-eye file named relative to the task file, its keys checked as
    a task's are; read as {"file": its path, its two keys in SI}."""

    expected = "the name of a hand-eye file (cell calibrate hand-eye writes one)"
    default = None

    def read(self, file: str | PathLike[str], path: str, raw: Any, to_si: ToSI) -> dict[str, Any]:
        if not isinstance(raw, str) or not raw.strip():
            raise TaskError(file, path, show(raw), self.expected)
        named = checked_file(Path(file).parent / raw.strip(), "yaml", file, path, relative_to="the task file")
        data = read_yaml(named)
        if data is None:
            raise TaskError(named, "", "an empty file", "a mapping of keys")
        return parse(named, "", data, HAND_EYE_FILE)["cell"]["arm"] | {"file": named}


MONO_FORMATS = {"Mono8": 8, "Mono12": 12, "Mono16": 16}    # PFNC name -> bits per pixel value
ANGLE = Rule(ok=lambda v: abs(v) <= np.pi, expected="an angle within [-180, 180] deg")
# defaults: the example cell, a UR5e on the table beside the part, the camera 5 cm past the flange
ARM = Section({
    "host": Text(default=None),
    "connect_timeout_s": Number(**POSITIVE, default=2.0),
    "base_position_m": Vector(default=(0.0, -0.40, 0.0)),
    "base_rpy_deg": Vector(default=(0.0, 0.0, 0.0)),
    "hand_eye_position_m": Vector(default=(0.0, 0.0, 0.05)),
    "hand_eye_rpy_deg": Vector(default=(0.0, 0.0, 0.0)),
    "hand_eye": _HandEyeFile(),
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
    "cti": Text(default=None),
    "serial_number": _SerialNumber(),
    "device_index": Integer(0, default=0),
    "pixel_format": Choice(*MONO_FORMATS, default=None),
    "gain": Number(lambda v: True, "a number (the device's Gain node, usually dB)", default=None),
    "frame_timeout_s": Number(**POSITIVE, default=1.0),
}, required=False)
DRIVER_KEYS = {"opencv": ("source", "exposure_unit_s", "discard_frames"),   # cell.camera keys
               "genicam": ("cti", "serial_number", "device_index", "pixel_format", "gain",
                           "frame_timeout_s"),                              # only a driver reads
               "simulated": ()}

LIGHTING = Section({
    "driver": Choice(*LIGHTING_DRIVERS, default="gardasoft"),
    "host": Text(default=None),
    "port": Integer(1, 65535, default=GARDASOFT_PORT),
    "channels": _ChannelCount(),
    "timeout_s": Number(**POSITIVE, default=1.0),
}, required=False)

SECTIONS = {"arm": ARM, "pan_tilt": PAN_TILT, "camera": CAMERA, "lighting": LIGHTING}   # the task's cell.<name>


def devices_config(file: str | PathLike[str], cell: dict[str, Any], written: dict[str, Any] | None,
                   bit_depth: int) -> DevicesConfig:
    """The parsed `cell` section's arm, pan_tilt, camera and lighting values -> DevicesConfig
    (lighting only when the task wrote the section), after the checks one key alone cannot make
    (TaskError naming the file and key). `written`: the section
    as the file wrote it, whose non-empty device sections are recorded as `given`; `bit_depth`:
    camera.sensor's, which a pixel format must carry. The base and hand-eye poses go to the
    task's Frames."""
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
    ramps_s = a["speed_m_s"] / a["acceleration_m_s2"]
    if a["move_timeout_s"] <= ramps_s:
        raise TaskError(file, "cell.arm.move_timeout_s", show(a["move_timeout_s"]),
                        f"more than the {ramps_s:.3g} s every move of the arm takes to speed up and brake "
                        "(speed_m_s / acceleration_m_s2)")
    arm = ArmConfig(
        host=a["host"], connect_timeout_s=a["connect_timeout_s"], workspace_min_m=a["workspace_min_m"], workspace_max_m=a["workspace_max_m"],
        speed_m_s=a["speed_m_s"], acceleration_m_s2=a["acceleration_m_s2"],
        move_timeout_s=a["move_timeout_s"], hand_eye_file=a["hand_eye"] and a["hand_eye"]["file"],
        move_timeout_given=stated(written, "arm", "move_timeout"))
    pan_tilt = PanTiltConfig(
        port=p["port"], baud=p["baud"], pan_id=p["pan_id"], tilt_id=p["tilt_id"],
        radius_id=p["radius_id"], pan_offset_rad=p["pan_offset_rad"],
        tilt_offset_rad=p["tilt_offset_rad"], radius_ticks=(int(p["radius_ticks"][0]), int(p["radius_ticks"][1])),
        speed_rad_s=np.radians(p["speed_deg_s"]), move_timeout_s=p["move_timeout_s"],
        tolerance_ticks=p["tolerance_ticks"], move_timeout_given=stated(written, "pan_tilt", "move_timeout"))
    camera = _camera_config(file, c, (written or {}).get("camera") or {}, bit_depth)
    lighting = LightingConfig(**cell["lighting"]) if "lighting" in given else None
    return DevicesConfig(Path(file), arm, pan_tilt, camera, tuple(given), lighting)


def stated(written: dict[str, Any] | None, section: str, base: str) -> bool:
    """Whether the cell section as written states cell.<section>.<base>_<unit> in any unit."""
    return any(_unit(str(key))[0] == base and value is not None
               for key, value in ((written or {}).get(section) or {}).items())


def hand_eye(file: str | PathLike[str], arm: dict[str, Any], written: dict[str, Any] | None) -> np.ndarray:
    """T_flange_cam of the parsed `cell.arm` (`written`: as the file wrote it): from the hand-eye
    file `hand_eye` names, else the two keys (defaults included); both ways is an error."""
    named = arm["hand_eye"]
    if named is None:
        return geometry.from_rpy(arm["hand_eye_rpy_rad"], arm["hand_eye_position_m"])
    for key in (k for k, v in (written or {}).items() if v is not None):
        if _unit(str(key))[0] in HAND_EYE_KEYS:
            raise TaskError(file, f"cell.arm.{key}", f"a value beside hand_eye '{named['file'].name}'",
                            "the hand-eye in one place: the file cell.arm.hand_eye names, or hand_eye_position_m "
                            "and hand_eye_rpy_deg in the task")
    return geometry.from_rpy(named["hand_eye_rpy_rad"], named["hand_eye_position_m"])


def _is_file(path):
    try:
        return path.is_file()
    except OSError:                                     # e.g. a name too long for the system
        return False


def _camera_config(file, c, written, bit_depth):
    """cell.camera -> CameraConfig: only the chosen driver's keys written, a GenTL producer that
    is a .cti file (relative to the task file), one way to name the device, and a pixel format
    with at least the sensor's bits (fewer would make up gray levels)."""
    driver = c["driver"]
    keys_of = {d: {_unit(k)[0] for k in keys} for d, keys in DRIVER_KEYS.items()}
    for key in (k for k, v in written.items() if v is not None):    # empty is absent, as in parse
        base = _unit(str(key))[0]                       # frame_timeout_ms is frame_timeout_s
        other = next((d for d, bases in keys_of.items() if d != driver and base in bases), None)
        if other and base not in keys_of[driver]:
            raise TaskError(file, f"cell.camera.{key}", f"a setting of driver {other}",
                            f"only the keys of driver {driver}: " + ", ".join(DRIVER_KEYS[driver]))
    cti = None
    if driver == "genicam":
        if c["cti"] is None:
            raise TaskError(file, "cell.camera.cti", "nothing",
                            "the GenTL producer file (.cti) of the camera's vendor (driver genicam)")
        cti = (Path(file).parent / c["cti"]).absolute()
        if cti.suffix.lower() != ".cti" or not _is_file(cti):
            raise TaskError(file, "cell.camera.cti", f"'{c['cti']}'" + ("" if _is_file(cti) else
                            ", which is not a file"), "a GenTL producer file (.cti), relative to "
                            "the task file or absolute")
    if c["serial_number"] is not None and written.get("device_index") is not None:
        raise TaskError(file, "cell.camera.device_index", f"{show(c['device_index'])} and "
                        f"serial_number '{c['serial_number']}' both", "the device named one way")
    fmt = c["pixel_format"]
    if fmt is not None and MONO_FORMATS[fmt] < bit_depth:
        raise TaskError(file, "cell.camera.pixel_format", f"{fmt} ({MONO_FORMATS[fmt]} bits)",
                        f"a format of at least camera.sensor.bit_depth {bit_depth} bits: " +
                        ", ".join(f for f, bits in MONO_FORMATS.items() if bits >= bit_depth))
    return CameraConfig(
        driver=driver, source=c["source"], exposure_unit_s=c["exposure_unit_s"],
        discard_frames=c["discard_frames"], cti=cti, serial_number=c["serial_number"],
        device_index=c["device_index"], pixel_format=fmt, gain=c["gain"],
        frame_timeout_s=c["frame_timeout_s"])
