"""Searches in lockstep (cell.planning.lockstep) against the same searches run alone, the
planner's refinement starts in lockstep against scipy's one start at a time, and the generator
Nelder-Mead (cell.planning.nelder_mead) against scipy's (bit for bit)."""
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


def scipy_refinement(start, lamp_rig, objective):
    """The refinement as it was written on scipy's minimize (the reference): (joints, Refinement)."""
    lo = np.array([lamp_rig.pan_range_rad[0], lamp_rig.tilt_range_rad[0], lamp_rig.radius_range_m[0]])
    hi = np.array([lamp_rig.pan_range_rad[1], lamp_rig.tilt_range_rad[1], lamp_rig.radius_range_m[1]])
    scale = np.array([np.radians(5.0), np.radians(5.0), 0.05])
    seen = {}

    def f(z):
        x = np.clip(np.asarray(start) + z * scale, lo, hi)
        if x.tobytes() not in seen:
            seen[x.tobytes()] = objective(x)
        return seen[x.tobytes()]

    res = minimize(f, np.zeros(3), method="Nelder-Mead",
                   options={"initial_simplex": np.vstack([np.zeros(3), np.eye(3)]), "xatol": 0.02, "fatol": 1e-4,
                            "maxfev": one_shot.REFINE_EVALUATIONS})
    return np.clip(np.asarray(start) + res.x * scale, lo, hi), one_shot.Refinement(
        bool(res.success), int(res.nfev), str(res.message), float(res.fun))


def test_refinement_starts_in_lockstep_equal_scipys_one_start_at_a_time(searched):
    """The starts refined together (one_shot.refine_all) against each refined alone by scipy's
    minimize: the same joints, verdict, message, evaluation count and objective, bit for bit; with
    too few evaluations allowed, the out-of-evaluations verdict in scipy's words too."""
    task, problem, starts = searched
    assert len(starts) > 1
    one = lambda j: float(one_shot.pose_objectives(problem, j[None])[0])  # noqa: E731
    for allowed in (one_shot.REFINE_EVALUATIONS, 12):
        one_shot.REFINE_EVALUATIONS, kept = allowed, one_shot.REFINE_EVALUATIONS
        try:
            together = one_shot.refine_all(problem, starts, task.lamp.rig)
            alone = [scipy_refinement(x, task.lamp.rig, one) for x in starts]
        finally:
            one_shot.REFINE_EVALUATIONS = kept
        for (x1, r1), (x2, r2) in zip(alone, together):
            assert np.array_equal(x1, x2) and r1 == r2
        assert {r.success for _, r in together} == ({True} if allowed > 12 else {False})


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


def test_the_centroid_of_negative_zeros_is_scipys_to_the_sign():
    """Simplices whose vertices share -0.0 coordinates: every point asked equal to scipy's, the
    sign of each zero included (the centroid sums from +0.0 as np.add.reduce does)."""
    for simplex in ([[-0.0, -0.0], [-0.0, 0.25], [0.25, -0.0]], [[-0.0, 0.1], [-0.0, -0.0], [0.3, -0.0]],
                    [[-0.0, -0.0, 0.2], [-0.0, 0.3, -0.0], [0.1, -0.0, -0.0], [-0.0, -0.0, -0.0]],
                    [[-0.0, -0.0, -0.0], [0.3, -0.0, -0.0], [-0.0, 0.3, -0.0], [0.2, 0.2, -0.0]]):   # z all -0.0
        asked_by_scipy = []

        def f(x):
            asked_by_scipy.append(np.array(x))
            return float(np.sum((np.asarray(x) - 0.05) ** 2))

        minimize(f, np.zeros(len(simplex[0])), method="Nelder-Mead",
                 options={"initial_simplex": simplex, "xatol": 1e-7, "fatol": 1e-12, "maxfev": 40})
        search = nelder_mead.minimize(simplex, 1e-7, 1e-12, 40)
        asked = []
        try:
            point = next(search)
            while True:
                asked.append(point)
                point = search.send(float(np.sum((point - 0.05) ** 2)))
        except StopIteration:
            pass
        assert len(asked) == len(asked_by_scipy)
        assert all(np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b))
                   for a, b in zip(asked, asked_by_scipy))
        assert any(np.signbit(a).any() for a in asked)      # negative zeros asked, not only given


def test_searches_driven_together_end_where_each_ends_alone():
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


