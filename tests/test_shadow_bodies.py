"""The moving bodies as shadow geometry (cell.collision.rays): the slab test against trimesh's
own ray casting, and the spot lamp's housing hiding feature samples from the camera."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from cell.collision.rays import segments_cross_boxes


def brute_force(T_cell_box, half_m, origins, targets):
    """(N,) whether each segment crosses the box mesh: an end inside it (behind every face's
    plane: the mesh is convex) or a face's plane met by the segment's line (trimesh's
    intersections.planes_lines, as its ray casting does) within the segment, at a point inside
    that triangle (trimesh's barycentric coordinates)."""
    box = trimesh.creation.box(extents=2.0 * half_m, transform=T_cell_box)
    d = targets - origins
    length = np.linalg.norm(d, axis=1)

    def inside(p):
        return np.all(np.einsum("fj,nfj->nf", box.face_normals, p[:, None] - box.triangles[None, :, 0]) < 0, axis=1)
    crossed = inside(origins) | inside(targets)
    for triangle, normal in zip(box.triangles, box.face_normals):
        n = len(origins)
        at, valid = trimesh.intersections.planes_lines(np.tile(triangle[0], (n, 1)), np.tile(normal, (n, 1)),
                                                       origins, d / length[:, None])
        rays = np.flatnonzero(valid)
        along = np.einsum("nj,nj->n", at - origins[rays], d[rays]) / length[rays]
        bary = trimesh.triangles.points_to_barycentric(np.tile(triangle, (len(rays), 1, 1)), at)
        hit = (along > 0) & (along < length[rays]) & np.all(bary >= 0, axis=1)
        crossed[rays[hit]] = True
    return crossed


def test_the_slab_test_agrees_with_trimesh_ray_casting_on_random_boxes_and_segments():
    rng = np.random.default_rng(26)
    agree = crossings = 0
    for _ in range(20):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.uniform(-0.2, 0.2, 3)
        half = rng.uniform(0.02, 0.3, 3)
        origins, targets = rng.uniform(-0.6, 0.6, (2, 300, 3))
        fast = segments_cross_boxes(origins, targets, T[None], half)[0]
        slow = brute_force(T, half, origins, targets)
        agree += np.sum(fast == slow)
        crossings += slow.sum()
    assert agree == 20 * 300 and 500 < crossings < 5500          # both outcomes well represented


def test_boxes_and_segments_broadcast_and_grazing_or_parallel_segments_do_not_cross():
    T = np.stack([np.eye(4)] * 2)
    T[1, :3, 3] = (5.0, 0.0, 0.0)
    half = np.array([1.0, 1.0, 1.0])
    # along x through both boxes; one along the face y = 1 (grazing); parallel to z inside; one short of the box
    origins = np.array([[-2.0, 0.0, 0.0], [-2.0, 1.0, 0.0], [0.5, 0.5, -3.0], [-3.0, 0.0, 0.0]])
    targets = np.array([[7.0, 0.0, 0.0], [7.0, 1.0, 0.0], [0.5, 0.5, 3.0], [-1.5, 0.0, 0.0]])
    assert segments_cross_boxes(origins, targets, T, half).tolist() == [[True, False, True, False],
                                                                         [True, False, False, False]]
    # one target for every origin
    assert segments_cross_boxes(origins[:1], np.zeros(3), T, half).tolist() == [[True], [False]]
