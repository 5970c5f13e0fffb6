"""Free cones: about each point's normal, the widest cone of directions from its shadow ray's
origin that no triangle of the mesh enters, overall and in each of funcs.SECTORS azimuth
sectors. A ray inside one reaches anything without meeting the mesh, so the gray and
visibility kernels cast only the rays outside them (on a feature with nothing overhanging it
most of them: the cone is the open sky above the point, wider where nothing stands near).

The half-angle beta is the smallest angle between the normal n and the direction from the
origin o to any point of a triangle, in float64 on the float32 geometry the rays see: 0 where
the axis o + t n (t > 0) meets a triangle, else the least over the triangles' edges (the angle
to a triangle seen from o is least on its boundary). A triangle at or below the tangent plane
through o limits nothing above it, so beta is at most 90 deg. A sector's beta counts the
triangles whose azimuths (those of their edges' short arcs about n, padded by PAD) reach into it,
each with its own least angle. The cosine kept is that of beta - MARGIN_RAD: a ray it lets
through passes every triangle by at least that angle (a ray the float32 BVH could see hit only
by rounding is cast, not skipped). Sectors are kept only where the narrowest cone is wider than
2 MARGIN_RAD, so that the directions they judge have a well-defined azimuth.
"""
import math
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from . import funcs
from ._arrays import output, unit_rows, vec3d
from .runtime import ensure_init, launch_sliced

if TYPE_CHECKING:
    from .mesh import WarpMesh

MARGIN_RAD = 1e-4
PAD = 1e-6                      # of the diamond angle (~1e-6 rad): sectors touched by rounding count
NO_CONE = 2.0                   # a cosine no <n, s> exceeds: every ray is cast
RAYS_PER_TRIANGLE = 0.5         # a point's cones cost about this many of its rays per triangle


def worth_finding(rays_per_point: int, mesh: "WarpMesh") -> bool:
    """Whether the free cones pay for themselves: each point casts (or has cast) at least
    RAYS_PER_TRIANGLE rays per triangle of the mesh, most of which its cones would spare."""
    return rays_per_point >= RAYS_PER_TRIANGLE * len(mesh.faces)


@wp.func
def segment_max_cos(p: wp.vec3d, q: wp.vec3d, n: wp.vec3d) -> wp.float64:
    """max over x on the segment [p, q] of <x, n> / |x|: with x = p + t (q - p) its derivative
    vanishes at the one t = (alpha B - beta A) / (beta B - alpha C) (alpha = <p, n>, beta =
    <q - p, n>, A = |p|^2, B = <p, q - p>, C = |q - p|^2), else the maximum is at an end.
    1 where the segment passes through the origin."""
    d = q - p
    al = wp.dot(p, n)
    be = wp.dot(d, n)
    a2 = wp.dot(p, p)
    b = wp.dot(p, d)
    c2 = wp.dot(d, d)
    q2 = a2 + wp.float64(2.0) * b + c2
    if a2 <= wp.float64(0.0) or q2 <= wp.float64(0.0):
        return wp.float64(1.0)
    best = wp.max(al / wp.sqrt(a2), (al + be) / wp.sqrt(q2))
    den = be * b - al * c2
    if den != wp.float64(0.0):
        t = (al * b - be * a2) / den
        if t > wp.float64(0.0) and t < wp.float64(1.0):
            x = p + t * d
            r = wp.length(x)
            if r <= wp.float64(0.0):
                return wp.float64(1.0)
            best = wp.max(best, wp.dot(x, n) / r)
    return best


@wp.func
def axis_meets(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, n: wp.vec3d) -> wp.bool:
    """The ray t n, t > 0, meets the triangle (a, b, c) (Moller-Trumbore; parallel: no)."""
    e1 = b - a
    e2 = c - a
    pv = wp.cross(n, e2)
    det = wp.dot(e1, pv)
    if det == wp.float64(0.0):
        return False
    inv = wp.float64(1.0) / det
    u = -wp.dot(a, pv) * inv
    qv = wp.cross(-a, e1)
    v = wp.dot(n, qv) * inv
    t = wp.dot(e2, qv) * inv
    return u >= wp.float64(0.0) and v >= wp.float64(0.0) and u + v <= wp.float64(1.0) and t > wp.float64(0.0)


@wp.func
def wrapped_sector(diamond: wp.float64) -> wp.int32:
    """funcs.sector_of a diamond angle taken modulo 4."""
    x = diamond
    if x < wp.float64(0.0):
        x = x + wp.float64(4.0)
    elif x >= wp.float64(4.0):
        x = x - wp.float64(4.0)
    return funcs.sector_of(x)


