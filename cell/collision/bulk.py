"""Bounds of bodies.distance between one fixed body and a moving body at K poses, all K at once
(NumPy over the poses): enough for most poses' yes or no against the padding without a pair's
distance (CollisionScene.lamp_check, the lamp's clearance over many lamp poses).

bodies.distance lies within SAMPLE_BOUND_M (h) below the true distance d, never above it (its
docstring), so a lower bound of d less h and an upper bound of d bound it. Per pair:

- box and box: the separating axes' largest gap (each box's three axes and their nine cross
  products; the two boxes' projections on any unit axis are at least d apart along it at most),
  and the SDF of one box at the other's point nearest its centre (a point of the one);
- box and capsule: bodies.bracket's two bounds, the segment's ends in the box's frame, and where
  they straddle the padding segment_to_box's own search along the segment;
- a mesh and a box or a capsule: SampleCells.bounds over its fine cells (the least SDF over the
  samples, as bodies.distance takes it, within each cell's radius of the SDF at its centre), a
  moving body whose inner point may lie inside the mesh (within the box holding it) unbounded
  below (bodies._contained);
- capsule and capsule: the distance from one's middle to the other's segment, less half its
  length for the lower bound (bodies.distance is exact there);
- any other pair: the bounding spheres' gap, less h, and no upper bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.collision.bodies import (BOX_SEARCH_ROUNDS, SAMPLE_BOUND_M, Body, Box, Capsule, Mesh,
                                  rectangle_sdf)

SEGMENT_SPACING = 8.0 ** (1 - BOX_SEARCH_ROUNDS) / 16.0     # segment_to_box's last spacing, at most (bodies.bracket)


@dataclass(frozen=True)
class Boxes:
    """One box at K poses: T_cell_box (K, 4, 4), half its size (3,)."""

    name: str
    T_cell_box: np.ndarray
    half_m: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return self.T_cell_box[:, :3, 3]

    @property
    def radius(self) -> float:
        return float(np.linalg.norm(self.half_m))

    def take(self, k: np.ndarray) -> Boxes:
        return Boxes(self.name, self.T_cell_box[k], self.half_m)


@dataclass(frozen=True)
class Capsules:
    """One capsule at K poses: the segments a-b (K, 3) each, its radius."""

    name: str
    a: np.ndarray
    b: np.ndarray
    radius_m: float

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.a + self.b)

    @property
    def radius(self) -> np.ndarray:
        return 0.5 * np.linalg.norm(self.b - self.a, axis=1) + self.radius_m

    def take(self, k: np.ndarray) -> Capsules:
        return Capsules(self.name, self.a[k], self.b[k], self.radius_m)


Moving = Boxes | Capsules


@dataclass(frozen=True)
class Fixed:
    """Bodies that stay while the moving one takes its K poses (the part, the fixture, the
    lights, the camera and the arm where they stand), grouped by kind for `gaps`."""

    bodies: tuple[Body, ...]
    kinds: tuple[np.ndarray, ...]           # the indices of the boxes, the capsules, the meshes, the others
    box_T: np.ndarray                       # (B, 4, 4)
    box_half: np.ndarray                    # (B, 3)
    capsule_ends: np.ndarray                # (C, 2, 3): a, b
    capsule_radius: np.ndarray              # (C,)
    mesh_box: np.ndarray                    # (M, 2, 3): the least and largest corner holding each mesh
    sphere: np.ndarray                      # (O, 4): the others' bounding spheres, centre and radius

    @classmethod
    def of(cls, bodies: tuple[Body, ...]) -> Fixed:
        kinds = tuple(np.array([k for k, body in enumerate(bodies) if test(body)], int) for test in (
            lambda b: isinstance(b, Box), lambda b: isinstance(b, Capsule), lambda b: isinstance(b, Mesh),
            lambda b: not isinstance(b, (Box, Capsule, Mesh))))
        boxes, capsules, meshes, others = ([bodies[k] for k in kind] for kind in kinds)
        return cls(bodies, kinds, np.array([b.T_cell_box for b in boxes]).reshape(-1, 4, 4),
                   np.array([b.half_m for b in boxes]).reshape(-1, 3),
                   np.array([(c.a, c.b) for c in capsules]).reshape(-1, 2, 3),
                   np.array([c.radius_m for c in capsules]),
                   np.array([m.aabb for m in meshes]).reshape(-1, 2, 3),
                   np.array([(*o.center, o.radius) for o in others]).reshape(-1, 4))

    def gaps(self, moving: Moving) -> np.ndarray:
        """(K, N) a lower bound of the true distance of each of the N bodies and the moving one at
        each pose, cheaper than `bounds`: from the body to the sphere holding the moving one (its
        centre's distance from a box or a capsule, from the box holding a mesh, else from the
        body's sphere, less the moving one's radius)."""
        c = moving.center
        out = np.empty((len(c), len(self.bodies)))
        box, capsule, mesh, other = self.kinds
        local = np.einsum("kbj,bji->kbi", c[:, None] - self.box_T[None, :, :3, 3], self.box_T[:, :3, :3])
        out[:, box] = rectangle_sdf(np.abs(local) - self.box_half)
        out[:, capsule] = (_point_segment(c[:, None], self.capsule_ends[:, 0], self.capsule_ends[:, 1])
                           - self.capsule_radius)
        out[:, mesh] = np.linalg.norm(np.maximum(np.maximum(self.mesh_box[:, 0] - c[:, None],
                                                            c[:, None] - self.mesh_box[:, 1]), 0.0), axis=2)
        out[:, other] = np.linalg.norm(c[:, None] - self.sphere[:, :3], axis=2) - self.sphere[:, 3]
        return out - np.reshape(moving.radius, (-1, 1))


def bounds(fixed: Body, moving: Moving, padding_m: float) -> tuple[np.ndarray, np.ndarray]:
    """((K,) a lower, (K,) an upper bound) of bodies.distance(fixed, moving at each pose); a box
    and a capsule's searched along the segment (_segment_search) where they straddle padding_m."""
    if isinstance(fixed, Mesh):
        return _mesh(fixed, moving)
    if isinstance(fixed, Box) and isinstance(moving, Boxes):
        lower, upper = _box_box(fixed, moving)
        return lower - SAMPLE_BOUND_M, upper
    if isinstance(fixed, Box) and isinstance(moving, Capsules):
        return _box_capsule(fixed.T_cell_box[None], fixed.half_m, moving.a, moving.b, moving.radius_m, padding_m)
    if isinstance(fixed, Capsule) and isinstance(moving, Boxes):
        return _box_capsule(moving.T_cell_box, moving.half_m, fixed.a[None], fixed.b[None], fixed.radius_m, padding_m)
    if isinstance(fixed, Capsule) and isinstance(moving, Capsules):
        to_middle = _point_segment(fixed.center[None], moving.a, moving.b) - fixed.radius_m - moving.radius_m
        return to_middle - 0.5 * fixed.length, to_middle
    spheres = np.linalg.norm(moving.center - fixed.center, axis=1) - moving.radius - fixed.radius
    return spheres - SAMPLE_BOUND_M, np.full(len(spheres), np.inf)


