"""The search objective's cheap forms against the plain NumPy they replace, bit for bit: the
requirements' smooth max over np.column_stack's table, the exposure's bounds as np.clip's, the
lamp tolerance ring's moves as one (tol cos psi / cos tilt, tol sin psi) per direction."""
from types import SimpleNamespace

import numpy as np

from cell.physics import costs
from cell.planning import evaluate, requirements


def ln_values(rng, count):
    """{name: (C,) ln f_i} with met (-inf), missed, unlit (inf) and constant (broadcast) columns."""
    out = {f"r{k}": rng.normal(0.0, 3.0, count) for k in range(13)}
    out["r3"][::3] = -np.inf
    out["r5"][-1] = np.inf
    out["r7"] = np.broadcast_to(np.float64(-0.25), (count,))
    return out


def test_objective_and_missed_are_those_of_column_stacks_table():
    rng = np.random.default_rng(5)
    for count in (1, 4, 37, 2000):
        values = ln_values(rng, count)
        table = np.column_stack(list(values.values()))
        with np.errstate(invalid="ignore"):
            expected = costs.log_sum_exp(table, axis=-1)
        assert np.array_equal(requirements.objective(values), expected)
        assert np.array_equal(requirements.missed(values), np.any(table > 0.0, axis=-1))


def test_exposure_for_gain_bounds_as_np_clip():
    rng = np.random.default_rng(6)
    gain = np.concatenate([10.0 ** rng.uniform(-9, 1, 200), [np.inf, 0.0, 1e-300]])
    kappa_open, shutter_range, f_range = 2.8, (2e-5, 0.05), (1.4, 16.0)
    shutter, kappa = evaluate.exposure_for_gain(gain, kappa_open, shutter_range, f_range)
    t_need = kappa_open**2 * gain
    with np.errstate(divide="ignore"):
        k = np.where(t_need < shutter_range[0], np.sqrt(shutter_range[0] / gain), kappa_open)
    assert np.array_equal(shutter, np.clip(t_need, *shutter_range))
    assert np.array_equal(kappa, np.clip(k, kappa_open, f_range[1]))


def test_centring_exposure_of_unlit_and_lit_poses():
    rng = np.random.default_rng(7)
    u = 10.0 ** rng.uniform(-3, 4, (9, 20))
    u[2] = 0.0                                   # unlit: inf shutter needed
    u[4, ::2] = 0.0
    shutter, kappa, t_need = evaluate.centring_exposure(u, (80.0, 160.0), 4.0, 2.8, (2e-5, 0.05), (1.4, 16.0))
    darkest = np.where(u > 0, u, np.inf).min(axis=-1)
    u_mid = np.where(np.isfinite(darkest), np.sqrt(np.where(np.isfinite(darkest), darkest, 0.0) * u.max(axis=-1)), 0.0)
    target = evaluate.target_gray((80.0 - 4.0, 160.0 - 4.0))
    gain = np.array([target / m if m > 0 else np.inf for m in u_mid])
    assert np.array_equal(t_need, 2.8**2 * gain) and t_need[2] == np.inf
    assert np.array_equal((shutter, kappa), evaluate.exposure_for_gain(gain, 2.8, (2e-5, 0.05), (1.4, 16.0)))


def test_tolerance_moves_are_the_ring_direction_by_direction():
    tol = np.radians(1.5)
    problem = SimpleNamespace(task=SimpleNamespace(requirements=SimpleNamespace(lamp_tolerance_rad=tol)))
    tilt = np.array([0.0, 0.7, -1.2, np.pi / 2])
    d_pan, d_tilt = evaluate.tolerance_moves(problem, tilt)
    assert d_pan.shape == d_tilt.shape == (evaluate.TOLERANCE_RING, len(tilt))
    for m in range(evaluate.TOLERANCE_RING):
        psi = 2.0 * np.pi * m / evaluate.TOLERANCE_RING
        assert np.array_equal(d_pan[m], tol * np.cos(psi) / np.maximum(np.cos(tilt), 1e-3))
        assert np.array_equal(d_tilt[m], np.full(len(tilt), tol * np.sin(psi)))
    problem.task.requirements.lamp_tolerance_rad = 0.0
    assert [a.shape for a in evaluate.tolerance_moves(problem, tilt)] == [(0, len(tilt))] * 2
