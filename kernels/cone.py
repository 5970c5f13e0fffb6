"""Free cones: about each point's normal, the widest cone of directions from its shadow ray's
origin that no triangle of the mesh enters. A ray inside it reaches anything without meeting
the mesh, so the gray and visibility kernels cast only the rays outside it (on a feature with
nothing overhanging it most of them: the cone is the open sky above the point).

The cone's half-angle beta is the smallest angle between the normal n and the direction from
the origin o to any point of any triangle, in float64 on the float32 geometry the rays see:
0 where the axis o + t n (t > 0) meets a triangle, else the least over the triangles' edges
(the angle to a triangle seen from o is least on its boundary). A triangle at or below the
tangent plane through o limits nothing above it, so beta is at most 90 deg. The cosine kept is
that of beta - MARGIN_RAD: a ray it lets through passes every triangle by at least that angle
(a ray the float32 BVH could see hit only by rounding is cast, not skipped).
"""
import numpy as np
import warp as wp

from ._arrays import output, unit_rows, vec3d
from .runtime import ensure_init

MARGIN_RAD = 1e-4
NO_CONE = 2.0                   # a cosine no <n, s> exceeds: every ray is cast
RAYS_PER_TRIANGLE = 0.5         # a point's cone costs about this many of its rays per triangle


def worth_finding(rays_per_point, mesh):
    """Whether the free cones pay for themselves: each point casts (or has cast) at least
    RAYS_PER_TRIANGLE rays per triangle of the mesh, most of which its cone would spare."""
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


@wp.kernel
def free_cone_kernel(origins: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
                     vertices: wp.array(dtype=wp.vec3d), faces: wp.array2d(dtype=wp.int32),
                     margin: wp.float64, free_cos: wp.array(dtype=wp.float64)):
    """One thread per point: every triangle against its cone."""
    i = wp.tid()
    o = origins[i]
    n = normals[i]
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
        best = wp.max(best, wp.max(segment_max_cos(a, b, n),
                                   wp.max(segment_max_cos(b, c, n), segment_max_cos(c, a, n))))
    beta = wp.acos(wp.min(best, wp.float64(1.0))) - margin
    out = wp.float64(NO_CONE)
    if beta > wp.float64(0.0):
        out = wp.cos(beta)
    free_cos[i] = out


def free_cone_cosines(mesh, origins, normals, margin_rad=MARGIN_RAD):
    """float64 (P,): cos(beta - margin) of each origin's free cone about its normal (module
    docstring), NO_CONE where it has none. A ray from the origin along unit s with <n, s> above
    it meets no triangle of `mesh` (a kernels.mesh.WarpMesh). Costs about P x F triangle tests."""
    device = ensure_init()
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    normals = unit_rows(normals, "normals")
    if len(normals) != len(origins):
        raise ValueError(f"{len(origins)} origins but {len(normals)} normals")
    free_cos, free_cos_wp = output(len(origins), np.float64, wp.float64)
    if len(origins) == 0:
        return free_cos
    wp.launch(free_cone_kernel, dim=len(origins), device=device, inputs=[
        vec3d(origins, "origins"), vec3d(normals, "normals"), vec3d(mesh.vertices, "vertices"),
        wp.array(np.ascontiguousarray(mesh.faces, dtype=np.int32), dtype=wp.int32, device=device),
        float(margin_rad)], outputs=[free_cos_wp])
    return free_cos
