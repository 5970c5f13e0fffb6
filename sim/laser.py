"""What the simulated camera sees of a laser aimed at its sensor (`cell calibrate camera-constant`,
sec. 4.1): while the beam is unblocked, its power P lands as a small Gaussian spot, each pixel
receiving P times its share of the spot, and the noiseless gray is G = c P_pixel t (eq. 10) with
the world's true c (task c * sim.truth.camera_constant_scale); then the sensor's read-out
(sim.world.SensorModel) with the task's noise, black_level and quantization. The arm's and the
lamp's poses play no part (the beam is aimed at the sensor, the lamp is off), nor do the scene's
effects (shadows, cone falloff, vignetting, defocus)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import ndtr

from sim.world import SensorModel

if TYPE_CHECKING:
    from cell.task.types import Task

SPOT_SIGMA_PX = 1.2         # the focused beam's rms radius on the sensor
SPOT_SPREAD_PX = 40.0       # the spot lands within this of the sensor's centre (drawn from the seed)


def spot_shares(shape: tuple[int, int], centre_rc: np.ndarray, sigma_px: float) -> np.ndarray:
    """Each pixel's share of a Gaussian spot (H, W): the normal distribution integrated over the
    pixel's square, (Phi(r + 1/2) - Phi(r - 1/2)) (Phi(c + 1/2) - Phi(c - 1/2)) in units of sigma
    about the centre; the shares sum to 1 when the spot lies well inside the image."""
    rows, cols = (np.arange(n, dtype=float) for n in shape)
    share = [ndtr((x + 0.5 - c) / sigma_px) - ndtr((x - 0.5 - c) / sigma_px) for x, c in zip((rows, cols), centre_rc)]
    return np.outer(*share)


class Beam(Protocol):
    """A laser aimed at the sensor (cell.calibration.camera_constant.Laser): its power, and
    whether its beam is blocked."""

    @property
    def power_w(self) -> float: ...
    @property
    def blocked(self) -> bool: ...


class LaserSpot:
    """The renderer a SimCamera calls, for a laser (anything with `power_w` and `blocked`,
    cell.calibration.camera_constant.Laser) aimed at the sensor: (H, W) gray at the set shutter time."""

    def __init__(self, task: Task, laser: Beam) -> None:
        sensor = task.camera.sensor
        self.task, self.laser, self.effects = task, laser, frozenset(task.sim.effects)
        self.camera_constant = sensor.camera_constant * task.sim.truth.camera_constant_scale
        self.sensor = SensorModel.of(sensor)
        self.rng = np.random.default_rng(task.sim.seed)
        shape = (sensor.height_px, sensor.width_px)
        self.centre_rc = (np.array(shape) - 1) / 2 + self.rng.uniform(-SPOT_SPREAD_PX, SPOT_SPREAD_PX, 2)
        self.shares = spot_shares(shape, self.centre_rc, SPOT_SIGMA_PX)

    def __call__(self, T_cell_cam: np.ndarray, lamp_pos: ArrayLike, lamp_aim: ArrayLike, shutter_s: float,
                 f_number: float, focus_m: float | None = None) -> np.ndarray:
        power_w = 0.0 if self.laser.blocked else self.laser.power_w
        gray = self.camera_constant * power_w * self.shares * shutter_s
        return self.sensor.read_out(gray, self.effects, self.rng)
