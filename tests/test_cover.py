"""The set cover (cell.planning.set_cover) against brute force over every subset of the candidate shots."""
from itertools import combinations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from cell.planning.set_cover import fewest_shots, tie_break


def brute_force(covers, travel):
    """(fewest shots, least travel among those) over all subsets covering every coverable row."""
    F, S = covers.shape
    need = covers.any(axis=1)
    for k in range(S + 1):
        sums = [sum(travel[s] for s in subset) for subset in combinations(range(S), k)
                if np.array_equal(covers[:, list(subset)].any(axis=1), need)]
        if sums:
            return k, min(sums)


@st.composite
def problems(draw):
    F, S = draw(st.integers(1, 6)), draw(st.integers(1, 7))
    covers = np.array(draw(st.lists(st.lists(st.booleans(), min_size=S, max_size=S), min_size=F, max_size=F)))
    # travel on a coarse grid of values: ties in travel happen too
    travel = np.array(draw(st.lists(st.sampled_from([0.0, 0.1, 0.25, 0.5, 1.0, 3.0]), min_size=S, max_size=S)))
    return covers, travel


@settings(max_examples=150, deadline=None)
@given(problems())
def test_milp_chooses_the_fewest_shots_and_the_least_travel_among_them(problem):
    covers, travel = problem
    cover = fewest_shots(covers, travel)
    chosen = list(cover.chosen)
    assert np.array_equal(covers[:, chosen].any(axis=1), covers.any(axis=1))      # every coverable row
    assert cover.coverable == tuple(np.flatnonzero(covers.any(axis=1)))
    count, least = brute_force(covers, travel)
    assert len(chosen) == count
    assert travel[chosen].sum() <= least + 1e-9
    assert cover.objective == pytest.approx(len(chosen) + tie_break(travel)[chosen].sum(), rel=1e-12)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(0.0, 1e3), min_size=1, max_size=20))
def test_the_tie_break_of_all_shots_together_is_worth_less_than_one_shot(travel):
    assert tie_break(travel).sum() < 1.0 / len(travel)


def test_a_far_shot_covering_two_features_beats_two_near_ones():
    """Hand-made: shot 2 covers both features but travels 100 m; the fewest shots win."""
    assert fewest_shots([[1, 0, 1], [0, 1, 1]], [0.0, 0.0, 100.0]).chosen == (2,)
    assert fewest_shots([[1, 0, 1], [0, 1, 1]], [0.0, 0.0, 100.0]).objective > 1.0


def test_a_feature_no_shot_covers_asks_for_no_shot():
    cover = fewest_shots([[0, 0], [1, 0]], [1.0, 0.0])
    assert cover.chosen == (0,) and cover.coverable == (1,)
    assert fewest_shots([[0, 0]], [0.0, 0.0]).chosen == ()
