"""cell.core.geometry's vector norm against np.linalg.norm, bit for bit."""
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
