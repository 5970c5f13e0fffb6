"""Pinhole camera of the task's sensor and lens (OpenCV convention: z forward, x right, y down).

K = [[f/p, 0, cx], [0, f/p, cy], [0, 0, 1]] with f the focal length, p the pixel pitch and the
principal point at the sensor centre. Shared by the simulated camera (rays per pixel) and the
closed loop (where the feature's samples land in the image).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry


class Sensor(Protocol):
    """What the pinhole model reads of a sensor (cell.task.types.Sensor, a layer above)."""

    @property
    def pixel_pitch_m(self) -> float: ...
    @property
    def width_px(self) -> int: ...
    @property
    def height_px(self) -> int: ...


class Lens(Protocol):
    """What the pinhole model reads of a lens (cell.task.types.Lens)."""

    @property
    def focal_length_m(self) -> float: ...


def intrinsics(sensor: Sensor, lens: Lens) -> np.ndarray:
    """3x3 camera matrix K [px]."""
    f_px = lens.focal_length_m / sensor.pixel_pitch_m
    return np.array([[f_px, 0.0, (sensor.width_px - 1) / 2.0],
                     [0.0, f_px, (sensor.height_px - 1) / 2.0],
                     [0.0, 0.0, 1.0]])


def project(K: np.ndarray, T_cell_cam: np.ndarray, points: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) (x right, y down) and depth along the optical axis (N,) [m] of
    cell-frame points; points behind the camera get NaN pixels."""
    local = geometry.apply(np.linalg.inv(T_cell_cam), np.asarray(points, dtype=float).reshape(-1, 3))
    z = local[:, 2]
    image = local @ K.T
    uv = np.empty((len(z), 2))
    with np.errstate(divide="ignore", invalid="ignore"):       # a column at a time: geometry.by_component's why
        np.divide(image[:, 0], z, out=uv[:, 0])
        np.divide(image[:, 1], z, out=uv[:, 1])
    uv[z <= 0] = np.nan
    return uv, z


def pixel_rays(K: np.ndarray, T_cell_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit ray directions (H*W, 3) in the cell frame through every pixel centre, row-major."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    pixels = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)])
    local = pixels @ np.linalg.inv(K).T
    return geometry.unit(geometry.rotate(T_cell_cam, local))


def view_angles(camera: ArrayLike, points: ArrayLike, normals: ArrayLike) -> np.ndarray:
    """(N,) angle between each surface normal and the direction to the camera [rad] (0: seen
    head-on, pi / 2: grazing)."""
    v = geometry.unit(geometry.by_component(np.subtract, camera, points))
    return np.arccos(np.clip(geometry.dot3(v, np.asarray(normals, float)), -1.0, 1.0))


def pixel_footprint(camera: ArrayLike, points: ArrayLike, normals: ArrayLike, pixel_pitch_m: float,
                    focal_length_m: float, angles: np.ndarray | None = None) -> np.ndarray:
    """(N,) the length one pixel covers on the surface at each point [m]: |p - C| pitch / f across
    the ray (the pinhole's magnification), stretched by 1 / cos(view angle) along the slant (the
    longer side of the pixel's footprint); inf where the camera is behind the surface. `angles`:
    view_angles of these camera, points and normals where the caller has them (the view angle
    requirement reads them too), else computed here."""
    distance = geometry.norm(geometry.by_component(np.subtract, points, camera))
    cos = np.cos(view_angles(camera, points, normals) if angles is None else angles)
    with np.errstate(divide="ignore"):
        return np.where(cos > 0, distance * pixel_pitch_m / focal_length_m / np.maximum(cos, 0.0), np.inf)


def frustum_corners(K: np.ndarray, T_cell_cam: np.ndarray, width: int, height: int, depth_m: float) -> np.ndarray:
    """(4, 3) cell-frame corners of the image (its outer pixel edges, clockwise in the image from
    top left) at depth_m along the optical axis: depth K^-1 [u, v, 1], a rectangle W p d / f by
    H p d / f."""
    corners = np.array([[-0.5, -0.5, 1.0], [width - 0.5, -0.5, 1.0], [width - 0.5, height - 0.5, 1.0],
                        [-0.5, height - 0.5, 1.0]])
    return geometry.apply(T_cell_cam, depth_m * corners @ np.linalg.inv(K).T)