@wp.func
def raise_arc(table: wp.array2d(dtype=wp.float64), row: int, p: wp.vec3d, q: wp.vec3d, u: wp.vec3d,
              w: wp.vec3d, value: wp.float64):
    """table[row, k] = max(it, value) over the sectors k that the edge [p, q] reaches: the short
    arc between its ends' azimuths, padded (one azimuth where both ends share it: an edge along
    the normal); every sector where an end lies (nearly) on the axis or the edge's shadow on the
    tangent plane passes (nearly) through o."""
    xp = wp.dot(p, u)
    yp = wp.dot(p, w)
    xq = wp.dot(q, u)
    yq = wp.dot(q, w)
    rp = wp.abs(xp) + wp.abs(yp)
    rq = wp.abs(xq) + wp.abs(yq)
    cross = xp * yq - yp * xq
    everywhere = rp <= wp.float64(1e-9) * wp.length(p) or rq <= wp.float64(1e-9) * wp.length(q)
    start = funcs.diamond_angle(xp, yp)
    end = funcs.diamond_angle(xq, yq)
    if not everywhere and wp.abs(cross) <= wp.float64(1e-12) * rp * rq:
        everywhere = xp * xq + yp * yq <= wp.float64(0.0)     # opposite azimuths: through o
        end = start
    elif cross < wp.float64(0.0):
        start = end
        end = funcs.diamond_angle(xp, yp)
    if everywhere:
        for k in range(funcs.SECTORS):
            table[row, k] = wp.max(table[row, k], value)
        return
    k = wrapped_sector(start - wp.float64(PAD))
    last = wrapped_sector(end + wp.float64(PAD))
    for _ in range(funcs.SECTORS):
        table[row, k] = wp.max(table[row, k], value)
        if k == last:
            break
        k = (k + 1) % funcs.SECTORS


@wp.func
def cone_cosine(best: wp.float64, margin: wp.float64) -> wp.float64:
    """cos(beta - margin) for beta = acos(best), NO_CONE where that angle is not positive."""
    beta = wp.acos(wp.min(best, wp.float64(1.0))) - margin
    if beta > wp.float64(0.0):
        return wp.cos(beta)
    return wp.float64(NO_CONE)


@wp.kernel
def free_cone_kernel(origins: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
                     vertices: wp.array(dtype=wp.vec3d), faces: wp.array2d(dtype=wp.int32),
                     margin: wp.float64, first: wp.int32, free_cos: wp.array(dtype=wp.float64),
                     sector_cos: wp.array2d(dtype=wp.float64)):
    """One thread per point, from `first` on (runtime.launch_sliced): every triangle against its
    cones (sector_cos holds the largest cosines met, then their cones)."""
    i = wp.tid() + first
    o = origins[i]
    n = normals[i]
    u = funcs.tangent_u(n)
    w = wp.cross(n, u)
    for k in range(funcs.SECTORS):
        sector_cos[i, k] = wp.float64(0.0)
    best = wp.float64(0.0)                  # cos 90 deg
    for f in range(faces.shape[0]):
        a = vertices[faces[f, 0]] - o
        b = vertices[faces[f, 1]] - o
        c = vertices[faces[f, 2]] - o
        if wp.max(wp.max(wp.dot(a, n), wp.dot(b, n)), wp.dot(c, n)) <= wp.float64(0.0):
            continue                        # at or below the tangent plane
        if axis_meets(a, b, c, n):
            best = wp.float64(1.0)
            break
        near = wp.max(segment_max_cos(a, b, n), wp.max(segment_max_cos(b, c, n), segment_max_cos(c, a, n)))
        best = wp.max(best, near)
        raise_arc(sector_cos, i, a, b, u, w, near)
        raise_arc(sector_cos, i, b, c, u, w, near)
        raise_arc(sector_cos, i, c, a, u, w, near)
    free_cos[i] = cone_cosine(best, margin)
    keep = cone_cosine(best, wp.float64(2.0) * margin) <= wp.float64(1.0)
    for k in range(funcs.SECTORS):
        sector = wp.float64(NO_CONE)
        if keep:
            sector = cone_cosine(sector_cos[i, k], margin)
        sector_cos[i, k] = sector


