"""The GenICam camera backend (cell.camera.driver: genicam): its settings, the PFNC conversion on
hand-made buffers, the real harvesters/GenTL path against genicam 1.6.0's software producer
viky.cti (a 400x400 Mono8 test pattern: white, with a black BouncingBallSize square moving one
pixel a frame), for the nodes viky lacks (ExposureTime, Gain, trigger) a fake device
(tests/genicam_fake.py), and `cell run --backend hw` on viky with the UR and servo emulators."""
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import genicam
import numpy as np
import pytest
from genicam import gentl

from cell.run.backends import hw_camera
from cell.cli import main
from cell.core.errors import DeviceFault, TaskError
from cell.devices.hw import genicam_camera
from cell.devices.hw.genicam_camera import GenICamCamera, mono_to_gray, pick_pixel_format
from cell.task.loader import load_task
from cell.devices.operator import Operator
from sim.dxl_emulator import DxlEmulator
from genicam_fake import Buffer, FakeCamera, FloatNode, NodeMap, harvester_of
from loopback import free_host
from simcell import device_settings, variant

TASK = "tasks/hinge.yaml"
VIKY = Path(genicam.__file__).parent / "viky.cti"
VIKY_SENSOR = SimpleNamespace(width_px=400, height_px=400, bit_depth=8)
YES = Operator(yes=True)


def genicam_settings(bit_depth=8, **keys):
    """cell.camera as load_task reads it, driver genicam on viky.cti unless keys say otherwise."""
    return device_settings({"camera": {"driver": "genicam", "cti": str(VIKY), **keys}},
                           bit_depth=bit_depth).camera


# --- settings -------------------------------------------------------------------------------

def test_genicam_settings_and_their_defaults(tmp_path):
    (tmp_path / "producer.cti").write_bytes(b"")
    task = load_task(variant(tmp_path, TASK, {"cell.camera": {
        "driver": "genicam", "cti": "producer.cti", "serial_number": 22345678, "frame_timeout_ms": 250}}))
    camera = task.cell.devices.camera
    assert camera.driver == "genicam" and camera.cti == tmp_path / "producer.cti"   # beside the task
    assert camera.serial_number == "22345678"          # YAML's integer is the serial number's text
    assert camera.frame_timeout_s == 0.25
    assert camera.pixel_format is None and camera.gain is None and camera.device_index == 0
    assert load_task(TASK).cell.devices.camera.driver == "opencv"


@pytest.mark.parametrize("camera, key, found, expected", [
    ({"driver": "genicam"}, "cell.camera.cti", "nothing", "GenTL producer file (.cti)"),
    ({"driver": "genicam", "cti": "nowhere.cti"}, "cell.camera.cti", "'nowhere.cti', which is not a file",
     ".cti"),
    ({"driver": "genicam", "cti": str(Path(TASK).resolve())}, "cell.camera.cti", "/hinge.yaml'", ".cti"),
    ({"driver": "genicam", "cti": str(VIKY), "source": 1}, "cell.camera.source",
     "a setting of driver opencv", "only the keys of driver genicam: cti, serial_number"),
    ({"pixel_format": "Mono8"}, "cell.camera.pixel_format", "a setting of driver genicam",
     "only the keys of driver opencv: source"),
    ({"frame_timeout_ms": 100}, "cell.camera.frame_timeout_ms", "a setting of driver genicam", "opencv"),
    ({"driver": "genicam", "cti": str(VIKY), "serial_number": "1", "device_index": 1},
     "cell.camera.device_index", "1 and serial_number '1' both", "the device named one way"),
    ({"driver": "genicam", "cti": str(VIKY), "pixel_format": "Mono8"}, "cell.camera.pixel_format",
     "Mono8 (8 bits)", "at least camera.sensor.bit_depth 12 bits: Mono12, Mono16"),
    ({"driver": "genicam", "cti": str(VIKY), "pixel_format": "RGB8"}, "cell.camera.pixel_format",
     "'RGB8'", "one of Mono8 | Mono12 | Mono16"),
    ({"driver": "gige"}, "cell.camera.driver", "'gige'", "one of opencv | genicam"),
])
def test_bad_genicam_settings_name_file_key_and_expectation(camera, key, found, expected):
    with pytest.raises(TaskError) as err:
        device_settings({"camera": camera}, bit_depth=12)
    assert err.value.key == key and err.value.found.endswith(found), err.value
    assert expected in err.value.expected, err.value


