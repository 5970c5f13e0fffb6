"""Device settings, the interfaces' safety checks, the simulated devices, and the real OpenCV
backend on files (the UR's connection: tests/test_ur_worker.py)."""
import io
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cell.devices import interfaces
from cell.run.backends import make_hw_devices
from cell.devices.interfaces import Devices
from cell.core.errors import DeviceFault, TaskError
from cell.devices.hw.opencv_camera import OpenCVCamera
from cell.task.loader import load_task
from cell.devices.operator import Operator
from cell.devices.rig import lamp_aim, lamp_joints, lamp_position
from cell.planning.scene import look_at
from cell.task.types import LampRig
from sim.arm import SimArm
from sim.camera import SimCamera
from sim.pantilt import SimPanTilt
from simcell import device_settings, variant

TASK = "tasks/hinge.yaml"
RIG = LampRig(pivot_m=np.array([0.006, 0.0, 0.004]), pan_range_rad=(-np.pi, np.pi),
              tilt_range_rad=(np.radians(5.0), np.radians(85.0)), radius_range_m=(0.15, 0.60),
              radius_axis="manual")
DEFAULTS = device_settings({}, TASK)
FRAMES = load_task(TASK).frames                     # the part at the origin, the default arm
HINGE_CAMERA = look_at(np.array([-0.019, 0.0, 0.503]), RIG.pivot_m)      # as the hinge plan has it


class Terminal(io.StringIO):
    """An interactive stdin whose operator presses Enter."""

    def isatty(self):
        return True


# --- settings -------------------------------------------------------------------------------

def test_defaults_are_the_example_cell_and_reach_no_network():
    assert DEFAULTS.arm.host is None and DEFAULTS.pan_tilt.port is None
    assert FRAMES.T_cell_base[:3, 3] == pytest.approx([0.0, -0.40, 0.0])
    assert FRAMES.T_flange_cam[:3, 3] == pytest.approx([0.0, 0.0, 0.05])
    assert DEFAULTS.pan_tilt.baud == 57600 and DEFAULTS.camera.exposure_unit_s == 1e-4


def test_settings_in_other_units_are_converted(tmp_path):
    task = load_task(variant(tmp_path, TASK, {
        "cell.arm": {"host": "192.0.2.10", "base_position_mm": [100, -500, 0], "base_rpy_deg": [0, 0, 90],
                     "connect_timeout_ms": 500},
        "cell.pan_tilt": {"port": "/dev/ttyUSB0", "speed_deg_s": 45, "tilt_offset_deg": -90}}))
    config = task.cell.devices
    assert config.arm.host == "192.0.2.10" and config.arm.connect_timeout_s == 0.5
    assert task.frames.T_cell_base[:3, 3] == pytest.approx([0.1, -0.5, 0.0])
    assert task.frames.T_cell_base[:3, 0] == pytest.approx([0.0, 1.0, 0.0])
    assert config.pan_tilt.speed_rad_s == pytest.approx(np.radians(45))
    assert config.pan_tilt.tilt_offset_rad == pytest.approx(-np.pi / 2)


@pytest.mark.parametrize("raw, key, expected", [
    ({"arm": {"hots": "10.0.0.2"}}, "cell.arm.hots", "did you mean 'host'"),
    ({"arm": {"host": 12}}, "cell.arm.host", "a non-empty text"),
    ({"arm": {"speed_m_s": 2.0}}, "cell.arm.speed_m_s", "a speed in (0, 0.25] m/s"),
    ({"arm": {"workspace_min_m": [0, 0, 0], "workspace_max_m": [1, 1, 0]}}, "cell.arm.workspace_max_m",
     "above workspace_min_m"),
    ({"pan_tilt": {"baud": 12345}}, "cell.pan_tilt.baud", "one of the SDK's rates"),
    ({"pan_tilt": {"pan_id": 2}}, "cell.pan_tilt.tilt_id", "distinct pan, tilt and radius ids"),
    ({"pan_tilt": {"pan_id": True}}, "cell.pan_tilt.pan_id", "an integer in 0..252"),
    ({"camera": {"source": -1}}, "cell.camera.source", "a camera index"),
    ({"lamp": {}}, "cell.lamp", "one of arm, pan_tilt, camera"),
])
def test_bad_settings_name_file_key_and_expectation(raw, key, expected):
    with pytest.raises(TaskError) as error:
        device_settings(raw, TASK)
    assert error.value.file == TASK and error.value.key == key and expected in error.value.expected
    assert error.value.exit_code == 2