def test_nelder_mead_asking_ahead_is_scipys_in_fewer_rounds():
    """nelder_mead.batches with `ahead` (each step's reflection, inside contraction and expansion asked
    together, a shrink's moved vertices together): scipy's x, f(x) and evaluation count bit for
    bit, every point scipy evaluates among those asked, converging and out of evaluations (some
    mid-shrink), in fewer rounds than points (0.55 of them here; 1 without `ahead`)."""
    rng = np.random.default_rng(8)
    rounds = evaluations = 0
    ends = set()
    for objective, start in [(f, x) for f in (rosenbrock_rows, plateau) for x in rng.uniform(-1.0, 1.0, (30, 2))]:
        d = rng.uniform(0.005, 0.3)
        simplex = [start, start + [d, 0.0], start + [0.0, d]]
        maxfev = int(rng.integers(3, 120))
        by_scipy = []

        def f(x):
            by_scipy.append(np.array(x).tobytes())
            return float(objective([x])[0])

        res = minimize(f, np.zeros(2), method="Nelder-Mead",
                       options={"initial_simplex": simplex, "xatol": 1e-7, "fatol": 1e-12, "maxfev": maxfev})
        search = nelder_mead.batches(simplex, 1e-7, 1e-12, maxfev, ahead=True)
        asked = set()
        try:
            points = next(search)
            while True:
                rounds += 1
                asked.update(p.tobytes() for p in points)
                points = search.send(objective(points))
        except StopIteration as stop:
            x, fun, nfev = stop.value
        assert np.array_equal(x, res.x) and fun == res.fun and nfev == res.nfev
        assert set(by_scipy) <= asked
        evaluations += nfev
        ends.add(nfev >= maxfev)
    assert ends == {True, False} and rounds < 0.6 * evaluations


def rosenbrock_nd(points, dim):
    """Rosenbrock's sum over consecutive coordinates, a value per point (row) alone."""
    x = np.array(points, float).reshape(-1, dim)
    return np.sum((1.0 - x[:, :-1]) ** 2 + 100.0 * (x[:, 1:] - x[:, :-1] ** 2) ** 2, axis=1)


def plateau_nd(points, dim):
    """A bowl, 2 outside a ball around the origin (equal values: the simplex's order among ties)."""
    x = np.array(points, float).reshape(-1, dim)
    bowl = np.sum((x - 0.1 * np.arange(1, dim + 1)) ** 2 * np.arange(1, dim + 1), axis=1) - 0.3 * x[:, 0] * x[:, -1]
    return np.where(np.linalg.norm(x, axis=1) <= 0.6, bowl, 2.0)


@pytest.mark.parametrize("dim", [3, 4])
def test_nelder_mead_in_more_dimensions_is_scipys_bit_for_bit(dim):
    """The lamp's refinement searches 3 joints: the generator Nelder-Mead, one point at a time
    and asking ahead, against scipy's in 3 and 4 dimensions (the centroid sums 3 and 4 rows, whose
    order of additions NumPy's reduction fixes), starts on a 0.1 grid and random ones, simplices
    partly outside the plateau's ball (ties), converging and out of evaluations."""
    rng = np.random.default_rng(20 + dim)
    ends = set()
    grid = [np.round(rng.integers(-6, 7, dim) * 0.1, 1) for _ in range(10)]
    for objective, start in [(f, x) for f in (rosenbrock_nd, plateau_nd)
                             for x in grid + list(rng.uniform(-0.8, 0.8, (15, dim)))]:
        d = rng.choice([0.1, 0.3, rng.uniform(0.005, 0.3)])
        simplex = np.vstack([start, start + d * np.eye(dim)])
        maxfev = int(rng.integers(dim + 1, 200))
        asked_by_scipy = []

        def f(x):
            asked_by_scipy.append(np.array(x))
            return float(objective([x], dim)[0])

        res = minimize(f, np.zeros(dim), method="Nelder-Mead",
                       options={"initial_simplex": simplex, "xatol": 1e-7, "fatol": 1e-12, "maxfev": maxfev})
        one = lockstep.drive([nelder_mead.minimize(simplex, 1e-7, 1e-12, maxfev)],
                             lambda asked: objective([p for _, p in asked], dim))[0]
        asked = []

        def batch(points):
            asked.extend(row.tobytes() for _, p in points for row in p)
            return [objective(p, dim) for _, p in points]

        ahead = lockstep.drive([nelder_mead.batches(simplex, 1e-7, 1e-12, maxfev)], batch)[0]
        for x, fun, nfev in (one, ahead):
            assert np.array_equal(x, res.x) and fun == res.fun and nfev == res.nfev
        assert {p.tobytes() for p in asked_by_scipy} <= set(asked)
        ends.add(res.nfev >= maxfev)
    assert ends == {True, False}
