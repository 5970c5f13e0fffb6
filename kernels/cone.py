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
