"""The one place that builds the cell's devices: the simulated cell (sim/) or the real one
(cell/devices/hw/). Nothing else in cell/ imports either, so the controller sees only the
interfaces of cell.devices.interfaces, and the real backends' SDKs load only for --backend hw."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cell.devices.interfaces import Camera, Device, Devices, LightController, speaking_for
from cell.core.errors import DeviceFault
from cell.devices.operator import Operator
from cell.devices.session import try_all
from cell.task.device_config import for_hw, genicam_sdk_missing

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.device_config import CameraConfig
    from cell.task.types import Task
    from sim.laser import Beam

OpenCamera = Callable[..., Camera]      # open(operator, arm=None, lamp=None, lights=None) -> the task's camera


def open_devices(task: Task, scene: Scene | None, backend: str, yes: bool = False, laser: Beam | None = None,
                 board: bool = False) -> Devices:
    """The cell's devices: the simulated cell (rendering `scene`, the spot of a laser aimed at
    the sensor, or with board the calibration.board) or, for backend hw, the real ones from the
    task's cell.arm / cell.pan_tilt / cell.camera settings (a real laser and board are the
    operator's). The sim has no operator to set the lamp radius: it confirms for itself."""
    if backend == "hw":
        return make_hw_devices(task, yes=yes, scene=scene)
    from sim.cell import make_sim_devices
    # --yes is said as given; without it the simulated cell confirms for itself, and says so
    return make_sim_devices(task, scene, Operator(yes=yes, simulated=True), laser=laser, board=board)


def make_hw_devices(task: Task, yes: bool = False, operator: Operator | None = None,
                    scene: Scene | None = None) -> Devices:
    """The real devices for --backend hw from the task's settings. Needs explicit `cell.arm.host`
    and `cell.pan_tilt.port` (no default reaches the network or a serial bus); connects arm,
    servos, camera and, if the task has cell.lighting, the lighting controller in turn and closes
    what was opened if a later one fails. With
    cell.camera.driver simulated the camera renders `scene` (default: the task's, built here)."""
    config = for_hw(task.cell.devices, task.channels)
    from cell.devices.hw.dynamixel import DynamixelPanTilt
    from cell.devices.hw.ur import URArm
    open_camera = hw_camera(task, scene=scene)

    operator = operator or Operator(yes=yes)
    opened: list[Any] = []            # arm, pan-tilt, lighting controller, camera
    lights: LightController | None = None
    try:
        with speaking_for(URArm):
            opened.append(arm := URArm(config.arm, task.frames))
        with speaking_for(DynamixelPanTilt):
            opened.append(lamp := DynamixelPanTilt(task.lamp.rig, config.pan_tilt, operator))
        if config.lighting:           # before the camera: a simulated one renders its read-back levels
            from cell.devices.hw.gardasoft import GardasoftController
            with speaking_for(GardasoftController):
                opened.append(lights := GardasoftController(config.lighting))
        with speaking_for(Camera):
            opened.append(camera := open_camera(operator, arm, lamp, lights))
    except Exception:
        try_all([device.close for device in reversed(opened)])
        raise
    return Devices(arm, lamp, camera, lights)


@dataclass(frozen=True)
class DeviceCheck:
    """One real device as `cell hw-check` found it: its state() if it answered, else the fault."""

    device: str
    address: str                      # host, serial port, camera source or host:port
    state: dict[str, Any] | None
    fault: str | None

    @property
    def problems(self) -> list[str]:
        """What its state reports a run would stop on (nothing when it did not answer)."""
        return self.state["problems"] if self.state is not None else []

    @property
    def ready(self) -> bool:
        """Answered, and reports nothing a run would stop on."""
        return self.fault is None and not self.problems


