"""BRDF of eq. (6)-(7) (Nayar-style diffuse + lobe + spike) and its Jacobian, eq. (8)-(9).

Directions point away from the surface point: n normal, s to the lamp, v to the camera.
R = rho (cos ti + sigma1 <v,r>^m1 + sigma2 <v,r>^m2), r = 2<n,s>n - s, and
<v,r> = 2 cos te cos ti - cos alpha (alpha: phase angle between s and v).
Clamps (physics notes): R = 0 if <n,s> <= 0 or <n,v> <= 0; lobe and spike are 0 if <v,r> <= 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.core.geometry import dot3, row_sum

if TYPE_CHECKING:
    from cell.physics.material import Material, Unresolved

DIFFUSE, LOBE, SPIKE = 0, 1, 2
TERM_NAMES = ("diffuse", "lobe", "spike")
OCCLUDED = -1
UNKNOWN = 3                 # possibly a spike the goniometer did not resolve (unresolved_spike)


def stable_power(base: ArrayLike, exponent: ArrayLike) -> np.ndarray:
    """base**exponent for base in [0, 1], exponent up to ~1e5; 0 where base <= 0.

    Computed as exp(m ln b) with b clamped to 1 and b <= 0 masked, so nothing under- or
    overflows to NaN or inf (ln b is exact for b near 1: b - 1 is exact there).
    """
    return stable_powers(base, exponent)[0]


def stable_powers(base: ArrayLike, *exponents: ArrayLike) -> tuple[np.ndarray, ...]:
    """stable_power(base, m) for each exponent m, ln b taken once for them all (the lobe's and
    the spike's powers of one mirror cosine): the same operations on the same numbers each."""
    b = np.minimum(np.asarray(base, dtype=float), 1.0)
    positive = b > 0.0
    log_b = np.log(np.where(positive, b, 1.0))
    return tuple(np.where(positive, np.exp(np.asarray(m, dtype=float) * log_b), 0.0) for m in exponents)


def mirror_cosine(cos_i: ArrayLike, cos_e: ArrayLike, cos_alpha: ArrayLike) -> np.ndarray:
    """<v,r> = 2 cos te cos ti - cos alpha (eq. 7), the cosine between camera and mirror direction."""
    return 2.0 * np.asarray(cos_e) * np.asarray(cos_i) - np.asarray(cos_alpha)


def brdf_terms(cos_i: ArrayLike, cos_e: ArrayLike, cos_alpha: ArrayLike, sigma1: float | np.ndarray,
               m1: float | np.ndarray, sigma2: float | np.ndarray,
               m2: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three bracketed terms of eq. (6): (cos ti, s1 c^m1, s2 c^m2), each clamped to 0 behind."""
    cos_i = np.asarray(cos_i, dtype=float)
    cos_e = np.asarray(cos_e, dtype=float)
    front = (cos_i > 0.0) & (cos_e > 0.0)
    c = mirror_cosine(cos_i, cos_e, cos_alpha)
    power1, power2 = stable_powers(c, m1, m2)
    diffuse = np.where(front, cos_i, 0.0)
    lobe = np.where(front, sigma1 * power1, 0.0)
    spike = np.where(front, sigma2 * power2, 0.0)
    return diffuse, lobe, spike


def reflectance(cos_i: ArrayLike, cos_e: ArrayLike, cos_alpha: ArrayLike, rho: float | np.ndarray,
                sigma1: float | np.ndarray, m1: float | np.ndarray, sigma2: float | np.ndarray,
                m2: float | np.ndarray) -> np.ndarray:
    """R of eq. (7) [1/sr-like, as the paper uses it]; finite and >= 0 for any valid input."""
    diffuse, lobe, spike = brdf_terms(cos_i, cos_e, cos_alpha, sigma1, m1, sigma2, m2)
    return rho * (diffuse + lobe + spike)


def dominant_term(cos_i: ArrayLike, cos_e: ArrayLike, cos_alpha: ArrayLike, sigma1: float | np.ndarray,
                  m1: float | np.ndarray, sigma2: float | np.ndarray, m2: float | np.ndarray) -> np.ndarray:
    """Sec. 5.2: index of the largest term (DIFFUSE, LOBE, SPIKE); OCCLUDED where R is clamped to 0.
    The largest as np.argmax over the three finds it (the first of equal ones; a NaN counts as
    the largest), by two comparisons instead of a stacked copy (a map asks thousands of cells)."""
    diffuse, lobe, spike = brdf_terms(cos_i, cos_e, cos_alpha, sigma1, m1, sigma2, m2)
    diffuse, lobe, spike = np.broadcast_arrays(diffuse, lobe, spike)
    lobe_wins = (lobe > diffuse) | (np.isnan(lobe) & ~np.isnan(diffuse))
    top = np.where(lobe_wins, lobe, diffuse)
    spike_wins = (spike > top) | (np.isnan(spike) & ~np.isnan(top))
    best = np.where(spike_wins, SPIKE, np.where(lobe_wins, LOBE, DIFFUSE))
    front = (np.asarray(cos_i) > 0.0) & (np.asarray(cos_e) > 0.0)
    return np.where(front, best, OCCLUDED)


def reflectance_jacobian(cos_i: ArrayLike, cos_e: ArrayLike, cos_alpha: ArrayLike, rho: float | np.ndarray,
                         sigma1: float | np.ndarray, m1: float | np.ndarray, sigma2: float | np.ndarray,
                         m2: float | np.ndarray) -> np.ndarray:
    """dR/d(rho, sigma1, m1, sigma2, m2), eq. (8)-(9) with the factor rho the paper drops.

    dR/dsigma_k = rho c^mk; dR/dm_k = rho sigma_k c^mk ln c (0 where c <= 0, since the term is 0).
    Returns an array of shape (..., 5).
    """
    cos_i = np.asarray(cos_i, dtype=float)
    cos_e = np.asarray(cos_e, dtype=float)
    front = (cos_i > 0.0) & (cos_e > 0.0)
    c = mirror_cosine(cos_i, cos_e, cos_alpha)
    positive = front & (c > 0.0)
    log_c = np.where(positive, np.log1p(np.minimum(np.where(positive, c, 1.0), 1.0) - 1.0), 0.0)
    p1 = np.where(positive, stable_power(c, m1), 0.0)
    p2 = np.where(positive, stable_power(c, m2), 0.0)
    d_rho = np.where(front, cos_i, 0.0) + sigma1 * p1 + sigma2 * p2
    return np.stack(np.broadcast_arrays(
        d_rho, rho * p1, rho * sigma1 * p1 * log_c, rho * p2, rho * sigma2 * p2 * log_c), axis=-1)


def phase_angle(s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """alpha between unit vectors (..., 3) = atan2(|s x v|, <s, v>), accurate at every angle
    (arccos of <s, v> is not near 0 and pi); the sums np.linalg.norm's and np.sum's bits (row_sum)."""
    s, v = np.asarray(s, dtype=float), np.asarray(v, dtype=float)
    return _phase_angle(s, v, dot3(s, v))


def _phase_angle(s: np.ndarray, v: np.ndarray, s_dot_v: np.ndarray) -> np.ndarray:
    """phase_angle given <s, v> (dot3's): np.cross's components a component at a time (its
    products and differences, (a1 b2) - (a2 b1) ..., in its order) and |s x v|^2 summed as
    row_sum sums, without (..., 3) arrays (a dominant-term map's thousands of cells against one
    view direction run NumPy's inner loop over 3 numbers once a cell)."""
    (s0, s1, s2), (v0, v1, v2) = (s[..., 0], s[..., 1], s[..., 2]), (v[..., 0], v[..., 1], v[..., 2])
    c0, c1, c2 = s1 * v2 - s2 * v1, s2 * v0 - s0 * v2, s0 * v1 - s1 * v0
    return np.arctan2(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2 + 0.0), s_dot_v)


def reflectance_vectors(n: ArrayLike, s: ArrayLike, v: ArrayLike, material: Material) -> np.ndarray:
    """R for unit vectors (..., 3): n normal, s to lamp, v to camera; material params at the phase angle."""
    n, s, v = (np.asarray(a, dtype=float) for a in (n, s, v))
    cos_i = dot3(n, s)                      # np.sum(n * s, axis=-1)'s bits
    cos_e = dot3(n, v)
    s_dot_v = dot3(s, v)
    p = material.at(_phase_angle(s, v, s_dot_v))
    return reflectance(cos_i, cos_e, np.clip(s_dot_v, -1.0, 1.0), p.rho, p.sigma1, p.m1, p.sigma2, p.m2)


def dominant_term_vectors(n: ArrayLike, s: ArrayLike, v: ArrayLike, material: Material) -> np.ndarray:
    """dominant_term() for unit vectors, with the material at the phase angle (the sums by dot3:
    np.sum(n * s, axis=-1)'s bits)."""
    n, s, v = (np.asarray(a, dtype=float) for a in (n, s, v))
    s_dot_v = dot3(s, v)
    p = material.at(_phase_angle(s, v, s_dot_v))
    return dominant_term(dot3(n, s), dot3(n, v), np.clip(s_dot_v, -1.0, 1.0), p.sigma1, p.m1, p.sigma2, p.m2)


def spike_keep_out(unresolved: Unresolved) -> float:
    """The angle [rad] between the half vector h = (s + v) / |s + v| and the normal within which
    an unresolved spike may lie: the goniometer's step, = sqrt(ln 2 / (2 M)), the half width of
    the widest term it cannot resolve (M = ln 2 / (2 step^2)). It read the mirror pose and poses
    at beta = +-step, +-2 step (beta: h's tilt from the normal, the spike's c^m ~ exp(-2 m
    beta^2)); a term narrower than the step showed at most between them, and c^m falls
    monotonically with beta, so from one step out the readings bound it by the fit's residual
    and within a step nothing does."""
    return float(unresolved.step_rad)


def unresolved_spike(n: ArrayLike, s: ArrayLike, v: ArrayLike, material: Material) -> np.ndarray:
    """bool mask for unit vectors (..., 3): a spike the material's goniometer did not resolve
    (Material.unresolved) may dominate here: the phase angle's parameters come from a row whose
    spike is unresolved, and h lies within spike_keep_out of the normal. Nowhere without one."""
    n, s, v = (np.asarray(a, dtype=float) for a in (n, s, v))
    if material.unresolved is None:
        return np.zeros(np.broadcast_shapes(n.shape, s.shape, v.shape)[:-1], bool)
    h = s + v
    cos_h = row_sum(n * h) / np.maximum(np.sqrt(row_sum(h * h)), 1e-300)     # np.sum's, np.linalg.norm's bits
    near = cos_h > np.cos(spike_keep_out(material.unresolved))
    return near & material.unresolved_spike(phase_angle(s, v))


def judged_term(dominant: ArrayLike, n: ArrayLike, s: ArrayLike, v: ArrayLike, material: Material) -> np.ndarray:
    """The dominant term (dominant_term_vectors', the kernels') as the planner judges it:
    UNKNOWN where an unresolved spike may dominate (unresolved_spike), OCCLUDED kept. The region
    map and every sample's check (search and certificate) read this one function."""
    dominant = np.asarray(dominant)
    return np.where((dominant != OCCLUDED) & unresolved_spike(n, s, v, material), UNKNOWN, dominant)
