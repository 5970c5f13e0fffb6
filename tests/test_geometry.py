"""cell.core.geometry's vector norm and row sum against np.linalg.norm and np.sum, bit for bit."""
import numpy as np
import pytest

from cell.core import geometry


@pytest.mark.parametrize("shape, axis", [((7, 3), -1), ((7, 3), 0), ((4, 5, 3), -1), ((4, 5, 3), 1), ((3,), -1)])
def test_norm_is_numpys_bit_for_bit(shape, axis):
    rng = np.random.default_rng(1)
    v = rng.normal(size=shape) * 10.0 ** rng.integers(-100, 100, size=shape)
    v.flat[0] = 0.0
    for keepdims in (False, True):
        assert np.array_equal(geometry.norm(v, axis=axis, keepdims=keepdims),
                              np.linalg.norm(v, axis=axis, keepdims=keepdims))
    assert np.array_equal(geometry.unit(v, axis=axis), v / np.linalg.norm(v, axis=axis, keepdims=True), equal_nan=True)


def test_norm_of_integers_is_of_floats():
    assert np.array_equal(geometry.norm(np.array([[3, 4, 12]])), np.linalg.norm(np.array([[3, 4, 12]]), axis=-1))


@pytest.mark.parametrize("shape", [(20000, 3), (4, 5, 3), (3,)])
def test_row_sum_is_numpys_sum_bit_for_bit(shape):
    """row_sum is np.sum(axis=-1) exactly, from 1e-12 to 1e12, signed zeros, infinities and NaN included."""
    rng = np.random.default_rng(5)
    rows = (rng.normal(size=shape) * 10.0 ** rng.integers(-12, 12, size=shape)).reshape(-1, 3)
    special = [[-0.0, -0.0, -0.0], [-0.0, 0.0, -0.0], [1.0, -1.0, -0.0], [np.inf, 1.0, 2.0], [np.inf, -np.inf, 0.0],
               [np.nan, 1.0, 0.0]]
    rows[:min(len(rows), 6)] = special[:len(rows)]
    rows = rows.reshape(shape)
    with np.errstate(invalid="ignore"):
        expected, found = np.sum(rows, axis=-1), geometry.row_sum(rows)
    assert np.array_equal(found, expected, equal_nan=True)
    assert np.array_equal(np.signbit(found), np.signbit(expected))
