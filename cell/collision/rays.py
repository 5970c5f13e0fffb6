"""The moving bodies as shadow geometry: whether straight segments (a camera's line of sight to a
sample, a lamp's ray to it) cross boxes or capsules, vectorised over many bodies and segments.

A box (centre c, axes R, half sizes h) and the segment o + t d, 0 < t < 1: in the box's frame
o' = R^T (o - c), d' = R^T d, each axis's slab |o'_i + t d'_i| < h_i holds for t between
(-h_i - o'_i) / d'_i and (h_i - o'_i) / d'_i (the whole line where d'_i = 0 and |o'_i| < h_i,
none where |o'_i| >= h_i); the segment crosses the box where the three intervals and (0, 1)
overlap: max(t_near) < min(t_far) (Kay and Kajiya's slabs; Ericson, Real-Time Collision
Detection 5.3.3). A segment touching a face only (grazing) does not cross.

Prefilters, cheap and never skipping a crossing: balls holding the bodies against the cone of
directions a bundle of segments spans (BallsSeen, SightCone), then capsules holding them
(box_capsules) against one segment standing for the bundle (segments_near_segments at a
widened radius).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry

NEAR_MARGIN_M = 1e-6      # a prefilter's radius widened well past floating-point rounding [m]


def dot(x: Sequence[np.ndarray], y: Sequence[np.ndarray]) -> np.ndarray:
    """(...) the dot products of vectors x and y given as their components (3 arrays each),
    broadcast, summed as x0 y0 + x2 y2 + x1 y1 (the order of np.einsum's two-lane loop on this
    machine, so its bits): a few elementwise operations, where np.einsum's setup costs tens of
    microseconds a call on the planner's small arrays, and on components, where (..., 3) arrays
    made of broadcast rows run NumPy's inner loop over 3 numbers (geometry.by_component)."""
    return x[0] * y[0] + x[2] * y[2] + x[1] * y[1]


def in_frames(R: np.ndarray, x: list[np.ndarray]) -> list[np.ndarray]:
    """The components (3 arrays (B, N)) of the vectors x, given as their components (3 arrays
    (N,) or (B, N), broadcast), in the frames R (B, 3, 3) (columns the axes): R_b^T x, component
    i summed as x_0 R_0i + x_1 R_1i + x_2 R_2i (np.einsum("bji,bnj->bni")'s order, its bits). A
    component at a time: a (B, N, 3) array made of (B, 1, 3) rows runs NumPy's inner loop over 3
    numbers (geometry.by_component)."""
    return [(x[0] * R[:, 0, i, None] + x[1] * R[:, 1, i, None]) + x[2] * R[:, 2, i, None] for i in range(3)]


def segments_cross_boxes(origins: ArrayLike, targets: ArrayLike, T_cell_box: ArrayLike,
                         half_m: ArrayLike) -> np.ndarray:
    """(B, N) whether the segment from each origin to its target crosses box b: origins and
    targets (N, 3) or one (3,) (broadcast), boxes' poses T_cell_box (B, 4, 4) and half sizes
    half_m (B, 3) or one (3,) [m]. One origin (the camera's lines of sight) is placed in each
    box's frame once, not once per target."""
    T = np.asarray(T_cell_box, float).reshape(-1, 4, 4)
    half = np.broadcast_to(np.asarray(half_m, float), (len(T), 3))                      # (B, 3)
    o, q = np.asarray(origins, float).reshape(-1, 3), np.asarray(targets, float).reshape(-1, 3)
    R, c = T[:, :3, :3], T[:, :3, 3]
    # each axis's slab a component at a time (in_frames), the three in turn: the values of the
    # (B, N, 3) arrays' max(axis=-1) and min(axis=-1), without their reductions over an axis of 3
    local = in_frames(R, [o[None, :, k] - c[:, k, None] for k in range(3)])             # (B, N or 1) each
    d = in_frames(R, [q[:, k] - o[:, k] for k in range(3)])                              # (B, N) each

    def slab(k: int) -> tuple[np.ndarray, np.ndarray]:
        """(t_near, t_far) of axis k's slab (B, N)."""
        h = half[:, k, None]
        inside = np.abs(local[k]) < h
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-h - local[k]) / d[k], (h - local[k]) / d[k]
        parallel = d[k] == 0.0
        return (np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)),
                np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)))
    x, y, z = slab(0), slab(1), slab(2)
    t_near = np.maximum(np.maximum(np.maximum(x[0], y[0]), z[0]), 0.0)
    t_far = np.minimum(np.minimum(np.minimum(x[1], y[1]), z[1]), 1.0)
    return t_near < t_far


