"""Throughput of the bulk gray kernel against its NumPy reference (for `cell bench`)."""
import time

import numpy as np

from . import reference
from .gray import gray_per_exposure


def _best_time(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def benchmark_gray(mesh, points, normals, camera_pos, table, power_w=0.23043,
                   cone_angle_rad=np.radians(12.0), camera_constant=1.5e16, pixel_area_m2=4.65e-6**2,
                   evaluations=1_000_000, reference_evaluations=20_000, shadows=True, repeat=3, seed=0):
    """Evaluations per second (candidate x point) of kernels.gray vs kernels.reference.

    Candidates: random lamps 0.15-0.6 m from the points' centroid on its upper hemisphere,
    aimed at it. The reference is timed on fewer evaluations (its brute-force shadow rays are
    slow) and both are reported per evaluation. Warm timing: the kernel is launched once first.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    center = points.mean(axis=0)

    def lamps(count):
        d = rng.normal(size=(count, 3))
        d[:, 2] = np.abs(d[:, 2])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return center + d * rng.uniform(0.15, 0.6, (count, 1)), -d

    def run(impl, count):
        pos, aim = lamps(count)
        return lambda: impl(mesh, points, normals, camera_pos, pos, aim, power_w, cone_angle_rad,
                            table, camera_constant, pixel_area_m2, shadows=shadows)

    n_warp = max(1, evaluations // len(points))
    n_ref = max(1, reference_evaluations // len(points))
    run(gray_per_exposure, 1)()                                    # compile or load once
    t_warp = _best_time(run(gray_per_exposure, n_warp), repeat)
    t_ref = _best_time(run(reference.gray_per_exposure, n_ref), 1)
    return {
        "points": len(points), "shadows": bool(shadows),
        "warp_evaluations": n_warp * len(points), "warp_s": t_warp,
        "warp_evaluations_per_s": n_warp * len(points) / t_warp,
        "numpy_evaluations": n_ref * len(points), "numpy_s": t_ref,
        "numpy_evaluations_per_s": n_ref * len(points) / t_ref,
    }