def test_hardware_backend_needs_an_explicit_host_and_port():
    task = SimpleNamespace(cell=SimpleNamespace(devices=DEFAULTS), channels={})    # no light on a channel
    with pytest.raises(TaskError, match=r"cell.arm.host: found nothing, expected the robot's address"):
        make_hw_devices(task)
    task.cell.devices = device_settings({"arm": {"host": "127.0.0.1"}}, TASK)
    with pytest.raises(TaskError, match="cell.pan_tilt.port"):
        make_hw_devices(task)


# --- arm ------------------------------------------------------------------------------------

def test_sim_arm_puts_the_camera_where_asked_for_both_example_tasks():
    arm = SimArm(DEFAULTS.arm, FRAMES)
    for T in (HINGE_CAMERA, look_at(np.array([0.0, 0.0175, 0.357]), np.array([0.0, 0.0, 0.008]))):
        arm.move_camera(T)
        assert arm.camera_pose() == pytest.approx(T, abs=1e-9)


@pytest.mark.parametrize("T, speed, reason", [
    (look_at(np.array([0.0, 0.0, 0.05]), np.zeros(3)), None, "camera at .* outside the workspace"),
    (HINGE_CAMERA, 0.2, r"speed 0.2 m/s outside \(0, 0.1\]"),
    (HINGE_CAMERA * 1.01, None, "not a rigid transform"),
])
def test_arm_refuses_before_moving(T, speed, reason):
    arm = SimArm(DEFAULTS.arm, FRAMES)
    before = arm.joints.copy()
    with pytest.raises(DeviceFault, match=reason):
        arm.move_camera(T, speed)
    assert np.array_equal(arm.joints, before) and arm.moves == 0


def test_unreachable_pose_inside_the_envelope_says_why():
    arm = SimArm(DEFAULTS.arm, FRAMES)
    with pytest.raises(DeviceFault, match="unreachable for the UR5e: wrist .* mm from the shoulder"):
        arm.move_camera(look_at(np.array([0.55, 0.55, 0.9]), np.array([0.6, 0.6, 0.0])))


def test_injected_arm_fault_on_the_second_move():
    arm = SimArm(DEFAULTS.arm, FRAMES, fail_on_move=2)
    arm.move_camera(HINGE_CAMERA)
    with pytest.raises(DeviceFault, match="protective stop during move 2"):
        arm.move_camera(HINGE_CAMERA)


# --- lamp rig -------------------------------------------------------------------------------

@settings(max_examples=100, deadline=None)
@given(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(0.1, 1.0))
def test_lamp_joints_invert_lamp_position_and_the_lamp_aims_at_the_pivot(pan, tilt, radius):
    p = lamp_position(RIG.pivot_m, pan, tilt, radius)
    assert np.array(lamp_joints(RIG.pivot_m, p)) == pytest.approx([pan, tilt, radius], abs=1e-9)
    assert RIG.pivot_m == pytest.approx(p + radius * lamp_aim(RIG.pivot_m, p), abs=1e-12)


def test_sim_pantilt_reads_back_the_quantized_joints():
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt, operator=Operator(yes=True, stdout=io.StringIO()))
    rig.move(np.radians(33.3), np.radians(41.7), 0.31)
    pan, tilt, radius = rig.joints()
    tick = 2 * np.pi / 4096
    assert pan / tick == pytest.approx(round(np.radians(33.3) / tick), abs=1e-9)
    assert abs(pan - np.radians(33.3)) <= tick / 2 and abs(tilt - np.radians(41.7)) <= tick / 2
    assert radius == 0.31
    position, aim = rig.lamp_pose()
    assert position == pytest.approx(lamp_position(RIG.pivot_m, pan, tilt, radius))


def test_pan_of_180_deg_wraps_to_the_servos_turn():
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt)
    rig.move(np.pi, np.radians(45.0), 0.3)
    assert rig.present[1] == 0 and rig.joints()[0] == pytest.approx(-np.pi)


@pytest.mark.parametrize("joints, reason", [
    ((0.0, np.radians(90.0), 0.3), r"tilt 90 deg outside the rig's range \[5, 85\] deg"),
    ((0.0, np.radians(45.0), 0.7), r"radius 0.7 m outside the rig's range \[0.15, 0.6\] m"),
])
def test_lamp_rig_refuses_joints_outside_its_ranges_before_moving(joints, reason):
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt)
    with pytest.raises(DeviceFault, match=reason):
        rig.move(*joints)
    assert rig.moves == 0


