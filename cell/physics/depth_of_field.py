"""Depth of field of sec. 4.3 with a positive object distance u (physics notes' erratum of
eq. 20-21, which use the German convention g = -u). f focal length, kappa f-number, sigma
circle of confusion, all in metres."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

# a number, or an array of them (the functions work elementwise)
Floats = float | np.ndarray


def near_limit(u: float, f: float, kappa: Floats, sigma: float) -> Floats:
    """near = u f^2 / (f^2 + kappa sigma (u - f))."""
    return u * f**2 / (f**2 + kappa * sigma * (u - f))


def far_limit(u: float, f: float, kappa: Floats, sigma: float) -> np.ndarray:
    """far = u f^2 / (f^2 - kappa sigma (u - f)); inf at or beyond the hyperfocal distance."""
    den = f**2 - kappa * sigma * (u - f)
    with np.errstate(divide="ignore"):
        return np.where(den > 0.0, u * f**2 / np.where(den > 0.0, den, 1.0), np.inf)


def blur_diameter(z: ArrayLike, u: float, f: float, kappa: float) -> np.ndarray:
    """Thin-lens circle of confusion on the sensor of a point at distance z, focus at u:
    c = f^2 |z - u| / (kappa (u - f) z) [m]; c = sigma exactly at near_limit and far_limit,
    and f^2 / (kappa (u - f)) for z = inf."""
    z = np.asarray(z, dtype=float)
    with np.errstate(invalid="ignore"):
        ratio = np.where(np.isfinite(z), np.abs(z - u) / z, 1.0)
    return f**2 * ratio / (kappa * (u - f))


def hyperfocal_distance(f: float, kappa: float, sigma: float) -> float:
    """Focus distance whose far limit is infinite: u_h = f + f^2 / (kappa sigma)."""
    return f + f**2 / (kappa * sigma)


def depth_of_field(u: float, f: float, kappa: Floats, sigma: float) -> np.ndarray:
    """far - near [m] (inf beyond the hyperfocal distance)."""
    return far_limit(u, f, kappa, sigma) - near_limit(u, f, kappa, sigma)


def f_number_for_depth(u: float, f: float, sigma: float, depth_m: float) -> float:
    """Smallest kappa whose depth of field at focus u is depth_m.

    With x = kappa sigma (u - f): far - near = 2 u f^2 x / (f^4 - x^2) = D, i.e. the quadratic
    D x^2 + 2 u f^2 x - D f^4 = 0, whose positive root is x = f^2 (sqrt(u^2 + D^2) - u) / D.
    That difference cancels for D << u (at D = 1e-9 m it is 0); multiplied by the conjugate,
    (h - u)(h + u) = h^2 - u^2 = D^2 with h = sqrt(u^2 + D^2), it is the stable form

        x = f^2 D / (sqrt(u^2 + D^2) + u),

    a sum of positive terms, accurate to a few ulp for every D > 0; kappa -> 0 as D -> 0.
    """
    if depth_m <= 0.0:
        return 0.0
    x = f**2 * depth_m / (np.hypot(u, depth_m) + u)
    return float(x / (sigma * (u - f)))


def near_limit_german(g: float, f: float, kappa: Floats, sigma: float) -> Floats:
    """The paper's eq. (20), d_n = f^2 g / (f^2 - kappa sigma (g + f)), with g = -u < 0: returns -near."""
    return f**2 * g / (f**2 - kappa * sigma * (g + f))


def far_limit_german(g: float, f: float, kappa: Floats, sigma: float) -> Floats:
    """The paper's eq. (21), d_f = f^2 g / (f^2 + kappa sigma (g + f)), with g = -u < 0: returns -far."""
    return f**2 * g / (f**2 + kappa * sigma * (g + f))