def free_cone_cosines(mesh: "WarpMesh", origins: ArrayLike, normals: ArrayLike,
                      margin_rad: float = MARGIN_RAD) -> tuple[np.ndarray, np.ndarray]:
    """(free_cos (P,), sector_cos (P, funcs.SECTORS)) float64: cos(beta - margin) of each
    origin's free cone about its normal, overall and per azimuth sector (funcs.sector_of of the
    diamond angle about funcs.tangent_u), NO_CONE where there is none (module docstring). A ray
    from the origin along unit s with <n, s> above its sector's (or the overall) cosine meets
    no triangle of `mesh` (a kernels.mesh.WarpMesh). Costs about P x F triangle tests."""
    device = ensure_init(__name__)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    normals = unit_rows(normals, "normals")
    if len(normals) != len(origins):
        raise ValueError(f"{len(origins)} origins but {len(normals)} normals")
    free_cos, free_cos_wp = output(len(origins), np.float64, wp.float64)
    sector_cos, sector_cos_wp = output((len(origins), funcs.SECTORS), np.float64, wp.float64)
    if len(origins):
        launch_sliced(free_cone_kernel, len(origins), [
            vec3d(origins, "origins"), vec3d(normals, "normals"), vec3d(mesh.vertices, "vertices"),
            wp.array(np.ascontiguousarray(mesh.faces, dtype=np.int32), dtype=wp.int32, device=device),
            float(margin_rad)], [free_cos_wp, sector_cos_wp], work_per_item=len(mesh.faces))
    return free_cos, sector_cos


PIECES = 16             # pieces each edge is cut into for cylinder_cone_cosine's bound
CYLINDER_SLACK_M = 1e-4  # a common cone is found for its cylinder this much wider (and 1 % of it lower), so
                         # that the next patch of one feature (another count of points) lies inside it
KEPT_CYLINDERS = 64      # cylinders whose cones are kept per mesh and normal (a part's features on one plane)
_KEPT: dict[tuple[bytes, bytes], list[tuple[tuple[float, float, float], float, float, float, float]]] = {}


def common_cone_cosine(mesh: "WarpMesh", axis_point: ArrayLike, normal: ArrayLike, radius_m: float, low_m: float,
                       margin_rad: float = MARGIN_RAD) -> float:
    """cylinder_cone_cosine of the cylinder (axis_point, normal, radius_m, low_m), or of one kept
    from before that holds it (its axis along the same normal, the other's tangential offset
    plus radius_m within its radius, low_m no lower, its margin no smaller: a cone common to
    every origin of that one is common to these): a feature's dense patch, asked again at each
    shot with another count of points, lies in the same cylinder. A cylinder not held by one
    kept is found CYLINDER_SLACK_M wider (and a hundredth of that lower) and kept, the
    KEPT_CYLINDERS most recent of each mesh and normal (of at most 8 meshes)."""
    n = np.asarray(normal, dtype=np.float64)
    c = np.asarray(axis_point, dtype=np.float64)
    key = (mesh.digest, n.tobytes())
    kept = _KEPT.pop(key, [])
    _KEPT[key] = kept
    (nx, ny, nz), (cx, cy, cz) = n.tolist(), c.tolist()
    for k, (at, radius, low, margin, cosine) in enumerate(kept):
        dx, dy, dz = cx - at[0], cy - at[1], cz - at[2]
        along = dx * nx + dy * ny + dz * nz
        off = math.sqrt(max((dx * dx + dy * dy + dz * dz) - along * along, 0.0))     # its part across n
        if off + radius_m <= radius and low_m >= low and margin_rad <= margin:
            kept.append(kept.pop(k))
            return cosine
    radius, low = radius_m + CYLINDER_SLACK_M, low_m - 0.01 * CYLINDER_SLACK_M
    cosine = cylinder_cone_cosine(mesh, c, n, radius, low, margin_rad)
    kept.append(((cx, cy, cz), radius, low, margin_rad, cosine))
    del kept[:-KEPT_CYLINDERS]
    meshes = {m for m, _ in _KEPT}
    if len(meshes) > 8:
        oldest = next(iter(_KEPT))[0]
        for gone in [k for k in _KEPT if k[0] == oldest]:
            del _KEPT[gone]
    return cosine


