"""The certificates of several features verified together (certificate.verify_all: their
specular points' searches in lockstep, one shared gray launch over every dense patch) against
each verified alone (certificate.verify), bit for bit."""
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from cell.planning import certificate, one_shot
from cell.planning.scene import build_scene
from cell.task.loader import load_task

TASKS = Path(__file__).resolve().parent.parent / "tasks"


def equal(a, b):
    """a == b exactly: arrays element for element (NaN equal to NaN), dataclasses field by field."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b, equal_nan=True)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(equal(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(equal(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))
    return a == b


@pytest.fixture(scope="module")
def problems_at_one_camera():
    """The bracket's first feature's shot, and each feature's search Problem at that shot's camera
    (a global search, no refinement: the samples, maps and focus a judged feature has)."""
    task = load_task(TASKS / "bracket.yaml")
    settings = replace(one_shot.PlannerSettings(), refine=False)
    say = lambda message: None  # noqa: E731
    plan, _ = one_shot.search(task.with_feature(0), settings, 1.0, np.zeros((0, 3)), say)
    problems = [one_shot.search(task.with_feature(g), settings, 1.0, np.zeros((0, 3)), say, plan.shot.T_cell_cam)[1]
                for g in range(len(task.features))]
    return plan.shot, problems


def test_certificates_verified_together_equal_each_verified_alone(problems_at_one_camera):
    shot, problems = problems_at_one_camera
    together = certificate.verify_all(problems, shot)
    alone = [certificate.verify(p, shot) for p in problems]
    assert len(together) == len(problems) >= 3
    for (v1, worst1), (v2, worst2) in zip(together, alone):
        assert equal(v1, v2) and equal(worst1, worst2)
    counts = [v.points for v, _ in alone]
    assert len(set(counts)) > 1                        # patches of different sizes: the shared rows are sliced
    assert len({v.holds for v, _ in alone}) == 2       # the shot holds on some features, not on others
    assert certificate.verify_all([], shot) == []


def test_specular_points_searched_together_equal_each_searched_alone(problems_at_one_camera):
    """The dense patches of every feature, their specular points for lamps all round: searched
    together (one launch a round) and alone, the same points and normals exactly; each on its
    own patch (within its radius of the centre) and at least as well aligned as its best dense point."""
    shot, problems = problems_at_one_camera
    scenes = [build_scene(p.task, certificate.dense_samples(p.task, p.scene), T_cell_cam=p.scene.T_cell_cam)
              for p in problems]
    centre = np.mean([s.center for s in scenes], axis=0)
    for angle in np.radians([0.0, 70.0, 140.0, 210.0, 280.0]):
        lamp = centre + 0.2 * np.array([np.cos(angle), np.sin(angle), 1.0])
        points, normals = certificate.specular_points(scenes, lamp)
        for k, s in enumerate(scenes):
            point, normal = certificate.specular_points([s], lamp)
            assert np.array_equal(point[0], points[k]) and np.array_equal(normal[0], normals[k])
            assert np.linalg.norm(points[k] - s.center) <= np.max(np.linalg.norm(s.points - s.center, axis=1))
            best_dense = certificate.mirror_alignment(s.points, s.normals, lamp, s.camera_position).max()
            found = certificate.mirror_alignment(points[k:k + 1], normals[k:k + 1], lamp, s.camera_position)[0]
            assert found >= best_dense - 1e-6         # the start re-projected onto the surface (float32)
