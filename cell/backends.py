"""The one place that builds the cell's devices: the simulated cell (sim/) or the real one
(cell/hw/). Nothing else in cell/ imports either, so the controller sees only cell.devices'
interfaces, and the real backends' SDKs load only for --backend hw."""
from cell.devices import Devices, speaking_for
from cell.errors import TaskError
from cell.operator import Operator
from cell.session import try_all


def open_devices(task, scene, backend, yes=False):
    """The cell's devices: the simulated cell (rendering `scene`) or, for backend hw, the real
    ones from the task's cell.arm / cell.pan_tilt / cell.camera settings. The sim has no operator
    to set the lamp radius: it confirms for itself."""
    if backend == "hw":
        return make_hw_devices(task, yes=yes, scene=scene)
    from sim.cell import make_sim_devices
    return make_sim_devices(task, scene, yes=True)


def make_hw_devices(task, yes=False, operator=None, scene=None):
    """The real devices for --backend hw from the task's settings. Needs explicit `cell.arm.host`
    and `cell.pan_tilt.port` (no default reaches the network or a serial bus); connects arm,
    servos, camera in turn and closes what was opened if a later one fails. The camera is
    cell.camera.driver's: OpenCV, or the simulator rendering `scene` (default: the task's, built
    here) from the real arm's and pan-tilt's read-back poses."""
    config = task.cell.devices
    if not config.arm.host:
        raise TaskError(config.task_file, "cell.arm.host", "nothing",
                        "the robot's address (required for --backend hw; there is no default)")
    if not config.pan_tilt.port:
        raise TaskError(config.task_file, "cell.pan_tilt.port", "nothing",
                        "the servos' serial port, e.g. /dev/ttyUSB0 (required for --backend hw)")
    from cell.hw.dynamixel import DynamixelPanTilt
    from cell.hw.ur import URArm

    operator = operator or Operator(yes=yes)
    opened = []
    try:
        with speaking_for(URArm):
            opened.append(URArm(config.arm, task.frames))
        with speaking_for(DynamixelPanTilt):
            opened.append(DynamixelPanTilt(task.lamp.rig, config.pan_tilt, operator))
        opened.append(_camera(task, scene, operator, *opened))
    except Exception:
        try_all([device.close for device in reversed(opened)])
        raise
    return Devices(*opened)


def _camera(task, scene, operator, arm, lamp):
    """The hw device set's camera, by cell.camera.driver."""
    config, bit_depth = task.cell.devices.camera, task.camera.sensor.bit_depth
    if config.driver == "simulated":
        from cell.scene import build_scene
        from sim.camera import SimCamera
        from sim.world import Renderer
        return SimCamera(Renderer(task, scene or build_scene(task)), arm, lamp, bit_depth)
    from cell.hw.opencv_camera import OpenCVCamera
    with speaking_for(OpenCVCamera):
        return OpenCVCamera(config, bit_depth, operator)
