"""Visibility maps (sec. 2.2): which azimuth/elevation directions escape the part from each
sample point, by ray casting the mesh."""
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from . import funcs
from ._arrays import output, unit_rows, vec3d
from .cone import NO_CONE, free_cone_cosines, worth_finding
from .runtime import ensure_init, launch_sliced

if TYPE_CHECKING:
    from .mesh import WarpMesh


@wp.kernel
def directions_kernel(frame: wp.mat33d, azimuth: wp.array(dtype=wp.float64), elevation: wp.array(dtype=wp.float64),
                      directions: wp.array2d(dtype=wp.vec3d)):
    """One thread per (elevation e, azimuth a): the direction (azimuth a, elevation e) of the
    feature frame in the mesh's frame, which every point's rays share."""
    e, a = wp.tid()
    directions[e, a] = wp.mul(frame, funcs.direction_from_angles(azimuth[a], elevation[e]))


@wp.kernel
def visibility_kernel(mesh_id: wp.uint64, points: wp.array(dtype=wp.vec3d),
                      normals: wp.array(dtype=wp.vec3d), directions: wp.array2d(dtype=wp.vec3d),
                      offset_m: wp.float64, max_dist: wp.float64, free_cos: wp.array(dtype=wp.float64),
                      sector_cos: wp.array2d(dtype=wp.float64), sectors: wp.int32, first: wp.int32,
                      visible: wp.array3d(dtype=wp.bool)):
    """One thread per (point p, elevation e), over every azimuth a (what depends on the point
    alone found once for the row), p from `first` on (a slice of the points:
    runtime.launch_sliced); no ray inside the point's free cones (its sectors' in row p of
    sector_cos, if `sectors`)."""
    i, e = wp.tid()
    p = i + first
    n = normals[p]
    row = -1
    if sectors != 0:
        row = p
    u = funcs.tangent_u(n)
    w = wp.cross(n, u)
    origin = points[p] + offset_m * n
    for a in range(directions.shape[1]):
        d = directions[e, a]
        cos_n = wp.dot(d, n)
        ok = False
        if cos_n > funcs.TANGENT_EPS:
            ok = True
            if funcs.needs_ray(free_cos[p], sector_cos, row, u, w, d, cos_n):
                ok = not funcs.ray_blocked(mesh_id, origin, d, max_dist)
        visible[p, e, a] = ok


def visibility_maps(mesh: "WarpMesh", points: ArrayLike, normals: ArrayLike, frame: ArrayLike, azimuth: ArrayLike,
                    elevation: ArrayLike, offset_m: float = 1e-5, max_dist: float = 10.0,
                    free_cones: bool = True) -> np.ndarray:
    """bool (P, E, A): True where the ray from point + offset_m * normal along the direction
    (azimuth a, elevation e) escapes the mesh within max_dist [m].

    Directions are (cos e cos a, cos e sin a, sin e) in the feature frame, whose columns
    (3x3 `frame`) are its x, y, z axes in the mesh's frame. Directions at or below a point's
    tangent plane (<d, n> <= 1e-9) are False: the part hides them itself.
    The feature's combined map is `combined_map(maps)`: visible from every sample.
    """
    device = ensure_init(__name__)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = unit_rows(normals, "normals")
    azimuth = np.ascontiguousarray(azimuth, dtype=np.float64).ravel()
    elevation = np.ascontiguousarray(elevation, dtype=np.float64).ravel()
    frame = np.asarray(frame, dtype=np.float64)
    if frame.shape != (3, 3):
        raise ValueError(f"frame must be 3x3, got {frame.shape}")
    if len(normals) != len(points):
        raise ValueError(f"{len(points)} points but {len(normals)} normals")
    shape = (len(points), len(elevation), len(azimuth))
    visible, visible_wp = output(shape, np.bool_, wp.bool)
    if visible.size == 0:
        return visible
    free_cos, sector_cos = np.full(len(points), NO_CONE), np.zeros((0, funcs.SECTORS))
    if free_cones and worth_finding(len(azimuth) * len(elevation), mesh):
        free_cos, sector_cos = free_cone_cosines(mesh, points + offset_m * normals, normals)
    directions = wp.empty(shape[1:], dtype=wp.vec3d, device=device)
    wp.launch(directions_kernel, dim=shape[1:], device=device,
              inputs=[wp.mat33d(*frame.ravel()), wp.array(azimuth, dtype=wp.float64, device=device),
                      wp.array(elevation, dtype=wp.float64, device=device)], outputs=[directions])
    launch_sliced(visibility_kernel, shape[:2], [
        mesh.id, vec3d(points, "points"), vec3d(normals, "normals"), directions, float(offset_m), float(max_dist),
        wp.array(free_cos, dtype=wp.float64, device=device), wp.array(sector_cos, dtype=wp.float64, device=device),
        int(len(sector_cos) > 0)], [visible_wp], work_per_item=len(elevation) * len(azimuth))
    return visible


def combined_map(maps: ArrayLike) -> np.ndarray:
    """The feature's map (E, A): a direction is visible if it is visible from every sample."""
    return np.asarray(np.asarray(maps).all(axis=0))
