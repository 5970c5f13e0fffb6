"""Camera-constant fit: a hand-made line G = b + c x, saturation, degenerate input."""
import numpy as np
from hypothesis import given, settings, strategies as st

from cell.calibrate import fit_camera_constant


@settings(max_examples=50, deadline=None)
@given(c=st.floats(1e14, 1e18), black=st.floats(0.0, 20.0), seed=st.integers(0, 2**31 - 1))
def test_fit_recovers_constant_and_black_level_and_ignores_saturated_pairs(c, black, seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.1, 1.0, size=(6, 64)) * 300.0 / c          # gray up to ~300 + black
    gray = black + c * x + rng.normal(0.0, 0.5, x.shape)
    clipped = np.minimum(gray, 255.0)
    fit = fit_camera_constant(x, clipped, 255.0)
    assert fit.saturated == int(np.sum(gray >= 255.0))
    assert fit.used + fit.saturated == x.size
    assert abs(fit.camera_constant / c - 1.0) < 6 * fit.stderr / c + 1e-9
    assert abs(fit.black_level - black) < 2.0
    assert 0.99 < fit.r2 <= 1.0


def test_fit_is_none_when_nothing_usable():
    x = np.full((3, 10), 1e-16)
    assert fit_camera_constant(x, np.full(x.shape, 255.0), 255.0) is None       # all saturated
    assert fit_camera_constant(x, np.full(x.shape, 100.0), 255.0) is None       # no spread in P t
    assert fit_camera_constant(x, np.full(x.shape, np.nan), 255.0) is None      # samples off image
