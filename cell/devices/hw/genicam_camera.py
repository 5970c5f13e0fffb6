"""An industrial camera (GigE Vision, USB3 Vision) through GenICam: `harvesters` loads the vendor's
GenTL producer (cell.camera.cti) and drives the device by its standard (SFNC) nodes. The lens is
set by the operator, as with OpenCV."""

from __future__ import annotations

from collections.abc import Iterable
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np
from genicam import genapi, gentl
from harvesters.core import Harvester

from cell.task.device_config import MONO_FORMATS
from cell.devices.interfaces import Camera
from cell.core.errors import DeviceFault
from cell.devices.hw.lens import ManualLensCamera
from cell.devices.session import try_all

if TYPE_CHECKING:
    from cell.devices.operator import Operator
    from cell.task.device_config import CameraConfig
    from cell.task.types import Sensor

# what genicam raises (harvesters passes it on): node access (genapi), transport layer (gentl)
GENICAM_ERRORS = (genapi.GenericException, gentl.GenericException)
UNAVAILABLE = (genapi.EAccessMode.NI, genapi.EAccessMode.NA)
WRITABLE = (genapi.EAccessMode.WO, genapi.EAccessMode.RW)


def pick_pixel_format(offered: Iterable[str], bit_depth: int) -> str | None:
    """The Mono format to stream from a sensor of `bit_depth` bits, of those `offered`: the one with
    exactly its bits, else the shallowest deeper one (shifted down: no gray level made up, the
    least data); None when every offered Mono format has fewer bits."""
    deep_enough = [f for f in offered if MONO_FORMATS.get(f, 0) >= bit_depth]
    return min(deep_enough, key=lambda f: MONO_FORMATS[f], default=None)


def mono_to_gray(raw: bytes | np.ndarray, pixel_format: str, width: int, height: int, bit_depth: int,
                 padding_x: int = 0) -> np.ndarray:
    """A PFNC Mono8 / Mono12 / Mono16 buffer (unpacked, little-endian; p bits LSB-aligned, so
    values 0 .. 2^p - 1; each row followed by `padding_x` bytes) as the sensor's gray levels
    G = v >> (p - b), 0 .. 2^b - 1: uint8 for b <= 8, else uint16. p < b would make up levels."""
    bits = MONO_FORMATS.get(pixel_format)
    if bits is None:
        raise DeviceFault(Camera.device, f"frames in {pixel_format}, expected one of "
                                         + ", ".join(MONO_FORMATS))
    if bits < bit_depth:
        raise DeviceFault(Camera.device, f"{pixel_format} frames carry {bits} bits, fewer than "
                                         f"camera.sensor.bit_depth {bit_depth}")
    size = 1 if bits == 8 else 2
    stride = width * size + padding_x
    raw = np.frombuffer(raw, np.uint8)
    if raw.size < height * stride - padding_x:
        raise DeviceFault(Camera.device, f"a {pixel_format} frame of {width}x{height} px needs "
                                         f"{height * stride - padding_x} bytes, the buffer has {raw.size}")
    rows = np.lib.stride_tricks.as_strided(raw, (height, width * size), (stride, 1))
    values = rows.copy().view("u1" if size == 1 else "<u2") & (2**bits - 1)
    return (values >> (bits - bit_depth)).astype(np.uint8 if bit_depth <= 8 else np.uint16)


def _offers(enumeration, entry):
    """Whether an enumeration node offers `entry` now."""
    return any(e.symbolic == entry and e.node.get_access_mode() not in UNAVAILABLE
               for e in enumeration.entries)


