"""The one place that builds the cell's devices: the simulated cell (sim/) or the real one
(cell/hw/). Nothing else in cell/ imports either, so the controller sees only cell.devices'
interfaces, and the real backends' SDKs load only for --backend hw."""
from cell.devices import Devices, speaking_for
from cell.errors import TaskError
from cell.operator import Operator
from cell.session import try_all


def open_devices(task, scene, backend, yes=False, laser=None):
    """The cell's devices: the simulated cell (rendering `scene`, or the spot of a laser aimed at
    the sensor) or, for backend hw, the real ones from the task's cell.arm / cell.pan_tilt /
    cell.camera settings (a real laser is the operator's). The sim has no operator to set the
    lamp radius: it confirms for itself."""
    if backend == "hw":
        return make_hw_devices(task, yes=yes)
    from sim.cell import make_sim_devices
    return make_sim_devices(task, scene, yes=True, laser=laser)


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
    from cell.hw.opencv_camera import OpenCVCamera
    from cell.hw.ur import URArm

    operator = operator or Operator(yes=yes)
    opened = []
    try:
        with speaking_for(URArm):
            opened.append(URArm(config.arm, task.frames))
        with speaking_for(DynamixelPanTilt):
            opened.append(DynamixelPanTilt(task.lamp.rig, config.pan_tilt, operator))
        with speaking_for(OpenCVCamera):
            opened.append(OpenCVCamera(config.camera, task.camera.sensor.bit_depth, operator))
    except Exception:
        try_all([device.close for device in reversed(opened)])
        raise
    return Devices(*opened)
