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

from collections.abc import Generator, Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.planning import defects, evaluate, lockstep, nelder_mead, requirements
from cell.planning.plan import Verification
from cell.core import geometry
from cell.physics.costs import RequirementValue

if TYPE_CHECKING:
    from cell.planning.plan import Shot
    from cell.planning.scene import Scene
    from cell.task.types import Task

DENSE_MAX = 20_000              # points: a 12 mm patch seen by 93 um pixels needs 13 000
# the requirements that depend on where the points are; the others are judged by the search
JUDGED = ("gray_min", "gray_max", "reflection_region", "no_shadow", "cone_coverage", "camera_view", "view_angle",
          "resolution", "depth_of_field", "defect_cnr")


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


def mirror_alignment(points: np.ndarray, normals: np.ndarray, lamp: ArrayLike, camera: ArrayLike) -> np.ndarray:
    """<v, r> at each point, r the lamp direction s mirrored about the normal (2 <n,s> n - s):
    1 where the mirror direction points at the camera, the spike's peak (eq. 6-7)."""
    s = geometry.unit(np.asarray(lamp, float) - points)
    v = geometry.unit(np.asarray(camera, float) - points)
    mirror = 2.0 * np.sum(normals * s, axis=-1, keepdims=True) * normals - s
    return np.sum(mirror * v, axis=-1)


def specular_points(scenes: Sequence[Scene], lamp: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Each scene's patch's specular point, where <v, r> is largest: the best of its dense points,
    refined by Nelder-Mead (scipy's, cell.planning.nelder_mead) over a step in the feature's
    tangent plane projected onto the surface (a highlight between the dense points, on a curved
    patch, is found to within float32); the step back to that best dense point where the search
    ends no better. Returns (points (K, 3), outward normals (K, 3)) on the surface. The K
    searches run in lockstep (cell.planning.lockstep.drive): each round's projections of all of
    them in one ClosestPoint launch and their <v, r> in one pass, each value from its own row
    alone, so each search ends where it would alone."""
    from kernels.proximity import ClosestPoint
    radius = [float(np.max(np.linalg.norm(s.points - s.center, axis=1))) for s in scenes]
    starts = np.array([s.points[int(np.argmax(mirror_alignment(s.points, s.normals, lamp, s.camera_position)))]
                       for s in scenes]).reshape(-1, 3)
    along_x = np.array([s.frame[:, 0] for s in scenes]).reshape(-1, 3)
    along_y = np.array([s.frame[:, 1] for s in scenes]).reshape(-1, 3)
    cameras = np.array([s.camera_position for s in scenes]).reshape(-1, 3)
    closest = ClosestPoint([s.warp_mesh for s in scenes], radius)
    queries = starts.copy()

    def place(k: int, step: np.ndarray) -> None:
        """Search k's query: its start moved by `step` in the feature's tangent plane."""
        queries[k] = starts[k] + step[0] * along_x[k] + step[1] * along_y[k]

    def values(asked: list[tuple[int, np.ndarray]]) -> list[float]:
        """-<v, r> at each asked (search, step)'s point on the surface; 2 off its patch (or no surface)."""
        for k, step in asked:
            place(k, step)
        point, _, normal = closest(queries)
        rows = [k for k, _ in asked]
        on = [k for k in rows if np.linalg.norm(point[k] - scenes[k].center) <= radius[k]]
        alignment = dict(zip(on, mirror_alignment(point[on], normal[on], lamp, cameras[on]))) if on else {}
        return [-float(alignment[k]) if k in alignment else 2.0 for k in rows]

    def search(k: int) -> Generator[np.ndarray, float, np.ndarray]:
        d = 0.02 * radius[k]
        x, fun, _ = yield from nelder_mead.minimize([[0.0, 0.0], [d, 0.0], [0.0, d]], 1e-7, 1e-12, 80)
        at_start = yield np.zeros(2)
        return x if fun <= at_start else np.zeros(2)

    for k, step in enumerate(lockstep.drive([search(k) for k in range(len(scenes))], values)):
        place(k, step)
    point, _, normal = closest(queries)
    return point, normal


def verify(problem: evaluate.Problem, shot: Shot) -> tuple[Verification, np.ndarray]:
    """(Verification of the shot on the dense patch, its worst points to add to the search's
    samples). problem: the search's Problem (its maps and albedo scale are kept)."""
    return verify_all([problem], shot)[0]


def verify_all(problems: Sequence[evaluate.Problem], shot: Shot) -> list[tuple[Verification, np.ndarray]]:
    """verify of `shot` on each Problem, of one part's features seen by the shot's camera (their
    mesh, lamp, camera and material as planned the same), together: their specular points'
    searches in lockstep (specular_points) and the gray kernel on every dense patch launched
    once for all (evaluate.SharedLaunches), each patch's values as its own launch's."""
    from cell.planning.scene import build_scene
    if not problems:
        return []
    scenes = [build_scene(p.task, dense_samples(p.task, p.scene), T_cell_cam=p.scene.T_cell_cam) for p in problems]
    points, normals = specular_points(scenes, shot.lamp_position)
    scenes = [replace(s, points=np.vstack([s.points, point]), normals=np.vstack([s.normals, normal]))
              for s, point, normal in zip(scenes, points, normals)]
    joined = replace(scenes[0], points=np.vstack([s.points for s in scenes]),
                     normals=np.vstack([s.normals for s in scenes]))
    shared = evaluate.SharedLaunches(evaluate.gray_inputs(problems[0].task, joined, problems[0].material),
                                     [len(s.points) for s in scenes])
    return [dense_verdict(p, s, shot, shared.rows(k)) for k, (p, s) in enumerate(zip(problems, scenes))]


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
