"""The sensor's digital output: the largest gray it reports and the integer levels its ADC
delivers (the rest of the EMVA 1288 model is radiometry's and the simulator's)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def saturation_level(bit_depth: int) -> int:
    """The largest gray a bit_depth sensor reports: a pixel there may truly be brighter."""
    return 2 ** int(bit_depth) - 1


def levels(gray: ArrayLike, bit_depth: int) -> np.ndarray:
    """Integer gray clipped to [0, saturation_level], as a bit_depth ADC delivers it (uint8 up
    to 8 bits, else uint16)."""
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    return np.clip(np.rint(gray), 0, saturation_level(bit_depth)).astype(dtype)
