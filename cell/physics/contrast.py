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

Where a defect lies (the simulator renders it there, the run measures it there; `footprint`): in
the feature's tangent plane through the defect's position, offsets (x, y) along the feature
frame's axes; a scratch along d(theta) = (cos theta, sin theta) is the strip |s| < w / 2 across
it (s along n x d) on the chord of the feature's disk through its position (a scratch runs
across the feature); a dent or a coating is the disk of its radius.
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


def scratch_chord(position_xy: ArrayLike, theta_rad: float, feature_radius_m: float) -> tuple[float, float]:
    """(t0, t1) [m]: where the line through a scratch's position (x, y) from the feature centre
    along d(theta) enters and leaves the feature's disk, |position + t d| = r, as distances
    along d from the position (t0 <= 0 <= t1 for a position within the disk)."""
    q = np.asarray(position_xy, float)
    d = np.array([np.cos(theta_rad), np.sin(theta_rad)])
    b = float(q @ d)
    root = np.sqrt(max(b * b - float(q @ q) + feature_radius_m**2, 0.0))
    return -b - root, -b + root


def across_along(offsets_xy: ArrayLike, theta_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(s, t) (P,) each offset's component across a groove along d(theta) (along n x d = (-sin,
    cos)) and along it [m]."""
    o = np.asarray(offsets_xy, float).reshape(-1, 2)
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return -s * o[:, 0] + c * o[:, 1], c * o[:, 0] + s * o[:, 1]


def footprint(offsets_xy: ArrayLike, kind: str, theta_rad: float = 0.0, width_m: float = 0.0,
              radius_m: float = 0.0, chord_m: tuple[float, float] = (-np.inf, np.inf)) -> tuple[np.ndarray, np.ndarray]:
    """(part (P,), outside (P,) [m]) of points at offsets (P, 2) from a defect's position: part 0
    off the defect; a scratch's wall at s > 0 (1: the normal turned about d by +beta, it faces
    -s) or at s < 0 (2: by -beta) within its chord (t0, t1) along d; a dent's or a coating's disk
    (1). `outside`: how far beyond the defect's edge a point lies (|s| - w / 2 beside the
    scratch's chord, inf beyond its ends; rho - a of a disk; <= 0 on it)."""
    o = np.asarray(offsets_xy, float).reshape(-1, 2)
    if kind == "scratch":
        s, t = across_along(o, theta_rad)
        outside = np.where((t >= chord_m[0]) & (t <= chord_m[1]), np.abs(s) - 0.5 * width_m, np.inf)
        part = np.where(outside <= 0.0, np.where(s > 0.0, 1, 2), 0)
        return part, outside
    outside = np.hypot(o[:, 0], o[:, 1]) - radius_m
    return np.where(outside <= 0.0, 1, 0), outside


def wall_normals(normals: ArrayLike, x_axis: ArrayLike, theta_rad: float, tilt_rad: float,
                 part: ArrayLike) -> np.ndarray:
    """(P, 3) the normal of each point on a scratch's wall `part` (1: turned about d(theta) by
    +tilt, 2: by -tilt; footprint's), d in each point's tangent plane from x_axis."""
    n = np.asarray(normals, float).reshape(-1, 3)
    x, y = tangent_axes(n, x_axis)
    d = np.cos(theta_rad) * x + np.sin(theta_rad) * y
    sign = np.where(np.asarray(part) == 1, 1.0, -1.0)
    return rotate(n, d, sign * tilt_rad)


def dimple_normals(normals: ArrayLike, x_axis: ArrayLike, offsets_xy: ArrayLike, radius_m: float,
                   depth_m: float) -> np.ndarray:
    """(P, 3) a dent's normal at points at offsets (x, y) (P, 2) from its centre, within its
    radius: leaning toward the centre by dent_tilt(rho), n' = cos(tilt) n - sin(tilt) u with u the
    unit offset in each point's tangent plane (dent_normals' field at the points themselves)."""
    n = np.asarray(normals, float).reshape(-1, 3)
    o = np.asarray(offsets_xy, float).reshape(-1, 2)
    x, y = tangent_axes(n, x_axis)
    rho = np.hypot(o[:, 0], o[:, 1])
    u = (o[:, :1] * x + o[:, 1:] * y) / np.maximum(rho, 1e-300)[:, None]
    tilt = dent_tilt(rho, radius_m, depth_m)[:, None]
    return np.cos(tilt) * n - np.sin(tilt) * u
