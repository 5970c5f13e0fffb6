"""The drives re-solved on basis captures (cell.run.channels) for a shot of several features,
each sample against its own feature's band, held to independent expectations: a brute force over
a grid of drive levels and exposures on the measured shares, the gray recomputed here as
G = b + t / kappa^2 sum_k w_k u_k with u_k = s_k / (w_k x_capture), and the lights of each
feature's plan joined sample by sample."""
import itertools

import numpy as np
import pytest

from cell.planning.plan import LightSetting
from cell.run import channels

GAIN = 0.004 / 2.0**2                # the capture's t / kappa^2 [s]
SHUTTER, F_NUMBERS = (1e-5, 0.02), (1.4, 16.0)


def two_patches(seed=3):
    """Shares of two channels over two patches of 12 samples each (the left asking 60-100, the
    right 150-210: nothing in common): channel 1 lights the left patch most, channel 2 the right;
    the basis captures measured channel 2 at 0.7 of its model and missed the right's first sample
    (off the image: NaN)."""
    rng = np.random.default_rng(seed)
    left, right = 12, 12
    model = np.array([np.r_[rng.uniform(0.8, 1.0, left), rng.uniform(0.1, 0.2, right)],
                      np.r_[rng.uniform(0.05, 0.1, left), rng.uniform(0.8, 1.0, right)]]) * 4e4
    drives = (0.5, 1.0)
    shares = []
    for k, (scale, drive) in enumerate(zip((1.0, 0.7), drives)):
        predicted = model[k] * drive * GAIN
        measured = scale * predicted
        if k == 1:
            measured = measured.copy()
            measured[left] = np.nan
        shares.append(channels.Share(k + 1, (f"bar_{k + 1}",), drive, predicted, measured))
    low = np.r_[np.full(left, 60.0), np.full(right, 150.0)]
    high = np.r_[np.full(left, 100.0), np.full(right, 210.0)]
    return shares, (low, high), left


def test_drives_are_re_solved_with_each_sample_in_its_own_feature_s_band():
    shares, (low, high), left = two_patches()
    black = 2.0
    basis = channels.resolve(shares, GAIN, (low, high), black, 1.4, SHUTTER, F_NUMBERS, {1: (0.0, 1.0), 2: (0.0, 1.0)},
                             {1: False, 2: False}, 0.0)
    assert basis.solved.feasible
    # the measured shares per exposure at full drive, recomputed here; the unseen sample left out
    seen = np.ones(len(low), bool)
    seen[left] = False
    unit = np.array([s.measured / (s.drive * GAIN) for s in shares])[:, seen]
    lo, hi = low[seen], high[seen]
    w, x = basis.solved.drive, basis.solved.shutter_s / basis.solved.f_number**2
    gray = black + x * (w @ unit)
    assert np.all(lo <= gray) and np.all(gray <= hi)
    assert np.min(np.minimum(gray - lo, hi - gray)) == pytest.approx(basis.solved.margin_gray, abs=1e-6)
    # a brute force over drives (every 0.05) and exposures (log-spaced): the program is as good
    gains = np.geomspace(SHUTTER[0] / F_NUMBERS[1]**2, SHUTTER[1] / 1.4**2, 4000)
    best = -np.inf
    for d in itertools.product(np.linspace(0.0, 1.0, 21), repeat=2):
        g = black + gains[:, None] * (np.asarray(d) @ unit)[None]
        best = max(best, float(np.max(np.minimum(g - lo, hi - g).min(axis=1))))
    assert best > 0 and basis.solved.margin_gray >= best - 1e-6
    # the weak channel measured as such
    assert [s.scale for s in shares] == pytest.approx([1.0, 0.7])


def light(name, channel, gray):
    return LightSetting(name, "bar", "fixed", channel, 0.5, np.zeros(3), np.array([0.0, 0.0, -1.0]),
                        np.asarray(gray, float))


def test_the_lights_of_several_features_plans_are_joined_sample_by_sample():
    a = [light("bar_left", 1, [1.0, 2.0]), light("bar_right", 2, [3.0, 4.0])]
    b = [light("bar_left", 1, [5.0]), light("bar_right", 2, [6.0])]
    joined = channels.joined([a, b])
    assert [x.name for x in joined] == ["bar_left", "bar_right"]
    assert joined[0].gray.tolist() == [1.0, 2.0, 5.0] and joined[1].gray.tolist() == [3.0, 4.0, 6.0]
    with pytest.raises(ValueError, match="different lights"):
        channels.joined([a, b[::-1]])
