"""A defect's contrast against the sensor's noise: the normals a defect's geometry gives a surface
point, the EMVA 1288 temporal noise at a gray, and the contrast-to-noise ratio (physics notes,
"Beyond the paper": defect geometry and noise).

Geometry, each in the point's tangent plane (n its unit normal, x a tangent axis, y = n x x):
- scratch, a V-groove of width w and depth h running along d = cos(theta) x + sin(theta) y:
  its walls are the normal turned about d by +-beta, beta = atan(2 h / w) (wall_tilt);
- dent, a spherical dimple of radius a and depth (sagitta) h: its curvature radius is
  R = (a^2 + h^2) / (2 h) and at distance rho from its centre, in tangent direction u, the normal
  leans toward the centre by asin(rho / R) (dent_tilt), up to its rim slope at rho = a;
- coating: the same normal, another material.

Noise (EMVA 1288, in gray levels): sigma^2 = K (G - b) + K^2 sigma_d^2 + 1/12, K the system gain
[gray/e-], sigma_d the dark noise [e-], b the black level; shot noise of (G - b) / K electrons,
dark noise and the quantisation's 1/12. CNR = |G_defect - G_good| / sqrt(sigma_good^2 +
sigma_defect^2): the difference of two single pixel readings (a defect pixel against a good one)
has exactly that standard deviation, so a CNR of k is a k-sigma detection of one pixel against
one; definitions by the good surface's noise alone would count the defect's own noise as signal.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def wall_tilt(width_m: float, depth_m: float) -> float:
    """beta = atan(2 h / w) [rad]: how far a V-groove's walls turn the normal."""
    return float(np.arctan2(2.0 * depth_m, width_m))


def dent_tilt(rho_m: ArrayLike, radius_m: float, depth_m: float) -> np.ndarray:
    """asin(rho / R), R = (a^2 + h^2) / (2 h) [rad]: a spherical dimple's normal tilt at distance
    rho from its centre (0 <= rho <= a; at the rim, atan(2 a h / (a^2 - h^2)))."""
    curvature_radius = (radius_m**2 + depth_m**2) / (2.0 * depth_m)
    return np.arcsin(np.clip(np.asarray(rho_m, float) / curvature_radius, 0.0, 1.0))


def rotate(vectors: ArrayLike, axes: ArrayLike, angles: ArrayLike) -> np.ndarray:
    """Rodrigues: vectors (..., 3) turned about unit axes (..., 3) by angles (...) [rad]."""
    v, k = np.asarray(vectors, float), np.asarray(axes, float)
    a = np.asarray(angles, float)[..., None]
    return (v * np.cos(a) + np.cross(k, v) * np.sin(a)
            + k * np.sum(k * v, axis=-1, keepdims=True) * (1.0 - np.cos(a)))


def tangent_axes(normals: ArrayLike, x_axis: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) (P, 3) at each unit normal: x_axis projected into the tangent plane (the feature
    frame's x carried onto a curved patch), y = n x x."""
    n = np.asarray(normals, float).reshape(-1, 3)
    x = np.asarray(x_axis, float) - (n @ np.asarray(x_axis, float))[:, None] * n
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return x, np.cross(n, x)


def scratch_normals(normals: ArrayLike, x_axis: ArrayLike, orientations_rad: ArrayLike, tilt_rad: float) -> np.ndarray:
    """(P, O, 2, 3) the two walls' normals of a scratch along each orientation theta (O,) from
    x_axis in each point's tangent plane: n turned about d(theta) by +tilt and -tilt."""
    n = np.asarray(normals, float).reshape(-1, 3)
    x, y = tangent_axes(n, x_axis)
    theta = np.asarray(orientations_rad, float)
    d = np.cos(theta)[None, :, None] * x[:, None] + np.sin(theta)[None, :, None] * y[:, None]   # (P, O, 3)
    walls = [rotate(np.broadcast_to(n[:, None], d.shape), d, sign * tilt_rad) for sign in (1.0, -1.0)]
    return np.stack(walls, axis=2)


def dent_normals(normals: ArrayLike, x_axis: ArrayLike, tilts_rad: ArrayLike, azimuths_rad: ArrayLike) -> np.ndarray:
    """(P, T A, 3) a dimple's normals at each point: leaning by each tilt (T,) toward the dent's
    centre from each azimuth (A,) of the tangent plane (the point at azimuth psi from the centre,
    u = cos(psi) x + sin(psi) y, has n' = cos(tilt) n - sin(tilt) u)."""
    n = np.asarray(normals, float).reshape(-1, 3)
    x, y = tangent_axes(n, x_axis)
    psi = np.asarray(azimuths_rad, float)
    u = np.cos(psi)[None, :, None] * x[:, None] + np.sin(psi)[None, :, None] * y[:, None]       # (P, A, 3)
    t = np.asarray(tilts_rad, float)[None, :, None, None]
    out = np.cos(t) * n[:, None, None] - np.sin(t) * u[:, None]                                 # (P, T, A, 3)
    return out.reshape(len(n), -1, 3)


def temporal_noise(gray: ArrayLike, black_level: float, gain_dn_per_e: float, dark_noise_e: float) -> np.ndarray:
    """sigma [gray] = sqrt(K (G - b) + K^2 sigma_d^2 + 1/12) at mean gray G (EMVA 1288; below b
    no shot noise)."""
    signal = np.maximum(np.asarray(gray, float) - black_level, 0.0)
    return np.sqrt(gain_dn_per_e * signal + (gain_dn_per_e * dark_noise_e) ** 2 + 1.0 / 12.0)


def cnr(gray_good: ArrayLike, gray_defect: ArrayLike, black_level: float, gain_dn_per_e: float,
        dark_noise_e: float, full_scale: float = np.inf) -> np.ndarray:
    """|G_defect - G_good| / sqrt(sigma_good^2 + sigma_defect^2), both grays clipped at the
    sensor's full scale first (a saturated pixel shows no difference)."""
    good = np.minimum(np.asarray(gray_good, float), full_scale)
    defect = np.minimum(np.asarray(gray_defect, float), full_scale)
    noise = np.hypot(temporal_noise(good, black_level, gain_dn_per_e, dark_noise_e),
                     temporal_noise(defect, black_level, gain_dn_per_e, dark_noise_e))
    return np.abs(defect - good) / noise
