"""The one place that builds the cell's devices: the simulated cell (sim/) or the real one
(cell/hw/). Nothing else in cell/ imports either, so the controller sees only cell.devices'
interfaces, and the real backends' SDKs load only for --backend hw."""
from cell.devices import Camera, Devices, speaking_for
from cell.errors import TaskError
from cell.operator import Operator
from cell.session import try_all


def open_devices(task, scene, backend, yes=False):
    """The cell's devices: the simulated cell (rendering `scene`) or, for backend hw, the real
    ones from the task's cell.arm / cell.pan_tilt / cell.camera settings. The sim has no operator
    to set the lamp radius: it confirms for itself."""
    if backend == "hw":
        return make_hw_devices(task, yes=yes)
    from sim.cell import make_sim_devices
    return make_sim_devices(task, scene, yes=True)


def make_hw_devices(task, yes=False, operator=None):
    """The real devices for --backend hw from the task's settings. Needs explicit `cell.arm.host`
    and `cell.pan_tilt.port` (no default reaches the network or a serial bus); connects arm,
    servos, camera in turn and closes what was opened if a later one fails."""
    config = task.cell.devices
    if not config.arm.host:
        raise TaskError(config.task_file, "cell.arm.host", "nothing",
                        "the robot's address (required for --backend hw; there is no default)")
    if not config.pan_tilt.port:
        raise TaskError(config.task_file, "cell.pan_tilt.port", "nothing",
                        "the servos' serial port, e.g. /dev/ttyUSB0 (required for --backend hw)")
    from cell.hw.dynamixel import DynamixelPanTilt
    from cell.hw.ur import URArm
    open_camera = hw_camera(task)

    operator = operator or Operator(yes=yes)
    opened = []
    try:
        with speaking_for(URArm):
            opened.append(URArm(config.arm, task.frames))
        with speaking_for(DynamixelPanTilt):
            opened.append(DynamixelPanTilt(task.lamp.rig, config.pan_tilt, operator))
        with speaking_for(Camera):
            opened.append(open_camera(operator))
    except Exception:
        try_all([device.close for device in reversed(opened)])
        raise
    return Devices(*opened)


def hw_camera(task):
    """open(operator) -> the real camera of the task's cell.camera.driver: OpenCV's VideoCapture,
    or a GenICam device, whose SDK (harvesters, the `genicam` extra) is imported only here: not
    installed is bad input before anything connects."""
    config = task.cell.devices.camera
    if config.driver == "opencv":
        from cell.hw.opencv_camera import OpenCVCamera
        return lambda operator: OpenCVCamera(config, task.camera.sensor.bit_depth, operator)
    try:
        from cell.hw.genicam_camera import GenICamCamera
    except ImportError as err:
        raise TaskError(task.path, "cell.camera.driver", f"genicam, but {err.name or err} cannot be "
                        "imported", "the GenICam SDK installed: "
                        "pip install 'lightplan-cell[genicam]'") from None
    return lambda operator: GenICamCamera(config, task.camera.sensor, operator)
