"""What the simulated camera sees of the ChArUco board (`cell calibrate hand-eye`): the board
(task calibration.board, cell.task.board.Board) as a textured plane on the table, OpenCV's printed
image mapped onto it (kernels.render.render_plane), seen from the true camera pose (the arm's
reported pose composed with the hand-eye error sim.truth.camera_offset_m / camera_rpy_deg, as in
sim.world.Renderer).

Lighting: a diffuse light over the board (the operator's calibration light, not the lamp, whose
12 deg cone aimed at the rig's pivot would light only part of a board beside the part) of
irradiance AMBIENT_IRRADIANCE; the print is Lambertian, reflectance PRINT_WHITE or PRINT_BLACK, the
table around it TABLE. So eq. (17) with the reflectance a: P = A_pixel E a / (8 kappa^2), and
G = c P t (eq. 10) with the world's true c. Each pixel is the mean of SUPERSAMPLE^2 rays spread
over its square (a box filter: the sensor integrates over its pixels, so the squares' edges land
at sub-pixel positions). Then the task's effects of the lens and the sensor: vignetting, defocus
(the board's depth), noise, black_level, quantization (sim.world). The part is not drawn: the
board lies beside it and it occludes nothing the routine needs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry
from cell.physics.radiometry import gray_value, pixel_power
from cell.physics.projection import intrinsics
from kernels.render import render_plane
from sim.world import SensorModel, defocus

if TYPE_CHECKING:
    from cell.task.types import Task

AMBIENT_IRRADIANCE = 20.0   # W/m^2 on the board: a diffuse LED panel over it (about 10 klx)
PRINT_WHITE = 0.85          # reflectance of the board's white (matte paper)
PRINT_BLACK = 0.04          # of its black print
TABLE = 0.25                # of the table around the board
SUPERSAMPLE = 3             # rays per pixel side
TEXELS_PER_SQUARE = 200     # the printed image's resolution on the plane


class BoardView:
    """The renderer a SimCamera calls for the board: (H, W) gray from the arm's reported camera
    pose at the set shutter time, f-number and focus."""

    def __init__(self, task: Task) -> None:
        sensor, truth = task.camera.sensor, task.sim.truth
        self.task, self.board, self.effects = task, task.board, frozenset(task.sim.effects)
        self.shape = (sensor.height_px, sensor.width_px)
        self.texel_m = self.board.square_m / TEXELS_PER_SQUARE
        printed = self.board.image(TEXELS_PER_SQUARE) / 255.0
        self.reflectance = PRINT_BLACK + (PRINT_WHITE - PRINT_BLACK) * printed
        self.camera_constant = sensor.camera_constant * truth.camera_constant_scale
        self.sensor = SensorModel.of(sensor)
        self.T_cam_true = geometry.from_rpy(truth.camera_rpy_rad, truth.camera_offset_m)
        self.rng = np.random.default_rng(task.sim.seed)
        K = intrinsics(sensor, task.camera.lens)
        # sub-pixel ray offsets at the centres of a SUPERSAMPLE x SUPERSAMPLE grid over each pixel
        offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
        v, u, dv, du = np.meshgrid(np.arange(self.shape[0], dtype=float), np.arange(self.shape[1], dtype=float),
                                   offsets, offsets, indexing="ij")
        pixels = np.column_stack([(u + du).ravel(), (v + dv).ravel(), np.ones(u.size)])
        self.rays_cam = geometry.unit(pixels @ np.linalg.inv(K).T)
        u, v = np.meshgrid(np.arange(self.shape[1]) - K[0, 2], np.arange(self.shape[0]) - K[1, 2])
        self.cos_field = K[0, 0] / np.sqrt(u**2 + v**2 + K[0, 0] ** 2)     # the pixel centre's ray to the axis

    def pixel_mean(self, per_ray: np.ndarray) -> np.ndarray:
        """(H, W): the mean of each pixel's rays."""
        return per_ray.reshape(*self.shape, SUPERSAMPLE * SUPERSAMPLE).mean(axis=2)

    def __call__(self, T_cell_cam: np.ndarray, lamp_pos: ArrayLike, lamp_aim: ArrayLike, shutter_s: float,
                 f_number: float, focus_m: float | None = None) -> np.ndarray:
        """Gray image (H, W), float or integers with quantization; the lamp plays no part."""
        T_cell_cam = np.asarray(T_cell_cam, float) @ self.T_cam_true
        dirs = np.einsum("ij,nj->ni", T_cell_cam[:3, :3], self.rays_cam)
        hit = render_plane(T_cell_cam[:3, 3], dirs, self.board.T_cell_board, self.reflectance, self.texel_m,
                           outside=TABLE)
        reflectance = self.pixel_mean(hit.value)
        power = pixel_power(self.task.camera.sensor.pixel_area_m2, AMBIENT_IRRADIANCE, reflectance, f_number)
        gray = gray_value(self.camera_constant, power, shutter_s)
        if "vignetting" in self.effects:
            gray = gray * self.cos_field**4
        if "defocus" in self.effects:
            depth = self.pixel_mean(np.where(hit.hit, hit.depth * self.rays_cam[:, 2], 1e3))
            if focus_m is None:
                focus_m = float(np.median(depth))
            gray = defocus(gray, depth, focus_m, self.task.camera.lens.focal_length_m, f_number,
                           self.task.camera.sensor.pixel_pitch_m)
        return self.sensor.read_out(gray, self.effects, self.rng)