def segments_near_segments(origins: ArrayLike, targets: ArrayLike, a: ArrayLike, b: ArrayLike,
                           radius_m: ArrayLike) -> np.ndarray:
    """(K, N) whether the segment from each origin to its target (N, 3, or one (3,)) passes
    within radius_m (K,) of segment k from a to b (K, 3): crosses capsule k. The segments'
    closest points by Ericson's clamped solution (Real-Time Collision Detection 5.1.9, as
    bodies.segment_distance), vectorised; the capsules' axes of nonzero length. One origin's
    offsets from the capsules are found once, not once per target."""
    a, b = np.asarray(a, float).reshape(-1, 3), np.asarray(b, float).reshape(-1, 3)
    p, q = np.asarray(origins, float).reshape(-1, 3), np.asarray(targets, float).reshape(-1, 3)
    # a component at a time (dot): d1 (1, N), d2 (K, 1), r = p - a (K, N or 1)
    d1 = [(q[:, k] - p[:, k])[None] for k in range(3)]
    d2 = [(b[:, k] - a[:, k])[:, None] for k in range(3)]
    r = [p[None, :, k] - a[:, k, None] for k in range(3)]
    A, E = dot(d1, d1), dot(d2, d2)
    B, C, F = dot(d1, d2), dot(d1, r), dot(d2, r)
    denom = A * E - B * B
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-18 * A * E, np.clip((B * F - C * E) / denom, 0.0, 1.0), 0.0)
        t = (B * s + F) / E
        s = np.where(t < 0.0, np.clip(-C / A, 0.0, 1.0), np.where(t > 1.0, np.clip((B - C) / A, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    gap = [r[k] + s * d1[k] - t * d2[k] for k in range(3)]
    return dot(gap, gap) < np.asarray(radius_m, float).reshape(-1, 1) ** 2


def box_capsules(T_cell_box: ArrayLike, half_m: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b (B, 3), radius (B,)) a capsule holding each box (poses T_cell_box (B, 4, 4), half
    sizes half_m (B, 3) or one (3,) [m]): its axis the box's longest, through the centre from face
    to face, its radius the other two half sizes' hypotenuse. A point of the box, |x_i| <= h_i in
    its frame, lies along that axis within the segment's extent and sqrt(h_j^2 + h_k^2) across it."""
    T = np.asarray(T_cell_box, float).reshape(-1, 4, 4)
    half = np.broadcast_to(np.asarray(half_m, float), (len(T), 3))
    axis = np.argmax(half, axis=1)
    rows = np.arange(len(T))
    along = T[rows, :3, axis] * half[rows, axis][:, None]
    across = np.sqrt(np.sum(half**2, axis=1) - half[rows, axis] ** 2)
    return T[:, :3, 3] - along, T[:, :3, 3] + along, across


def capsule_balls(a: ArrayLike, b: ArrayLike, radius_m: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres (M, 3), radii (M,), first (K,)) balls holding capsules k (axes a-b (K, 3), radii
    radius_m (K,)), n_k = max(1, ceil(|b - a| / 2 r_k)) along each, the first of capsule k at
    index first[k]: piece j of the axis, of length l = |b - a| / n_k, about its middle x_j; a
    point within r_k of the piece lies within l / 2 + r_k (at most twice r_k) of x_j."""
    a, b = np.asarray(a, float).reshape(-1, 3), np.asarray(b, float).reshape(-1, 3)
    radius = np.broadcast_to(np.asarray(radius_m, float), (len(a),))
    length = np.sqrt(np.sum((b - a) ** 2, axis=1))
    pieces = np.maximum(1, np.ceil(length / (2.0 * radius))).astype(int)
    body = np.repeat(np.arange(len(pieces)), pieces)
    first = np.cumsum(pieces) - pieces
    at = (np.arange(len(body)) - np.repeat(first, pieces) + 0.5) / pieces[body]
    return a[body] + at[:, None] * (b - a)[body], 0.5 * length[body] / pieces[body] + radius[body], first


@dataclass(frozen=True)
class BallsSeen:
    """Balls as seen from a point o: a segment from o meets ball k (centre c_k, radius r_k, at
    d_k = |c_k - o| > r_k) only if its direction lies within asin(r_k / d_k) of c_k - o (the
    ball lies in the cone from o tangent to it) and it reaches d_k - r_k; with o inside a ball,
    every segment may."""

    origin: np.ndarray          # (3,)
    unit: np.ndarray            # (K, 3) towards each centre (0 where o is inside the ball)
    cos2: np.ndarray            # (K,) cos^2 of each ball's angular radius (0 where o is inside)
    reach2: np.ndarray          # (K,) (d_k - r_k)^2, 0 where o is inside

    @classmethod
    def of(cls, origin: ArrayLike, centres: ArrayLike, radii: ArrayLike) -> BallsSeen:
        o = np.asarray(origin, float).reshape(3)
        v = np.asarray(centres, float).reshape(-1, 3) - o
        r = np.asarray(radii, float).reshape(-1)
        d = np.sqrt(np.sum(v * v, axis=1))
        outside = d > r
        with np.errstate(divide="ignore", invalid="ignore"):
            unit = np.where(outside[:, None], v / d[:, None], 0.0)
            cos2 = np.where(outside, 1.0 - (r / d) ** 2, 0.0)
        return cls(o, unit, cos2, np.where(outside, d - r, 0.0) ** 2)

    def met_by(self, ends: ArrayLike) -> np.ndarray:
        """(K, C) whether the segment from the origin to each end (C, 3) may meet ball k (not
        finite: not)."""
        v = geometry.by_component(np.subtract, np.asarray(ends, float).reshape(-1, 3), self.origin)
        along = self.unit @ v.T                                   # (K, C) |v| cos(angle)
        vv = geometry.dot3(v, v)                                  # np.sum(v * v, axis=1)'s bits
        return (along >= 0.0) & (along * along >= self.cos2[:, None] * vv) & (vv >= self.reach2[:, None])


@dataclass(frozen=True)
class SpokesNear:
    """Pieces of rays from a point o (spokes: o + s u, start <= s <= end, |u| = 1) against one
    segment p + t d (0 <= t <= 1), the segment's products fixed: w = o - p, |w|^2, <d, w>,
    |d|^2, so a spoke costs its <u, w> and <u, d> (one product for all) and a few operations on
    (C,) arrays. The closest points as Ericson's clamped solution (Real-Time Collision Detection
    5.1.9, as segments_near_segments) on the piece o + start u + sigma L u (L = end - start) and
    the segment: a = L^2, b = L <u, d>, c = L (<u, w> + start), e = |d|^2, f = <d, w> + start
    <u, d>, and the squared distance |r + sigma L u - t d|^2 = |r|^2 + sigma^2 a + t^2 e +
    2 sigma c - 2 t f - 2 sigma t b, |r|^2 = |w|^2 + 2 start <u, w> + start^2 (r = w + start u),
    expanded: its rounding (~1e-16 of |r|^2) far below a prefilter's margin (NEAR_MARGIN_M). A
    spoke or the segment of length 0 is its point (sigma = 0, t = 0)."""

    uv: np.ndarray              # (3, 2) the columns w, d
    ww: float                   # |w|^2
    dw: float                   # <d, w>
    dd: float                   # |d|^2

    @classmethod
    def of(cls, origin: ArrayLike, p: ArrayLike, q: ArrayLike) -> SpokesNear:
        w = np.asarray(origin, float).reshape(3) - np.asarray(p, float).reshape(3)
        d = np.asarray(q, float).reshape(3) - np.asarray(p, float).reshape(3)
        return cls(np.stack([w, d], axis=1), float(w @ w), float(d @ w), float(d @ d))

    def near(self, unit: np.ndarray, start: ArrayLike, end: ArrayLike, radius_m: float) -> np.ndarray:
        """(C,) whether the spoke along each unit direction (C, 3) from start to end [m] from o
        (each one, or (C,)) passes within radius_m of the segment (not finite: not)."""
        uw, ud = (unit @ self.uv).T
        start = np.asarray(start, float)
        length = end - start
        a, b, c = length * length, length * ud, length * (uw + start)
        e, f = self.dd, self.dw + start * ud
        with np.errstate(divide="ignore", invalid="ignore"):
            if e > 0.0:
                denom = a * e - b * b
                sigma = np.where(denom > 1e-18 * a * e, np.minimum(np.maximum((b * f - c * e) / denom, 0.0), 1.0), 0.0)
                t = (b * sigma + f) / e
                sigma = np.where(t < 0.0, np.minimum(np.maximum(-c / a, 0.0), 1.0),
                                 np.where(t > 1.0, np.minimum(np.maximum((b - c) / a, 0.0), 1.0), sigma))
                t = np.minimum(np.maximum(t, 0.0), 1.0)
            else:
                sigma, t = np.minimum(np.maximum(-c / a, 0.0), 1.0), 0.0
            sigma = np.where(a > 0.0, sigma, 0.0)
        gap2 = (self.ww + start * (2.0 * uw + start) + sigma * (sigma * a + 2.0 * c) + t * (t * e - 2.0 * f)
                - 2.0 * sigma * t * b)
        return gap2 < radius_m * radius_m


@dataclass(frozen=True)
class SightCone:
    """The segments from an apex (the camera) to points within rho of a middle m: the cone from
    the apex tangent to that sphere (axis w, half angle alpha, sin alpha = rho / |m - apex|),
    reaching |m - apex| + rho along w. A ball (centre x, radius R) meets it only if
    b cos alpha - a sin alpha <= R, a = <x - apex, w>, b = |x - apex - a w| (x's signed distance
    from the plane tangent to the cone along its side facing x, the cone behind that plane) and
    -R <= a <= |m - apex| + rho + R; with the apex inside the sphere, any ball may."""

    apex: np.ndarray            # (3,)
    middle: np.ndarray          # (3,)
    rho: float
    axis: np.ndarray            # (3,) unit
    length: float               # |m - apex| + rho
    sin: float
    cos: float

    @classmethod
    def of(cls, apex: ArrayLike, middle: ArrayLike, rho: float) -> SightCone:
        apex, middle = np.asarray(apex, float).reshape(3), np.asarray(middle, float).reshape(3)
        v = middle - apex
        d = float(np.sqrt(v @ v))
        if d <= rho:
            return cls(apex, middle, rho, np.zeros(3), np.inf, 1.0, 0.0)     # every direction: the test always holds
        return cls(apex, middle, rho, v / d, d + rho, rho / d, float(np.sqrt(1.0 - (rho / d) ** 2)))

    def meets(self, centres: ArrayLike, radius: ArrayLike) -> np.ndarray:
        """(C,) whether a ball of `radius` (one, or (C,)) about each centre (C, 3) may meet the cone
        (not finite: not)."""
        v = np.asarray(centres, float).reshape(-1, 3) - self.apex
        r = np.asarray(radius, float)
        a = v @ self.axis
        b = np.sqrt(np.maximum(np.sum(v * v, axis=1) - a * a, 0.0))
        return (b * self.cos - a * self.sin <= r) & (a >= -r) & (a <= self.length + r)
