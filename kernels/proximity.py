"""Closest points on the mesh (BVH query): project feature samples onto the surface
without trimesh.proximity, which needs the optional `rtree` package."""
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from ._arrays import output
from .runtime import ensure_init, launch_sliced

if TYPE_CHECKING:
    from .mesh import WarpMesh


@wp.func
def closest_on(mesh: wp.uint64, query: wp.vec3d, max_dist: wp.float32):
    """(the closest point on the mesh to `query` within max_dist (float32 BVH query), its face,
    its outward face normal); NaN, -1 and 0 where none lies within it."""
    q = wp.mesh_query_point_no_sign(mesh, wp.vec3(query), max_dist)
    if q.result:
        return (wp.vec3d(wp.mesh_eval_position(mesh, q.face, q.u, q.v)), q.face,
                wp.vec3d(wp.mesh_eval_face_normal(mesh, q.face)))
    nan = wp.float64(wp.nan)
    zero = wp.float64(0.0)
    return wp.vec3d(nan, nan, nan), -1, wp.vec3d(zero, zero, zero)


@wp.kernel
def closest_point_kernel(mesh: wp.uint64, queries: wp.array(dtype=wp.vec3d), max_dist: wp.float32,
                         first: wp.int32, point: wp.array(dtype=wp.vec3d), face: wp.array(dtype=wp.int32),
                         normal: wp.array(dtype=wp.vec3d)):
    """One thread per query point from `first` on (runtime.launch_sliced): closest_on into its row."""
    i = wp.tid() + first
    p, f, n = closest_on(mesh, queries[i], max_dist)
    point[i] = p
    face[i] = f
    normal[i] = n


QUERY_WORK = 5.0       # runtime.slices's evaluations (some 60 ns each) a closest-point query costs: some
                       # 300 ns on one thread on the 40-feature part (lightplan_tasks.many_features)


def closest_points(mesh: "WarpMesh", queries: ArrayLike,
                   max_dist: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For queries (N, 3) [m]: (closest surface points (N, 3), face index (N,), outward face
    normal (N, 3)); NaN / -1 / 0 where no triangle lies within max_dist. Float32 accuracy. The
    launch is split over threads (runtime.launch_sliced; a dense patch's 10 000 queries): each
    query is answered alone, so the same bits."""
    ensure_init(__name__)
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    n = len(queries)
    point, point_wp = output((n, 3), np.float64, wp.vec3d)
    face, face_wp = output(n, np.int32, wp.int32)
    normal, normal_wp = output((n, 3), np.float64, wp.vec3d)
    if n:       # the queries read where they lie (the launch returns before they can change)
        launch_sliced(closest_point_kernel, n,
                      [mesh.id, wp.array(queries, dtype=wp.vec3d, device="cpu", copy=False), np.float32(max_dist)],
                      [point_wp, face_wp, normal_wp], work_per_item=QUERY_WORK)
    return point, face, normal