def test_servo_position_limits_are_checked_before_moving():
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt, limits={2: (2048, 2900)})
    with pytest.raises(DeviceFault, match=r"servo 2: goal tick 3015 outside its position limits"):
        rig.move(0.0, np.radians(85.0), 0.3)


def test_injected_hardware_error_names_the_servo_and_safe_stop_turns_its_torque_off():
    arm = SimArm(DEFAULTS.arm, FRAMES)
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt, fail_on_move=2, fail_bits=0x24)
    cell = Devices(arm, rig, SimCamera(lambda *a: np.zeros((4, 4), np.uint8), arm, rig))
    rig.move(0.0, np.radians(45.0), 0.3)
    with pytest.raises(DeviceFault, match=r"servo 2: Hardware Error Status 0x24 \(overheating, overload") as f:
        rig.move(0.1, np.radians(45.0), 0.3)
    assert cell.safe_stop(f.value) == []
    assert rig.torque == {1: False, 2: False}


def test_another_devices_fault_keeps_the_servo_torque_on():
    arm = SimArm(DEFAULTS.arm, FRAMES)
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt)
    Devices(arm, rig, SimCamera(None, arm, rig)).safe_stop(DeviceFault("arm", "protective stop"))
    assert rig.torque == {1: True, 2: True}


def test_manual_radius_prompts_the_operator_once_per_radius():
    out = io.StringIO()
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt, operator=Operator(stdin=Terminal("\n\n"), stdout=out))
    rig.move(0.0, np.radians(45.0), 0.3)
    rig.move(0.5, np.radians(30.0), 0.3)
    assert out.getvalue().count("set the lamp radius (pivot to lamp) to 300.0 mm") == 1
    assert rig.joints()[2] == 0.3


def test_manual_radius_without_a_terminal_or_yes_fails_before_anything_moves():
    with pytest.raises(DeviceFault, match="stdin is not a terminal: run with --yes"):
        SimPanTilt(RIG, DEFAULTS.pan_tilt, operator=Operator(stdin=io.StringIO("\n")))


def test_operator_closing_stdin_is_a_fault():
    rig = SimPanTilt(RIG, DEFAULTS.pan_tilt, operator=Operator(stdin=Terminal(""), stdout=io.StringIO()))
    with pytest.raises(DeviceFault, match="stdin closed before the operator confirmed"):
        rig.move(0.0, np.radians(45.0), 0.3)


# --- sim camera -----------------------------------------------------------------------------

def test_sim_camera_renders_from_the_read_back_poses_and_settings():
    calls = []
    arm, rig = SimArm(DEFAULTS.arm, FRAMES), SimPanTilt(RIG, DEFAULTS.pan_tilt)

    def render(T_cell_cam, lamp_pos, lamp_aim_, shutter_s, f_number, focus_m):
        calls.append((T_cell_cam, lamp_pos, lamp_aim_, shutter_s, f_number, focus_m))
        return np.full((3, 4), 7, np.uint8)

    camera = SimCamera(render, arm, rig)
    with pytest.raises(DeviceFault, match="before the shutter time and f-number were set"):
        camera.capture()
    arm.move_camera(HINGE_CAMERA)
    rig.move(0.0, np.radians(45.0), 0.3)
    assert camera.set_exposure(0.0116) == 0.0116
    camera.set_aperture(5.6)
    assert camera.capture().shape == (3, 4) and calls[-1][-1] is None     # the renderer's focus
    camera.set_focus(0.5)
    camera.capture()
    T, lamp_pos, aim, shutter_s, f_number, focus_m = calls[-1]
    assert T == pytest.approx(HINGE_CAMERA) and (shutter_s, f_number, focus_m) == (0.0116, 5.6, 0.5)
    assert lamp_pos == pytest.approx(rig.lamp_pose()[0]) and aim == pytest.approx(rig.lamp_pose()[1])


def test_sim_camera_injected_timeout():
    arm, rig = SimArm(DEFAULTS.arm, FRAMES), SimPanTilt(RIG, DEFAULTS.pan_tilt)
    camera = SimCamera(lambda *a: np.zeros((2, 2), np.uint8), arm, rig, fail_on_capture=1, timeout_s=0.5)
    with pytest.raises(DeviceFault, match=r"camera: capture timed out after 0.5 s"):
        camera.capture()


