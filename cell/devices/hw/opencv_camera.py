"""The real camera through cv2.VideoCapture (a V4L2 device index, or a video or image-sequence
path, which exercises the same capture code). Manual exposure goes through
CAP_PROP_AUTO_EXPOSURE (raw V4L2 1 = manual) and CAP_PROP_EXPOSURE in `exposure_unit_s` steps;
OpenCV has no lens control, so the operator sets the f-number and the focus."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from cell.core.errors import DeviceFault
from cell.devices.hw.lens import ManualLensCamera

if TYPE_CHECKING:
    from cell.devices.operator import Operator
    from cell.task.device_config import CameraConfig

V4L2_MANUAL_EXPOSURE = 1

# OpenCV's own log lines ("[ WARN:0@0.046] global cap_v4l.cpp:914 ...") stay off the terminal: a
# camera that does not open is a DeviceFault naming the source, in one line
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


class OpenCVCamera(ManualLensCamera):
    def __init__(self, config: CameraConfig, bit_depth: int, operator: Operator) -> None:
        super().__init__(bit_depth, operator, "OpenCV has no lens control")
        self.config = config
        self._capture = cv2.VideoCapture(config.source)
        if not self._capture.isOpened():
            raise DeviceFault(self.device, f"cannot open {config.source!r} with cv2.VideoCapture")

    def set_exposure(self, shutter_s: float) -> float:
        """Manual exposure, read back: returns the shutter time the camera reports [s]."""
        unit = self.config.exposure_unit_s
        value = round(shutter_s / unit)
        for prop, name, v in ((cv2.CAP_PROP_AUTO_EXPOSURE, "CAP_PROP_AUTO_EXPOSURE", V4L2_MANUAL_EXPOSURE),
                              (cv2.CAP_PROP_EXPOSURE, "CAP_PROP_EXPOSURE", value)):
            if not self._capture.set(prop, v):
                raise DeviceFault(self.device, f"{self.config.source!r} refused {name} = {v} "
                                               f"(shutter {shutter_s * 1e3:.3g} ms)")
        actual = self._capture.get(cv2.CAP_PROP_EXPOSURE) * unit
        if not actual > 0:
            raise DeviceFault(self.device, f"{self.config.source!r} reads back exposure {actual} s")
        for _ in range(self.config.discard_frames):     # still exposed with the old setting
            self._read()
        self.shutter_s = actual
        return actual

    def _read(self):
        ok, frame = self._capture.read()
        if not ok or frame is None:
            raise DeviceFault(self.device, f"no frame from {self.config.source!r}")
        return frame

    def capture(self) -> np.ndarray:
        return self._gray(self._read())

    def state(self) -> dict[str, Any]:
        """The source, OpenCV's backend, one frame's size, channels and bit depth, the FOURCC
        the capture reports and the exposure setting, by get() only: nothing is set. OpenCV cannot
        ask a camera its model or exposure range (on V4L2 `v4l2-ctl --all` shows them): None."""
        frame, problems = self._read(), []
        try:
            self._gray(frame)
        except DeviceFault as fault:
            problems.append(fault.reason)
        fourcc = int(self._capture.get(cv2.CAP_PROP_FOURCC))
        exposure = self._capture.get(cv2.CAP_PROP_EXPOSURE)
        return {"source": self.config.source, "model": None, "backend": self._capture.getBackendName(),
                "width_px": frame.shape[1], "height_px": frame.shape[0],
                "channels": 1 if frame.ndim == 2 else frame.shape[2], "bit_depth": 8 * frame.itemsize,
                "pixel_format": fourcc.to_bytes(4, "little").decode("latin-1") if fourcc > 0 else None,
                "exposure_s": exposure * self.config.exposure_unit_s if exposure > 0 else None,
                "exposure_range_s": None, "problems": problems}

    def _gray(self, frame):
        if frame.ndim == 3 and frame.shape[2] == 1:
            frame = frame[..., 0]
        elif frame.ndim == 3:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        expected = np.uint8 if self.bit_depth <= 8 else np.uint16
        if frame.dtype != expected:
            raise DeviceFault(self.device, f"frames are {frame.dtype}, a {self.bit_depth}-bit sensor "
                                           f"gives {np.dtype(expected)}")
        return frame

    def close(self) -> None:
        self._capture.release()
