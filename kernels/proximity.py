"""Closest points on the mesh (BVH query): project feature samples onto the surface
without trimesh.proximity, which needs the optional `rtree` package."""
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from ._arrays import output
from .runtime import ensure_init, launch_sliced

if TYPE_CHECKING:
    from collections.abc import Sequence

    from .mesh import WarpMesh


@wp.func
def answer(mesh: wp.uint64, query: wp.vec3d, max_dist: wp.float32, i: int, point: wp.array(dtype=wp.vec3d),
           face: wp.array(dtype=wp.int32), normal: wp.array(dtype=wp.vec3d)):
    """Query i's closest point on the mesh within max_dist (float32 BVH query), its face and
    outward face normal, into row i; NaN, -1 and 0 where none lies within it."""
    q = wp.mesh_query_point_no_sign(mesh, wp.vec3(query), max_dist)
    if q.result:
        point[i] = wp.vec3d(wp.mesh_eval_position(mesh, q.face, q.u, q.v))
        face[i] = q.face
        normal[i] = wp.vec3d(wp.mesh_eval_face_normal(mesh, q.face))
    else:
        point[i] = wp.vec3d(wp.float64(wp.nan), wp.float64(wp.nan), wp.float64(wp.nan))
        face[i] = -1
        normal[i] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.kernel
def closest_point_kernel(meshes: wp.array(dtype=wp.uint64), queries: wp.array(dtype=wp.vec3d),
                         max_dist: wp.array(dtype=wp.float32), first: wp.int32, point: wp.array(dtype=wp.vec3d),
                         face: wp.array(dtype=wp.int32), normal: wp.array(dtype=wp.vec3d)):
    """One thread per query point from `first` on (runtime.launch_sliced), each on its own mesh
    within its own max_dist."""
    i = wp.tid() + first
    answer(meshes[i], queries[i], max_dist[i], i, point, face, normal)


@wp.kernel
def closest_point_one_mesh_kernel(mesh: wp.uint64, queries: wp.array(dtype=wp.vec3d), max_dist: wp.float32,
                                  first: wp.int32, point: wp.array(dtype=wp.vec3d), face: wp.array(dtype=wp.int32),
                                  normal: wp.array(dtype=wp.vec3d)):
    """closest_point_kernel on one mesh within one max_dist (closest_points: a patch's thousands
    of queries, without an array of the same id and distance for each)."""
    i = wp.tid() + first
    answer(mesh, queries[i], max_dist, i, point, face, normal)


def _per_query(ids: ArrayLike, max_dists: ArrayLike) -> tuple[wp.array, wp.array]:
    """The kernel's per-query mesh ids and max_dist (float32, as Warp took a float32 argument)."""
    ids = np.asarray(ids, dtype=np.uint64)
    dists = np.broadcast_to(np.asarray(max_dists, dtype=np.float32), ids.shape).copy()
    return wp.array(ids, dtype=wp.uint64, device="cpu"), wp.array(dists, dtype=wp.float32, device="cpu")


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
        launch_sliced(closest_point_one_mesh_kernel, n,
                      [mesh.id, wp.array(queries, dtype=wp.vec3d, device="cpu", copy=False), np.float32(max_dist)],
                      [point_wp, face_wp, normal_wp], work_per_item=QUERY_WORK)
    return point, face, normal


class ClosestPoint:
    """closest_points of K queries at a time, query k on meshes[k] within max_dists[k], its launch
    recorded once (wp.launch(record_cmd=True)) and run again on each new set of queries written
    into the same array: searches that ask one point after another (the certificates' specular
    points, some 80 queries each, several in lockstep) skip the launch's argument packing and
    array wrapping each time, the same kernel on the same inputs, so the same results bit for
    bit as closest_points's."""

    def __init__(self, meshes: "Sequence[WarpMesh]", max_dists: ArrayLike) -> None:
        device = ensure_init(__name__)
        k = len(meshes)
        self.query = np.zeros((k, 3))
        self.point, point_wp = output((k, 3), np.float64, wp.vec3d)
        self.face, face_wp = output(k, np.int32, wp.int32)
        self.normal, normal_wp = output((k, 3), np.float64, wp.vec3d)
        query_wp = wp.array(self.query, dtype=wp.vec3d, device="cpu", copy=False)
        ids, dists = _per_query([m.id for m in meshes], max_dists)
        # the meshes (their BVHs) and the Warp views live as long as the recorded launch that points at them
        self._kept = (tuple(meshes), ids, dists, query_wp, point_wp, face_wp, normal_wp)
        self._launch = wp.launch(closest_point_kernel, dim=k, device=device, inputs=[ids, query_wp, dists, 0],
                                 outputs=[point_wp, face_wp, normal_wp], record_cmd=True)

    def __call__(self, queries: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(closest surface points (K, 3), face indices (K,), outward face normals (K, 3)) of
        queries (K, 3), closest_points's values; copies, not the launch's own arrays."""
        self.query[:] = np.asarray(queries, dtype=np.float64).reshape(self.query.shape)
        self._launch.launch()
        return self.point.copy(), self.face.copy(), self.normal.copy()
