"""The moving bodies as shadow geometry: whether straight segments (a camera's line of sight to a
sample, a lamp's ray to it) cross boxes or capsules, vectorised over many bodies and segments.

A box (centre c, axes R, half sizes h) and the segment o + t d, 0 < t < 1: in the box's frame
o' = R^T (o - c), d' = R^T d, each axis's slab |o'_i + t d'_i| < h_i holds for t between
(-h_i - o'_i) / d'_i and (h_i - o'_i) / d'_i (the whole line where d'_i = 0 and |o'_i| < h_i,
none where |o'_i| >= h_i); the segment crosses the box where the three intervals and (0, 1)
overlap: max(t_near) < min(t_far) (Kay and Kajiya's slabs; Ericson, Real-Time Collision
Detection 5.3.3). A segment touching a face only (grazing) does not cross.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def segments_cross_boxes(origins: ArrayLike, targets: ArrayLike, T_cell_box: ArrayLike,
                         half_m: ArrayLike) -> np.ndarray:
    """(B, N) whether the segment from each origin to its target crosses box b: origins and
    targets (N, 3) or one (3,) (broadcast), boxes' poses T_cell_box (B, 4, 4) and half sizes
    half_m (B, 3) or one (3,) [m]."""
    T = np.asarray(T_cell_box, float).reshape(-1, 4, 4)
    half = np.broadcast_to(np.asarray(half_m, float), (len(T), 3))[:, None]             # (B, 1, 3)
    o, q = np.broadcast_arrays(np.asarray(origins, float).reshape(-1, 3), np.asarray(targets, float).reshape(-1, 3))
    R, c = T[:, :3, :3], T[:, :3, 3]
    local = np.einsum("bji,bnj->bni", R, o[None] - c[:, None])                          # (B, N, 3)
    d = np.einsum("bji,nj->bni", R, q - o)
    inside = np.abs(local) < half
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - local) / d, (half - local) / d
    parallel = d == 0.0
    near = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    far = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    t_near = np.maximum(near.max(axis=-1), 0.0)
    t_far = np.minimum(far.min(axis=-1), 1.0)
    return t_near < t_far


def segments_near_segments(origins: ArrayLike, targets: ArrayLike, a: ArrayLike, b: ArrayLike,
                           radius_m: ArrayLike) -> np.ndarray:
    """(K, N) whether the segment from each origin to its target (N, 3, or one (3,)) passes
    within radius_m (K,) of segment k from a to b (K, 3): crosses capsule k. The segments'
    closest points by Ericson's clamped solution (Real-Time Collision Detection 5.1.9, as
    bodies.segment_distance), vectorised; the capsules' axes of nonzero length."""
    a, b = np.asarray(a, float).reshape(-1, 3), np.asarray(b, float).reshape(-1, 3)
    p, q = np.broadcast_arrays(np.asarray(origins, float).reshape(-1, 3), np.asarray(targets, float).reshape(-1, 3))
    d1, d2 = q - p, b - a                                               # (N, 3), (K, 3)
    r = p[None] - a[:, None]                                            # (K, N, 3)
    A, E = np.einsum("nj,nj->n", d1, d1)[None], np.einsum("kj,kj->k", d2, d2)[:, None]
    B, C, F = np.einsum("nj,kj->kn", d1, d2), np.einsum("nj,knj->kn", d1, r), np.einsum("kj,knj->kn", d2, r)
    denom = A * E - B * B
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-18 * A * E, np.clip((B * F - C * E) / denom, 0.0, 1.0), 0.0)
        t = (B * s + F) / E
        s = np.where(t < 0.0, np.clip(-C / A, 0.0, 1.0), np.where(t > 1.0, np.clip((B - C) / A, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    gap = r + s[..., None] * d1[None] - t[..., None] * d2[:, None]
    return np.einsum("knj,knj->kn", gap, gap) < np.asarray(radius_m, float).reshape(-1, 1) ** 2


def points_to_segments(points: ArrayLike, a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """The distance from each point to the segment a -> b, broadcast over points, a and b (..., 3)
    [m]: |p - a - s (b - a)|, s = <p - a, b - a> / |b - a|^2 clipped to [0, 1]; a point or segment
    not finite gives NaN (compares false)."""
    p, a, b = (np.asarray(x, float) for x in (points, a, b))
    d = b - a
    with np.errstate(invalid="ignore"):
        s = np.clip(np.einsum("...j,...j->...", p - a, d) / np.maximum(np.einsum("...j,...j->...", d, d), 1e-300),
                    0.0, 1.0)
        return np.linalg.norm(p - a - s[..., None] * d, axis=-1)
