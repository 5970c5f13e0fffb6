"""The sensor's digital output: the largest gray it reports and the integer levels its ADC
delivers, and the EMVA 1288 figures of its temporal noise with the defaults assumed where a task's
camera.sensor gives none (the simulator's noise, sim.world.SensorModel, and the planner's
contrast-to-noise ratio, cell.physics.contrast, both read them here). The rest of the EMVA 1288
model is radiometry's and the simulator's."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


FULL_WELL_E = 10_000.0      # electrons at full scale: assumed, typical of 4.65 um pixels
READ_NOISE_E = 10.0         # rms electrons: assumed, typical of machine-vision sensors
BLACK_LEVEL = 0.02          # of full scale, rounded (5 gray at 8 bits): keeps read noise above 0


def system_gain(bit_depth: int, system_gain_dn_per_e: float | None = None) -> float:
    """K [gray per electron]: the datasheet's, else full scale over FULL_WELL_E electrons."""
    return float(system_gain_dn_per_e or saturation_level(bit_depth) / FULL_WELL_E)


def dark_noise(dark_noise_e: float | None = None) -> float:
    """sigma_d [electrons rms]: the datasheet's, else READ_NOISE_E."""
    return READ_NOISE_E if dark_noise_e is None else float(dark_noise_e)


def saturation_level(bit_depth: int) -> int:
    """The largest gray a bit_depth sensor reports: a pixel there may truly be brighter."""
    return 2 ** int(bit_depth) - 1


def levels(gray: ArrayLike, bit_depth: int) -> np.ndarray:
    """Integer gray clipped to [0, saturation_level], as a bit_depth ADC delivers it (uint8 up
    to 8 bits, else uint16)."""
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    return np.clip(np.rint(gray), 0, saturation_level(bit_depth)).astype(dtype)
