"""Solvers in lockstep (cell.planning.lockstep) against the same solvers run alone, the
planner's refinement starts in lockstep against one start at a time, and the generator
Nelder-Mead (cell.planning.nelder_mead) against scipy's (bit for bit)."""
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize

from cell.planning import lockstep, nelder_mead, one_shot
from cell.task.loader import load_task

TASKS = Path(__file__).resolve().parent.parent / "tasks"


def rosenbrock_rows(points):
    """A value per point, each from its own row alone."""
    x = np.array(points, float).reshape(-1, 2)
    return (1.0 - x[:, 0]) ** 2 + 100.0 * (x[:, 1] - x[:, 0] ** 2) ** 2


def nelder_mead_from(start, maxfev):
    def solver(objective):
        res = minimize(lambda z: objective(np.array(z)), start, method="Nelder-Mead", options={"maxfev": maxfev})
        return res.x, res.fun, res.nfev
    return solver


def test_solvers_in_lockstep_end_where_each_ends_alone_and_share_batches():
    starts = [(-1.2, 1.0), (0.0, 0.0), (2.0, -1.0), (1.5, 1.5)]
    fevs = [40, 200, 120, 80]              # they end at different steps: the batch shrinks as they do
    alone = [nelder_mead_from(s, n)(lambda p: float(rosenbrock_rows([p])[0])) for s, n in zip(starts, fevs)]
    sizes = []

    def batch(points):
        sizes.append(len(points))
        return rosenbrock_rows(points)

    together = lockstep.run([nelder_mead_from(s, n) for s, n in zip(starts, fevs)], batch)
    for (x1, f1, n1), (x2, f2, n2) in zip(alone, together):
        assert np.array_equal(x1, x2) and f1 == f2 and n1 == n2
    assert sum(sizes) == sum(n for _, _, n in alone)      # every evaluation asked once
    assert max(sizes) == len(starts) and len(sizes) == max(n for _, _, n in alone)
    assert sizes == sorted(sizes, reverse=True)


def test_a_failing_solver_or_batch_raises_and_leaves_no_one_waiting():
    def failing(objective):
        objective(np.zeros(2))
        raise RuntimeError("solver failed")

    with pytest.raises(RuntimeError, match="solver failed"):
        lockstep.run([failing, nelder_mead_from((0.0, 0.0), 50)], rosenbrock_rows)

    def broken(points):
        raise ValueError("batch failed")

    with pytest.raises(ValueError, match="batch failed"):
        lockstep.run([nelder_mead_from((0.0, 0.0), 50), nelder_mead_from((1.0, 0.0), 50)], broken)
    assert not [t for t in threading.enumerate() if t.name.startswith("lockstep-")]


@pytest.fixture(scope="module")
def searched():
    """The ring task's search (a spot and other lights) without refinement: its Problem and starts."""
    task = load_task(TASKS / "ring.yaml")
    settings = replace(one_shot.PlannerSettings(), refine=False)
    _, problem = one_shot.search(task, settings, 1.0, np.zeros((0, 3)), lambda m: None)
    pan, tilt, radius = one_shot.candidate_grid(task.lamp.rig, settings)
    starts = one_shot.pick_starts(pan, tilt, problem.maps.candidate_objective, settings.starts,
                                  np.radians(2 * settings.pan_step_deg))
    return task, problem, [np.array([pan[k], tilt[k], radius[k]]) for k in starts]


def test_pose_objectives_of_many_poses_equal_each_alone(searched):
    task, problem, starts = searched
    rng = np.random.default_rng(3)
    poses = np.vstack(starts + [x + rng.normal(0, [0.1, 0.1, 0.02]) for x in starts])
    together = one_shot.pose_objectives(problem, poses)
    alone = np.array([one_shot.pose_objectives(problem, x[None])[0] for x in poses])
    assert np.array_equal(together, alone) and np.all(np.isfinite(together))


