"""Closest points on the mesh (BVH query): project feature samples onto the surface
without trimesh.proximity, which needs the optional `rtree` package."""
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from ._arrays import output, vec3d
from .runtime import ensure_init

if TYPE_CHECKING:
    from .mesh import WarpMesh


@wp.kernel
def closest_point_kernel(mesh_id: wp.uint64, queries: wp.array(dtype=wp.vec3d), max_dist: wp.float32,
                         point: wp.array(dtype=wp.vec3d), face: wp.array(dtype=wp.int32),
                         normal: wp.array(dtype=wp.vec3d)):
    """One thread per query point."""
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh_id, wp.vec3(queries[i]), max_dist)
    if q.result:
        point[i] = wp.vec3d(wp.mesh_eval_position(mesh_id, q.face, q.u, q.v))
        face[i] = q.face
        normal[i] = wp.vec3d(wp.mesh_eval_face_normal(mesh_id, q.face))
    else:
        point[i] = wp.vec3d(wp.float64(wp.nan), wp.float64(wp.nan), wp.float64(wp.nan))
        face[i] = -1
        normal[i] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


def closest_points(mesh: "WarpMesh", queries: ArrayLike,
                   max_dist: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For queries (N, 3) [m]: (closest surface points (N, 3), face index (N,), outward face
    normal (N, 3)); NaN / -1 / 0 where no triangle lies within max_dist. Float32 accuracy."""
    device = ensure_init(__name__)
    queries = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    n = len(queries)
    point, point_wp = output((n, 3), np.float64, wp.vec3d)
    face, face_wp = output(n, np.int32, wp.int32)
    normal, normal_wp = output((n, 3), np.float64, wp.vec3d)
    if n:
        wp.launch(closest_point_kernel, dim=n, device=device,
                  inputs=[mesh.id, vec3d(queries, "queries"), float(max_dist)],
                  outputs=[point_wp, face_wp, normal_wp])
    return point, face, normal
