"""The simulator's camera: one primary ray per pixel, shaded with the planner's own funcs."""
from typing import NamedTuple
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from . import funcs
from .emission import axis_intensity
from ._arrays import output, profile2d, table2d, unit_rows, vec3d
from .cone import NO_CONE
from .runtime import ensure_init, launch_sliced

if TYPE_CHECKING:
    from .mesh import WarpMesh


def _ray_outputs(n):
    """(value, hit, depth) of n rays, each a NumPy array and its zero-copy Warp view."""
    return output(n, np.float64, wp.float64), output(n, np.bool_, wp.bool), output(n, np.float64, wp.float64)


class RenderResult(NamedTuple):
    """Per ray (N,): gray per exposure c A Phi R / 8 (0 on a miss), hit, depth [m] along the
    ray (inf on a miss) and the hit face's outward normal (N, 3) (0 on a miss)."""

    value: np.ndarray
    hit: np.ndarray
    depth: np.ndarray
    normal: np.ndarray


@wp.kernel
def render_kernel(mesh_id: wp.uint64, origin: wp.vec3d, ray_dirs: wp.array(dtype=wp.vec3d),
                  max_dist: wp.float64, shadows: wp.int32, cone: wp.int32, offset_m: wp.float64,
                  no_sectors: wp.array2d(dtype=wp.float64), lamps: wp.array(dtype=wp.vec3d),
                  lamp_axes: wp.array(dtype=wp.vec3d), intensity_w_sr: wp.float64,
                  profile: wp.array2d(dtype=wp.float64),
                  table: wp.array2d(dtype=wp.float64),
                  camera_constant: wp.float64, pixel_area_m2: wp.float64,
                  shading_normals: wp.array(dtype=wp.vec3d), part_faces: wp.int32, first: wp.int32,
                  value: wp.array(dtype=wp.float64), hit: wp.array(dtype=wp.bool),
                  depth: wp.array(dtype=wp.float64), normal: wp.array(dtype=wp.vec3d)):
    """One thread per pixel ray, from `first` on (runtime.launch_sliced) (its hit point's free
    cones unknown: every shadow ray cast), its value summed over the point lamps (each with its
    own shadow ray); shaded with the face's normal, or with shading_normals[i] when given (one per
    ray: a surface the mesh does not hold). A ray whose first face is from part_faces on (an
    occluder's) sees nothing: a miss."""
    i = wp.tid() + first
    d = ray_dirs[i]
    q = wp.mesh_query_ray(mesh_id, wp.vec3(origin), wp.vec3(d), wp.float32(max_dist))
    if not q.result or q.face >= part_faces:
        value[i] = wp.float64(0.0)
        hit[i] = False
        depth[i] = wp.float64(wp.inf)
        normal[i] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        return
    t = wp.float64(q.t)
    n = wp.vec3d(q.normal)
    shade_n = n
    if shading_normals.shape[0] > 0:
        shade_n = shading_normals[i]
    at = funcs.surface(origin + t * d, shade_n, origin, offset_m, wp.float64(NO_CONE), -1)
    total = wp.float64(0.0)
    for j in range(lamps.shape[0]):
        sh = funcs.shade_point(mesh_id, shadows, cone, at, no_sectors, lamps[j], lamp_axes[j], intensity_w_sr,
                               profile, table, camera_constant, pixel_area_m2)
        total += sh.value
    value[i] = total
    hit[i] = True
    depth[i] = t
    normal[i] = n


def render(mesh: "WarpMesh", origin: ArrayLike, ray_dirs: ArrayLike, lamp_pos: ArrayLike, lamp_axis: ArrayLike,
           power_w: float, cone_angle_rad: float, table: ArrayLike, camera_constant: float, pixel_area_m2: float,
           shadows: bool = True, cone: bool = True, offset_m: float = 1e-5, max_dist: float = 10.0,
           profile: ArrayLike | None = None, shading_normals: ArrayLike | None = None,
           part_faces: int | None = None) -> RenderResult:
    """Shade the first hit of each ray from `origin` (the camera centre) along unit
    `ray_dirs` (N, 3), lit by one lamp, or by E point lamps (lamp_pos, lamp_axis (E, 3), each
    emitting power_w: an extended light's emitter points, cell.planning.lights.emitters), their
    values summed, each with its own shadow ray (soft shadows): RenderResult(value, hit, depth, normal).

    The hit point is origin + depth * dir (float64 from the float32 hit distance); its normal
    is the mesh's outward face normal (a back face gives cos te <= 0, so R = 0). The shading
    is kernels.funcs.shade_point, the same as gray_per_exposure at that point and normal, with
    the lamp's angular profile (M, 2) (None: eq. (11)'s ideal cone). shading_normals (N, 3), unit,
    shades each hit with its own normal instead of the face's (a defect's, sim.world); the
    returned normal stays the face's. The mesh's faces from part_faces on (None: none) are
    occluders (the fixed lights' housings, after the part's: cell.planning.scene.Scene.shadow_mesh):
    they block shadow rays, and a pixel ray meeting one first sees nothing (dark, as a miss).
    """
    device = ensure_init(__name__)
    dirs = unit_rows(ray_dirs, "ray_dirs")
    n = len(dirs)
    (value, value_wp), (hit, hit_wp), (depth, depth_wp) = _ray_outputs(n)
    normal, normal_wp = output((n, 3), np.float64, wp.vec3d)
    if n == 0:
        return RenderResult(value, hit, depth, normal)
    lamps = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
    axes = unit_rows(np.broadcast_to(np.asarray(lamp_axis, dtype=np.float64).reshape(-1, 3), lamps.shape), "lamp_axis")
    shading = np.zeros((0, 3)) if shading_normals is None else unit_rows(shading_normals, "shading_normals")
    if len(shading) not in (0, n):
        raise ValueError(f"shading_normals must have one row per ray ({n}), got {len(shading)}")
    launch_sliced(render_kernel, n, [
        mesh.id, wp.vec3d(*np.asarray(origin, dtype=np.float64)), vec3d(dirs, "ray_dirs"),
        float(max_dist), int(bool(shadows)), int(bool(cone)), float(offset_m),
        wp.empty((0, funcs.SECTORS), dtype=wp.float64, device=device), vec3d(lamps, "lamp_pos"), vec3d(axes, "lamp_axis"),
        axis_intensity(power_w, cone_angle_rad, profile), profile2d(profile, cone_angle_rad), table2d(table),
        float(camera_constant), float(pixel_area_m2),
        vec3d(shading, "shading_normals"), len(mesh.faces) if part_faces is None else int(part_faces),
    ], [value_wp, hit_wp, depth_wp, normal_wp], work_per_item=1 + len(lamps))
    return RenderResult(value, hit, depth, normal)


