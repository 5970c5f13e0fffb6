"""Lamp rig geometry: the lamp moves on a sphere around the pivot and aims at it; pan about
the cell's +z axis, tilt is the elevation above the cell's xy plane (hardware notes)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry

# The pan-tilt's links behind the lamp, which hold it on its radius (hardware notes; the planner's
# bodies, cell.collision.scene.rig_links, and the simulator's, sim.obstacles, are each built from
# these): the tilt servo, a Dynamixel X-series 430 (ROBOTIS e-Manual: 28.5 x 46.5 x 34 mm,
# W x H x D), its axes the lamp's: 34 mm across the aim and horizontal, 46.5 mm across it, 28.5 mm
# along it, its front face on the lamp's axis behind it, at the lamp housing's back (a compact head
# riding with the lamp) or, where the task declares the rig's reach (cell.collision.rig_reach_m),
# that far from the pivot, standing still as the radius changes; then the arm, a tube of this
# radius along the lamp's axis from the housing's back to the servo's front face.
RIG_ARM_RADIUS_M = 0.010
TILT_SERVO_SIZE_M = (0.034, 0.0465, 0.0285)


def lamp_position(pivot: ArrayLike, pan: ArrayLike, tilt: ArrayLike, radius: ArrayLike) -> np.ndarray:
    """p = pivot + r (cos t cos p, cos t sin p, sin t); broadcasts over pan/tilt/radius arrays."""
    pan, tilt, radius = np.broadcast_arrays(np.asarray(pan, float), np.asarray(tilt, float),
                                            np.asarray(radius, float))
    offset = np.stack([np.cos(tilt) * np.cos(pan), np.cos(tilt) * np.sin(pan), np.sin(tilt)], axis=-1)
    return np.asarray(pivot, float) + radius[..., None] * offset


def lamp_aim(pivot: ArrayLike, position: ArrayLike) -> np.ndarray:
    """Unit aim direction of a lamp at `position` pointing at the pivot."""
    return geometry.unit(np.asarray(pivot, float) - np.asarray(position, float))


def lamp_frame(pivot: ArrayLike, position: ArrayLike) -> np.ndarray:
    """(..., 3, 3) the lamp's axes in the cell frame at `position` (..., 3): z its aim at the pivot,
    x horizontal (z x the cell's z; the cell's x when the lamp is straight above the pivot), y = z x x."""
    z = lamp_aim(pivot, position)
    x = np.stack([-z[..., 1], z[..., 0], np.zeros_like(z[..., 0])], axis=-1)       # (0, 0, 1) x z
    norm = np.sqrt(x[..., :1] ** 2 + x[..., 1:2] ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = np.where(norm > 1e-9, x / norm, (1.0, 0.0, 0.0))
    y = np.stack([z[..., 1] * x[..., 2] - z[..., 2] * x[..., 1], z[..., 2] * x[..., 0] - z[..., 0] * x[..., 2],
                  z[..., 0] * x[..., 1] - z[..., 1] * x[..., 0]], axis=-1)          # z x x
    return np.stack([x, y, z], axis=-1)


def lamp_joints(pivot: ArrayLike, position: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pan, tilt, radius) that put the lamp at `position` (inverse of lamp_position)."""
    d = np.asarray(position, float) - np.asarray(pivot, float)
    radius = np.linalg.norm(d, axis=-1)
    return np.arctan2(d[..., 1], d[..., 0]), np.arcsin(np.clip(d[..., 2] / radius, -1, 1)), radius