def test_refinement_starts_in_lockstep_equal_one_start_at_a_time(searched):
    task, problem, starts = searched
    assert len(starts) > 1
    together = one_shot.refine_all(problem, starts, task.lamp.rig)
    alone = [one_shot.refine(x, task.lamp.rig, lambda j: float(one_shot.pose_objectives(problem, j[None])[0]))
             for x in starts]
    for (x1, r1), (x2, r2) in zip(alone, together):
        assert np.array_equal(x1, x2) and r1 == r2


def plateau(points):
    """A value per point: a bowl off-centre, 2 outside a disk around it (as the specular point's
    search off its patch), so that searches reflect, expand, contract and shrink."""
    x = np.array(points, float).reshape(-1, 2)
    bowl = (x[:, 0] - 0.3) ** 2 + 3.0 * (x[:, 1] + 0.2) ** 2 - 0.4 * x[:, 0] * x[:, 1]
    return np.where(np.hypot(x[:, 0], x[:, 1]) <= 0.5, bowl, 2.0)


def test_the_generator_nelder_mead_is_scipys_bit_for_bit():
    """The same points asked in the same order, the same x, f(x) and evaluation count as scipy's
    minimize(method="Nelder-Mead") with an initial simplex, xatol, fatol and maxfev: searches that
    converge and searches that run out of evaluations (some mid-shrink)."""
    rng = np.random.default_rng(7)
    ends = set()
    for objective, start in [(f, x) for f in (rosenbrock_rows, plateau) for x in rng.uniform(-1.0, 1.0, (30, 2))]:
        d = rng.uniform(0.005, 0.3)
        simplex = [start, start + [d, 0.0], start + [0.0, d]]
        maxfev = int(rng.integers(8, 120))
        asked_by_scipy = []

        def f(x):
            asked_by_scipy.append(np.array(x))
            return float(objective([x])[0])

        res = minimize(f, np.zeros(2), method="Nelder-Mead",
                       options={"initial_simplex": simplex, "xatol": 1e-7, "fatol": 1e-12, "maxfev": maxfev})
        search = nelder_mead.minimize(simplex, 1e-7, 1e-12, maxfev)
        asked = []
        try:
            point = next(search)
            while True:
                asked.append(point)
                point = search.send(float(objective([point])[0]))
        except StopIteration as stop:
            x, fun, nfev = stop.value
        assert len(asked) == len(asked_by_scipy) and all(np.array_equal(a, b) for a, b in zip(asked, asked_by_scipy))
        assert np.array_equal(x, res.x) and fun == res.fun and nfev == res.nfev
        ends.add(nfev >= maxfev)
    assert ends == {True, False}


def test_generator_searches_driven_together_end_where_each_ends_alone():
    """lockstep.drive: every round one batch of the points of the searches still running, the
    batches shrinking as searches end; each search's result its own alone."""
    simplices = [[(-1.2, 1.0), (-1.1, 1.0), (-1.2, 1.1)], [(0.0, 0.0), (0.2, 0.0), (0.0, 0.2)],
                 [(2.0, -1.0), (2.5, -1.0), (2.0, -0.5)]]
    fevs = [40, 200, 120]

    def alone(simplex, maxfev):
        return lockstep.drive([nelder_mead.minimize(simplex, 1e-7, 1e-12, maxfev)],
                              lambda asked: rosenbrock_rows([p for _, p in asked]))[0]

    sizes = []

    def batch(asked):
        sizes.append([k for k, _ in asked])
        return rosenbrock_rows([p for _, p in asked])

    together = lockstep.drive([nelder_mead.minimize(s, 1e-7, 1e-12, n) for s, n in zip(simplices, fevs)], batch)
    for (x1, f1, n1), (x2, f2, n2) in zip([alone(s, n) for s, n in zip(simplices, fevs)], together):
        assert np.array_equal(x1, x2) and f1 == f2 and n1 == n2
    assert sizes[0] == [0, 1, 2] and len(sizes) == max(n for _, _, n in together)
    assert [len(s) for s in sizes] == sorted((len(s) for s in sizes), reverse=True)
    assert sum(len(s) for s in sizes) == sum(n for _, _, n in together)