class PlaneResult(NamedTuple):
    """Per ray (N,): the texture's value where the ray meets the plane (`outside` beyond the
    texture, 0 on a miss), hit, depth [m] along the ray (inf on a miss)."""

    value: np.ndarray
    hit: np.ndarray
    depth: np.ndarray


@wp.kernel
def plane_kernel(origin: wp.vec3d, ray_dirs: wp.array(dtype=wp.vec3d), plane_origin: wp.vec3d,
                 plane_x: wp.vec3d, plane_y: wp.vec3d, texel_m: wp.float64,
                 texture: wp.array2d(dtype=wp.float64), outside: wp.float64,
                 value: wp.array(dtype=wp.float64), hit: wp.array(dtype=wp.bool),
                 depth: wp.array(dtype=wp.float64)):
    """One thread per ray: the plane through plane_origin spanned by the unit plane_x, plane_y,
    met at t = ((o_p - o) . n) / (d . n) from either side; texel (floor(y / texel), floor(x / texel))."""
    i = wp.tid()
    d = ray_dirs[i]
    n = wp.cross(plane_x, plane_y)
    dn = wp.dot(d, n)
    t = wp.float64(0.0)
    if dn != wp.float64(0.0):
        t = wp.dot(plane_origin - origin, n) / dn
    if t <= wp.float64(0.0):
        value[i] = wp.float64(0.0)
        hit[i] = False
        depth[i] = wp.float64(wp.inf)
        return
    p = origin + t * d - plane_origin
    col = wp.int32(wp.floor(wp.dot(p, plane_x) / texel_m))
    row = wp.int32(wp.floor(wp.dot(p, plane_y) / texel_m))
    v = outside
    if row >= 0 and row < texture.shape[0] and col >= 0 and col < texture.shape[1]:
        v = texture[row, col]
    value[i] = v
    hit[i] = True
    depth[i] = t


def render_plane(origin: ArrayLike, ray_dirs: ArrayLike, T_world_plane: np.ndarray, texture: np.ndarray,
                 texel_m: float, outside: float = 0.0) -> "PlaneResult":
    """Where each ray from `origin` along unit `ray_dirs` (N, 3) meets the plane z = 0 of the
    frame T_world_plane, the texture's value there: texture (rows, cols) covers x in
    [0, cols * texel_m), y in [0, rows * texel_m), texel (r, c) the square from (c, r) * texel_m
    (nearest: no filtering, which supersampling the rays does); `outside` beyond it.
    PlaneResult(value, hit, depth)."""
    device = ensure_init(__name__)
    dirs = unit_rows(ray_dirs, "ray_dirs")
    n = len(dirs)
    (value, value_wp), (hit, hit_wp), (depth, depth_wp) = _ray_outputs(n)
    if n == 0:
        return PlaneResult(value, hit, depth)
    T = np.asarray(T_world_plane, dtype=np.float64)
    tex = wp.array(np.ascontiguousarray(texture, dtype=np.float64), dtype=wp.float64, device=device)
    wp.launch(plane_kernel, dim=n, device=device, inputs=[
        wp.vec3d(*np.asarray(origin, dtype=np.float64)), vec3d(dirs, "ray_dirs"), wp.vec3d(*T[:3, 3]),
        wp.vec3d(*T[:3, 0]), wp.vec3d(*T[:3, 1]), float(texel_m), tex, float(outside),
    ], outputs=[value_wp, hit_wp, depth_wp])
    return PlaneResult(value, hit, depth)