def check_hw_devices(task: Task) -> list[DeviceCheck]:
    """`cell hw-check`: each real device of the task opened alone and read-only, asked its
    state() and closed, so one that fails does not hide the others. Reading only: nothing moves,
    no torque or setting changes, no control script is uploaded, no frame exposure is set; a
    DeviceCheck per device (arm, pan-tilt, camera, and the lighting controller if the task has
    cell.lighting: its firmware and every channel's level read, no `GT1`). The camera's frames
    are compared with camera.sensor, as a run does."""
    config = for_hw(task.cell.devices, task.channels)
    from cell.devices.hw.dynamixel import DynamixelPanTilt
    from cell.devices.hw.ur import URArm
    open_camera = hw_camera(task, read_only=True)

    no_prompt = Operator(yes=True)    # nothing is set by hand in a check, so nothing is asked
    sensor = task.camera.sensor
    checks = [
        _check(URArm, str(config.arm.host), lambda: URArm(config.arm, task.frames, read_only=True)),
        _check(DynamixelPanTilt, str(config.pan_tilt.port),
               lambda: DynamixelPanTilt(task.lamp.rig, config.pan_tilt, no_prompt, read_only=True)),
        _check(Camera, camera_address(config.camera), lambda: open_camera(no_prompt)),
    ]
    camera = checks[-1].state
    lighting = config.lighting
    if lighting:
        from cell.devices.hw.gardasoft import GardasoftController
        checks.append(_check(GardasoftController, f"{lighting.host}:{lighting.port}",
                             lambda: GardasoftController(lighting, read_only=True)))
    if camera and (camera["width_px"], camera["height_px"]) != (sensor.width_px, sensor.height_px):
        camera["problems"].append(f"frames are {camera['width_px']}x{camera['height_px']}, camera.sensor is "
                                  f"{sensor.width_px}x{sensor.height_px}: set the camera's resolution")
    return checks


def _check(kind: type[Device], address: str,
           open_device: Callable[[], Device]) -> DeviceCheck:
    device = None
    try:
        with speaking_for(kind):
            device = open_device()
            return DeviceCheck(kind.device, address, device.state(), None)
    except DeviceFault as fault:
        return DeviceCheck(kind.device, address, None, fault.reason)
    finally:
        if device is not None:
            try_all([device.close])


def camera_address(config: CameraConfig) -> str:
    """Where the camera is found: OpenCV's source, or the GenTL producer and the device in it."""
    if config.driver == "simulated":
        return "simulated (renders the task's scene)"
    if config.driver != "genicam":
        return str(config.source)
    device = f"serial {config.serial_number}" if config.serial_number else f"device {config.device_index}"
    return f"{config.cti} {device}"


def hw_camera(task: Task, read_only: bool = False, scene: Scene | None = None) -> OpenCamera:
    """open(operator, arm=None, lamp=None, lights=None) -> the camera of the task's
    cell.camera.driver: OpenCV's VideoCapture, a GenICam device, whose SDK (harvesters, the
    `genicam` extra) is imported only here: not installed is bad input before anything connects,
    or the simulator rendering `scene` (default: the task's) from `arm`'s and `lamp`'s read-back
    poses and the lighting controller's read-back levels, a dry run of a real arm, lamp rig and
    lighting controller without a camera. read_only: a GenICam device opened without its set-up, for `cell
    hw-check` (OpenCV's and the simulated camera set nothing when they open)."""
    config, bit_depth = task.cell.devices.camera, task.camera.sensor.bit_depth
    if config.driver == "opencv":
        from cell.devices.hw.opencv_camera import OpenCVCamera
        return lambda operator, arm=None, lamp=None, lights=None: OpenCVCamera(config, bit_depth, operator)
    if config.driver == "simulated":
        from cell.planning.scene import build_scene
        from sim.camera import SimCamera
        from sim.world import Renderer
        return lambda operator, arm=None, lamp=None, lights=None: SimCamera(
            Renderer(task, scene or build_scene(task)), arm, lamp, bit_depth, lights=lights)
    try:
        from cell.devices.hw.genicam_camera import GenICamCamera
    except ImportError as err:            # for_hw found the SDK, but it does not import
        raise genicam_sdk_missing(task.path, err.name or str(err)) from None
    return lambda operator, arm=None, lamp=None, lights=None: GenICamCamera(config, task.camera.sensor, operator,
                                                                            read_only=read_only)
