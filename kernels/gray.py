"""Gray value per exposure for every (candidate lamp, sample point): the planner's bulk job."""
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import funcs
from ._arrays import output, profile2d, table2d, unit_rows, vec3d
from .runtime import ensure_init


@dataclass(frozen=True)
class GrayResult:
    """Per (candidate, point), shape (C, P).

    value: c A_pixel Phi R / 8 = G / (t / kappa^2) [gray s^-1]; 0 when shadowed.
    shadowed: lamp behind the point's tangent plane, or (with shadows) the mesh blocks it.
    off_axis: angle between the lamp's axis and the ray lamp -> point [rad] (cone coverage:
        the point is inside the nominal cone iff off_axis <= gamma / 2; the lamp's profile at
        this angle scales the value).
    dominant: 0 diffuse, 1 lobe, 2 spike, -1 camera or lamp behind the surface (BRDF only).
    """

    value: np.ndarray
    shadowed: np.ndarray
    off_axis: np.ndarray
    dominant: np.ndarray


@wp.kernel
def gray_kernel(mesh_id: wp.uint64, shadows: wp.int32, cone: wp.int32, offset_m: wp.float64,
                points: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
                camera: wp.vec3d, lamp_pos: wp.array(dtype=wp.vec3d),
                lamp_axis: wp.array(dtype=wp.vec3d), power_w: wp.float64,
                cone_angle_rad: wp.float64, profile: wp.array2d(dtype=wp.float64),
                table: wp.array2d(dtype=wp.float64),
                camera_constant: wp.float64, pixel_area_m2: wp.float64,
                value: wp.array2d(dtype=wp.float64), shadowed: wp.array2d(dtype=wp.bool),
                off_axis: wp.array2d(dtype=wp.float64), dominant: wp.array2d(dtype=wp.int8)):
    """One thread per (candidate lamp c, sample point p)."""
    c, p = wp.tid()
    sh = funcs.shade_point(mesh_id, shadows, cone, offset_m, points[p], normals[p], camera,
                           lamp_pos[c], lamp_axis[c], power_w, cone_angle_rad, profile, table,
                           camera_constant, pixel_area_m2)
    value[c, p] = sh.value
    shadowed[c, p] = sh.shadowed
    off_axis[c, p] = sh.off_axis
    dominant[c, p] = wp.int8(sh.dominant)


class GrayInputs:
    """The inputs that stay fixed while a planner tries lamp poses (the scene, the camera, the
    lamp, the material), converted to Warp arrays once: a search calls the kernel hundreds of
    times on a few candidates each, where converting them every call cost 10x the kernel's work.

    mesh: kernels.mesh.WarpMesh or None (no cast shadows); points, normals (P, 3) [m];
    camera_pos (3,); power_w, cone_angle_rad: eq. (11); table (K, 6): Material.table(); shadow
    rays start at point + offset_m * normal; profile (M, 2) [off_axis_rad, relative]: the lamp's
    angular profile (None: eq. (11)'s ideal cone). Call with lamp_pos (C, 3) and lamp_axis
    (C, 3) (the aims, normalized here) for a GrayResult of (C, P) NumPy arrays."""

    def __init__(self, mesh, points, normals, camera_pos, power_w, cone_angle_rad, table,
                 camera_constant, pixel_area_m2, shadows=True, cone=True, offset_m=1e-5, profile=None):
        self.device = ensure_init()
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        normals = unit_rows(normals, "normals")
        if len(normals) != len(points):
            raise ValueError(f"{len(points)} points but {len(normals)} normals")
        self.count = len(points)
        use_shadows = bool(shadows) and mesh is not None
        self._mesh = mesh                       # keeps the BVH alive as long as its id is used
        self._leading = [mesh.id if use_shadows else wp.uint64(0), int(use_shadows), int(bool(cone)),
                         float(offset_m), vec3d(points, "points"), vec3d(normals, "normals"),
                         wp.vec3d(*np.asarray(camera_pos, dtype=np.float64))]
        self._trailing = [float(power_w), float(cone_angle_rad), profile2d(profile, cone_angle_rad),
                          table2d(table), float(camera_constant), float(pixel_area_m2)]

    def __call__(self, lamp_pos, lamp_axis):
        lamp_pos = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
        lamp_axis = unit_rows(np.broadcast_to(np.asarray(lamp_axis, dtype=np.float64), lamp_pos.shape),
                              "lamp_axis")
        shape = (len(lamp_pos), self.count)
        value, value_wp = output(shape, np.float64, wp.float64)
        shadowed, shadowed_wp = output(shape, np.bool_, wp.bool)
        off_axis, off_axis_wp = output(shape, np.float64, wp.float64)
        dominant, dominant_wp = output(shape, np.int8, wp.int8)
        if value.size:
            wp.launch(gray_kernel, dim=shape, device=self.device,
                      inputs=self._leading + [vec3d(lamp_pos, "lamp_pos"), vec3d(lamp_axis, "lamp_axis")]
                      + self._trailing, outputs=[value_wp, shadowed_wp, off_axis_wp, dominant_wp])
        return GrayResult(value, shadowed, off_axis, dominant)


def gray_per_exposure(mesh, points, normals, camera_pos, lamp_pos, lamp_axis, power_w,
                      cone_angle_rad, table, camera_constant, pixel_area_m2,
                      shadows=True, cone=True, offset_m=1e-5, profile=None):
    """Gray per exposure c A_pixel Phi R / 8 for C candidate lamps x P sample points, in one
    call (GrayInputs, which keeps the fixed inputs, has the arguments' meaning). Returns
    GrayResult of (C, P) NumPy arrays."""
    return GrayInputs(mesh, points, normals, camera_pos, power_w, cone_angle_rad, table, camera_constant,
                      pixel_area_m2, shadows, cone, offset_m, profile)(lamp_pos, lamp_axis)
