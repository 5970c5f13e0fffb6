"""The certificates' specular points (cell.planning.certificate.specular_points) searched in one
launch, a thread a patch. Each thread finds its patch's radius (the largest |point - centre|)
and start (the dense point of the largest <v, r>, mirror_alignment's eq. 6-7, np.argmax's
first), then runs scipy's Nelder-Mead (scipy.optimize.minimize(method="Nelder-Mead"), without
bounds, not adaptive, from the initial simplex (0, 0), (d, 0), (0, d), with xatol, fatol and
maxfev) over a step (a, b) in the feature's tangent plane from the start, each step projected
onto the surface (kernels.proximity.closest_on within the patch's radius) and judged by -<v, r>
there, 2 off the patch.

Every operation is IEEE double on its own, in the order of the Python and NumPy it replaces
(cell.planning.certificate's alignment_at and mirror_alignment, on_patch, the radius's sum of
squares, the step's `start + a x + b y`, scipy's reflection, expansion, contractions and
shrink, its centroid summed from +0.0): Warp emits each operation of a kernel as a statement of
its own, which the compiler does not fuse into a multiply-add (its `fuse_fp` fuses only within
one C++ expression), so the same bits; the simplex is ordered as np.argsort orders three values
(ascending, NaN last, equal values in their order: tests/test_certificate.py holds NumPy to it).
Where a point lies so near the patch's rim that the sum of squares' root cannot decide it as
np.linalg.norm does (certificate.on_patch's band), the search stops and says so (`decided`
False): its caller searches that patch in Python.

A patch of 10 000 points costs some 0.3 ms: the start's scan about two thirds, the search's 80
closest-point queries and its arithmetic the rest; in Python the search alone cost some 25
rounds of 100 us (a query launch and the steps' arithmetic in Python floats).
"""
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from ._arrays import output, vec3d_view
from .proximity import closest_on
from .runtime import ensure_init

if TYPE_CHECKING:
    from collections.abc import Sequence

    from .mesh import WarpMesh

wp.set_module_options({"enable_backward": False})


@wp.func
def projected(mesh: wp.uint64, max_dist: wp.float32, start: wp.vec3d, along_x: wp.vec3d, along_y: wp.vec3d,
              a: wp.float64, b: wp.float64):
    """(point, face, outward normal) of the step (a, b): kernels.proximity's closest point to
    start + a x + b y (each component (s + a x) + b y) within max_dist."""
    return closest_on(mesh, wp.vec3d(start[0] + a * along_x[0] + b * along_y[0],
                                     start[1] + a * along_x[1] + b * along_y[1],
                                     start[2] + a * along_x[2] + b * along_y[2]), max_dist)


@wp.func
def alignment(point: wp.vec3d, normal: wp.vec3d, lamp: wp.vec3d, camera: wp.vec3d) -> wp.float64:
    """<v, r> at the point (certificate.alignment_at's operations in its order; IEEE's NaN or
    infinity where the lamp or the camera is at the point, as NumPy's)."""
    zero = wp.float64(0.0)
    sx = lamp[0] - point[0]
    sy = lamp[1] - point[1]
    sz = lamp[2] - point[2]
    vx = camera[0] - point[0]
    vy = camera[1] - point[1]
    vz = camera[2] - point[2]
    s_length = wp.sqrt(((sx * sx + sy * sy) + sz * sz) + zero)
    v_length = wp.sqrt(((vx * vx + vy * vy) + vz * vz) + zero)
    sx = sx / s_length
    sy = sy / s_length
    sz = sz / s_length
    vx = vx / v_length
    vy = vy / v_length
    vz = vz / v_length
    twice = wp.float64(2.0) * (((normal[0] * sx + normal[1] * sy) + normal[2] * sz) + zero)
    return (((twice * normal[0] - sx) * vx + (twice * normal[1] - sy) * vy) + (twice * normal[2] - sz) * vz) + zero


@wp.struct
class Patch:
    """What a search's evaluations read: the mesh and the query's reach (float32, as
    kernels.proximity takes it), the start and tangent axes of the steps, the patch's centre,
    radius and rim band, the lamp and the camera."""

    mesh: wp.uint64
    reach: wp.float32
    start: wp.vec3d
    along_x: wp.vec3d
    along_y: wp.vec3d
    center: wp.vec3d
    radius: wp.float64
    rim: wp.float64
    lamp: wp.vec3d
    camera: wp.vec3d


@wp.func
def value(patch: Patch, step: wp.vec2d):
    """(-<v, r> at the step's point, 2 off the patch (or no surface within reach); whether
    on_patch's root decided it: False within the rim band of the radius, where np.linalg.norm's
    rounding decides)."""
    point, face, normal = projected(patch.mesh, patch.reach, patch.start, patch.along_x, patch.along_y, step[0],
                                    step[1])
    dx = point[0] - patch.center[0]
    dy = point[1] - patch.center[1]
    dz = point[2] - patch.center[2]
    distance = wp.sqrt((dx * dx + dy * dy) + dz * dz)
    if wp.isnan(distance):
        return wp.float64(2.0), True
    if wp.abs(distance - patch.radius) <= patch.rim:
        return wp.float64(0.0), False
    if distance <= patch.radius:
        return -alignment(point, normal, patch.lamp, patch.camera), True
    return wp.float64(2.0), True