# --- OpenCV camera on files -----------------------------------------------------------------

def opencv_camera(source, bit_depth=8, stdout=None):
    return OpenCVCamera(replace(DEFAULTS.camera, source=str(source), discard_frames=0), bit_depth,
                        Operator(yes=True, stdout=stdout or io.StringIO()))


def test_opencv_camera_captures_gray_frames_from_a_video_file(tmp_path):
    path = tmp_path / "frames.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48), isColor=True)
    for gray in (20, 70, 120):
        writer.write(np.full((48, 64, 3), gray, np.uint8))
    writer.release()
    camera = opencv_camera(path)
    for gray in (20, 70, 120):
        frame = camera.capture()
        assert frame.shape == (48, 64) and frame.dtype == np.uint8
        assert frame.mean() == pytest.approx(gray, abs=1.0)
    with pytest.raises(DeviceFault, match="no frame from"):
        camera.capture()
    camera.close()


def test_opencv_camera_reads_an_image_sequence_and_refuses_exposure_on_a_file(tmp_path):
    for i, gray in enumerate((10, 200)):
        cv2.imwrite(str(tmp_path / f"frame_{i:03d}.png"), np.full((8, 6), gray, np.uint8))
    out = io.StringIO()
    camera = opencv_camera(tmp_path / "frame_%03d.png", stdout=out)
    assert camera.capture().max() == 10
    with pytest.raises(DeviceFault, match="refused CAP_PROP_AUTO_EXPOSURE = 1"):
        camera.set_exposure(0.0116)
    camera.set_aperture(5.6)
    assert "camera: set the lens to f/5.6" in out.getvalue()
    camera.set_focus(0.5)
    camera.set_focus(0.5004)                    # within a millimetre: not asked again
    assert out.getvalue().count("camera: focus the lens at 500 mm") == 1
    with pytest.raises(DeviceFault, match="frames are uint8, a 12-bit sensor gives uint16"):
        opencv_camera(tmp_path / "frame_%03d.png", bit_depth=12).capture()


def test_opencv_camera_missing_file_is_a_fault(tmp_path):
    with pytest.raises(DeviceFault, match="cannot open .*missing.avi"):
        opencv_camera(tmp_path / "missing.avi")


def test_a_calibrated_hand_eye_moves_the_flange_and_keeps_the_camera_where_asked():
    arm = SimArm(DEFAULTS.arm, FRAMES.with_transform("T_flange_cam", look_at(np.array([0.0, 0.03, 0.08]),
                                                                            np.array([0.0, 0.03, 1.0]))))
    arm.move_camera(HINGE_CAMERA)
    assert arm.camera_pose() == pytest.approx(HINGE_CAMERA, abs=1e-9)
    assert arm.frames.T_cell_base is FRAMES.T_cell_base and FRAMES.T_flange_cam[:3, 3] == pytest.approx(
        [0.0, 0.0, 0.05])                                   # the task's own frames are unchanged
    with pytest.raises(ValueError, match="no transform 'T_cell_lamp'"):
        FRAMES.with_transform("T_cell_lamp", np.eye(4))


def test_the_flange_must_stay_in_the_workspace_too():
    interfaces.check_arm_motion(DEFAULTS.arm, FRAMES, HINGE_CAMERA, 0.1)
    looking_up = look_at(np.array([0.0, 0.0, 0.12]), np.array([0.0, 0.0, 1.0]))   # flange 5 cm below
    with pytest.raises(DeviceFault, match=r"flange at \[0.0, 0.0, 0.07\] m is outside the workspace"):
        interfaces.check_arm_motion(DEFAULTS.arm, FRAMES, looking_up, 0.1)


def test_no_stdin_at_all_or_a_closed_one_is_no_operator_not_a_traceback(monkeypatch, tmp_path):
    """Started with stdin closed (`<&-`) Python has sys.stdin None; a closed stream raises on
    isatty: either way nobody can answer, a DeviceFault before anything moves."""
    monkeypatch.setattr("sys.stdin", None)
    with pytest.raises(DeviceFault, match="needs the operator"):
        Operator().require("pan-tilt", "the lamp radius")
    closed = open(tmp_path / "in.txt", "w")
    closed.close()
    with pytest.raises(DeviceFault, match="needs the operator"):
        Operator(stdin=closed).require("camera", "the lens")
