"""The cell's bodies as collision geometry, and a conservative distance between two of them.

A box and a capsule have exact signed distance functions (SDF, negative inside), vectorised over
points. A mesh (the part, the fixture) is its surface sampled once (`surface_samples`) with every
surface point within SAMPLE_BOUND_M of a sample. An SDF is 1-Lipschitz, so for a body A sampled
within h and a body B with an exact SDF,

    d(A, B) >= min_k sdf_B(a_k) - h                                    (sampled lower bound)

and that bound is <= 0 whenever A and B overlap, unless B lies wholly inside A; that case is
caught by one point of B inside A (`_contained`). So `distance` never reports a clearance larger
than the true one: it errs by at most h on the safe side, and overlap gives <= 0. A box against a
ring's or a dome's housing is searched instead (`box_to_revolved`), within BOX_TOLERANCE_M.
A mesh's samples are grouped in cells (`SampleCells`) so that the least over them is found
where it can lie, the same value; `bracket` gives cheap bounds of a pair's distance, enough for
the yes/no of a clearance against the padding (scene.Pairs.clear) when they lie on one side of it.

This stands in for FCL (python-fcl has no wheel for this platform): trimesh's primitives are built
the same way, and an SDF over NumPy arrays needs no BVH for the few thousand samples a part has.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from cell.core import geometry

SAMPLE_BOUND_M = 0.002       # every surface point of a sampled body within this of a sample (h)
BOX_GRID_M = SAMPLE_BOUND_M * np.sqrt(2.0)   # a square grid of pitch s covers within s / sqrt 2
MESH_EDGE_M = SAMPLE_BOUND_M * np.sqrt(3.0)  # a triangle of edges <= e: every point within e / sqrt 3
                                             # of a vertex (its circumradius, or half its longest edge)
SEGMENT_TOLERANCE_M = 1e-5   # segment_min's least value within this of the true one
BOX_TOLERANCE_M = 1e-4       # box_to_revolved's bound within this of the true distance
CELL_M = 3 * SAMPLE_BOUND_M  # a mesh's samples grouped in cubes of this side (SampleCells) and
COARSE_CELLS = 4             # in cubes of this many of those on a side
ROUNDING_M = 1e-9            # far above the rounding of the cheap bounds (~1e-15 m)
BOX_SEARCH_ROUNDS = 4        # segment_to_box's rounds of 17 points: its answer within |b - a| / 8192


@dataclass(frozen=True)
class Box:
    """A box: its centre and axes T_cell_box (4x4), half its size along each axis [m]."""

    name: str
    T_cell_box: np.ndarray
    half_m: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return self.T_cell_box[:3, 3]

    @cached_property
    def radius(self) -> float:
        """Of the sphere about the centre holding the box."""
        return float(np.linalg.norm(self.half_m))

    def local(self, points: ArrayLike) -> np.ndarray:
        """(N, 3) the points (N, 3) in the box's frame."""
        return (np.asarray(points, float).reshape(-1, 3) - self.center) @ self.T_cell_box[:3, :3]

    def sdf(self, points: ArrayLike) -> np.ndarray:
        """Signed distance (N,) [m] of points (N, 3) (rectangle_sdf of q = |p| - half, p local)."""
        return rectangle_sdf(np.abs(self.local(points)) - self.half_m)

    def samples(self) -> np.ndarray:
        """(N, 3) points on its surface, every surface point within SAMPLE_BOUND_M of one."""
        return geometry.apply(self.T_cell_box, _box_surface(tuple(np.round(self.half_m, 9))))


