"""NumPy <-> Warp conversions shared by the wrappers (CPU: zero-copy where possible)."""
import numpy as np
import warp as wp
from numpy.typing import ArrayLike, DTypeLike

from .emission import hard_cone_profile


def vec3d(a: ArrayLike, name: str) -> wp.array:
    """(N, 3) float64 -> wp.array(vec3d)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return wp.array(a, dtype=wp.vec3d, device="cpu")


def vec3d_view(a: np.ndarray, name: str) -> wp.array:
    """(N, 3) C-contiguous float64 -> wp.array(vec3d) over the same memory (vec3d's values, no
    copy, no allocation: on a thread beside another each Warp call hands the GIL over); the
    caller keeps `a` alive, and unchanged, while the view is read."""
    if a.dtype != np.float64 or a.ndim != 2 or a.shape[1] != 3 or not a.flags.c_contiguous:
        raise ValueError(f"{name} must be a C-contiguous float64 array of shape (N, 3), got {a.dtype} {a.shape}")
    return wp.array(a, dtype=wp.vec3d, device="cpu", copy=False)


def unit_rows(a: ArrayLike, name: str) -> np.ndarray:
    """Rows of (N, 3) scaled to unit length (float64)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    # np.linalg.norm's arithmetic (add.reduce adds a row's three squares in turn), as elementwise
    # operations: NumPy's reduction over an axis of 3 costs some 6 times as much on many rows
    norm = np.sqrt((a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1]) + a[:, 2] * a[:, 2])
    if np.any(norm == 0.0):
        raise ValueError(f"{name} has a zero-length row")
    # a / norm[:, None]'s quotients a column at a time: over (N, 1) lengths NumPy's inner loop runs over 3 numbers a row
    out = np.empty_like(a)
    for k in range(3):
        np.divide(a[:, k], norm, out=out[:, k])
    return out


def with_slopes(t: np.ndarray) -> wp.array:
    """Table (K, 1 + N) [x, y_1..y_N] -> (K, 1 + 2N) [x, y_1..y_N, slope_1..slope_N]: slope_i of
    row j is (y_i[j+1] - y_i[j]) / (x[j+1] - x[j]), numpy.interp's (0 on the last row), so the
    kernels interpolate without a division."""
    slopes = np.zeros_like(t[:, 1:])
    slopes[:-1] = np.diff(t[:, 1:], axis=0) / np.diff(t[:, :1], axis=0)
    return wp.array(np.hstack([t, slopes]), dtype=wp.float64, device="cpu")


def table2d(table: ArrayLike) -> wp.array:
    """Material table (K, 6) [phase_rad, rho, sigma1, m1, sigma2, m2], ascending phase, with its
    slopes (with_slopes): (K, 11)."""
    t = np.ascontiguousarray(table, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 6 or len(t) < 1:
        raise ValueError(f"material table must have shape (K, 6), got {t.shape}")
    if np.any(np.diff(t[:, 0]) <= 0.0):
        raise ValueError("material table phase angles must be strictly ascending")
    return with_slopes(t)


def profile2d(profile: ArrayLike | None, cone_angle_rad: float) -> wp.array:
    """Lamp profile (M, 2) [off_axis_rad, relative], angles ascending from 0; None: eq. (11)'s
    ideal cone, 1 up to gamma/2 and 0 beyond (kernels.emission.hard_cone_profile).
    With its slopes (with_slopes): (M, 3)."""
    if profile is None:
        profile = hard_cone_profile(cone_angle_rad)
    p = np.ascontiguousarray(profile, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError(f"lamp profile must have shape (M >= 2, 2), got {p.shape}")
    if p[0, 0] != 0.0 or np.any(np.diff(p[:, 0]) <= 0.0):
        raise ValueError("lamp profile off-axis angles must start at 0 and be strictly ascending")
    return with_slopes(p)


def output(shape: int | tuple[int, ...], dtype: DTypeLike, wp_dtype: type) -> tuple[np.ndarray, wp.array]:
    """A NumPy output array and a zero-copy Warp view of it (NumPy owns the memory)."""
    out = np.empty(shape, dtype=dtype)
    return out, wp.array(out, dtype=wp_dtype, device="cpu", copy=False)
