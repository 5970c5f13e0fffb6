"""The order of a run's shots (cell.run.route): exact against brute force over every permutation,
the heuristic beyond the exact limit within 2 % of the exact optimum and never longer than nearest
neighbour."""
import itertools

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from cell.run import route


def random_matrix(rng, n, symmetric=True):
    """travel_matrix of a random start and n stops (camera and lamp each in a 1 m cube); not
    symmetric: each leg stretched by its own factor 1-1.5 (a move one way longer than back)."""
    poses = [(rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.5, 0.5, 3)) for _ in range(n + 1)]
    D = route.travel_matrix(poses[0], poses[1:])
    return D if symmetric else D * rng.uniform(1.0, 1.5, D.shape)


def brute_force(D):
    """The shortest open path's length over every permutation of the stops, in NumPy."""
    n = len(D) - 1
    orders = np.array(list(itertools.permutations(range(1, n + 1))))
    starts = np.zeros((len(orders), 1), int)
    paths = np.hstack([starts, orders])
    return float(D[paths[:, :-1], paths[:, 1:]].sum(axis=1).min())


def test_a_leg_is_the_cameras_travel_plus_the_lamps_and_an_unknown_lamp_counts_nothing():
    a = (np.zeros(3), np.array([0.0, 0.0, 1.0]))
    b = (np.array([3.0, 4.0, 0.0]), np.array([0.0, 1.0, 1.0]))
    assert route.leg(a, b) == pytest.approx(5.0 + 1.0)
    assert route.leg((np.zeros(3), np.full(3, np.nan)), b) == pytest.approx(5.0)


@pytest.mark.parametrize("n", range(0, 10))
@pytest.mark.parametrize("symmetric", [True, False])
def test_the_shots_order_is_the_shortest_by_brute_force(n, symmetric):
    rng = np.random.default_rng(n)
    for _ in range(3 if n < 9 else 1):
        D = random_matrix(rng, n, symmetric)
        order = route.shortest_order(D)
        assert sorted(order) == list(range(n))
        if n:
            assert route.length(D, order) == pytest.approx(brute_force(D), abs=1e-12)


@pytest.mark.parametrize("n", range(3, 10))
def test_the_heuristic_finds_the_brute_force_optimum_of_small_instances(n):
    rng = np.random.default_rng(100 + n)
    for symmetric in (True, False):
        D = random_matrix(rng, n, symmetric)
        order = route.heuristic_order(D)
        assert sorted(order) == list(range(n))
        assert route.length(D, order) == pytest.approx(brute_force(D), rel=1e-9)


def neighbours(order):
    """Every order one 2-opt move (a reversed run) or one Or-opt move (a run of 1-3 moved) away,
    written out as lists: the definition local_search's matrix arithmetic must agree with."""
    order = list(order)
    n = len(order)
    for a in range(n):
        for e in range(a + 1, n):
            yield order[:a] + order[a:e + 1][::-1] + order[e + 1:]
    for size in (1, 2, 3):
        for a in range(n - size + 1):
            run, rest = order[a:a + size], order[:a] + order[a + size:]
            for at in range(len(rest) + 1):
                yield rest[:at] + run + rest[at:]


@pytest.mark.parametrize("symmetric", [True, False])
def test_local_search_ends_where_no_single_move_shortens_the_path(symmetric):
    rng = np.random.default_rng(7)
    for n in (2, 5, 14, 25):
        D = random_matrix(rng, n, symmetric)
        start = tuple(rng.permutation(n))
        order = route.local_search(D, start)
        assert sorted(order) == list(range(n))
        best = route.length(D, order)
        assert best <= route.length(D, start) + 1e-12
        assert min(route.length(D, other) for other in neighbours(order)) >= best - 1e-9

def test_the_heuristic_is_within_2_percent_of_held_karps_optimum_up_to_12_shots():
    rng = np.random.default_rng(28)
    for n in range(10, route.EXACT_MAX + 1):
        for symmetric in (True, False):
            for _ in range(4):
                D = random_matrix(rng, n, symmetric)
                exact = route.length(D, route.held_karp(D))
                heuristic = route.length(D, route.heuristic_order(D))
                assert exact - 1e-12 <= heuristic <= 1.02 * exact


def test_held_karp_at_11_shots_beats_nearest_neighbour_where_it_failed_before():
    """The issue's 11 shots: nearest neighbour travelled 4.5 % more than the exact order; here on
    random instances the exact order is never longer, and shorter on most."""
    rng = np.random.default_rng(11)
    ratios = []
    for _ in range(10):
        D = random_matrix(rng, 11)
        ratios.append(route.length(D, route.nearest_neighbour(D)) / route.length(D, route.shortest_order(D)))
    assert min(ratios) >= 1.0 - 1e-12 and sum(r > 1.0 + 1e-9 for r in ratios) >= 5


@settings(max_examples=25, deadline=None)
@given(n=st.integers(route.EXACT_MAX + 1, 40), seed=st.integers(0, 2**32 - 1), symmetric=st.booleans())
def test_beyond_the_exact_limit_the_order_is_never_longer_than_nearest_neighbours(n, seed, symmetric):
    D = random_matrix(np.random.default_rng(seed), n, symmetric)
    order = route.shortest_order(D)
    assert sorted(order) == list(range(n))
    assert route.length(D, order) <= route.length(D, route.nearest_neighbour(D)) + 1e-12


def test_nearest_neighbour_goes_each_time_to_the_nearest_stop_left():
    D = random_matrix(np.random.default_rng(0), 15)
    order, here = route.nearest_neighbour(D), 0
    assert sorted(order) == list(range(15))
    for k, i in enumerate(order):
        assert D[here, i + 1] == min(D[here, j + 1] for j in order[k:])
        here = i + 1


def test_the_open_path_does_not_return_to_the_start():
    """Stops on a line beyond the start: the open path walks out once (length of the farthest),
    where a closed tour would also walk back; a start amid them goes to the nearer end first."""
    line = [(np.array([x, 0.0, 0.0]), None) for x in (0.3, 0.1, 0.5, 0.2, 0.4)]
    for solve in (route.held_karp, route.heuristic_order):
        D = route.travel_matrix((np.zeros(3), None), line)
        assert route.length(D, solve(D)) == pytest.approx(0.5)
        D = route.travel_matrix((np.array([0.35, 0.0, 0.0]), None), line)
        assert route.length(D, solve(D)) == pytest.approx(0.15 + 0.4)
