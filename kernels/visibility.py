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
def axes_kernel(points: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d), offset_m: wp.float64,
                u: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), origin: wp.array(dtype=wp.vec3d)):
    """One thread per point: what its rays share, whatever their direction: the tangent axes
    u, n x u that give a direction's sector (funcs.tangent_u) and the rays' origin."""
    p = wp.tid()
    n = normals[p]
    u[p] = funcs.tangent_u(n)
    w[p] = wp.cross(n, u[p])
    origin[p] = points[p] + offset_m * n


@wp.func
def escapes(mesh_id: wp.uint64, d: wp.vec3d, n: wp.vec3d, u: wp.vec3d, w: wp.vec3d, origin: wp.vec3d,
            free_cos: wp.float64, sector_cos: wp.array2d(dtype=wp.float64), row: wp.int32,
            max_dist: wp.float64) -> wp.bool:
    """Whether the ray from origin along the unit direction d escapes the mesh within max_dist:
    not where d is at or below the tangent plane (<d, n> <= TANGENT_EPS), no ray cast inside
    the point's free cones (free_cos, its sectors' in `row` of sector_cos; none if -1)."""
    cos_n = wp.dot(d, n)
    if cos_n > funcs.TANGENT_EPS:
        if funcs.needs_ray(free_cos, sector_cos, row, u, w, d, cos_n):
            return not funcs.ray_blocked(mesh_id, origin, d, max_dist)
        return True
    return False


@wp.kernel
def visibility_kernel(mesh_id: wp.uint64, normals: wp.array(dtype=wp.vec3d), u: wp.array(dtype=wp.vec3d),
                      w: wp.array(dtype=wp.vec3d), origin: wp.array(dtype=wp.vec3d),
                      directions: wp.array2d(dtype=wp.vec3d), max_dist: wp.float64,
                      free_cos: wp.array(dtype=wp.float64), sector_cos: wp.array2d(dtype=wp.float64),
                      sectors: wp.int32, first: wp.int32, visible: wp.array3d(dtype=wp.bool)):
    """One thread per (point p, elevation e), over every azimuth a, p from `first` on (a slice
    of the points: runtime.launch_sliced); its sectors' cones in row p of sector_cos, if `sectors`."""
    i, e = wp.tid()
    p = i + first
    row = -1
    if sectors != 0:
        row = p
    for a in range(directions.shape[1]):
        visible[p, e, a] = escapes(mesh_id, directions[e, a], normals[p], u[p], w[p], origin[p], free_cos[p],
                                   sector_cos, row, max_dist)


@wp.kernel
def all_see_kernel(mesh_id: wp.uint64, normals: wp.array(dtype=wp.vec3d), u: wp.array(dtype=wp.vec3d),
                   w: wp.array(dtype=wp.vec3d), origin: wp.array(dtype=wp.vec3d),
                   directions: wp.array2d(dtype=wp.vec3d), max_dist: wp.float64,
                   free_cos: wp.array(dtype=wp.float64), sector_cos: wp.array2d(dtype=wp.float64),
                   sectors: wp.int32, first: wp.int32, visible: wp.array2d(dtype=wp.bool)):
    """One thread per (elevation e, azimuth a), e from `first` on (a slice of the rows:
    runtime.launch_sliced): whether the direction escapes from every point, the points taken in
    turn until one it does not escape from (no ray of the points after it cast)."""
    i, a = wp.tid()
    e = i + first
    d = directions[e, a]
    ok = bool(True)
    p = int(0)
    while ok and p < normals.shape[0]:
        row = -1
        if sectors != 0:
            row = p
        ok = escapes(mesh_id, d, normals[p], u[p], w[p], origin[p], free_cos[p], sector_cos, row, max_dist)
        p += 1
    visible[e, a] = ok


