"""The certificates of several features verified together (certificate.verify_all: one shared
gray launch over every dense patch) against each verified alone (certificate.verify), bit for bit."""
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from cell.planning import certificate, one_shot
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