def _box_box(fixed: Box, moving: Boxes) -> tuple[np.ndarray, np.ndarray]:
    """(K,) bounds of the true distance between two boxes: the largest gap of their projections
    on a separating axis (each box's axes and their cross products, unit), and the SDF of each at
    the other's point nearest its centre (the least of the two)."""
    A, B = fixed.T_cell_box[:3, :3], moving.T_cell_box[:, :3, :3]
    cross = np.cross(A.T[None, :, None, :], np.swapaxes(B, 1, 2)[:, None, :, :]).reshape(len(B), 9, 3)
    norm = np.linalg.norm(cross, axis=2, keepdims=True)
    cross = np.where(norm > 1e-9, cross / np.maximum(norm, 1e-300), np.nan)    # parallel axes: no axis
    axes = np.concatenate([np.broadcast_to(A.T, (len(B), 3, 3)), np.swapaxes(B, 1, 2), cross], axis=1)
    d = moving.center - fixed.center
    gap = (np.abs(np.einsum("kaj,kj->ka", axes, d)) - np.abs(axes @ A) @ fixed.half_m
           - np.abs(np.einsum("kaj,kjl->kal", axes, B)) @ moving.half_m)
    lower = np.nanmax(gap, axis=1)
    near_fixed = fixed.center + np.clip(d @ A, -fixed.half_m, fixed.half_m) @ A.T            # (K, 3)
    near_moving = moving.center + np.einsum("kjl,kl->kj", B, np.clip(np.einsum("kjl,kj->kl", B, -d),
                                                                      -moving.half_m, moving.half_m))
    at_fixed = rectangle_sdf(np.abs(np.einsum("kj,kjl->kl", near_fixed - moving.center, B)) - moving.half_m)
    at_moving = rectangle_sdf(np.abs((near_moving - fixed.center) @ A) - fixed.half_m)
    return lower, np.minimum(at_fixed, at_moving)


