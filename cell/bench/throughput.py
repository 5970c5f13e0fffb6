"""Throughput of the bulk kernels against their NumPy references and trimesh's ray casters
(for `cell bench`).

Each pair is measured side by side in one call, warm (each Warp kernel runs once before it is
timed), as the median of `repeat` runs. The NumPy references cast brute-force rays (every ray
against every triangle, cost per evaluation independent of the batch), so they are timed on at
most `reference_evaluations` and compared per evaluation. Each call returns rows
{name, size, warp_per_s, reference, reference_size, reference_per_s, ratio, unavailable}.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from cell.physics import reference
from kernels.gray import gray_per_exposure
from kernels.visibility import visibility_maps
from kernels.mesh import WarpMesh


def wall_times(fn: Callable[[], object], repeat: int) -> list[float]:
    """Wall time of each of `repeat` (at least 1) calls of fn() [s]."""
    times = []
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def median_time(fn: Callable[[], object], repeat: int) -> float:
    """Median wall time of `repeat` calls of fn() [s]."""
    return float(np.median(wall_times(fn, repeat)))


def _row(name, size, warp_per_s, ref_name, ref_size=0, ref_per_s=None, unavailable=None):
    return {"name": name, "size": int(size), "warp_per_s": warp_per_s, "reference": ref_name,
            "reference_size": int(ref_size), "reference_per_s": ref_per_s,
            "ratio": None if ref_per_s is None else warp_per_s / ref_per_s, "unavailable": unavailable}


def benchmark_gray(mesh: WarpMesh, points: ArrayLike, normals: ArrayLike, camera_pos: ArrayLike, table: np.ndarray,
                   power_w: float = 0.23043, cone_angle_rad: float = np.radians(12.0),
                   camera_constant: float = 1.5e16, pixel_area_m2: float = 4.65e-6**2,
                   evaluations: int = 1_000_000, reference_evaluations: int = 20_000, shadows: bool = True,
                   repeat: int = 3, seed: int = 0) -> list[dict[str, Any]]:
    """Gray evaluations (candidate x point) per second, kernels.gray vs cell.physics.reference.

    Candidates: random lamps 0.15-0.6 m from the points' centroid on its upper hemisphere,
    aimed at it. Returns one row, named "gray" (with shadow rays) or "gray, no shadows"; with
    shadows also "gray vs numpy + embree": NumPy's arithmetic with Embree casting the shadow rays
    (trimesh.ray.ray_pyembree, the optional [bench] extra), at the kernel's own size.
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
    n_ref = max(1, min(evaluations, reference_evaluations) // len(points))
    run(gray_per_exposure, 1)()
    t_warp = median_time(run(gray_per_exposure, n_warp), repeat)
    t_ref = median_time(run(reference.gray_per_exposure, n_ref), 1)
    name = "gray" if shadows else "gray, no shadows"
    rows = [_row(name, n_warp * len(points), n_warp * len(points) / t_warp, "numpy", n_ref * len(points),
                 n_ref * len(points) / t_ref)]
    if shadows:       # what a user would write instead: NumPy arithmetic, Embree's shadow rays
        try:
            blocked = _blocked_by(mesh, "ray_pyembree")
        except ImportError as missing:
            rows.append(_row("gray vs numpy + embree", n_warp * len(points), rows[0]["warp_per_s"],
                             "numpy + trimesh.ray.ray_pyembree",
                             unavailable=f"needs {missing.name or missing}, not installed"))
            return rows
        n_embree = max(1, evaluations // len(points))
        impl = functools.partial(reference.gray_per_exposure, blocked=blocked)
        t_embree = median_time(run(impl, n_embree), 1)
        rows.append(_row("gray vs numpy + embree", n_warp * len(points), rows[0]["warp_per_s"],
                         "numpy + trimesh.ray.ray_pyembree", n_embree * len(points),
                         n_embree * len(points) / t_embree))
    return rows


def benchmark_visibility(mesh: WarpMesh, points: ArrayLike, normals: ArrayLike, frame: np.ndarray,
                         azimuth: np.ndarray, elevation: np.ndarray, reference_evaluations: int = 20_000,
                         reference_rays: int = 100_000, repeat: int = 3,
                         offset_m: float = 1e-5) -> list[dict[str, Any]]:
    """Visibility evaluations (point x direction) per second, kernels.visibility vs
    cell.physics.reference (on the first points, up to reference_evaluations); and rays per second
    on the rays above each tangent plane, every one cast (the kernel without its free cones), vs
    trimesh's ray_triangle and embree casters (up to reference_rays of them). Returns three rows."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    normals = np.asarray(normals, dtype=float).reshape(-1, 3)
    per_point = len(azimuth) * len(elevation)
    size = len(points) * per_point
    n_ref = max(1, min(len(points), reference_evaluations // per_point))

    def run(impl, count, **options):
        return lambda: impl(mesh, points[:count], normals[:count], frame, azimuth, elevation, **options)

    run(visibility_maps, 1)()
    t_warp = median_time(run(visibility_maps, len(points)), repeat)
    t_rays = median_time(run(visibility_maps, len(points), free_cones=False), repeat)
    t_ref = median_time(run(reference.visibility_maps, n_ref), 1)
    rows = [_row("visibility", size, size / t_warp, "numpy", n_ref * per_point, n_ref * per_point / t_ref)]

    dirs = reference.feature_directions(frame, azimuth, elevation).reshape(-1, 3)
    p, d = np.nonzero(normals @ dirs.T > reference.TANGENT_EPS)
    rays_per_s = len(p) / t_rays
    pick = np.random.default_rng(0).permutation(len(p))[:reference_rays]
    origins, ray_dirs = points[p[pick]] + offset_m * normals[p[pick]], dirs[d[pick]]
    for name, module in (("rays vs trimesh", "ray_triangle"), ("rays vs embree", "ray_pyembree")):
        try:
            caster = _trimesh_caster(mesh, module)
            caster(origins[:1], ray_dirs[:1])
        except ImportError as missing:      # trimesh's casters need rtree or embreex
            rows.append(_row(name, len(p), rays_per_s, f"trimesh.ray.{module}",
                             unavailable=f"needs {missing.name or missing}, not installed"))
            continue
        t_ref = median_time(lambda: caster(origins, ray_dirs), 1)
        rows.append(_row(name, len(p), rays_per_s, f"trimesh.ray.{module}", len(pick), len(pick) / t_ref))
    return rows


def _blocked_by(mesh, module):
    """blocked(origins, dirs, max_dist) -> bool (R,) of trimesh.ray.<module>: the first hit
    nearer than max_dist along each ray."""
    import importlib

    import trimesh
    ray = importlib.import_module(f"trimesh.ray.{module}")
    intersector = ray.RayMeshIntersector(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False))

    def blocked(origins, dirs, max_dist):
        hits, index, _ = intersector.intersects_location(origins, dirs, multiple_hits=False)
        out = np.zeros(len(origins), dtype=bool)
        out[index] = np.linalg.norm(hits - origins[index], axis=1) < np.broadcast_to(max_dist, len(origins))[index]
        return out
    return blocked


def _trimesh_caster(mesh, module):
    """intersects_any(origins, directions) of trimesh.ray.<module> on the mesh."""
    import importlib

    import trimesh
    ray = importlib.import_module(f"trimesh.ray.{module}")
    intersector = ray.RayMeshIntersector(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False))
    return intersector.intersects_any
