"""NumPy references of the kernels in kernels/, for the tests and `cell bench`.

Here in cell, not in kernels, because they are built from the readable physics (cell.physics.brdf,
radiometry) and cell.physics.material, and kernels/ knows nothing of cell; rays by brute-force
Moller-Trumbore over every triangle in float64 (trimesh's ray module would need the optional
`rtree` package, which the project does not depend on). Slow, readable, independent of Warp.
`mesh` is anything with .vertices (V, 3) and .faces (F, 3): a WarpMesh (its float32
geometry, exactly what the kernels see) or a trimesh.Trimesh.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry
from cell.physics.material import Material
from cell.physics import brdf, radiometry
from kernels.gray import GrayResult
from kernels.render import RenderResult

TANGENT_EPS = 1e-9          # as kernels.funcs.TANGENT_EPS
_CHUNK = 1 << 19            # rays x triangles per NumPy batch


# blocked(origins (R, 3), unit dirs (R, 3), max_dist (R,)) -> bool (R,): a triangle lies on each ray
RayBlocker = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


class TriangleMesh(Protocol):
    """A WarpMesh or a trimesh.Trimesh: vertices (V, 3), faces (F, 3)."""

    @property
    def vertices(self) -> np.ndarray: ...
    @property
    def faces(self) -> np.ndarray: ...


def _triangles(mesh):
    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    v0 = tri[:, 0]
    return v0, tri[:, 1] - v0, tri[:, 2] - v0


def _ray_triangle_t(v0, e1, e2, origins, dirs):
    """(R, F) distance along each unit ray to each triangle, inf where it misses."""
    pvec = np.cross(dirs[:, None, :], e2[None])
    det = np.einsum("fk,rfk->rf", e1, pvec)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    ok = np.abs(det) > 1e-14 * scale[None]
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origins[:, None, :] - v0[None]
    u = np.einsum("rfk,rfk->rf", tvec, pvec) * inv
    qvec = np.cross(tvec, e1[None])
    w = np.einsum("rk,rfk->rf", dirs, qvec) * inv
    t = np.einsum("fk,rfk->rf", e2, qvec) * inv
    ok &= (u >= 0.0) & (w >= 0.0) & (u + w <= 1.0) & (t > 0.0)
    return np.where(ok, t, np.inf)


def ray_first_hit(mesh: TriangleMesh, origins: ArrayLike, dirs: ArrayLike,
                  max_dist: ArrayLike = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Closest hit of each ray (R, 3) along unit dirs: (t (R,), face (R,)); inf / -1 on a miss."""
    v0, e1, e2 = _triangles(mesh)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    t_out = np.full(len(origins), np.inf)
    face = np.full(len(origins), -1)
    step = max(1, _CHUNK // len(v0))
    for i in range(0, len(origins), step):
        t = _ray_triangle_t(v0, e1, e2, origins[i:i + step], dirs[i:i + step])
        k = np.argmin(t, axis=1)
        best = t[np.arange(len(t)), k]
        hit = best < max_dist
        t_out[i:i + step] = np.where(hit, best, np.inf)
        face[i:i + step] = np.where(hit, k, -1)
    return t_out, face


def ray_hits_any(mesh: TriangleMesh, origins: ArrayLike, dirs: ArrayLike, max_dist: ArrayLike) -> np.ndarray:
    """bool (R,): a triangle lies within max_dist (scalar or (R,)) along each unit ray."""
    t, _ = ray_first_hit(mesh, origins, dirs)
    return t < max_dist


def _material(table):
    t = np.asarray(table, dtype=np.float64)
    return Material("table", "cell.physics.reference", *t.T)


def gray_per_exposure(mesh: TriangleMesh | None, points: ArrayLike, normals: ArrayLike, camera_pos: ArrayLike,
                      lamp_pos: ArrayLike, lamp_axis: ArrayLike, power_w: float, cone_angle_rad: float,
                      table: ArrayLike, camera_constant: float, pixel_area_m2: float, shadows: bool = True,
                      cone: bool = True, offset_m: float = 1e-5, profile: np.ndarray | None = None,
                      blocked: RayBlocker | None = None) -> GrayResult:
    """NumPy version of kernels.gray.gray_per_exposure (same arguments, same GrayResult).
    blocked(origins, dirs, max_dist) -> bool (R,) casts the shadow rays (default: ray_hits_any on
    the mesh; `cell bench` passes Embree's, what a user would write instead of our kernel)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = geometry.unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    lamps = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
    axis = geometry.unit(np.broadcast_to(np.asarray(lamp_axis, dtype=np.float64), lamps.shape))
    to_lamp = lamps[:, None, :] - points[None]                      # (C, P, 3)
    d = np.linalg.norm(to_lamp, axis=-1)
    s = geometry.direction(to_lamp)         # 0 for a lamp at the point (shadowed), as the kernel's
    v = geometry.direction(np.asarray(camera_pos, dtype=np.float64) - points)[None]     # 0: unseen
    material = _material(table)
    reflectance = brdf.reflectance_vectors(n[None], s, v, material)
    dominant = brdf.dominant_term_vectors(n[None], s, v, material).astype(np.int8)
    # the chord's angle 2 asin(|a + s| / 2) = acos(<a, -s>) for a unit s, as the kernel takes it
    off_axis = 2.0 * np.arcsin(np.minimum(0.5 * np.linalg.norm(axis[:, None, :] + s, axis=-1), 1.0))
    lit_at = np.where(d > 0.0, d, np.inf)   # a lamp at the point lights nothing there (no 1/0)
    irradiance = radiometry.cone_irradiance(power_w, cone_angle_rad, lit_at, off_axis if cone else 0.0, profile)
    shadowed = np.sum(n[None] * s, axis=-1) <= 0.0                  # attached shadow
    if shadows and mesh is not None:
        c, p = np.nonzero(~shadowed)
        cast = blocked or (lambda o, u, t: ray_hits_any(mesh, o, u, t))
        shadowed[c, p] = cast(points[p] + offset_m * n[p], s[c, p], d[c, p])
    value = radiometry.gray_per_exposure(camera_constant, pixel_area_m2, irradiance, reflectance)
    return GrayResult(np.where(shadowed, 0.0, value), shadowed, off_axis, dominant)


def feature_directions(frame: ArrayLike, azimuth: ArrayLike, elevation: ArrayLike) -> np.ndarray:
    """(E, A, 3) unit directions of the azimuth/elevation grid, in the mesh's frame."""
    local = geometry.direction_from_angles(np.asarray(azimuth, float)[None, :],
                                           np.asarray(elevation, float)[:, None])
    return local @ np.asarray(frame, dtype=np.float64).T


def visibility_maps(mesh: TriangleMesh, points: ArrayLike, normals: ArrayLike, frame: ArrayLike,
                    azimuth: ArrayLike, elevation: ArrayLike, offset_m: float = 1e-5,
                    max_dist: float = 10.0) -> np.ndarray:
    """NumPy version of kernels.visibility.visibility_maps: bool (P, E, A)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = geometry.unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    dirs = feature_directions(frame, azimuth, elevation)
    shape = (len(points),) + dirs.shape[:2]
    d = np.broadcast_to(dirs[None], shape + (3,))
    above = np.einsum("peak,pk->pea", d, n) > TANGENT_EPS
    visible = np.zeros(shape, dtype=bool)
    p, e, a = np.nonzero(above)
    visible[p, e, a] = ~ray_hits_any(mesh, points[p] + offset_m * n[p], d[p, e, a], max_dist)
    return visible


def render(mesh: TriangleMesh, origin: ArrayLike, ray_dirs: ArrayLike, lamp_pos: ArrayLike, lamp_axis: ArrayLike,
           power_w: float, cone_angle_rad: float, table: ArrayLike, camera_constant: float, pixel_area_m2: float,
           shadows: bool = True, cone: bool = True, offset_m: float = 1e-5, max_dist: float = 10.0,
           profile: np.ndarray | None = None) -> RenderResult:
    """NumPy version of kernels.render.render (same arguments, same RenderResult; E point lamps
    (E, 3) summed)."""
    origin = np.asarray(origin, dtype=np.float64)
    dirs = geometry.unit(np.asarray(ray_dirs, dtype=np.float64).reshape(-1, 3))
    t, face = ray_first_hit(mesh, np.broadcast_to(origin, dirs.shape), dirs, max_dist)
    hit = face >= 0
    v0, e1, e2 = _triangles(mesh)
    normal = np.zeros_like(dirs)
    normal[hit] = geometry.unit(np.cross(e1[face[hit]], e2[face[hit]]))
    value = np.zeros(len(dirs))
    if hit.any():
        lamps = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
        axes = np.broadcast_to(np.asarray(lamp_axis, dtype=np.float64).reshape(-1, 3), lamps.shape)
        g = gray_per_exposure(mesh if shadows else None, origin + t[hit, None] * dirs[hit],
                              normal[hit], origin, lamps, axes, power_w,
                              cone_angle_rad, table, camera_constant, pixel_area_m2,
                              shadows=shadows, cone=cone, offset_m=offset_m, profile=profile)
        value[hit] = g.value.sum(axis=0)
    return RenderResult(value, hit, t, normal)
