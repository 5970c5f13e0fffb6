"""The search objective's cheap forms against the plain NumPy they replace, bit for bit: the
requirements' smooth max over np.column_stack's table, the exposure's bounds as np.clip's, the
lamp tolerance ring's moves as one (tol cos psi / cos tilt, tol sin psi) per direction."""
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cell.physics import costs
from cell.planning import evaluate, requirements

TASKS = Path(__file__).resolve().parent.parent / "tasks"


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


def all_rows(problem, positions, drive):
    """The reference: lit_by_all of unit_gray over every lamp (nominal and moved alike)."""
    from cell.devices import rig
    return evaluate.lit_by_all(problem, evaluate.unit_gray(problem, positions, rig.lamp_aim(
        problem.task.lamp.rig.pivot_m, positions)), drive)


@pytest.fixture(scope="module", params=["ring", "ring unresolved", "hinge"])
def problems(request, tmp_path_factory):
    """A Problem with two other lights (ring), the same with a material whose spike the goniometer
    did not resolve (its terms judged), and one with the spot alone (hinge)."""
    from cell.planning.scene import build_scene
    from cell.task.loader import load_material, load_task
    from test_unresolved import MEASURED, write_material
    task = load_task(TASKS / f"{request.param.split()[0]}.yaml")
    scene = build_scene(task, 32)
    material = None
    if "unresolved" in request.param:
        material = load_material(write_material(tmp_path_factory.mktemp("m") / "m.yaml", MEASURED))
        assert material.unresolved is not None
    return evaluate.build_problem(task, scene, None, material=material)


def test_candidates_judge_the_nominal_lamps_as_unit_gray_of_every_lamp_does(problems):
    """candidates (the nominal poses judged in full, the tolerance's moved poses their gray alone)
    equal, bit for bit, lit_by_all of unit_gray over all lamps, sliced; with and without the
    tolerance, at the default and at given drives, an unlit pose (behind the part) among them."""
    from cell.devices import rig
    problem = problems
    rng = np.random.default_rng(11)
    lamp_rig = problem.task.lamp.rig
    pan = np.concatenate([rng.uniform(*lamp_rig.pan_range_rad, 6), [0.0]])
    tilt = np.concatenate([rng.uniform(*lamp_rig.tilt_range_rad, 6), [lamp_rig.tilt_range_rad[0]]])
    radius = np.concatenate([rng.uniform(*lamp_rig.radius_range_m, 6), [lamp_rig.radius_range_m[1]]])
    n = len(pan)
    lights = len(problem.task.lights)
    for drive in (None, np.linspace(0.3, 1.0, 1 + lights)):
        for tolerance in (True, False):
            c = evaluate.candidates(problem, pan, tilt, radius, tolerance=tolerance, drive=drive)
            d_pan, d_tilt = (evaluate.tolerance_moves(problem, tilt) if tolerance
                             else (np.zeros((0, n)), np.zeros((0, n))))
            m = len(d_pan)
            positions = rig.lamp_position(lamp_rig.pivot_m, np.concatenate([pan, (pan + d_pan).ravel()]),
                                          np.concatenate([tilt, (tilt + d_tilt).ravel()]),
                                          np.concatenate([radius] * (m + 1)))
            drives = problem.full_drive(n) if drive is None else np.tile(drive, (n, 1))
            u, shadowed, off_axis, dominant = all_rows(problem, positions, np.concatenate([drives] * (m + 1)))
            gain = (c.shutter / c.kappa**2)[:, None]
            b = problem.black_level
            assert np.array_equal(c.gray, b + u[:n] * gain)
            assert np.array_equal(c.moved_gray[:m], b + u[n:].reshape(m, n, u.shape[1]) * gain)
            assert all(np.array_equal(x, y) for x, y in ((c.shadowed, shadowed[:n]), (c.off_axis, off_axis[:n]),
                                                        (c.dominant, dominant[:n]), (c.position, positions[:n])))
            assert c.moved_gray.shape[0] >= m


def test_at_exposure_judges_the_nominal_lamp_as_unit_gray_of_every_lamp_does(problems):
    """at_exposure with the tolerance's moved poses: the same bits as lit_by_all of unit_gray over
    the nominal and the moved lamps together."""
    from cell.devices import rig
    problem = problems
    lamp_rig = problem.task.lamp.rig
    joints = (0.4, 0.9, float(np.mean(lamp_rig.radius_range_m)))
    position = rig.lamp_position(lamp_rig.pivot_m, *joints)
    c = evaluate.at_exposure(problem, position, 0.004, 4.0, joints=joints)
    d_pan, d_tilt = evaluate.tolerance_moves(problem, np.array([joints[1]]))
    positions = np.vstack([position[None]] + [rig.lamp_position(lamp_rig.pivot_m, joints[0] + dp, joints[1] + dt,
                                                                joints[2]).reshape(1, 3) for dp, dt in zip(d_pan, d_tilt)])
    u, shadowed, off_axis, dominant = all_rows(problem, positions, np.tile(problem.full_drive(1), (len(positions), 1)))
    gain, b, m = 0.004 / 4.0**2, problem.black_level, len(positions) - 1
    assert np.array_equal(c.gray, b + u[:1] * gain) and np.array_equal(c.moved_gray[:m], b + u[1:, None] * gain)
    assert all(np.array_equal(x, y[:1]) for x, y in ((c.shadowed, shadowed), (c.off_axis, off_axis),
                                                    (c.dominant, dominant)))