@dataclass(frozen=True)
class Capsule:
    """The points within `radius_m` of the segment a-b (cell frame)."""

    name: str
    a: np.ndarray
    b: np.ndarray
    radius_m: float

    @cached_property
    def center(self) -> np.ndarray:
        return 0.5 * (self.a + self.b)

    @cached_property
    def length(self) -> float:
        return _length(self.b - self.a)

    @cached_property
    def radius(self) -> float:
        return float(0.5 * self.length + self.radius_m)

    def sdf(self, points: ArrayLike) -> np.ndarray:
        """Signed distance (N,) [m]: the distance to the segment, less the radius."""
        p = np.asarray(points, float).reshape(-1, 3)
        ab = self.b - self.a
        t = np.clip((p - self.a) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0)
        return np.linalg.norm(p - self.a - t[:, None] * ab, axis=1) - self.radius_m


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in the cell frame (the part, the fixture): its vertices and faces for the
    inside test, and its surface samples (every surface point within SAMPLE_BOUND_M of one)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    points: np.ndarray = field(repr=False)

    @classmethod
    def of(cls, name: str, mesh: trimesh.Trimesh, T_cell_mesh: np.ndarray) -> Mesh:
        vertices = geometry.apply(T_cell_mesh, mesh.vertices)
        return cls(name, vertices, np.asarray(mesh.faces), surface_samples(vertices, mesh.faces))

    @cached_property
    def center(self) -> np.ndarray:
        return 0.5 * (self.points.min(axis=0) + self.points.max(axis=0))

    @cached_property
    def radius(self) -> float:
        return float(np.linalg.norm(self.points - self.center, axis=1).max() + SAMPLE_BOUND_M)

    @cached_property
    def cells(self) -> SampleCells:
        return SampleCells.of(self.points)

    @cached_property
    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """(least, largest) corner of the box holding its vertices, so the closed surface."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def contains(self, point: ArrayLike) -> bool:
        """The point inside the closed surface (generalised winding number above 1/2); a point
        outside the box holding it sees the surface within a half-space, under less than 2 pi
        (winding number below 1/2), so it is not asked."""
        p = np.asarray(point, float)
        if np.any(p < self.aabb[0]) or np.any(p > self.aabb[1]):
            return False
        return geometry.winding_number(self.vertices, self.faces, point) > 0.5


@dataclass(frozen=True)
class SampleCells:
    """A mesh's samples grouped in two levels of cubes: fine cells of side CELL_M, coarse ones of
    side COARSE_CELLS * CELL_M. Fine cell c holds points[start[c]:start[c + 1]], all within
    radius[c] of centre[c]; coarse cell C holds the fine cells coarse_start[C]:coarse_start[C + 1]
    and their samples, all within coarse_radius[C] of coarse_centre[C]. For a 1-Lipschitz sdf
    a cell's least value over its samples lies in [sdf(centre) - radius, sdf(centre) + radius],
    so the least over all samples lies in [min lower, min upper] over the coarse cells (`bounds`)
    and is found in the fine cells whose lower bound is at most the least upper bound known, in
    coarse cells that pass the same test (`least`)."""

    points: np.ndarray          # (N, 3) the samples, cell by cell
    start: np.ndarray           # (C + 1,) the fine cells' first samples
    centre: np.ndarray          # (C, 3)
    radius: np.ndarray          # (C,)
    coarse_start: np.ndarray    # (K + 1,) the coarse cells' first fine cells
    coarse_centre: np.ndarray   # (K, 3)
    coarse_radius: np.ndarray   # (K,)

    @classmethod
    def of(cls, points: np.ndarray) -> SampleCells:
        fine = np.floor((points - points.min(axis=0)) / CELL_M).astype(np.int64)
        coarse = fine // COARSE_CELLS
        order = np.lexsort((*fine.T[::-1], *coarse.T[::-1]))          # by coarse cell, then fine
        points, fine, coarse = points[order], fine[order], coarse[order]
        new_fine = np.concatenate([[True], np.any(fine[1:] != fine[:-1], axis=1)])
        new_coarse = np.concatenate([[True], np.any(coarse[1:] != coarse[:-1], axis=1)])
        start, first = (np.append(np.flatnonzero(new), len(points)) for new in (new_fine, new_coarse))
        centre, radius = _spheres(points, start)
        coarse_centre, coarse_radius = _spheres(points, first)
        coarse_start = np.searchsorted(start, first)
        return cls(points, start, centre, radius, coarse_start, coarse_centre, coarse_radius)

    def bounds(self, sdf: Callable[[np.ndarray], np.ndarray]) -> tuple[float, float]:
        """(a lower, an upper bound) of the least sdf over the samples, from the fine cells."""
        at = sdf(self.centre)
        return float((at - self.radius).min()), float((at + self.radius).min())

    def least(self, sdf: Callable[[np.ndarray], np.ndarray]) -> float:
        """The least sdf over the samples: the very value sdf(points).min() (each sample's value
        is the same computed alone or among all), evaluated only in the cells that may hold it."""
        at = sdf(self.coarse_centre)
        upper = float((at + self.coarse_radius).min())
        cells = _ranges(self.coarse_start, np.flatnonzero(at - self.coarse_radius <= upper + ROUNDING_M))
        at = sdf(self.centre[cells])
        upper = min(upper, float((at + self.radius[cells]).min()))
        return float(sdf(self.points[_ranges(self.start, cells[at - self.radius[cells] <= upper + ROUNDING_M])]).min())


def _spheres(points: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centres (G, 3), radii (G,)) spheres holding each group of points[start[g]:start[g + 1]]:
    the middle of its bounding box and its farthest point from it."""
    centre = 0.5 * (np.minimum.reduceat(points, start[:-1], axis=0) + np.maximum.reduceat(points, start[:-1], axis=0))
    far = np.linalg.norm(points - np.repeat(centre, np.diff(start), axis=0), axis=1)
    return centre, np.maximum.reduceat(far, start[:-1])