def cylinder_cone_cosine(mesh: "WarpMesh", axis_point: ArrayLike, normal: ArrayLike, radius_m: float, low_m: float,
                         margin_rad: float = MARGIN_RAD) -> float:
    """cos(beta - margin) of a free cone about the unit `normal` common to every origin o within
    radius_m of the axis axis_point + t normal and with <o, normal> >= low_m (a flat patch's shadow-ray
    origins: their common cone, where finding each point's (free_cone_cosines) costs more than
    the few rays a certificate casts from it), NO_CONE where there is none. beta bounds from below
    the angle between the normal and the direction from any such o to any point x of the mesh:
    of a triangle only its part above o's plane can be met, so only its part with <x, n> >=
    low_m counts (clipped); where that part's projection along the normal comes within radius_m
    of the axis (some o meets it along the normal, or nearly) there is no cone; else, for each o,
    the angle to it is least on its boundary (the module docstring), and on a piece of a clipped
    edge (each cut into PIECES) at least atan2(d - radius_m, h): h the piece's greatest height
    above low_m (o lies no lower), d its projection's least distance from the axis (o's at most
    radius_m). The cut across the triangle lies at low_m: nothing on it is above any o. Float64
    on the float32 geometry the rays see, less margin_rad as free_cone_cosines."""
    n = np.asarray(normal, dtype=np.float64)
    c = np.asarray(axis_point, dtype=np.float64)
    v = mesh.vertices[mesh.faces]                                  # (F, 3 corners, 3)
    h = v @ n - low_m                                              # (F, 3) heights above low_m
    v, h = v[h.max(axis=1) > 0.0], h[h.max(axis=1) > 0.0]
    if not len(v):
        return float(np.cos(np.pi / 2 - margin_rad))
    a, b = v, np.roll(v, -1, axis=1)                                # each triangle's edges a -> b
    ha, hb = h, np.roll(h, -1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):          # an edge that does not cross: its `at` unread
        t = ha / (ha - hb)                                          # where an edge crosses low_m
        at = a + t[..., None] * (b - a)
    crossing = (ha >= 0.0) != (hb >= 0.0)
    a2 = np.where((ha < 0.0)[..., None], at, a)                    # the edges clipped to h >= 0
    b2 = np.where((hb < 0.0)[..., None], at, b)
    ha2, hb2 = np.maximum(ha, 0.0), np.maximum(hb, 0.0)
    kept = (ha >= 0.0) | (hb >= 0.0)
    # the cut (h = 0) joins the two crossing points of a triangle cut by low_m
    first = np.argmax(crossing, axis=1)
    last = 2 - np.argmax(crossing[:, ::-1], axis=1)
    rows = np.arange(len(v))
    cut = crossing.sum(axis=1) == 2
    ends = np.concatenate([np.stack([a2, b2], axis=2)[kept],                             # (S, 2, 3)
                           np.stack([at[rows, first], at[rows, last]], axis=1)[cut]])
    heights = np.concatenate([np.stack([ha2, hb2], axis=2)[kept], np.zeros((int(cut.sum()), 2))])
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    flat = np.stack([(ends - c) @ u, (ends - c) @ w], axis=-1)      # (S, 2 ends, 2) about the axis
    if _segment_distance(flat[:, 0], flat[:, 1]).min() <= radius_m or _axis_meets(v, h, c, n, low_m):
        return float(NO_CONE)
    steps = np.linspace(0.0, 1.0, PIECES + 1)
    along = flat[:, :1] + steps[None, :, None] * (flat[:, 1:] - flat[:, :1])            # (S, PIECES + 1, 2)
    up = heights[:, :1] + steps[None, :] * (heights[:, 1:] - heights[:, :1])            # (S, PIECES + 1)
    d = _segment_distance(along[:, :-1].reshape(-1, 2), along[:, 1:].reshape(-1, 2)) - radius_m
    top = np.maximum(up[:, :-1], up[:, 1:]).ravel()
    beta = float(np.min(np.arctan2(d, top))) - margin_rad
    return float(np.cos(beta)) if beta > 0.0 else float(NO_CONE)


def _segment_distance(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(S,) the least distance from the origin to each segment p -> q (S, 2)."""
    d = q - p
    length2 = np.sum(d * d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.where(length2 > 0.0, -np.sum(p * d, axis=1) / length2, 0.0), 0.0, 1.0)
    x = p + t[:, None] * d
    return np.sqrt(np.sum(x * x, axis=1))


def _axis_meets(v: np.ndarray, h: np.ndarray, c: np.ndarray, n: np.ndarray, low_m: float) -> bool:
    """Whether the line c + t n meets some triangle v (F, 3, 3) at a point above low_m (its
    projection holds the axis: the boundary's distances alone would not tell)."""
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    p = np.cross(n, e2)
    det = np.sum(e1 * p, axis=1)
    ok = np.abs(det) > 0.0                                          # parallel to the axis: its edges tell
    with np.errstate(divide="ignore", invalid="ignore"):
        s = c - v[:, 0]
        b1 = np.sum(s * p, axis=1) / det
        q = np.cross(s, e1)
        b2 = (q @ n) / det
        t = np.sum(e2 * q, axis=1) / det
        inside = ok & (b1 >= 0.0) & (b2 >= 0.0) & (b1 + b2 <= 1.0)
        return bool(np.any(inside & ((c + t[:, None] * n) @ n - low_m >= 0.0)))
