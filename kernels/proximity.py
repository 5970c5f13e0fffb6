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


class ClosestPoint:
    """closest_points of one query at a time, its launch recorded once (wp.launch(record_cmd=True))
    and run again on each new query written into the same array: a search that asks one point
    after another (the certificate's specular point, some 80 queries) skips the launch's
    argument packing and array wrapping each time, the same kernel on the same inputs, so the
    same results bit for bit."""

    def __init__(self, mesh: "WarpMesh", max_dist: float = 10.0) -> None:
        device = ensure_init(__name__)
        self.query = np.zeros((1, 3))
        self.point, point_wp = output((1, 3), np.float64, wp.vec3d)
        self.face, face_wp = output(1, np.int32, wp.int32)
        self.normal, normal_wp = output((1, 3), np.float64, wp.vec3d)
        query_wp = wp.array(self.query, dtype=wp.vec3d, device="cpu", copy=False)
        # the mesh (its BVH) and the Warp views live as long as the recorded launch that points at them
        self._kept = (mesh, query_wp, point_wp, face_wp, normal_wp)
        self._launch = wp.launch(closest_point_kernel, dim=1, device=device,
                                 inputs=[mesh.id, query_wp, float(max_dist)],
                                 outputs=[point_wp, face_wp, normal_wp], record_cmd=True)

    def __call__(self, query: ArrayLike) -> tuple[np.ndarray, int, np.ndarray]:
        """(closest surface point (3,), face index, outward face normal (3,)) of one query (3,),
        closest_points's values; copies, not the launch's own arrays."""
        self.query[0] = np.asarray(query, dtype=np.float64).reshape(3)
        self._launch.launch()
        return self.point[0].copy(), int(self.face[0]), self.normal[0].copy()