def _rays(mesh: "WarpMesh", points: ArrayLike, normals: ArrayLike, frame: ArrayLike, azimuth: ArrayLike,
          elevation: ArrayLike, offset_m: float, max_dist: float, free_cones: bool) -> tuple[int, int, int, list]:
    """(points P, elevations E, azimuths A, the kernels' inputs from `mesh_id` to `sectors`):
    the inputs checked, the directions (directions_kernel), each point's axes and ray origin
    (axes_kernel) and, where they pay (cone.worth_finding), its free cones."""
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
    count, rows, columns = len(points), len(elevation), len(azimuth)
    if not (count and rows and columns):
        return count, rows, columns, []
    free_cos, sector_cos = np.full(count, NO_CONE), np.zeros((0, funcs.SECTORS))
    if free_cones and worth_finding(rows * columns, mesh):
        free_cos, sector_cos = free_cone_cosines(mesh, points + offset_m * normals, normals)
    directions = wp.empty((rows, columns), dtype=wp.vec3d, device=device)
    wp.launch(directions_kernel, dim=(rows, columns), device=device,
              inputs=[wp.mat33d(*frame.ravel()), wp.array(azimuth, dtype=wp.float64, device=device),
                      wp.array(elevation, dtype=wp.float64, device=device)], outputs=[directions])
    normals_wp = vec3d(normals, "normals")
    axes = [wp.empty(count, dtype=wp.vec3d, device=device) for _ in range(3)]
    wp.launch(axes_kernel, dim=count, device=device, inputs=[vec3d(points, "points"), normals_wp, float(offset_m)],
              outputs=axes)
    return count, rows, columns, [mesh.id, normals_wp, *axes, directions, float(max_dist),
                                  wp.array(free_cos, dtype=wp.float64, device=device),
                                  wp.array(sector_cos, dtype=wp.float64, device=device), int(len(sector_cos) > 0)]


def visibility_maps(mesh: "WarpMesh", points: ArrayLike, normals: ArrayLike, frame: ArrayLike, azimuth: ArrayLike,
                    elevation: ArrayLike, offset_m: float = 1e-5, max_dist: float = 10.0,
                    free_cones: bool = True) -> np.ndarray:
    """bool (P, E, A): True where the ray from point + offset_m * normal along the direction
    (azimuth a, elevation e) escapes the mesh within max_dist [m].

    Directions are (cos e cos a, cos e sin a, sin e) in the feature frame, whose columns
    (3x3 `frame`) are its x, y, z axes in the mesh's frame. Directions at or below a point's
    tangent plane (<d, n> <= 1e-9) are False: the part hides them itself.
    The feature's combined map is `combined_map(maps)` (visible_from_all finds it alone).
    """
    count, rows, columns, inputs = _rays(mesh, points, normals, frame, azimuth, elevation, offset_m, max_dist,
                                         free_cones)
    visible, visible_wp = output((count, rows, columns), np.bool_, wp.bool)
    if inputs:
        launch_sliced(visibility_kernel, (count, rows), inputs, [visible_wp], work_per_item=rows * columns)
    return visible


def visible_from_all(mesh: "WarpMesh", points: ArrayLike, normals: ArrayLike, frame: ArrayLike,
                     azimuth: ArrayLike, elevation: ArrayLike, offset_m: float = 1e-5, max_dist: float = 10.0,
                     free_cones: bool = True) -> np.ndarray:
    """bool (E, A): combined_map(visibility_maps(...)) of the same arguments, a direction
    visible where its ray escapes from every point, found without the points' own maps: each
    direction's points in turn until the first whose ray does not escape (half the sphere is
    below a point's tangent plane: one point's test settles it). True everywhere without points."""
    count, rows, columns, inputs = _rays(mesh, points, normals, frame, azimuth, elevation, offset_m, max_dist,
                                         free_cones)
    visible, visible_wp = output((rows, columns), np.bool_, wp.bool)
    if not inputs:
        visible[:] = count == 0
    else:
        launch_sliced(all_see_kernel, (rows, columns), inputs, [visible_wp], work_per_item=columns * count)
    return visible


def combined_map(maps: ArrayLike) -> np.ndarray:
    """The feature's map (E, A): a direction is visible if it is visible from every sample."""
    return np.asarray(np.asarray(maps).all(axis=0))
