"""A plan's certificate: the chosen shot checked on the feature patch at the camera's own
sampling density, not only at the search's samples. Gray (with shadows and the cone, clipped at
full scale), visibility in the image and the depth of field are judged at every point by the
same requirements as the search (cell.planning.requirements), at the shot's fixed exposure, and so is
each point's dominant BRDF term (brdf.judged_term, as the search's samples: a lamp where a spike
the goniometer did not resolve may lie is refused at every point). A specular highlight or a
rim point out of focus between the search's samples shows up here; the planner
then adds the worst points to its samples and searches again (cell.planning.one_shot.plan).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.planning import defects, evaluate, requirements
from cell.planning.plan import Verification
from cell.devices import rig
from cell.core import geometry
from cell.physics.costs import RequirementValue

if TYPE_CHECKING:
    from concurrent.futures import Future

    from cell.physics.material import Material
    from cell.planning.plan import Shot
    from cell.planning.scene import Scene
    from cell.task.types import Task

DENSE_MAX = 20_000              # points: a 12 mm patch seen by 93 um pixels needs 13 000
# the requirements that depend on where the points are; the others are judged by the search
JUDGED = ("gray_min", "gray_max", "reflection_region", "no_shadow", "cone_coverage", "camera_view", "view_angle",
          "resolution", "depth_of_field", "defect_cnr")
SIMPLEX_STEP = 0.02             # of the patch's radius: the specular search's first simplex's side
XATOL, FATOL, MAXFEV = 1e-7, 1e-12, 80          # the specular search's ends (scipy's Nelder-Mead options) [m, 1, 1]
ON_PATCH_MARGIN = 1e-9          # of the radius: the band about the rim on_patch decides by np.linalg.norm


def worse_of(values: Iterable[RequirementValue], verification: Verification) -> tuple[RequirementValue, ...]:
    """The requirement values (costs.RequirementValue) on the samples with each the certificate
    judges replaced by its dense value where that is worse: each reported where it is worse."""
    dense = {r.name: r for r in verification.judged}
    return tuple(dense[r.name] if r.name in dense and dense[r.name].value > r.value else r for r in values)


def dense_samples(task: Task, scene: Scene) -> int:
    """Points for the camera's density: the patch's area over a pixel's footprint on it
    (distance x pitch / focal length), at least the search's and at most DENSE_MAX."""
    focus = float(np.linalg.norm(scene.camera_position - scene.center))
    footprint = focus * task.camera.sensor.pixel_pitch_m / task.camera.lens.focal_length_m
    count = np.pi * task.feature.radius_m**2 / footprint**2
    return int(np.clip(count, len(scene.points), DENSE_MAX))


def dense_scene(task: Task, scene: Scene) -> Scene:
    """The dense patch (dense_samples of them) of the one-feature task's feature, seen by `scene`'s
    camera: what verify judges a search's Problem (task, scene) on."""
    from cell.planning.scene import build_scene
    return build_scene(task, dense_samples(task, scene), T_cell_cam=scene.T_cell_cam)


def mirror_alignment(points: np.ndarray, normals: np.ndarray, lamp: ArrayLike, camera: ArrayLike) -> np.ndarray:
    """<v, r> at each point, r the lamp direction s mirrored about the normal (2 <n,s> n - s):
    1 where the mirror direction points at the camera, the spike's peak (eq. 6-7). A component
    at a time (NumPy's operations on (N, 3) arrays against one lamp or camera, in their order:
    the same bits), each sum over x, y, z ((a + b) + c) + 0.0 as geometry.row_sum's: a dense
    patch's 10 000 points without (N, 3) arrays, whose inner loop runs over 3 numbers a point."""
    points, normals = np.asarray(points, float), np.asarray(normals, float)
    lamp, camera = np.asarray(lamp, float), np.asarray(camera, float)
    (px, py, pz), (nx, ny, nz) = (points[..., k] for k in range(3)), (normals[..., k] for k in range(3))
    sx, sy, sz = lamp[..., 0] - px, lamp[..., 1] - py, lamp[..., 2] - pz
    vx, vy, vz = camera[..., 0] - px, camera[..., 1] - py, camera[..., 2] - pz
    s_length = np.sqrt(sx * sx + sy * sy + sz * sz + 0.0)
    v_length = np.sqrt(vx * vx + vy * vy + vz * vz + 0.0)
    sx, sy, sz = sx / s_length, sy / s_length, sz / s_length
    vx, vy, vz = vx / v_length, vy / v_length, vz / v_length
    twice = 2.0 * (nx * sx + ny * sy + nz * sz + 0.0)
    return (twice * nx - sx) * vx + (twice * ny - sy) * vy + (twice * nz - sz) * vz + 0.0


