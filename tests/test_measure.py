"""The feature's surface gray in a capture: a 5x5 mean within the region keeps shading and
averages pixel noise down 5x (independent expectations: a linear ramp, white noise's sigma/5)."""
import numpy as np

from cell.run.measurement import local_mean


def disk(shape, centre, radius):
    v, u = np.mgrid[:shape[0], :shape[1]]
    return np.hypot(u - centre[0], v - centre[1]) < radius


def test_a_linear_shading_passes_unchanged_inside_the_region():
    mask = disk((120, 160), (80, 60), 50)
    ramp = 100.0 + 0.3 * np.mgrid[:120, :160][1]               # +0.3 gray per pixel across
    inner = disk((120, 160), (80, 60), 47)                      # 5x5 window wholly inside
    np.testing.assert_allclose(local_mean(ramp, mask)[inner], ramp[inner], atol=1e-9)
    edge = mask & ~inner                                        # window cut by the region's edge
    assert np.max(np.abs(local_mean(ramp, mask)[edge] - ramp[edge])) <= 2 * 0.3 + 1e-9
    assert np.all(local_mean(ramp, mask)[~mask] == 0.0)


def test_white_noise_is_averaged_down_five_times():
    rng = np.random.default_rng(3)
    mask = disk((300, 300), (150, 150), 140)
    noise = rng.normal(0.0, 2.0, (300, 300))
    inner = disk((300, 300), (150, 150), 137)
    assert abs(np.std(local_mean(120.0 + noise, mask)[inner]) / (2.0 / 5.0) - 1.0) < 0.05