@wp.func
def trial(patch: Patch, centroid: wp.vec2d, worst: wp.vec2d, p: wp.float64, q: wp.float64):
    """(x, its value, decided) of scipy's trial point p centroid - q worst, a component at a
    time: the reflection (2, 1), expansion (3, 2), outside (1.5, 0.5) and inside (0.5, -0.5)
    contractions (1 w is w, and a - (-0.5 w) is a + 0.5 w, bit for bit)."""
    x = wp.vec2d(p * centroid[0] - q * worst[0], p * centroid[1] - q * worst[1])
    f, ok = value(patch, x)
    return x, f, ok


@wp.func
def halfway(best: wp.vec2d, x: wp.vec2d) -> wp.vec2d:
    """scipy's shrink of a vertex: best + 0.5 (x - best), a component at a time."""
    half = wp.float64(0.5)
    return wp.vec2d(best[0] + half * (x[0] - best[0]), best[1] + half * (x[1] - best[1]))


@wp.func
def before(a: wp.float64, b: wp.float64) -> bool:
    """a sorts before b as np.argsort sorts: ascending, NaN last."""
    return a < b or (wp.isnan(b) and not wp.isnan(a))


@wp.func
def swapped(x: wp.vec2d, y: wp.vec2d, fx: wp.float64, fy: wp.float64):
    """Two vertices and their values, exchanged."""
    return y, x, fy, fx


@wp.kernel
def specular_search_kernel(meshes: wp.array(dtype=wp.uint64), points: wp.array(dtype=wp.vec3d),
                           normals: wp.array(dtype=wp.vec3d), bounds: wp.array(dtype=wp.int32),
                           frames: wp.array(dtype=wp.vec3d), lamp: wp.vec3d,
                           rim_fraction: wp.float64, step_fraction: wp.float64, xatol: wp.float64,
                           fatol: wp.float64, maxfev: wp.int32, point: wp.array(dtype=wp.vec3d),
                           normal: wp.array(dtype=wp.vec3d), decided: wp.array(dtype=wp.int32)):
    """Search k over patch k's dense points (rows bounds[k] to bounds[k + 1]), its centre,
    tangent axes x and y and camera frames[4 k] to frames[4 k + 3]: its radius the
    largest |point - centre| (the root of the largest ((dx dx + dy dy) + dz dz) + 0.0), its start
    the first point of the largest <v, r> (np.argmax's, a NaN first), then Nelder-Mead from the
    simplex (0, 0), (d, 0), (0, d), d = step_fraction x radius; its best step where its value is
    no worse than the start's, else (0, 0), projected onto the surface (point, normal). decided[k]
    0 where a point fell within rim_fraction x radius of the rim (the rest then means nothing)."""
    k = wp.tid()
    c = frames[4 * k]
    eye = frames[4 * k + 3]
    zero = wp.float64(0.0)
    farthest = wp.float64(-wp.inf)
    best = wp.float64(wp.nan)
    first = bounds[k]
    s = points[first]
    for i in range(first, bounds[k + 1]):
        p = points[i]
        dx = p[0] - c[0]
        dy = p[1] - c[1]
        dz = p[2] - c[2]
        squared = ((dx * dx + dy * dy) + dz * dz) + zero
        if wp.isnan(squared) or squared > farthest:
            if not wp.isnan(farthest):
                farthest = squared
        aligned = alignment(p, normals[i], lamp, eye)
        if i == first or (not wp.isnan(best) and (wp.isnan(aligned) or aligned > best)):
            best = aligned
            s = p
    patch = Patch()
    patch.mesh = meshes[k]
    patch.radius = wp.sqrt(farthest)
    patch.reach = wp.float32(patch.radius)
    patch.rim = rim_fraction * patch.radius
    patch.start = s
    patch.along_x = frames[4 * k + 1]
    patch.along_y = frames[4 * k + 2]
    patch.center = c
    patch.lamp = lamp
    patch.camera = eye
    x0 = wp.vec2d(zero, zero)
    x1 = wp.vec2d(step_fraction * patch.radius, zero)
    x2 = wp.vec2d(zero, step_fraction * patch.radius)
    f0, ok0 = value(patch, x0)
    f1, ok1 = value(patch, x1)
    f2, ok2 = value(patch, x2)
    ok = ok0 and ok1 and ok2
    at_start = f0
    calls = int(3)
    sorts = int(2)                       # scipy sorts twice before its loop, then once after each step
    while ok and sorts > 0:
        if before(f1, f0):
            x0, x1, f0, f1 = swapped(x0, x1, f0, f1)
        if before(f2, f1):
            x1, x2, f1, f2 = swapped(x1, x2, f1, f2)
            if before(f1, f0):
                x0, x1, f0, f1 = swapped(x0, x1, f0, f1)
        sorts -= 1
        if sorts == 0 and calls < maxfev:
            if (wp.abs(x1[0] - x0[0]) <= xatol and wp.abs(x1[1] - x0[1]) <= xatol and wp.abs(x2[0] - x0[0]) <= xatol
                    and wp.abs(x2[1] - x0[1]) <= xatol and wp.abs(f0 - f1) <= fatol and wp.abs(f0 - f2) <= fatol):
                break
            # a step: the centroid of the best two summed from +0.0, then scipy's trial points in its order,
            # each while evaluations last (one past maxfev ends the step where it stands)
            xbar = wp.vec2d(((zero + x0[0]) + x1[0]) / wp.float64(2.0), ((zero + x0[1]) + x1[1]) / wp.float64(2.0))
            xr, fxr, ok = trial(patch, xbar, x2, wp.float64(2.0), wp.float64(1.0))
            calls += 1
            shrink = bool(False)
            if not ok:
                break
            if fxr < f0:
                if calls < maxfev:
                    xe, fxe, ok = trial(patch, xbar, x2, wp.float64(3.0), wp.float64(2.0))
                    calls += 1
                    if not fxe < fxr:       # NaN too: the reflection kept
                        xe = xr
                        fxe = fxr
                    x2 = xe
                    f2 = fxe
            elif fxr < f1:
                x2 = xr
                f2 = fxr
            elif calls < maxfev:
                outside = fxr < f2
                to_centroid = wp.float64(0.5)
                to_worst = wp.float64(-0.5)
                if outside:
                    to_centroid = wp.float64(1.5)
                    to_worst = wp.float64(0.5)
                xc, fxc, ok = trial(patch, xbar, x2, to_centroid, to_worst)
                calls += 1
                if (outside and fxc <= fxr) or (not outside and fxc < f2):
                    x2 = xc
                    f2 = fxc
                else:
                    shrink = True
            if shrink and ok:       # each vertex moved halfway to the best, then judged, while evaluations last
                x1 = halfway(x0, x1)
                if calls < maxfev:
                    f1, ok = value(patch, x1)
                    calls += 1
                    if ok:
                        x2 = halfway(x0, x2)
                        if calls < maxfev:
                            f2, ok = value(patch, x2)
                            calls += 1
            sorts = 1
    decided[k] = wp.where(ok, 1, 0)
    lowest = wp.min(wp.min(f0, f1), f2)
    if wp.isnan(f0) or wp.isnan(f1) or wp.isnan(f2):
        lowest = f0 + f1 + f2                           # np.min's NaN
    step = x0
    if not lowest <= at_start:
        step = wp.vec2d(zero, zero)
    p, face, n = projected(patch.mesh, patch.reach, patch.start, patch.along_x, patch.along_y, step[0], step[1])
    point[k] = p
    normal[k] = n