def specular_points(scenes: Sequence[Scene], lamp: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Each scene's patch's specular point, where <v, r> is largest: the best of its dense points,
    refined by Nelder-Mead (scipy's) over a step in the feature's tangent plane projected onto
    the surface (a highlight between the dense points, on a curved patch, is found to within
    float32); the step back to that best dense point where the search ends no better. Returns
    (points (K, 3), outward normals (K, 3)) on the surface. The K searches run in one launch, a
    thread each (kernels.specular: scipy's arithmetic and this module's <v, r> and on_patch, the
    same bits); a search whose point fell in on_patch's band at the rim, where np.linalg.norm's
    rounding decides, is searched again here (specular_point_alone)."""
    from kernels.specular import specular_search
    points, normals, decided = specular_search(
        [s.warp_mesh for s in scenes], [s.points for s in scenes], [s.normals for s in scenes],
        [s.center for s in scenes], [s.frame[:, 0] for s in scenes], [s.frame[:, 1] for s in scenes],
        [s.camera_position for s in scenes], lamp, ON_PATCH_MARGIN, SIMPLEX_STEP, XATOL, FATOL, MAXFEV)
    for k in np.flatnonzero(~decided).tolist():
        points[k], normals[k] = specular_point_alone(scenes[k], lamp)
    return points, normals


def specular_point_alone(scene: Scene, lamp: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """specular_points of one patch, searched in Python: scipy's Nelder-Mead over the step, each
    point projected by its own closest_points query and judged by alignment_at, off the patch by
    on_patch (np.linalg.norm's decision at the rim)."""
    from scipy.optimize import minimize

    from kernels.proximity import closest_points
    offsets = geometry.by_component(np.subtract, scene.points, scene.center)
    radius = math.sqrt(float(np.max(geometry.dot3(offsets, offsets))))
    start = scene.points[int(np.argmax(mirror_alignment(scene.points, scene.normals, lamp, scene.camera_position)))]
    lamp_at, camera, center = np.asarray(lamp, float).tolist(), scene.camera_position.tolist(), scene.center.tolist()

    def at(step: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        query = start + step[0] * scene.frame[:, 0] + step[1] * scene.frame[:, 1]
        point, _, normal = closest_points(scene.warp_mesh, query[None], max_dist=radius)
        if not on_patch(point[0].tolist(), center, radius):
            return point[0], normal[0], 2.0
        return point[0], normal[0], -alignment_at(point[0].tolist(), normal[0].tolist(), lamp_at, camera)

    d = SIMPLEX_STEP * radius
    found = minimize(lambda step: at(step)[2], np.zeros(2), method="Nelder-Mead",
                     options={"initial_simplex": [[0.0, 0.0], [d, 0.0], [0.0, d]], "xatol": XATOL, "fatol": FATOL,
                              "maxfev": MAXFEV})
    point, normal, _ = at(found.x if found.fun <= at(np.zeros(2))[2] else np.zeros(2))
    return point, normal


def on_patch(point: list[float], center: list[float], radius: float) -> bool:
    """|point - center| <= radius as the 3-vector's np.linalg.norm decides it (the root of a
    BLAS dot product, whose rounding a sum of squares need not share): the sum of squares'
    root where that is clearly on or off (more than ON_PATCH_MARGIN of the radius from it, far
    beyond an ulp's difference), np.linalg.norm's own near the rim (and for NaN: off)."""
    dx, dy, dz = point[0] - center[0], point[1] - center[1], point[2] - center[2]
    distance = math.sqrt((dx * dx + dy * dy) + dz * dz)
    if abs(distance - radius) > ON_PATCH_MARGIN * radius:
        return distance <= radius
    return bool(np.linalg.norm(np.array([dx, dy, dz])) <= radius)


def alignment_at(point: list[float], normal: list[float], lamp: list[float], camera: list[float]) -> float:
    """mirror_alignment at one point, in Python floats: the same IEEE operations in the same
    order, each sum of three ((a + b) + c) + 0.0 as geometry.row_sum's, so the same
    bits (tests/test_certificate.py holds them equal); NumPy's own (NaN) where the lamp or the
    camera is at the point."""
    (px, py, pz), (nx, ny, nz) = point, normal
    sx, sy, sz = lamp[0] - px, lamp[1] - py, lamp[2] - pz
    vx, vy, vz = camera[0] - px, camera[1] - py, camera[2] - pz
    s_length = math.sqrt(((sx * sx + sy * sy) + sz * sz) + 0.0)
    v_length = math.sqrt(((vx * vx + vy * vy) + vz * vz) + 0.0)
    if not (s_length > 0.0 and v_length > 0.0):
        return float(mirror_alignment(np.array([point]), np.array([normal]), lamp, camera)[0])
    sx, sy, sz = sx / s_length, sy / s_length, sz / s_length
    vx, vy, vz = vx / v_length, vy / v_length, vz / v_length
    twice = 2.0 * (((nx * sx + ny * sy) + nz * sz) + 0.0)
    return (((twice * nx - sx) * vx + (twice * ny - sy) * vy) + (twice * nz - sz) * vz) + 0.0


def verify(problem: evaluate.Problem, shot: Shot) -> tuple[Verification, np.ndarray]:
    """(Verification of the shot on the dense patch, its worst points to add to the search's
    samples). problem: the search's Problem (its maps and albedo scale are kept)."""
    return verify_all([problem], shot)[0]


def verify_all(problems: Sequence[evaluate.Problem], shot: Shot,
               dense: Sequence[Future[Scene]] | None = None) -> list[tuple[Verification, np.ndarray]]:
    """verify of `shot` on each Problem, of one part's features seen by the shot's camera (their
    mesh, lamp, camera and material as planned the same), together (lit: their specular points
    and the gray kernel on every dense patch launched once for all). `dense`: each Problem's
    dense_scene being made (kernels.runtime.in_background), else made here."""
    if not problems:
        return []
    scenes = ([d.result() for d in dense] if dense is not None else
              [dense_scene(p.task, p.scene) for p in problems])
    patches, shared = lit(problems[0].task, problems[0].material, shot, scenes)
    return verdicts(problems, shot, patches, shared)


def lit(task: Task, material: Material, shot: Shot, scenes: Sequence[Scene],
        beside: bool = False) -> tuple[list[Scene], evaluate.SharedLaunches]:
    """The dense patches `scenes` of one part's features seen by the shot's camera, each with
    its specular point last (specular_points: their searches in one launch), and the gray kernel
    over all of them (evaluate.SharedLaunches: each patch's values as its own launch's). With
    `beside`, its launch at the shot's lamp and the camera's shadow flags are begun on a thread
    beside (SharedLaunches.begin), for a caller that judges the samples meanwhile; else each is
    launched when asked, split over the process's threads (verify_all: nothing to do meanwhile)."""
    points, normals = specular_points(scenes, shot.lamp_position)
    patches = [replace(s, points=np.vstack([s.points, point]), normals=np.vstack([s.normals, normal]))
               for s, point, normal in zip(scenes, points, normals)]
    joined = replace(patches[0], points=np.vstack([s.points for s in patches]),
                     normals=np.vstack([s.normals for s in patches]))
    counts = [len(s.points) for s in patches]
    ends = np.cumsum(counts).tolist()
    shared = evaluate.SharedLaunches(evaluate.gray_inputs(task, joined, material,
                                                          flat=list(zip([0] + ends[:-1], ends))), counts)
    if beside:
        lamp = np.asarray(shot.lamp_position, float).reshape(1, 3)
        shared.begin(lamp, rig.lamp_aim(task.lamp.rig.pivot_m, lamp), joined.camera_position)
    return patches, shared


def verdicts(problems: Sequence[evaluate.Problem], shot: Shot, patches: Sequence[Scene],
             shared: evaluate.SharedLaunches, which: Sequence[int] | None = None) -> list[tuple[Verification, np.ndarray]]:
    """dense_verdict of each Problem on its patch (lit's; `which`: their indices among lit's,
    default in order)."""
    which = range(len(problems)) if which is None else which
    return [dense_verdict(p, patches[k], shot, shared.rows(k)) for p, k in zip(problems, which)]


def dense_verdict(problem: evaluate.Problem, scene: Scene, shot: Shot,
                  rows: evaluate.Rows) -> tuple[Verification, np.ndarray]:
    """verify's result on the dense `scene` (its specular point last), its gray kernel's `rows`."""
    task = problem.task
    dense = evaluate.build_problem(task, scene, problem.maps, focus_m=problem.focus_m, material=problem.material,
                                   gray=rows)
    off = () if shot.drive is None else tuple(int(k) for k in np.flatnonzero(shot.drive[1:] <= 0.0))
    dense = replace(dense, kappa_open=problem.kappa_open,
                    lights_off=off)         # the lights at drive 0 add nothing: not computed on the dense patch
    c = evaluate.at_exposure(dense, shot.lamp_position, shot.exposure.shutter_s, shot.exposure.f_number,
                             drive=shot.drive)
    ln = {name: v for name, v in requirements.ln_values(dense, c).items() if name in JUDGED}
    judged = tuple(replace(r, detail=f"on the dense patch ({len(scene.points)} points): {r.detail}")
                   for r in requirements.judged(dense, c, ln))
    gray = np.minimum(c.gray[0], 2.0 ** task.camera.sensor.bit_depth - 1)
    low, high = dense.band
    miss = np.maximum(low - c.gray[0], c.gray[0] - high)
    depths = scene.sample_depths()
    specular = len(scene.points) - 1                # the extra point: specular_points's
    worst = int(np.argmax(miss))
    picks = {worst, specular, int(np.argmin(c.gray[0])), int(np.argmax(c.gray[0])), int(np.argmin(depths)),
             int(np.argmax(depths))} | set(np.flatnonzero(c.shadowed[0])[:4].tolist())
    picks |= set(np.flatnonzero(requirements.wrong_reflection(dense, c)[0])[:4].tolist())
    found = defects.judge(dense, c) if task.feature.defects else ()
    picks |= {int(np.argmin(np.linalg.norm(scene.points - d.position_m, axis=1))) for d in found}
    result = Verification(all(r.met for r in judged), len(scene.points), float(gray.min()), float(gray.max()),
                          scene.points[worst], float(gray[worst]), scene.points[specular], float(gray[specular]),
                          judged, defects=found)
    return result, scene.points[sorted(picks)]