def _ranges(start: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """The indices start[g]:start[g + 1] of each of the groups, one after the other."""
    count = start[groups + 1] - start[groups]
    return np.repeat(start[groups] - np.cumsum(count) + count, count) + np.arange(count.sum())


@dataclass(frozen=True)
class Annulus:
    """A ring light's housing: the solid of revolution about the z axis of T_cell_body whose
    cross-section is the rectangle r in [inner_m, outer_m] (from the axis), z in z_m (its own
    frame). Its SDF is the rectangle's in the (r, z) half-plane (Box's formula in 2D): exact,
    as a point's nearest point of a solid of revolution lies in the point's own meridian plane."""

    name: str
    T_cell_body: np.ndarray
    inner_m: float
    outer_m: float
    z_m: tuple[float, float]

    @property
    def center(self) -> np.ndarray:
        return geometry.apply(self.T_cell_body, np.array([0.0, 0.0, 0.5 * sum(self.z_m)]))

    @property
    def radius(self) -> float:
        return float(np.hypot(self.outer_m, 0.5 * (self.z_m[1] - self.z_m[0])))

    @property
    def point(self) -> np.ndarray:
        """A point of the body (for the containment test)."""
        return geometry.apply(self.T_cell_body, np.array([self.inner_m, 0.0, self.z_m[0]]))

    def sdf(self, points: ArrayLike) -> np.ndarray:
        """Signed distance (N,) [m]: |max(q, 0)| + min(max_i q_i, 0), q = |(r, z) - middle| - half."""
        r, z = _meridian(self.T_cell_body, points)
        return rectangle_sdf(np.column_stack([np.abs(r - 0.5 * (self.inner_m + self.outer_m)) - 0.5 * (self.outer_m - self.inner_m),
                                              np.abs(z - 0.5 * sum(self.z_m)) - 0.5 * (self.z_m[1] - self.z_m[0])]))

    def hull_gap(self, corners: np.ndarray) -> np.ndarray:
        """A lower bound (N,) [m] of the distance from each flat convex patch, its corners
        (N, K, 3), to the body: the larger of its gaps to two sets holding the body, the slab
        z in z_m (the height is linear on the patch: its range is the corners') and the
        outside of the hole's cylinder, inner_m - max r (r is convex: its largest at a corner)."""
        r, z = _meridian(self.T_cell_body, corners.reshape(-1, 3))
        r, z = r.reshape(corners.shape[:2]), z.reshape(corners.shape[:2])
        slab = np.maximum(z.min(axis=1) - self.z_m[1], self.z_m[0] - z.max(axis=1))
        return np.maximum(np.maximum(slab, self.inner_m - r.max(axis=1)), 0.0)


@dataclass(frozen=True)
class Shell:
    """A dome light's housing: the spherical shell from inner_m to outer_m about the point
    centre_m along the z axis of T_cell_body (its pole on that axis at 0), on the pole's side of
    the plane through that centre (its rim), outside the cylinder of hole_m about the axis (the
    camera's hole; 0: none). Its SDF is the cross-section's in the (r, w = z - centre_m)
    half-plane: +-the distance to its boundary, two arcs (rho = inner_m, outer_m, polar angle from
    asin(hole / rho) to 90 deg), the rim's segment (w = 0) and the hole's (r = hole_m); exact as
    Annulus's."""

    name: str
    T_cell_body: np.ndarray
    centre_m: float
    inner_m: float
    outer_m: float
    hole_m: float = 0.0

    @property
    def center(self) -> np.ndarray:
        return geometry.apply(self.T_cell_body, np.array([0.0, 0.0, self.centre_m]))

    @property
    def radius(self) -> float:
        return float(self.outer_m)

    @property
    def point(self) -> np.ndarray:
        """A point of the body (on its rim)."""
        return geometry.apply(self.T_cell_body, np.array([self.inner_m, 0.0, self.centre_m]))

    def polar_start(self, rho: float) -> float:
        """The polar angle [rad] (from the axis at the pole) where the hole's cylinder meets the
        sphere of radius rho."""
        return float(np.arcsin(min(self.hole_m / rho, 1.0)))

    def sdf(self, points: ArrayLike) -> np.ndarray:
        """Signed distance (N,) [m] (the class's boundary pieces)."""
        r, z = _meridian(self.T_cell_body, points)
        w = z - self.centre_m
        rho, polar = np.hypot(r, w), np.arctan2(r, -w)
        near = []
        for arc in (self.inner_m, self.outer_m):
            start = self.polar_start(arc)
            ends = np.array([[arc * np.sin(start), -arc * np.cos(start)], [arc, 0.0]])
            to_end = np.min(np.hypot(r[:, None] - ends[:, 0], w[:, None] - ends[:, 1]), axis=1)
            near.append(np.where((polar >= start) & (polar <= 0.5 * np.pi), np.abs(rho - arc), to_end))
        near.append(np.hypot(r - np.clip(r, self.inner_m, self.outer_m), w))            # the rim
        if self.hole_m > 0.0:
            top, bottom = (-np.sqrt(max(arc**2 - self.hole_m**2, 0.0)) for arc in (self.inner_m, self.outer_m))
            near.append(np.hypot(r - self.hole_m, w - np.clip(w, bottom, top)))
        inside = (rho >= self.inner_m) & (rho <= self.outer_m) & (w <= 0.0) & (r >= self.hole_m)
        return np.where(inside, -1.0, 1.0) * np.min(near, axis=0)

    def hull_gap(self, corners: np.ndarray) -> np.ndarray:
        """A lower bound (N,) [m] of the distance from each flat convex patch, its corners
        (N, K, 3), to the body: the largest of its gaps to three sets holding the body, the rim's
        half-space w <= 0 (w is linear on the patch: its least at a corner), the outside of the
        inner sphere, inner_m - max rho, and of the hole's cylinder, hole_m - max r (rho and r
        are convex: their largest at a corner)."""
        r, z = _meridian(self.T_cell_body, corners.reshape(-1, 3))
        r, w = r.reshape(corners.shape[:2]), z.reshape(corners.shape[:2]) - self.centre_m
        gap = np.maximum(w.min(axis=1), self.inner_m - np.hypot(r, w).max(axis=1))
        return np.maximum(np.maximum(gap, self.hole_m - r.max(axis=1)), 0.0)


Body = Box | Capsule | Mesh | Annulus | Shell
Revolved = Annulus | Shell


def rectangle_sdf(q: np.ndarray) -> np.ndarray:
    """A box's or a rectangle's signed distance (...,) from q (..., D) = |x| - half, x in its own
    frame: |max(q, 0)| + min(max_i q_i, 0); it grows with each q_i."""
    out = np.maximum(q, 0.0)
    return np.sqrt(np.add.reduce(out * out, axis=-1)) + np.minimum(q.max(axis=-1), 0.0)   # np.linalg.norm's sum


def _meridian(T_cell_body: np.ndarray, points: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(r, z) (N,) each of points (N, 3) in the body's frame: the distance from its z axis and
    the height along it."""
    local = (np.asarray(points, float).reshape(-1, 3) - T_cell_body[:3, 3]) @ T_cell_body[:3, :3]
    return np.hypot(local[:, 0], local[:, 1]), local[:, 2]


def surface_samples(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """(N, 3) vertices of the mesh subdivided until every edge is at most MESH_EDGE_M: every
    point of the surface lies within MESH_EDGE_M / sqrt 3 = SAMPLE_BOUND_M of one of them."""
    v, _ = trimesh.remesh.subdivide_to_size(np.asarray(vertices, float), np.asarray(faces), MESH_EDGE_M,
                                            max_iter=64)
    return np.asarray(v, float)


@lru_cache(maxsize=64)
def _box_surface(half: tuple[float, float, float]) -> np.ndarray:
    """Grid points on the six faces of a box centred at 0 (its own frame), pitch <= BOX_GRID_M,
    each face's edges included."""
    half_m = np.array(half)
    faces = []
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        gu = np.linspace(-half_m[u], half_m[u], max(2, int(np.ceil(2 * half_m[u] / BOX_GRID_M)) + 1))
        gv = np.linspace(-half_m[v], half_m[v], max(2, int(np.ceil(2 * half_m[v] / BOX_GRID_M)) + 1))
        U, V = np.meshgrid(gu, gv, indexing="ij")
        for side in (-1.0, 1.0):
            face = np.empty((U.size, 3))
            face[:, axis], face[:, u], face[:, v] = side * half_m[axis], U.ravel(), V.ravel()
            faces.append(face)
    return np.vstack(faces)


def segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> float:
    """The distance between segments p1-q1 and p2-q2 (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = float(d1 @ d1), float(d2 @ d2), float(d2 @ r)
    if a <= 1e-18 and e <= 1e-18:
        return _length(r)
    if a <= 1e-18:
        s, t = 0.0, _unit(f / e)
    else:
        c = float(d1 @ r)
        if e <= 1e-18:
            s, t = _unit(-c / a), 0.0
        else:
            b = float(d1 @ d2)
            denom = a * e - b * b
            s = _unit((b * f - c * e) / denom) if denom > 1e-18 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                s, t = _unit(-c / a), 0.0
            elif t > 1.0:
                s, t = _unit((b - c) / a), 1.0
    return _length(p1 + s * d1 - (p2 + t * d2))


def _unit(x: float) -> float:
    """x clipped to [0, 1]."""
    return min(max(x, 0.0), 1.0)


def _length(v: np.ndarray) -> float:
    """|v| of a vector (3,): np.linalg.norm's very sum, sqrt(v . v), without its checks."""
    return math.sqrt(v.dot(v))


def segment_to_box(box: Box, a: np.ndarray, b: np.ndarray, rounds: int = BOX_SEARCH_ROUNDS, n: int = 17) -> float:
    """A lower bound of min over the segment a-b of box.sdf, within |b - a| / 8192 of it. A convex
    body's SDF is convex, so along a segment its minimum lies beside the best of n evenly spaced
    points: each round searches n points between the best one's neighbours of the last."""
    lo, hi, ab, steps = 0.0, 1.0, b - a, np.arange(float(n))
    for _ in range(rounds):
        t = steps * ((hi - lo) / (n - 1)) + lo            # np.linspace(lo, hi, n), its very arithmetic
        t[-1] = hi
        d = box.sdf(a + t[:, None] * ab)
        k = int(d.argmin())
        lo, hi = float(t[max(k - 1, 0)]), float(t[min(k + 1, n - 1)])
    return float(d[k] - (t[1] - t[0]) * _length(ab))


def segment_min(sdf: Callable[[np.ndarray], np.ndarray], a: np.ndarray, b: np.ndarray,
                tolerance_m: float = SEGMENT_TOLERANCE_M) -> float:
    """A lower bound of min over the segment a-b of a 1-Lipschitz sdf (any body's, convex or not),
    within tolerance_m of it, by branch and bound: on a piece of length L whose ends have values
    f0, f1 no value is below (f0 + f1 - L) / 2; pieces whose bound could beat the least value
    found by more than the tolerance are halved, the rest dropped."""
    t = np.linspace(0.0, 1.0, 17)
    f = sdf(a + t[:, None] * (b - a))
    lo, hi, f_lo, f_hi = t[:-1], t[1:], f[:-1], f[1:]
    best, length = float(f.min()), float(np.linalg.norm(b - a))
    while True:
        bound = 0.5 * (f_lo + f_hi - (hi - lo) * length)
        keep = bound < best - tolerance_m
        if not keep.any():
            return float(min(best, bound.min())) if len(bound) else best
        lo, hi, f_lo, f_hi = lo[keep], hi[keep], f_lo[keep], f_hi[keep]
        mid = 0.5 * (lo + hi)
        f_mid = sdf(a + mid[:, None] * (b - a))
        best = min(best, float(f_mid.min()))
        lo, hi = np.concatenate([lo, mid]), np.concatenate([mid, hi])
        f_lo, f_hi = np.concatenate([f_lo, f_mid]), np.concatenate([f_mid, f_hi])


_STEPS = np.arange(3.0)                                   # a patch's 3 x 3 grid of halves
_NEW_I, _NEW_J = np.array([1, 0, 1, 2, 1]), np.array([0, 1, 1, 1, 2])    # its points not a corner
_CHILD_I = np.array([[0, 1, 0, 1], [0, 1, 0, 1], [1, 2, 1, 2], [1, 2, 1, 2]])   # its quarters' corners
_CHILD_J = np.array([[0, 0, 1, 1], [1, 1, 2, 2], [0, 0, 1, 1], [1, 1, 2, 2]])   # (00, 10, 01, 11 each)


def box_to_revolved(box: Box, body: Annulus | Shell, tolerance_m: float = BOX_TOLERANCE_M) -> float:
    """A lower bound of the least distance from the box's surface to the body, within tolerance_m
    of it (<= 0 where they meet; the bodies' distance when apart, as a point of the box nearest the
    body lies on its surface), by branch and bound over patches of the box's faces. The distance d
    to any closed set makes d^2 - |x|^2 concave (an infimum of affine functions of x), so on a patch
    whose corners c_k are d_k from the body and rho from the patch's centre,

        d(x)^2 >= sum_k l_k d_k^2 - sum_k l_k |c_k - x|^2 >= min_k d_k^2 - rho^2       (x = sum_k l_k c_k)

    and the body's hull_gap bounds it too (exact for a flat contact, as a face over a ring's front,
    which the first bound meets only as rho -> 0). The least d found at a corner is an upper bound;
    a patch whose bound is below it by more than the tolerance is quartered, any other dropped,
    and the answer is the least of that value and the dropped patches' bounds."""
    T, half = box.T_cell_box, box.half_m
    origin, eu, ev = [], [], []
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        for side in (-1.0, 1.0):
            origin.append(T[:3, 3] + side * half[axis] * T[:3, axis] - half[u] * T[:3, u] - half[v] * T[:3, v])
            eu.append(2.0 * half[u] * T[:3, u])
            ev.append(2.0 * half[v] * T[:3, v])
    o, eu_, ev_ = np.array(origin), np.array(eu), np.array(ev)
    corners = np.stack([o, o + eu_, o + ev_, o + eu_ + ev_], axis=1)               # (N, 4, 3): 00, 10, 01, 11
    f = body.sdf(corners.reshape(-1, 3)).reshape(-1, 4)
    best, floor = float(f.min()), np.inf
    while best > 0.0:
        rho2 = 0.25 * (np.einsum("ij,ij->i", eu_, eu_) + np.einsum("ij,ij->i", ev_, ev_))
        bound = np.maximum(np.sqrt(np.maximum(f.min(axis=1) ** 2 - rho2, 0.0)), body.hull_gap(corners))
        keep = bound < best - tolerance_m
        if not keep.all():
            floor = min(floor, float(bound[~keep].min()))
        if not keep.any():
            return min(best, floor)
        o, eu_, ev_, f = o[keep], 0.5 * eu_[keep], 0.5 * ev_[keep], f[keep]
        grid = o[:, None, None, :] + _STEPS[:, None, None] * eu_[:, None, None, :] \
            + _STEPS[None, :, None] * ev_[:, None, None, :]                             # (N, 3, 3, 3): o + i eu + j ev
        g = np.empty((len(o), 3, 3))
        g[:, ::2, ::2] = f.reshape(-1, 2, 2).transpose(0, 2, 1)                       # the parents' corners, [i, j]
        g[:, _NEW_I, _NEW_J] = body.sdf(grid[:, _NEW_I, _NEW_J].reshape(-1, 3)).reshape(-1, 5)
        best = min(best, float(g[:, _NEW_I, _NEW_J].min()))
        o, eu_, ev_ = grid[:, :2, :2].reshape(-1, 3), np.repeat(eu_, 4, axis=0), np.repeat(ev_, 4, axis=0)
        f, corners = g[:, _CHILD_I, _CHILD_J].reshape(-1, 4), grid[:, _CHILD_I, _CHILD_J].reshape(-1, 4, 3)
    return best


def lower_bound(a: Body, b: Body) -> float:
    """A cheap lower bound of distance(a, b): their bounding spheres' gap."""
    return float(np.linalg.norm(a.center - b.center) - a.radius - b.radius)


def distance(a: Body, b: Body) -> float:
    """A lower bound of the distance between two bodies [m], within SAMPLE_BOUND_M of it (exact
    for two capsules, within a segment's length / 8192 for a capsule and a box, within
    SEGMENT_TOLERANCE_M for a capsule and a ring's or dome's housing, within BOX_TOLERANCE_M for
    a box and one); <= 0 when they overlap.
    Two meshes, or two lights' housings, are not compared (the part may rest on its fixture;
    neither moves)."""
    if isinstance(a, Capsule) and isinstance(b, Capsule):
        return segment_distance(a.a, a.b, b.a, b.b) - a.radius_m - b.radius_m
    if isinstance(a, Box) and isinstance(b, Capsule):
        return segment_to_box(a, b.a, b.b) - b.radius_m
    if isinstance(a, Capsule) and isinstance(b, Box):
        return segment_to_box(b, a.a, a.b) - a.radius_m
    if isinstance(a, Capsule) and isinstance(b, (Annulus, Shell)):
        a, b = b, a
    if isinstance(a, (Annulus, Shell)) and isinstance(b, Capsule):
        return segment_min(a.sdf, b.a, b.b) - b.radius_m
    if isinstance(a, Box) and isinstance(b, (Annulus, Shell)):
        a, b = b, a
    if isinstance(a, (Annulus, Shell)) and isinstance(b, Box):
        return min(box_to_revolved(b, a), _contained(a, b))
    if isinstance(b, Mesh):
        a, b = b, a                        # sample the mesh; b has an exact SDF
    if not isinstance(a, (Mesh, Box)) or isinstance(b, Mesh):
        raise ValueError(f"no distance between two fixed bodies ({a.name}, {b.name})")
    least = a.cells.least(b.sdf) if isinstance(a, Mesh) else float(b.sdf(a.samples()).min())
    return min(least - SAMPLE_BOUND_M, _contained(b, a))


def bracket(a: Body, b: Body) -> tuple[float, float]:
    """(a lower, an upper bound) of distance(a, b) [m], cheaper than it, up to rounding (~1e-15 m):
    a capsule and a box, the least of the box's SDF along the segment is at least Box.sdf's
    formula at q_i = min over the segment of |x_i| - h_i (it grows with each q_i; x_i is linear
    along it), less segment_to_box's last spacing times |b - a| (its answer is no lower), and at
    most its value at the segment's ends and middle (segment_to_box's answer is no higher); a
    mesh, its sample cells' bounds (SampleCells.bounds). Other pairs: none (-inf, +inf)."""
    if isinstance(a, Capsule) and isinstance(b, Box):
        a, b = b, a
    if isinstance(a, Box) and isinstance(b, Capsule):
        local = a.local(np.stack([b.a, b.center, b.b]))
        crossed = (local[0] <= 0.0) != (local[2] <= 0.0)          # the segment crosses x_i = 0
        q = np.where(crossed, 0.0, np.minimum(np.abs(local[0]), np.abs(local[2]))) - a.half_m
        spacing = 8.0 ** (1 - BOX_SEARCH_ROUNDS) / 16.0          # segment_to_box's last, at most
        return (float(rectangle_sdf(q)) - spacing * b.length - b.radius_m,
                float(rectangle_sdf(np.abs(local) - a.half_m).min()) - b.radius_m)
    if isinstance(b, Mesh):
        a, b = b, a
    if isinstance(a, Mesh) and isinstance(b, (Box, Capsule)):
        lower, upper = a.cells.bounds(b.sdf)
        inside = _contained(b, a)
        return min(lower - SAMPLE_BOUND_M, inside), min(upper - SAMPLE_BOUND_M, inside)
    return -np.inf, np.inf


def _contained(inner: Box | Capsule | Annulus | Shell, outer: Body) -> float:
    """<= 0 when a point of `inner` lies inside `outer` (the case the sampled bound misses: inner
    wholly inside outer), else +inf."""
    point = inner.a if isinstance(inner, Capsule) else inner.center if isinstance(inner, Box) else inner.point
    if isinstance(outer, Mesh):
        return -float(np.linalg.norm(outer.points - point, axis=1).min()) if outer.contains(point) else np.inf
    depth = float(outer.sdf(point)[0])
    return depth if depth <= 0.0 else np.inf
