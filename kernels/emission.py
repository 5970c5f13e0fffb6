"""A lamp's on-axis intensity from its power and angular profile (energy conservation), plain
Python and NumPy: computed once per lamp, not per evaluation, and the one implementation that
cell.physics.radiometry (the NumPy reference, the goniometer) and the kernels (the planner, the
simulator's renderer, the refit) all use. It sits here because kernels/ may import nothing of
cell/; cell.physics.radiometry exports it under the same names."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike


def hard_cone_profile(cone_angle_rad: float) -> np.ndarray:
    """Eq. (11)'s ideal cone as a lamp profile (2, 2) [off_axis_rad, relative]: 1 up to gamma/2
    and, being the table's last angle, 0 beyond it."""
    return np.array([[0.0, 1.0], [0.5 * float(cone_angle_rad), 1.0]])


def _u_minus_sin(u: float) -> float:
    """u - sin u without cancellation: its series below 0.25 (next term < 1e-15 relative)."""
    if u >= 0.25:
        return u - math.sin(u)
    u2 = u * u
    return u * u2 * (1 / 6 - u2 * (1 / 120 - u2 * (1 / 5040 - u2 * (1 / 362880 - u2 / 39916800))))


def profile_solid_angle(profile: ArrayLike) -> float:
    """Omega_p = 2 pi integral_0^pi p(theta) sin(theta) dtheta [sr] of a profile (M, 2)
    [off_axis_rad ascending from 0, relative], linear between its angles and 0 beyond the last:
    the solid angle a lamp of on-axis intensity I(0) fills, P = I(0) Omega_p. Exact per linear
    segment, p = r0 + b (theta - t0) on [t0, t1], h = t1 - t0:
    integral = r0 (cos t0 - cos t1) + b (sin t1 - sin t0 - h cos t1), written without
    cancellation for narrow lamps and short segments as
    r0 2 sin((t0 + t1)/2) sin(h/2) + b (2 sin t1 sin^2(h/2) - cos t1 (h - sin h)).
    The hard cone (1 up to gamma/2) gives eq. (11)'s 2 pi (1 - cos(gamma/2)) = 4 pi sin^2(gamma/4),
    to rounding (the form here is the more accurate one for narrow cones)."""
    p = np.asarray(profile, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError(f"lamp profile must have shape (M >= 2, 2), got {p.shape}")
    if p[0, 0] != 0.0 or np.any(np.diff(p[:, 0]) <= 0.0):
        raise ValueError("lamp profile off-axis angles must start at 0 and be strictly ascending")
    total = 0.0
    for (t0, r0), (t1, r1) in zip(p[:-1].tolist(), p[1:].tolist()):
        h = t1 - t0
        half_sin = math.sin(0.5 * h)
        part = r0 * 2.0 * math.sin(0.5 * (t0 + t1)) * half_sin
        if r1 != r0:
            part += (r1 - r0) / h * (2.0 * math.sin(t1) * half_sin * half_sin - math.cos(t1) * _u_minus_sin(h))
        total += part
    return 2.0 * math.pi * total


def axis_intensity(power_w: float, cone_angle_rad: float, profile: ArrayLike | None = None) -> float:
    """I(0) = P / Omega_p [W/sr]: the lamp's power spread over its profile (profile_solid_angle),
    so the lamp emits P whatever its profile; None: eq. (11)'s ideal cone of full opening angle
    gamma, I(0) = P / (2 pi (1 - cos(gamma/2))). With a profile the cone angle does not enter
    (cell.task.loader refuses a cone angle that contradicts the profile)."""
    if profile is None:
        profile = hard_cone_profile(cone_angle_rad)
    return float(power_w) / profile_solid_angle(profile)
