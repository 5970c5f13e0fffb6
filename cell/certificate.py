"""A plan's certificate: the chosen shot checked on the feature patch at the camera's own
sampling density, not only at the search's samples. Gray (with shadows and the cone, clipped at
full scale), visibility in the image and the depth of field are judged at every point by the
same requirements as the search (cell.requirements), at the shot's fixed exposure. A specular
highlight or a rim point out of focus between the search's samples shows up here; the planner
then adds the worst points to its samples and searches again (cell.planner.plan).
"""
from dataclasses import dataclass, replace

import numpy as np

from cell import evaluate, geometry, requirements

DENSE_MAX = 20_000              # points: a 12 mm patch seen by 93 um pixels needs 13 000
# the requirements that depend on where the points are; the others are judged by the search
JUDGED = ("gray_min", "gray_max", "no_shadow", "cone_coverage", "camera_view", "depth_of_field")


@dataclass(frozen=True)
class Verification:
    """The dense check of one shot: `holds` when every point meets every JUDGED requirement;
    the points checked, their gray range, the worst point (farthest out of the band, else the
    one nearest its edge), the specular point (where the mirror direction of the lamp is nearest
    the camera's) and the requirements that failed there."""

    holds: bool
    points: int
    gray_min: float
    gray_max: float
    worst_m: np.ndarray
    worst_gray: float
    specular_m: np.ndarray
    specular_gray: float
    judged: tuple               # costs.RequirementValue of each JUDGED requirement on the dense patch
    rounds: int = 0             # searches again with worst points added

    @property
    def failing(self):
        return tuple(r for r in self.judged if not r.met)

    def to_json(self):
        return {"holds": self.holds, "points": self.points, "gray_min": self.gray_min, "gray_max": self.gray_max,
                "worst": {"position_m": self.worst_m.tolist(), "gray": self.worst_gray},
                "specular": {"position_m": self.specular_m.tolist(), "gray": self.specular_gray},
                "failing": [{"name": r.name, "value": r.value, "detail": r.detail} for r in self.failing],
                "rounds": self.rounds}


def dense_samples(task, scene):
    """Points for the camera's density: the patch's area over a pixel's footprint on it
    (distance x pitch / focal length), at least the search's and at most DENSE_MAX."""
    focus = float(np.linalg.norm(scene.camera_position - scene.center))
    footprint = focus * task.camera.sensor.pixel_pitch_m / task.camera.lens.focal_length_m
    count = np.pi * task.feature.radius_m**2 / footprint**2
    return int(np.clip(count, len(scene.points), DENSE_MAX))


def verify(problem, shot):
    """(Verification of the shot on the dense patch, its worst points to add to the search's
    samples). problem: the search's Problem (its maps and albedo scale are kept)."""
    from cell.scene import build_scene
    task = problem.task
    scene = build_scene(task, dense_samples(task, problem.scene))
    dense = evaluate.build_problem(task, scene, problem.maps, albedo_scale=1.0)
    dense = replace(dense, material=problem.material, focus_m=problem.focus_m, kappa_open=problem.kappa_open)
    c = evaluate.at_exposure(dense, shot.lamp_position, shot.exposure.shutter_s, shot.exposure.f_number)
    ln = {name: v for name, v in requirements.ln_values(dense, c).items() if name in JUDGED}
    judged = tuple(replace(r, detail=f"on the dense patch ({len(scene.points)} points): {r.detail}")
                   for r in requirements.judged(dense, c, ln))
    gray = np.minimum(c.gray[0], 2.0 ** task.camera.sensor.bit_depth - 1)
    low, high = dense.band
    miss = np.maximum(low - c.gray[0], c.gray[0] - high)
    depths = scene.sample_depths()
    s = geometry.unit(shot.lamp_position - scene.points)
    v = geometry.unit(scene.camera_position - scene.points)
    mirror = 2.0 * np.sum(scene.normals * s, axis=-1, keepdims=True) * scene.normals - s
    specular = int(np.argmax(np.sum(mirror * v, axis=-1)))
    worst = int(np.argmax(miss))
    picks = {worst, specular, int(np.argmin(c.gray[0])), int(np.argmax(c.gray[0])), int(np.argmin(depths)),
             int(np.argmax(depths))} | set(np.flatnonzero(c.shadowed[0])[:4].tolist())
    result = Verification(all(r.met for r in judged), len(scene.points), float(gray.min()), float(gray.max()),
                          scene.points[worst], float(gray[worst]), scene.points[specular], float(gray[specular]),
                          judged)
    return result, scene.points[sorted(picks)]