def _box_segment(T_cell_box: np.ndarray, half_m: np.ndarray, a: np.ndarray, b: np.ndarray,
                 radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(K,) bodies.bracket's bounds of a box and a capsule, box poses (K or 1, 4, 4) and segments
    (K or 1, 3) broadcast: the least SDF along the segment at least Box.sdf's formula at q_i =
    min over it of |x_i| - h_i, less segment_to_box's spacing times its length, at most its value
    at the segment's ends and middle."""
    points = np.stack(np.broadcast_arrays(a, 0.5 * (a + b), b), axis=1)                # (K, 3, 3)
    local = (points - T_cell_box[:, None, :3, 3]) @ T_cell_box[:, :3, :3]
    crossed = (local[:, 0] <= 0.0) != (local[:, 2] <= 0.0)
    q = np.where(crossed, 0.0, np.minimum(np.abs(local[:, 0]), np.abs(local[:, 2]))) - half_m
    length = np.linalg.norm(b - a, axis=-1)
    return (rectangle_sdf(q) - SEGMENT_SPACING * length - radius_m,
            rectangle_sdf(np.abs(local) - half_m).min(axis=1) - radius_m)


def _box_capsule(T_cell_box: np.ndarray, half_m: np.ndarray, a: np.ndarray, b: np.ndarray, radius_m: float,
                 padding_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(K,) bounds of bodies.distance of a box and a capsule, box poses (K or 1, 4, 4) and
    segments (K or 1, 3) broadcast: _box_segment's, and where they straddle padding_m
    segment_to_box's search (_segment_search: within its last spacing times the segment's
    length of bodies.distance's value, either way)."""
    lower, upper = _box_segment(T_cell_box, half_m, a, b, radius_m)
    k = np.flatnonzero((lower < padding_m) & (upper >= padding_m))
    if len(k):
        def at(x: np.ndarray) -> np.ndarray:
            return x if len(x) == 1 else x[k]
        value, slack = _segment_search(at(T_cell_box), at(a), at(b), half_m)
        lower[k], upper[k] = value - slack - radius_m, value + slack - radius_m
    return lower, upper


def _segment_search(T_cell_box: np.ndarray, a: np.ndarray, b: np.ndarray, half_m: np.ndarray,
                    rounds: int = BOX_SEARCH_ROUNDS, n: int = 17) -> tuple[np.ndarray, np.ndarray]:
    """(K,) bodies.segment_to_box of K boxes and segments (each K or 1, broadcast), all at once:
    each round n evenly spaced points between the best one's neighbours of the last, and (K,) its
    last spacing times the segment's length (the convex SDF's least is within it of the value)."""
    count = max(len(T_cell_box), len(a), len(b))
    T_cell_box = np.broadcast_to(T_cell_box, (count, 4, 4))
    a, b = np.broadcast_to(a, (count, 3)), np.broadcast_to(b, (count, 3))
    rows, steps = np.arange(len(a)), np.arange(float(n))
    lo, hi = np.zeros(len(a)), np.ones(len(a))
    for _ in range(rounds):
        t = steps * ((hi - lo) / (n - 1))[:, None] + lo[:, None]
        t[:, -1] = hi
        local = (a[:, None] + t[..., None] * (b - a)[:, None] - T_cell_box[:, None, :3, 3]) @ T_cell_box[:, :3, :3]
        d = rectangle_sdf(np.abs(local) - half_m)
        k = d.argmin(axis=1)
        lo, hi = t[rows, np.maximum(k - 1, 0)], t[rows, np.minimum(k + 1, n - 1)]
    return d[rows, k], (t[:, 1] - t[:, 0]) * np.linalg.norm(b - a, axis=1)


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., ) the distance of points p from segments a-b, broadcast."""
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - a - t[..., None] * ab, axis=-1)


def _mesh(mesh: Mesh, moving: Moving) -> tuple[np.ndarray, np.ndarray]:
    """(K,) bounds of bodies.distance(mesh, moving): the least SDF of the moving body over the
    mesh's samples within each fine cell's radius of its value at the cell's centre (less h, as
    bodies.distance takes it); unbounded below where the moving body's inner point
    (bodies._contained's: a box's centre, a capsule's end a) lies within the mesh's box."""
    cells = mesh.cells
    if isinstance(moving, Boxes):
        local = (cells.centre[None] - moving.center[:, None]) @ moving.T_cell_box[:, :3, :3]
        at = rectangle_sdf(np.abs(local) - moving.half_m)
        inner = moving.center
    else:
        at = _point_segment(cells.centre[None], moving.a[:, None], moving.b[:, None]) - moving.radius_m
        inner = moving.a
    lower = (at - cells.radius).min(axis=1) - SAMPLE_BOUND_M
    least, largest = mesh.aabb
    inside = np.all((inner >= least) & (inner <= largest), axis=1)
    return np.where(inside, -np.inf, lower), (at + cells.radius).min(axis=1) - SAMPLE_BOUND_M