def test_cell_check_refuses_bad_genicam_settings_with_exit_2(tmp_path, capsys):
    task = variant(tmp_path, TASK, {"cell.camera": {"driver": "genicam", "cti": "missing.cti"}})
    assert main(["check", str(task)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cell.camera.cti" in err[0] and "missing.cti" in err[0], err


def test_cell_check_of_a_genicam_task_loads_no_genicam_library(tmp_path):
    """The SDK is imported when the camera is opened, never to check a task (a fresh interpreter)."""
    task = variant(tmp_path, TASK, {"cell.camera": {"driver": "genicam", "cti": str(VIKY)}})
    code = (f"import sys; from cell.cli import main; assert main(['check', {str(task)!r}]) == 0; "
            "print([m for m in ('harvesters', 'genicam', 'cv2') if m in sys.modules])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_genicam_driver_without_its_sdk_is_bad_input_before_anything_connects(tmp_path, monkeypatch):
    task = load_task(variant(tmp_path, TASK, {"cell.camera": {"driver": "genicam", "cti": str(VIKY)}}))
    monkeypatch.delitem(sys.modules, "cell.devices.hw.genicam_camera")
    monkeypatch.setitem(sys.modules, "harvesters.core", None)        # import fails, as uninstalled
    with pytest.raises(TaskError) as err:
        hw_camera(task)
    assert err.value.key == "cell.camera.driver" and "lightplan-cell[genicam]" in err.value.expected


# --- PFNC to the sensor's gray levels, on buffers made by hand -------------------------------

MONO12 = bytes([0xFF, 0x0F, 0x00, 0x08, 0x01, 0x00, 0x34, 0x02])     # 4095, 2048, 1, 0x234 = 564
MONO16 = bytes([0xFF, 0xFF, 0x00, 0x80, 0x34, 0x12, 0x0F, 0x00])     # 65535, 32768, 0x1234 = 4660, 15


@pytest.mark.parametrize("raw, fmt, bit_depth, gray, dtype", [
    (MONO12, "Mono12", 12, [4095, 2048, 1, 564], np.uint16),
    (MONO12, "Mono12", 10, [1023, 512, 0, 141], np.uint16),          # >> 2: 564 / 4 = 141
    (MONO12, "Mono12", 8, [255, 128, 0, 35], np.uint8),              # >> 4: 564 / 16 = 35.25
    (MONO16, "Mono16", 16, [65535, 32768, 4660, 15], np.uint16),
    (MONO16, "Mono16", 12, [4095, 2048, 291, 0], np.uint16),         # 0x1234 >> 4 = 0x123
    (MONO16, "Mono16", 8, [255, 128, 18, 0], np.uint8),              # 0x1234 >> 8 = 0x12
    (bytes([0, 127, 128, 255]), "Mono8", 8, [0, 127, 128, 255], np.uint8),
    (bytes([0, 127, 128, 255]), "Mono8", 6, [0, 31, 32, 63], np.uint8),
])
def test_mono_buffers_become_the_sensors_gray_levels(raw, fmt, bit_depth, gray, dtype):
    image = mono_to_gray(raw, fmt, 2, 2, bit_depth)
    assert image.dtype == dtype and image.tolist() == [gray[:2], gray[2:]]


def test_row_padding_is_skipped_and_bits_beyond_the_format_ignored():
    # 2x2 Mono12, each row followed by 3 padding bytes; 0xF001 has bits above the 12 (PFNC: zero)
    raw = bytes([0x01, 0xF0, 0x02, 0x00, 0xAA, 0xBB, 0xCC, 0x03, 0x00, 0x04, 0x00])
    assert mono_to_gray(raw, "Mono12", 2, 2, 12, padding_x=3).tolist() == [[1, 2], [3, 4]]


@pytest.mark.parametrize("raw, fmt, bit_depth, reason", [
    (bytes(4), "Mono8", 12, "Mono8 frames carry 8 bits, fewer than camera.sensor.bit_depth 12"),
    (bytes(7), "Mono12", 12, "needs 8 bytes, the buffer has 7"),
    (bytes(12), "RGB8", 8, "frames in RGB8"),
])
def test_a_buffer_that_cannot_give_the_sensors_levels_is_a_camera_fault(raw, fmt, bit_depth, reason):
    with pytest.raises(DeviceFault) as err:
        mono_to_gray(raw, fmt, 2, 2, bit_depth)
    assert err.value.device == "camera" and reason in err.value.reason


@pytest.mark.parametrize("bit_depth, offered, chosen", [
    (8, ["RGB8", "Mono16", "Mono12", "Mono8"], "Mono8"),
    (12, ["Mono8", "Mono12", "Mono16"], "Mono12"),
    (10, ["Mono8", "Mono12", "Mono16"], "Mono12"),     # no Mono10 here: the shallowest deeper one
    (14, ["Mono8", "Mono12", "Mono16"], "Mono16"),
    (6, ["Mono16", "Mono8"], "Mono8"),
    (12, ["RGBa8", "Mono8"], None),                   # viky.cti for a 12-bit sensor
])
def test_the_default_pixel_format_carries_the_sensors_bits_with_the_least_data(bit_depth, offered, chosen):
    assert pick_pixel_format(offered, bit_depth) == chosen


# --- the real harvesters path against viky.cti -----------------------------------------------

class Exposure:
    """Lays a fake ExposureTime (1 us steps) over viky's real node map, which lacks one; every
    other node, the stream and the frames are the producer's own."""

    def __init__(self):
        self.node = FloatNode(1000.0, 10.0, 1e6, step=1.0)

    def over(self, nodes):
        exposure = self

        class Overlaid(NodeMap):
            def has_node(self, name):
                return name == "ExposureTime" or nodes.has_node(name)

            def __getattr__(self, name):
                return exposure.node if name == "ExposureTime" else getattr(nodes, name)

        return Overlaid({})


def viky_camera(config, sensor=VIKY_SENSOR):
    """GenICamCamera on viky with the ExposureTime overlay; .real: viky's own node map."""
    overlay = Exposure()

    class VikyWithExposure(GenICamCamera):
        def _nodes(self):
            self.real = super()._nodes()
            return overlay.over(self.real)

    return VikyWithExposure(config, sensor, YES)


def square_of_zeros(image):
    """(row, col, side) of the black square in a white frame; asserts that is all it holds."""
    dark = np.argwhere(image == 0)
    (r0, c0), (r1, c1) = dark.min(0), dark.max(0)
    assert np.unique(image).tolist() == [0, 255]
    assert r1 - r0 == c1 - c0 and len(dark) == (r1 - r0 + 1) ** 2      # a full square, nothing else
    return int(r0), int(c0), int(r1 - r0 + 1)


def test_viky_lacks_exposure_time_the_fault_names_node_and_device_and_releases_it():
    for _ in range(2):      # the first open released the device: the second reaches the same node
        with pytest.raises(DeviceFault) as err:
            GenICamCamera(genicam_settings(), VIKY_SENSOR, YES)
        assert err.value.device == "camera"
        assert "Viky serial 0 (viky.cti) has no ExposureTime node" in err.value.reason


def test_frames_from_viky_are_its_test_pattern_at_its_shape_and_dtype():
    camera = viky_camera(genicam_settings())
    try:
        assert camera.triggered is False and camera.pixel_format == "Mono8"  # free-running: no trigger
        camera.real.BouncingBallSize.value = 13          # the producer's pattern, set through GenICam
        first, second = camera.capture(), camera.capture()
        for image in (first, second):
            assert image.shape == (400, 400) and image.dtype == np.uint8
            assert square_of_zeros(image)[2] == 13
        assert square_of_zeros(first)[:2] != square_of_zeros(second)[:2]    # each capture a new frame
        assert camera.real.PixelFormat.value == "Mono8"
    finally:
        camera.close()


def test_viky_devices_by_serial_number_and_index():
    camera = viky_camera(genicam_settings(serial_number="2"))
    camera.close()
    assert camera.name == "Viky serial 2 (viky.cti)"
    camera = viky_camera(genicam_settings(device_index=1))
    camera.close()
    assert camera.name == "Viky serial 1 (viky.cti)"
    for keys, reason in (({"serial_number": "7"}, "0 devices with serial number '7'"),
                         ({"device_index": 3}, "cell.camera.device_index 3, but")):
        with pytest.raises(DeviceFault) as err:
            viky_camera(genicam_settings(**keys))
        assert reason in err.value.reason and "Viky serial 0, Viky serial 1, Viky serial 2" in err.value.reason


@pytest.mark.parametrize("sensor, keys, reason", [
    (SimpleNamespace(width_px=640, height_px=480, bit_depth=8), {},
     "delivers 400x400 px (Width, Height), camera.sensor is 640x480 px"),
    (SimpleNamespace(width_px=400, height_px=400, bit_depth=12), {},
     "offers PixelFormat RGBa8, Mono8; needed a Mono format of at least camera.sensor.bit_depth 12"),
    (SimpleNamespace(width_px=400, height_px=400, bit_depth=12), {"pixel_format": "Mono16"},
     "offers PixelFormat RGBa8, Mono8; needed cell.camera.pixel_format Mono16"),
    (VIKY_SENSOR, {"gain": 3.0}, "has no Gain node, which sets the gain (cell.camera.gain)"),
])
def test_what_viky_cannot_do_is_a_fault_at_connect(sensor, keys, reason):
    with pytest.raises(DeviceFault) as err:
        viky_camera(genicam_settings(sensor.bit_depth, **keys), sensor)
    assert reason in err.value.reason and err.value.device == "camera"


def test_a_frame_later_than_its_timeout_is_a_fault_and_the_stream_stops():
    """genicam's own TimeoutException from viky at 2 frames/s with a 0.2 s frame timeout."""
    camera = viky_camera(genicam_settings(frame_timeout_ms=200))
    try:
        camera.set_exposure(1e-3)
        camera.real.AcquisitionFrameRate.value = 2.0
        with pytest.raises(DeviceFault) as err:
            camera.capture()
        assert "sent no frame within 0.201 s" in err.value.reason
        assert not camera._acquirer.is_acquiring()
    finally:
        camera.close()


# --- exposure, gain, trigger: the nodes viky lacks, on a fake device -------------------------

def fake_camera(monkeypatch, device, bit_depth=12, **keys):
    """GenICamCamera on `device` (a FakeCamera) through a fake Harvester; returns it and the list
    of acquirers it created."""
    opened = []
    monkeypatch.setattr(genicam_camera, "Harvester", harvester_of(device, opened))
    sensor = SimpleNamespace(width_px=device.width, height_px=device.height, bit_depth=bit_depth)
    return GenICamCamera(genicam_settings(bit_depth, **keys), sensor, YES), opened


def test_exposure_is_set_in_microseconds_and_the_device_value_read_back(monkeypatch):
    device = FakeCamera()
    camera, _ = fake_camera(monkeypatch, device)
    assert camera.set_exposure(5.558e-3) == pytest.approx(5.5535e-3)   # 383 lines of 14.5 us
    assert device.nodes.ExposureTime.value == pytest.approx(5553.5)
    assert camera.shutter_s == pytest.approx(5.5535e-3)
    with pytest.raises(DeviceFault) as err:
        camera.set_exposure(2.0)
    assert "ExposureTime 2e+06 us outside its range 20..1e+06 us" in err.value.reason


def test_auto_exposure_and_auto_gain_are_off_and_the_gain_fixed(monkeypatch):
    device = FakeCamera()
    fake_camera(monkeypatch, device, gain=6.0)
    assert device.nodes.ExposureAuto.value == "Off" and device.nodes.GainAuto.value == "Off"
    assert device.nodes.Gain.value == 6.0
    untouched = FakeCamera()
    untouched.nodes.Gain.value = 2.5
    fake_camera(monkeypatch, untouched)                  # gain: null leaves the device's, fixed
    assert untouched.nodes.Gain.value == 2.5 and untouched.nodes.GainAuto.value == "Off"
    with pytest.raises(DeviceFault) as err:
        fake_camera(monkeypatch, FakeCamera(), gain=30.0)
    assert "cell.camera.gain 30 outside FakeCam serial FAKE-1" in err.value.reason


def test_software_trigger_takes_one_frame_per_capture_at_the_new_exposure(monkeypatch):
    device = FakeCamera()
    camera, _ = fake_camera(monkeypatch, device)
    nodes = device.nodes
    assert camera.triggered
    assert (nodes.TriggerSelector.value, nodes.TriggerMode.value, nodes.TriggerSource.value) == \
        ("FrameStart", "On", "Software")
    camera.set_exposure(1e-3)                            # 69 lines: 1000.5 us
    first = camera.capture()
    camera.set_exposure(2.5e-3)                          # 172 lines: 2494 us
    second = camera.capture()
    assert nodes.TriggerSoftware.executed == 2 and device.frames == 2        # nothing discarded
    assert (first[0, 0], second[0, 0]) == (1, 2)
    assert set(first.ravel()[1:]) == {1000} and set(second.ravel()[1:]) == {2494}
    assert first.shape == (6, 8) and first.dtype == np.uint16


def test_free_running_drops_the_frame_exposed_before_the_change(monkeypatch):
    """Without a trigger the first frame after an exposure change still has the old exposure
    (3000 us here): the capture is the second frame, at the new one."""
    device = FakeCamera(trigger=False)
    camera, _ = fake_camera(monkeypatch, device)
    assert not camera.triggered
    camera.set_exposure(1e-3)
    image = camera.capture()
    assert image[0, 0] == 2 and set(image.ravel()[1:]) == {1000}
    assert not device.acquiring                          # each capture stops the stream again
    assert camera.capture()[0, 0] == 4


@pytest.mark.parametrize("bit_depth, fmt, level", [
    (8, "Mono8", 255),            # 1000 us clips at Mono8's 255
    (12, "Mono12", 1000),
    (10, "Mono12", 250),          # 1000 >> 2
    (16, "Mono16", 1000),
])
def test_the_stream_format_follows_the_sensors_bit_depth(monkeypatch, bit_depth, fmt, level):
    device = FakeCamera()
    camera, _ = fake_camera(monkeypatch, device, bit_depth=bit_depth)
    camera.set_exposure(1e-3)
    assert device.nodes.PixelFormat.value == fmt
    assert set(camera.capture().ravel()[1:]) == {level}


def test_frames_in_another_format_than_set_are_a_fault(monkeypatch):
    """As TLSimu.cti (genicam 1.5.0) does: PixelFormat Mono12 accepted, Mono8 frames sent."""
    camera, _ = fake_camera(monkeypatch, FakeCamera(sends="Mono8"))
    with pytest.raises(DeviceFault) as err:
        camera.capture()
    assert "sent Mono8 frames, its PixelFormat is set to Mono12" in err.value.reason


def test_what_genicam_raises_becomes_a_fault_naming_the_camera(monkeypatch):
    device = FakeCamera()
    camera, opened = fake_camera(monkeypatch, device)

    def unplugged():
        raise gentl.IoException("GenTL exception: device lost")

    device.nodes.TriggerSoftware.action = unplugged
    with pytest.raises(DeviceFault) as err:
        camera.capture()
    assert err.value.device == "camera"
    assert err.value.reason == ("FakeCam serial FAKE-1 (viky.cti), capturing: IoException: "
                                "GenTL exception: device lost")
    device.nodes.ExposureTime.node.mode = genicam_camera.genapi.EAccessMode.RO
    with pytest.raises(DeviceFault) as err:
        camera.set_exposure(1e-3)
    assert "setting the exposure: AccessException: Node is not writable" in err.value.reason
    camera.close()
    camera.close()                                       # twice is harmless (safe stop, then close)
    assert opened[0].destroyed and not device.acquiring


def test_a_device_without_exposure_time_fails_at_connect_and_is_released(monkeypatch):
    device, opened = FakeCamera(), []
    del device.nodes._nodes["ExposureTime"]
    monkeypatch.setattr(genicam_camera, "Harvester", harvester_of(device, opened))
    with pytest.raises(DeviceFault) as err:
        GenICamCamera(genicam_settings(12), SimpleNamespace(width_px=8, height_px=6, bit_depth=12), YES)
    assert "FakeCam serial FAKE-1 (viky.cti) has no ExposureTime node" in err.value.reason
    assert opened[0].destroyed


@pytest.mark.parametrize("delivered, reason", [
    (None, "sent a buffer without its image information"),   # harvesters could not make a Buffer
    ("no payload", "sent a buffer without an image"),
])
def test_a_buffer_harvesters_cannot_read_is_a_fault(monkeypatch, delivered, reason):
    camera, opened = fake_camera(monkeypatch, FakeCamera())
    if delivered is not None:
        delivered = Buffer(None)
        delivered.payload = None                         # an unsupported payload type
    monkeypatch.setattr(opened[0], "fetch", lambda timeout: delivered)
    with pytest.raises(DeviceFault) as err:
        camera.capture()
    assert reason in err.value.reason


# --- the whole hw path: exit 3 naming the camera, before anything moves ----------------------

def test_cell_run_on_viky_is_exit_3_naming_camera_and_node_before_anything_moves(tmp_path, capsys):
    """The real ur_rtde against the UR emulator, the real dynamixel_sdk against the pty servos,
    the real harvesters against viky.cti: the missing ExposureTime ends the run at connect."""
    host = free_host()
    controller = subprocess.Popen([sys.executable, "-m", "sim.ur_controller", "--host", host,
                                   "--max-seconds", "60"], stdout=subprocess.PIPE, text=True)
    try:
        assert controller.stdout.readline().strip() == "READY"
        with DxlEmulator(ids=(1, 2)) as servos:
            task = variant(tmp_path, TASK, {
                "camera.sensor.width_px": 400, "camera.sensor.height_px": 400,   # viky's frames
                "cell.arm.host": host, "cell.pan_tilt.port": servos.port,
                "cell.camera": {"driver": "genicam", "cti": str(VIKY)}})
            out = tmp_path / "run"
            assert main(["run", str(task), "--backend", "hw", "--yes", "--out", str(out)]) == 3
    finally:
        controller.terminate()
        controller.wait(timeout=10)
        controller.stdout.close()
    fault = json.loads((out / "report.json").read_text())["fault"]
    assert fault["device"] == "camera" and "has no ExposureTime node" in fault["error"]
    assert fault["stop_failures"] == [] and fault["release_failures"] == []
    assert [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()] == \
        ["plan", "fault"]
    assert "Traceback" not in capsys.readouterr().err


def test_hw_checks_read_only_state_of_viky_reads_its_nodes_and_sets_none():
    """`cell hw-check`'s camera: opened read-only, viky's own node map (400 x 400, Mono8 or RGBa8
    offered; its default format is left as it was) and the ExposureTime it lacks named as a
    problem; its PixelFormat is not set, unlike a run's connect."""
    camera = GenICamCamera(genicam_settings(), VIKY_SENSOR, YES, read_only=True)
    try:
        before = camera._nodes().PixelFormat.value
        state = camera.state()
        assert camera._nodes().PixelFormat.value == before
    finally:
        camera.close()
    assert (state["width_px"], state["height_px"]) == (400, 400)
    assert state["pixel_format"] == before and set(state["pixel_formats"]) == {"Mono8", "RGBa8"}
    assert state["model"] == "Viky serial 0 (viky.cti)" and state["exposure_s"] is None
    assert state["problems"] == ["Viky serial 0 (viky.cti) has no ExposureTime node (GenICam SFNC name)"]
