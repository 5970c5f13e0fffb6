"""The order in which a run visits its shots: the shortest open path from the start pose through
every shot once, a leg's travel the camera's distance plus the lamp's (straight lines in the cell
frame: a stand-in for the arm's and the servos' motion). Exact by Held-Karp's dynamic programme
over subsets, O(n^2 2^n), up to EXACT_MAX shots; beyond, the better of nearest neighbour and
LKH-3's Lin-Kernighan search (elkai), so never longer than nearest neighbour."""
from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

Positions = tuple[np.ndarray, np.ndarray | None]    # (camera, lamp) in the cell frame [m]; the lamp's may be unknown

EXACT_MAX = 12              # 2^12 subsets x 12^2 in NumPy: about 4 ms (15 shots: 0.1 s; each shot more doubles it)
LKH_RESOLUTION = 1e-6       # LKH reads integer weights: legs in steps of 1e-6 of the longest leg


def leg(a: Positions, b: Positions) -> float:
    """Travel between two poses (camera position, lamp position) [m]: |camera| + |lamp|; a lamp
    position that is unknown (None or NaN, a manual radius nobody confirmed yet) counts 0."""
    camera = float(np.linalg.norm(np.subtract(a[0], b[0])))
    lamp = np.linalg.norm(np.subtract(a[1], b[1])) if a[1] is not None and b[1] is not None else 0.0
    return camera + (float(lamp) if np.isfinite(lamp) else 0.0)


def travel_matrix(start: Positions, stops: Sequence[Positions]) -> np.ndarray:
    """(n + 1, n + 1) leg lengths, index 0 the start pose, i + 1 stop i."""
    poses = [start, *stops]
    return np.array([[leg(a, b) for b in poses] for a in poses])


def length(D: np.ndarray, order: Sequence[int]) -> float:
    """Travel of visiting stops in `order` from the start (travel_matrix D)."""
    path = [0, *(i + 1 for i in order)]
    return float(sum(D[a, b] for a, b in itertools.pairwise(path)))


def method(n: int) -> str:
    """How shortest_order orders n stops, in a few words for the run's log."""
    return "exact" if n <= EXACT_MAX else "the shorter of Lin-Kernighan's (LKH-3) and nearest neighbour's"


def shortest_order(D: np.ndarray) -> tuple[int, ...]:
    """The order (a tuple of stop indices) of the shortest open path from the start through every
    stop of travel_matrix D: exact (held_karp) for up to EXACT_MAX stops, heuristic_order beyond."""
    return held_karp(D) if len(D) - 1 <= EXACT_MAX else heuristic_order(D)


def heuristic_order(D: np.ndarray) -> tuple[int, ...]:
    """lin_kernighan's order or nearest_neighbour's, whichever is shorter: never longer than
    nearest neighbour, whatever LKH finds."""
    return min((nearest_neighbour(D), lin_kernighan(D)), key=lambda order: length(D, order))


def held_karp(D: np.ndarray) -> tuple[int, ...]:
    """The exact shortest open path from the start over every stop (Held-Karp):
    cost[S, i] = min over j in S - {i} of cost[S - {i}, j] + D[j, i], cost[{i}, i] = D[start, i],
    the subsets S taken by size, each size's in one NumPy step per last stop i."""
    n = len(D) - 1
    if n == 0:
        return ()
    masks = np.arange(1 << n)
    bits = masks[:, None] >> np.arange(n) & 1          # bits[S, i]: stop i in subset S
    size = bits.sum(axis=1)
    cost = np.full((1 << n, n), np.inf)                 # inf: the path cannot end at a stop not in S
    last = np.zeros((1 << n, n), np.intp)
    cost[1 << np.arange(n), np.arange(n)] = D[0, 1:]
    for k in range(2, n + 1):
        layer = masks[size == k]
        for i in range(n):
            S = layer[bits[layer, i] == 1]
            via = cost[S ^ 1 << i] + D[1:, i + 1]      # via[s, j]: over S - {i} ending at j, then to i
            j = np.argmin(via, axis=1)
            cost[S, i], last[S, i] = via[np.arange(len(S)), j], j
    S, j = (1 << n) - 1, int(np.argmin(cost[-1]))
    order = []
    while S:
        order.append(j)
        S, j = S ^ 1 << j, int(last[S, j])
    return tuple(reversed(order))


def lin_kernighan(D: np.ndarray) -> tuple[int, ...]:
    """An open path from the start by LKH-3 (elkai): the tour of the asymmetric matrix whose
    return legs to the start cost nothing is the open path. LKH reads integer weights, so the legs
    are rounded to LKH_RESOLUTION of the longest; the start is index 0 of the tour."""
    import elkai
    n = len(D) - 1
    if n < 2:                               # LKH wants 3 nodes at least
        return tuple(range(n))
    scale = 1.0 / (LKH_RESOLUTION * max(float(D.max()), 1e-12))
    weights = np.rint(D * scale).astype(np.int64)
    weights[:, 0] = 0
    tour = elkai.DistanceMatrix(weights.tolist()).solve_tsp(runs=1)[:-1]    # it closes at the start
    k = tour.index(0)
    return tuple(i - 1 for i in tour[k + 1:] + tour[:k])


def nearest_neighbour(D: np.ndarray) -> tuple[int, ...]:
    """From the start, always to the nearest stop not yet visited."""
    left, here, order = set(range(len(D) - 1)), 0, []
    while left:
        here = min(left, key=lambda i: D[here, i + 1]) + 1
        order.append(here - 1)
        left.remove(here - 1)
    return tuple(order)
