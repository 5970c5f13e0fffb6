"""Poses named by frames (T_a_b maps b coordinates into a) and the direction conventions
of the physics notes (azimuth/elevation with elevation as latitude)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation


def transform(rotation: ArrayLike | None = None, translation: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def from_rpy(rpy_rad: ArrayLike, translation: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Extrinsic x-y-z roll/pitch/yaw (task files' `rpy_deg`, converted) to a transform."""
    return transform(Rotation.from_euler("xyz", rpy_rad).as_matrix(), translation)


def from_ur_pose(pose: ArrayLike) -> np.ndarray:
    """UR wire pose [x, y, z, rx, ry, rz] (metres, rotation vector) to a transform."""
    pose = np.asarray(pose, dtype=float)
    return transform(Rotation.from_rotvec(pose[3:]).as_matrix(), pose[:3])


def to_ur_pose(T: np.ndarray) -> np.ndarray:
    """Transform to the UR wire pose [x, y, z, rx, ry, rz]."""
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def rotation_angle(T_a: ArrayLike, T_b: ArrayLike) -> float:
    """The angle of the rotation between two poses' orientations [rad]: arccos((tr(R_a^T R_b) - 1) / 2)."""
    cos = (np.trace(np.asarray(T_a)[:3, :3].T @ np.asarray(T_b)[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))


def line_path(T_from: np.ndarray, T_to: np.ndarray) -> tuple[Callable[[float], np.ndarray], float]:
    """(the pose at s in [0, 1] of the straight move from T_from to T_to, as a UR controller's
    moveL makes it: the position linear, the orientation turning about one axis by slerp,
    R_from (I + sin(s a) K + (1 - cos(s a)) K^2) (Rodrigues' formula, K the cross-product matrix
    of the unit axis, a the angle); that angle [rad]). A piece of it, s from s_a to s_b, is the
    straight move between its ends: the same line and the same turn."""
    turn = Rotation.from_matrix(T_from[:3, :3].T @ T_to[:3, :3]).as_rotvec()
    angle = float(np.linalg.norm(turn))
    K = np.cross(np.eye(3), turn / angle) if angle > 0 else np.zeros((3, 3))

    def pose(s: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = T_from[:3, :3] @ (np.eye(3) + np.sin(s * angle) * K + (1 - np.cos(s * angle)) * K @ K)
        T[:3, 3] = (1 - s) * T_from[:3, 3] + s * T_to[:3, 3]
        return T

    return pose, angle


def apply(T: np.ndarray, points: ArrayLike) -> np.ndarray:
    """Map points (..., 3) through T."""
    points = np.asarray(points, dtype=float)
    return by_component(np.add, points @ T[:3, :3].T, T[:3, 3])


def rotate(T: np.ndarray, vectors: ArrayLike) -> np.ndarray:
    """Map directions (..., 3) through T's rotation."""
    return np.asarray(vectors, dtype=float) @ T[:3, :3].T


# (..., 3) arrays of at least this many numbers are combined a component at a time (by_component):
# below some 1 200 vectors numpy's one broadcast operation costs less than three
BY_COMPONENT_SIZE = 3600
# the norms of at least this many numbers' 3-vectors are summed by dot3: below some 64 vectors
# numpy's reduction costs less than dot3's five operations
DOT3_SIZE = 192


def dot3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(...) the dot products of 3-vectors x and y (..., 3), broadcast: row_sum(x * y) without
    forming x * y, ((x0 y0 + x1 y1) + x2 y2) + 0.0, np.sum(x * y, axis=-1)'s bits, where the
    reduction over an axis of 3 costs some 6 times as much on the planner's (N, 3) arrays (140 us
    against 23 us at 9 500 points) and x * y of a (3,) and an (N, 3) runs an inner loop over 3."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2] + 0.0


def norm(v: ArrayLike, axis: int = -1, keepdims: bool = False) -> np.ndarray:
    """|v| along axis: sqrt(sum v^2), np.linalg.norm's own arithmetic for a vector norm along an
    axis (add.reduce of v * v: the same bits) without its dispatch, which costs more than the
    sum on a few vectors (a search's objective asks it at every evaluation); 3-vectors along the
    last axis by dot3 (the same bits again)."""
    v = np.asarray(v, dtype=float)
    if v.size >= DOT3_SIZE and v.shape[-1] == 3 and axis in (-1, v.ndim - 1):
        length = np.sqrt(dot3(v, v))
        return length[..., None] if keepdims else length
    return np.sqrt((v * v).sum(axis=axis, keepdims=keepdims))


def row_sum(a: np.ndarray) -> np.ndarray:
    """np.sum(a, axis=-1) of vectors (..., 3), bit for bit: ((a0 + a1) + a2) + 0.0, np.add.reduce's
    order (from +0.0: a row of -0.0 sums to +0.0), as three columns' adds instead of a reduction
    whose inner loop runs once a row (a third of the time on thousands of rows)."""
    return a[..., 0] + a[..., 1] + a[..., 2] + 0.0


def by_component(op: np.ufunc, a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """op(a, b) (np.subtract, np.divide, ...) of 3-vectors a (..., 3) and b (..., 3) or
    (..., 1), broadcast: numpy's own values, a component at a time where they are many. An (N, 3)
    array less one point, or over (N, 1) lengths, runs numpy's inner loop over 3 numbers, N
    times: some 5 times the cost of three (N,) operations (157 against 33 us at 9 500 points);
    on fewer than BY_COMPONENT_SIZE numbers the one operation is cheaper."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if max(a.size, b.size) < BY_COMPONENT_SIZE or a.shape[-1:] != (3,) or b.ndim == 0:
        return op(a, b)
    shape = np.broadcast_shapes(a.shape, b.shape)
    if shape[-1:] != (3,):
        return op(a, b)
    out = np.empty(shape)
    for k in range(3):
        op(a[..., k], b[..., k if b.shape[-1] == 3 else 0], out=out[..., k])
    return out


def unit(v: ArrayLike, axis: int = -1) -> np.ndarray:
    """v / |v| along axis."""
    v = np.asarray(v, dtype=float)
    length = norm(v, axis=axis, keepdims=True)
    return by_component(np.divide, v, length) if v.size >= BY_COMPONENT_SIZE and axis in (-1, v.ndim - 1) \
        else v / length


def direction(v: ArrayLike, axis: int = -1) -> np.ndarray:
    """v / |v| along axis, and 0 where |v| = 0, as Warp's wp.normalize: the direction from a point
    to a lamp or a camera at that very point is 0, so <n, s> = 0 there (shadowed, unseen), where
    unit() gives NaN (0/0)."""
    v = np.asarray(v, dtype=float)
    length = norm(v, axis=axis, keepdims=True)
    return np.divide(v, length, out=np.zeros_like(v), where=length > 0.0)


def frame_from_normal(normal: ArrayLike, reference: ArrayLike = (1.0, 0.0, 0.0)) -> np.ndarray:
    """3x3 rotation whose columns are (x, y, z) of a frame with +z = normal; x is the
    reference projected into the tangent plane (any fixed axis when they are parallel)."""
    z = unit(normal)
    ref = np.asarray(reference, dtype=float)
    if abs(np.dot(ref, z)) > 0.99:
        ref = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = unit(ref - np.dot(ref, z) * z)
    return np.column_stack([x, np.cross(z, x), z])


def direction_from_angles(azimuth: ArrayLike, elevation: ArrayLike) -> np.ndarray:
    """Unit vector(s) (..., 3) for azimuth phi in [-pi, pi) and elevation (latitude) theta."""
    azimuth, elevation = np.broadcast_arrays(np.asarray(azimuth, float), np.asarray(elevation, float))
    ce = np.cos(elevation)
    return np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)], axis=-1)


def angles_from_direction(d: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth in [-pi, pi), elevation in [-pi/2, pi/2]) of direction(s) (..., 3)."""
    d = unit(d)
    az = np.arctan2(d[..., 1], d[..., 0])
    az = np.where(az >= np.pi, az - 2 * np.pi, az)
    return az, np.arcsin(np.minimum(np.maximum(d[..., 2], -1.0), 1.0))      # np.clip's values, not its checks


def haversine_distance(az1: float | np.ndarray, el1: float | np.ndarray, az2: float | np.ndarray,
                       el2: float | np.ndarray) -> np.ndarray:
    """Great-circle angle of eq. (2)-(3): d = 2 atan2(sqrt a, sqrt(1 - a)),
    a = h(el2 - el1) + cos el1 cos el2 h(az2 - az1), h(x) = sin^2(x / 2)."""
    a = np.sin(0.5 * (el2 - el1)) ** 2 + np.cos(el1) * np.cos(el2) * np.sin(0.5 * (az2 - az1)) ** 2
    a = np.clip(a, 0.0, 1.0)
    return 2.0 * np.arctan2(np.sqrt(a), np.sqrt(1.0 - a))


def winding_number(vertices: ArrayLike, faces: ArrayLike, point: ArrayLike) -> float:
    """Generalized winding number of a triangle mesh about a point: the solid angle its triangles
    subtend, over 4 pi (Van Oosterom and Strackee's formula per triangle). 1 inside a closed,
    outward-oriented mesh, 0 outside, 1/2 on the surface; robust to small holes."""
    tri = np.asarray(vertices, float)[np.asarray(faces)] - np.asarray(point, float)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
           + np.einsum("ij,ij->i", c, a) * lb)
    return float(np.sum(np.arctan2(det, den)) / (2.0 * np.pi))


def bounding_sphere(points: ArrayLike) -> tuple[np.ndarray, float]:
    """A sphere holding the points (N, 3): its centre, the middle of their bounding box, and its
    radius, their largest distance from it [m]."""
    points = np.asarray(points, float).reshape(-1, 3)
    # a column at a time: the same values as min(axis=0), a tenth of its cost on (N, 3)
    lowest = np.array([points[:, k].min() for k in range(3)])
    highest = np.array([points[:, k].max() for k in range(3)])
    middle = 0.5 * (lowest + highest)
    offset = by_component(np.subtract, points, middle)
    return middle, float(np.sqrt(dot3(offset, offset).max()))     # sqrt is monotonic: the largest norm's bits