def specular_search(meshes: "Sequence[WarpMesh]", points: "Sequence[np.ndarray]", normals: "Sequence[np.ndarray]",
                    centers: ArrayLike, along_x: ArrayLike, along_y: ArrayLike, cameras: ArrayLike, lamp: ArrayLike,
                    rim_fraction: float, step_fraction: float, xatol: float, fatol: float,
                    maxfev: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K searches (one a patch: its mesh, dense points and normals (N_k, 3), centre, tangent axes
    and camera (K, 3); one lamp) in one launch, a thread each: (points (K, 3), outward normals
    (K, 3), decided (K,) bool: False where the search met the rim's band and must be searched
    again in Python)."""
    device = ensure_init(__name__)
    k = len(meshes)
    point, point_wp = output((k, 3), np.float64, wp.vec3d)
    normal, normal_wp = output((k, 3), np.float64, wp.vec3d)
    decided, decided_wp = output(k, np.int32, wp.int32)
    if k:
        if min(len(p) for p in points) == 0:
            raise ValueError("a specular search needs a patch of at least one point")
        bounds = np.concatenate([[0], np.cumsum([len(p) for p in points])]).astype(np.int32)
        frames = np.stack([np.asarray(v, dtype=np.float64).reshape(k, 3) for v in (centers, along_x, along_y, cameras)],
                          axis=1).reshape(4 * k, 3)
        joined = np.vstack(points).astype(np.float64), np.vstack(normals).astype(np.float64)
        wp.launch(specular_search_kernel, dim=k, device=device,   # the views' arrays live through the launch
                  inputs=[wp.array(np.array([m.id for m in meshes], dtype=np.uint64), dtype=wp.uint64, device=device),
                          vec3d_view(joined[0], "points"), vec3d_view(joined[1], "normals"),
                          wp.array(bounds, dtype=wp.int32, device=device, copy=False), vec3d_view(frames, "frames"),
                          wp.vec3d(*np.asarray(lamp, dtype=np.float64).reshape(3).tolist()),
                          float(rim_fraction), float(step_fraction), float(xatol), float(fatol), int(maxfev)],
                  outputs=[point_wp, normal_wp, decided_wp])
    return point, normal, decided.astype(bool)