class GenICamCamera(ManualLensCamera):
    """A GenICam device, found in the producer's list by cell.camera.serial_number or
    device_index, checked at connect (before anything moves) to have the task's Width x Height,
    an ExposureTime node and a Mono pixel format with the sensor's bits, then set up: PixelFormat
    (cell.camera.pixel_format, or pick_pixel_format), ExposureAuto and GainAuto Off, ExposureMode
    Timed and AcquisitionMode Continuous where offered, Gain to cell.camera.gain if given (else
    left as the device has it, fixed by GainAuto Off).

    Software trigger (TriggerSelector FrameStart, TriggerMode On, TriggerSource Software, one
    TriggerSoftware per capture) where the device has it. Else free-running: each capture starts
    the stream, discards the first frame (its exposure may have begun before the capture, or
    with the exposure before a change) and keeps the second, then stops the stream, so no frame
    from before a move or an exposure change is ever returned.

    Whatever genicam raises, and any missing node, is a DeviceFault naming the camera."""

    def __init__(self, config: CameraConfig, sensor: Sensor, operator: Operator, read_only: bool = False) -> None:
        """read_only (`cell hw-check`): the device is opened and its nodes only read, not set up."""
        super().__init__(sensor.bit_depth, operator, "a GenICam camera's lens is set by hand here")
        if config.cti is None:
            raise DeviceFault(self.device, "no GenTL producer to open (cell.camera.cti)")
        self.config = config
        self.name = f"the GenTL producer {config.cti}"
        self._harvester, self._acquirer = Harvester(), None
        try:
            with self._speaking("opening the device"):
                self._harvester.add_file(str(config.cti))
                self._harvester.update()
                info = self._device_info()
                self.name = f"{info.model} serial {info.serial_number} ({config.cti.name})"
                self._acquirer = self._harvester.create(info)
            if not read_only:
                with self._speaking("setting it up"):
                    self._set_up(sensor)
        except BaseException:
            try_all([self.close])                           # the fault to report is the first
            raise

    def state(self) -> dict[str, Any]:
        """The device's model and serial, Width x Height, PixelFormat (with the bits it carries),
        ExposureTime and its range, by reading nodes only (`cell hw-check`); `problems`: a node a
        run needs that is missing, or no Mono format with the sensor's bits."""
        with self._speaking("reading its state"):
            def read(name):
                node = self._present(name)
                return None if node is None else node.value
            problems = [f"{self.name} has no {name} node (GenICam SFNC name)"
                        for name in ("Width", "Height", "PixelFormat", "ExposureTime") if self._present(name) is None]
            formats = self._present("PixelFormat")
            offered = [] if formats is None else [e.symbolic for e in formats.entries
                                                  if e.node.get_access_mode() not in UNAVAILABLE]
            if formats is not None and pick_pixel_format(offered, self.bit_depth) is None:
                problems.append(f"{self.name} offers PixelFormat {', '.join(offered)}: no Mono format of "
                                f"camera.sensor.bit_depth {self.bit_depth} bits or more")
            exposure = self._present("ExposureTime")
            pixel_format = read("PixelFormat")
            return {"source": str(self.config.cti), "model": self.name, "backend": "GenICam (harvesters)",
                    "width_px": read("Width"), "height_px": read("Height"),
                    "channels": 1 if pixel_format in MONO_FORMATS else None,
                    "bit_depth": MONO_FORMATS.get(pixel_format), "pixel_format": pixel_format,
                    "pixel_formats": offered,
                    "exposure_s": None if exposure is None else exposure.value * 1e-6,
                    "exposure_range_s": None if exposure is None else [exposure.min * 1e-6, exposure.max * 1e-6],
                    "problems": problems}

    def _device_info(self):
        infos = self._harvester.device_info_list
        listed = ", ".join(f"{i.model} serial {i.serial_number}" for i in infos)
        if not infos:
            raise DeviceFault(self.device, f"{self.name} finds no device")
        serial = self.config.serial_number
        if serial is not None:
            found = [i for i in infos if i.serial_number == serial]
            if len(found) != 1:
                raise DeviceFault(self.device, f"{self.name} lists {len(found)} devices with serial "
                                               f"number {serial!r} (cell.camera.serial_number): {listed}")
            return found[0]
        index = self.config.device_index
        if index >= len(infos):
            raise DeviceFault(self.device, f"cell.camera.device_index {index}, but {self.name} lists "
                                           f"{len(infos)} devices: {listed}")
        return infos[index]

    def _nodes(self):
        """The remote device's node map."""
        return self._acquirer.remote_device.node_map

    def _node(self, name, why):
        """The device's node `name`; missing or unavailable is a fault naming it."""
        node = self._present(name)
        if node is None:
            raise DeviceFault(self.device, f"{self.name} has no {name} node, which {why} "
                                           "(GenICam SFNC name)")
        return node

    def _present(self, name):
        """The node `name` if the device has it available, else None."""
        nodes = self._nodes()
        node = getattr(nodes, name) if nodes.has_node(name) else None
        return node if node is not None and node.node.get_access_mode() not in UNAVAILABLE else None

    def _choose(self, name, entry):
        """Set the enumeration `name` to `entry` where the device offers it; whether it did. A
        read-only node already at `entry` is fine, one at another value a fault."""
        node = self._present(name)
        if node is None or not _offers(node, entry):
            return False
        if node.value != entry:
            if node.node.get_access_mode() not in WRITABLE:
                raise DeviceFault(self.device, f"{self.name}'s {name} is {node.value} and read-only; "
                                               f"needed {entry}")
            node.value = entry
        return True

    def _set_up(self, sensor):
        width = self._node("Width", "gives the image size").value
        height = self._node("Height", "gives the image size").value
        if (width, height) != (sensor.width_px, sensor.height_px):
            raise DeviceFault(self.device, f"{self.name} delivers {width}x{height} px (Width, Height), "
                                           f"camera.sensor is {sensor.width_px}x{sensor.height_px} px")
        formats = self._node("PixelFormat", "sets the pixel format")
        offered = [e.symbolic for e in formats.entries if e.node.get_access_mode() not in UNAVAILABLE]
        wanted = self.config.pixel_format or pick_pixel_format(offered, self.bit_depth)
        if wanted not in offered:
            asked = (f"cell.camera.pixel_format {wanted}" if self.config.pixel_format else
                     f"a Mono format of at least camera.sensor.bit_depth {self.bit_depth} bits")
            raise DeviceFault(self.device, f"{self.name} offers PixelFormat {', '.join(offered)}; "
                                           f"needed {asked} (of {', '.join(MONO_FORMATS)})")
        formats.value = wanted
        self.pixel_format = wanted
        exposure = self._node("ExposureTime", "sets the shutter time")
        if exposure.node.get_access_mode() not in WRITABLE:
            raise DeviceFault(self.device, f"{self.name}'s ExposureTime node is not writable")
        for name, entry in (("ExposureAuto", "Off"), ("GainAuto", "Off"), ("ExposureMode", "Timed"),
                            ("AcquisitionMode", "Continuous")):
            self._choose(name, entry)
        if self.config.gain is not None:
            gain = self._node("Gain", "sets the gain (cell.camera.gain)")
            if not gain.min <= self.config.gain <= gain.max:
                raise DeviceFault(self.device, f"cell.camera.gain {self.config.gain:g} outside "
                                               f"{self.name}'s Gain range {gain.min:g}..{gain.max:g}")
            gain.value = self.config.gain
        self.triggered = self._software_trigger()

    def _software_trigger(self):
        """Frames on software trigger if the device has it (True), else free-running with every
        trigger off (False)."""
        self._choose("TriggerSelector", "FrameStart")
        mode, source = self._present("TriggerMode"), self._present("TriggerSource")
        if (self._present("TriggerSoftware") is None or mode is None or not _offers(mode, "On")
                or source is None or not _offers(source, "Software")):
            self._choose("TriggerMode", "Off")
            return False
        source.value = "Software"
        mode.value = "On"
        return True

    @contextmanager
    def _speaking(self, doing):
        try:
            yield
        except GENICAM_ERRORS as err:
            message = " ".join(str(err).split()) or "no message"
            raise DeviceFault(self.device, f"{self.name}, {doing}: {type(err).__name__}: "
                                           f"{message}") from err

    def set_exposure(self, shutter_s: float) -> float:
        """ExposureTime [us, SFNC] set with the stream stopped and read back: returns the shutter
        time the device uses [s] (devices round it, e.g. to whole sensor lines)."""
        with self._speaking("setting the exposure"):
            self._stop()
            node = self._node("ExposureTime", "sets the shutter time")
            exposure_us = shutter_s * 1e6
            if not node.min <= exposure_us <= node.max:
                raise DeviceFault(self.device, f"{self.name}: ExposureTime {exposure_us:.6g} us "
                                               f"outside its range {node.min:.6g}..{node.max:.6g} us")
            node.value = exposure_us
            actual = node.value * 1e-6
        if not actual > 0:
            raise DeviceFault(self.device, f"{self.name} reads back ExposureTime {actual * 1e6} us")
        self.shutter_s = actual
        return actual

    def capture(self) -> np.ndarray:
        with self._speaking("capturing"):
            self._start()
            if self.triggered:
                self._node("TriggerSoftware", "triggers a frame").execute()
                return self._fetch()
            try:
                self._fetch()                               # discarded: see the class docstring
                return self._fetch()
            finally:
                self._stop()

    def _fetch(self):
        """The next frame as gray levels, within the shutter time plus frame_timeout_s."""
        timeout = (self.shutter_s or 0.0) + self.config.frame_timeout_s
        try:
            buffer = self._acquirer.fetch(timeout=timeout)
        except gentl.TimeoutException:
            raise DeviceFault(self.device, f"{self.name} sent no frame within {timeout:.3g} s "
                                           "(shutter + cell.camera.frame_timeout_s)") from None
        if buffer is None:                                  # harvesters could not read it
            raise DeviceFault(self.device, f"{self.name} sent a buffer without its image information")
        with buffer:
            components = buffer.payload.components if buffer.payload is not None else []
            if not components:
                raise DeviceFault(self.device, f"{self.name} sent a buffer without an image")
            image = components[0]
            if image.data_format != self.pixel_format:
                raise DeviceFault(self.device, f"{self.name} sent {image.data_format} frames, its "
                                               f"PixelFormat is set to {self.pixel_format}")
            raw = np.ascontiguousarray(image.data).view(np.uint8)
            return mono_to_gray(raw, image.data_format, image.width, image.height, self.bit_depth,
                                image.x_padding)

    def _start(self):
        if not self._acquirer.is_acquiring():
            self._acquirer.start()

    def _stop(self):
        if self._acquirer.is_acquiring():
            self._acquirer.stop()

    def close(self) -> None:
        """Stop the stream, release the device and the producer (again: nothing more to do)."""
        acquirer, self._acquirer = self._acquirer, None
        with self._speaking("closing"):
            try:
                if acquirer is not None:
                    try:
                        if acquirer.is_acquiring():
                            acquirer.stop()
                    finally:
                        acquirer.destroy()
            finally:
                self._harvester.reset()
