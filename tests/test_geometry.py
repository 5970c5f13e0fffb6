"""cell.core.geometry's vector arithmetic (norm, unit, dot3, row_sum, by_component, bounding_sphere) against NumPy's, bit for bit."""
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


def spread(rng, shape):
    """Normal numbers scaled over many decades, some exactly 0 and -0."""
    v = rng.normal(size=shape) * 10.0 ** rng.integers(-30, 30, size=shape)
    v.flat[::17] = 0.0
    v.flat[5::19] = -0.0
    return v


@pytest.mark.parametrize("shape", [(9500, 3), (40, 3), (2, 700, 3), (3,)])
def test_dot3_norm_and_unit_on_many_vectors_are_numpys_bit_for_bit(shape):
    """dot3 against np.sum(x * y, axis=-1), norm and unit against np.linalg.norm, on contiguous
    arrays and on strided views (every other row, a transposed stack's rows)."""
    rng = np.random.default_rng(2)
    x, y = spread(rng, shape), spread(rng, shape)
    if len(shape) == 2:         # rows whose products are all -0.0 (np.sum gives +0.0), or meet inf
        x[:3] = [[-0.0, -0.0, -0.0], [1.0, -0.0, 0.0], [np.inf, 1.0, 0.0]]
        y[:3] = [[1.0, 2.0, 3.0], [-0.0, 1.0, -2.0], [1.0, -np.inf, 1.0]]
    views = [(x, y)] + ([(x[::2], y[::2]), (np.ascontiguousarray(np.moveaxis(x, -1, 0)).T, y.T.T)]
                        if len(shape) == 2 else [])
    for a, b in views:
        with np.errstate(invalid="ignore"):
            found, expected = geometry.dot3(a, b), np.sum(a * b, axis=-1)
            assert np.array_equal(found, expected, equal_nan=True)
            assert np.array_equal(np.signbit(found), np.signbit(expected))
            assert np.array_equal(geometry.norm(a), np.linalg.norm(a, axis=-1))
            assert np.array_equal(geometry.unit(a), a / np.linalg.norm(a, axis=-1, keepdims=True), equal_nan=True)


def test_by_component_is_numpys_broadcast_bit_for_bit():
    """by_component(op, a, b) against op(a, b): many points less one point and one point less many,
    over their lengths (N, 1), a stack against a row of points, and few vectors (one operation)."""
    rng = np.random.default_rng(3)
    many, one, lengths = spread(rng, (9500, 3)), spread(rng, (3,)), np.abs(spread(rng, (9500, 1))) + 1e-300
    stack, row = spread(rng, (4, 500, 3)), spread(rng, (500, 3))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for op in (np.subtract, np.add, np.divide, np.multiply):
            for a, b in ((many, one), (one, many), (many, lengths), (stack, row), (many[:5], one)):
                out = geometry.by_component(op, a, b)
                assert out.shape == op(a, b).shape and np.array_equal(out, op(a, b), equal_nan=True)


def test_bounding_sphere_is_the_bounding_box_middle_and_the_largest_distance():
    """The sphere's middle is the bounding box's (np.min / np.max over the points) and its radius
    the largest np.linalg.norm from it, bit for bit; every point lies within it."""
    rng = np.random.default_rng(4)
    for n in (1, 7, 9500):
        points = rng.normal(size=(n, 3)) * rng.uniform(1e-3, 10.0) + rng.normal(size=3)
        middle, radius = geometry.bounding_sphere(points)
        expected = 0.5 * (points.min(axis=0) + points.max(axis=0))
        assert np.array_equal(middle, expected)
        assert radius == np.linalg.norm(points - expected, axis=1).max()
        assert np.all(np.linalg.norm(points - middle, axis=1) <= radius)


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
