"""GenICam devices for the tests, as harvesters presents them to cell.devices.hw.genicam_camera: node
proxies (`value`, `min`, `max`, `entries`, `execute()`, `node.get_access_mode()`), a node map
(`has_node`, attributes), an image acquirer and a Harvester. Used where no software producer on
PyPI has the nodes: viky.cti (genicam 1.6.0) has no ExposureTime, Gain or trigger, and neither
has TLSimu.cti (genicam 1.5.0) an ExposureTime.

FakeCamera is a sensor whose every pixel reads floor(exposure in us) (in the pixel format's
bits, clipped) except pixel (0, 0), the frame's number (1, 2, ...). Free-running, a frame is
exposed with the ExposureTime in effect when the frame before it was taken (a pipeline of one,
as sensors latch the exposure at the start of integration): the first frame after a change still
has the old exposure. A software-triggered frame is exposed after its trigger: the current one.
"""
from dataclasses import dataclass, field

import numpy as np
from genicam import genapi, gentl

RW, RO, NA = genapi.EAccessMode.RW, genapi.EAccessMode.RO, genapi.EAccessMode.NA
BITS = {"Mono8": 8, "Mono12": 12, "Mono16": 16}


class Access:
    def __init__(self, mode):
        self.mode = mode

    def get_access_mode(self):
        return self.mode


class FloatNode:
    """An IFloat quantized to `step` (a line time, say): reads back round(v / step) * step."""

    def __init__(self, value, low, high, step=None, mode=RW):
        self.min, self.max, self.step, self.node = low, high, step, Access(mode)
        self._value = value

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if self.node.mode != RW:
            raise genapi.AccessException("Node is not writable")
        self._value = round(v / self.step) * self.step if self.step else float(v)


@dataclass
class Entry:
    symbolic: str
    node: Access = field(default_factory=lambda: Access(RO))


class EnumNode:
    def __init__(self, value, *symbolics):
        self.entries = [Entry(s) for s in symbolics]
        self.node, self._value = Access(RW), value

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if v not in [e.symbolic for e in self.entries]:
            raise genapi.InvalidArgumentException(f"cannot convert value '{v}'")
        self._value = v


class IntNode:
    def __init__(self, value):
        self.value, self.node = value, Access(RO)


class CommandNode:
    def __init__(self, action):
        self.action, self.node, self.executed = action, Access(RW), 0

    def execute(self):
        self.executed += 1
        self.action()


class NodeMap:
    def __init__(self, nodes):
        self._nodes = nodes

    def has_node(self, name):
        return name in self._nodes

    def __getattr__(self, name):
        try:
            return self.__dict__["_nodes"][name]
        except KeyError:
            raise AttributeError(name) from None


@dataclass
class Image:
    """harvesters' Component2DImage: `data` as harvesters expands it (uint8 or uint16)."""
    data: np.ndarray
    data_format: str
    width: int
    height: int
    x_padding: int = 0


class Buffer:
    def __init__(self, image):
        self.payload = type("Payload", (), {"components": [image]})()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class FakeCamera:
    """A camera with ExposureTime, ExposureAuto, Gain, GainAuto, PixelFormat and, if `trigger`,
    TriggerSelector / TriggerMode / TriggerSource / TriggerSoftware. `sends` overrides the pixel
    format its frames say they are in (TLSimu.cti, for one, takes PixelFormat Mono12 and still
    sends Mono8)."""

    def __init__(self, width=8, height=6, trigger=True, formats=("Mono8", "Mono12", "Mono16"),
                 exposure_us=3000.0, sends=None):
        self.width, self.height, self.sends = width, height, sends
        self.acquiring, self.frames, self.pending = False, 0, 0
        nodes = {
            "Width": IntNode(width), "Height": IntNode(height),
            "PixelFormat": EnumNode(formats[0], *formats),
            "ExposureTime": FloatNode(exposure_us, 20.0, 1e6, step=14.5),
            "ExposureAuto": EnumNode("Continuous", "Off", "Once", "Continuous"),
            "Gain": FloatNode(0.0, 0.0, 24.0),
            "GainAuto": EnumNode("Continuous", "Off", "Continuous"),
        }
        if trigger:
            nodes.update({
                "TriggerSelector": EnumNode("AcquisitionStart", "AcquisitionStart", "FrameStart"),
                "TriggerMode": EnumNode("Off", "Off", "On"),
                "TriggerSource": EnumNode("Line1", "Line1", "Software"),
                "TriggerSoftware": CommandNode(self._trigger)})
        self.nodes = NodeMap(nodes)
        self.latched_us = exposure_us           # what the next free-running frame is exposed with

    def _trigger(self):
        if self.acquiring and self.nodes.TriggerMode.value == "On":
            self.pending += 1

    def frame(self, exposure_us):
        self.frames += 1
        fmt = self.nodes.PixelFormat.value
        bits = BITS[fmt]
        image = np.full((self.height, self.width), min(int(exposure_us), 2**bits - 1),
                        np.uint8 if bits == 8 else np.uint16)
        image[0, 0] = self.frames
        return Buffer(Image(image.ravel(), self.sends or fmt, self.width, self.height))

    def fetch(self, timeout):
        exposure_us = self.nodes.ExposureTime.value
        if not self.acquiring:
            raise gentl.TimeoutException("not acquiring")
        if "TriggerMode" in self.nodes._nodes and self.nodes.TriggerMode.value == "On":
            if not self.pending:
                raise gentl.TimeoutException("no trigger")
            self.pending -= 1
            return self.frame(exposure_us)
        frame, self.latched_us = self.frame(self.latched_us), exposure_us
        return frame


class Acquirer:
    def __init__(self, camera):
        self.camera, self.destroyed = camera, False
        self.remote_device = type("RemoteDevice", (), {"node_map": camera.nodes})()

    def is_acquiring(self):
        return self.camera.acquiring

    def start(self):
        self.camera.acquiring = True

    def stop(self):
        self.camera.acquiring, self.camera.pending = False, 0

    def fetch(self, timeout):
        return self.camera.fetch(timeout)

    def destroy(self):
        self.destroyed = True


@dataclass
class Info:
    model: str
    serial_number: str


def harvester_of(camera, opened):
    """A Harvester class listing `camera` (serial 'FAKE-1'); each acquirer created is appended
    to `opened`."""
    class Harvester:
        device_info_list = [Info("FakeCam", "FAKE-1")]

        def add_file(self, path):
            self.cti = path

        def update(self):
            pass

        def create(self, info):
            opened.append(Acquirer(camera))
            return opened[-1]

        def reset(self):
            pass

    return Harvester
