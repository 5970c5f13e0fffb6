"""The order in which a run visits its shots: the shortest open path from the start pose through
every shot once, a leg's travel the camera's distance plus the lamp's (straight lines in the cell
frame: a stand-in for the arm's and the servos' motion). Exact by Held-Karp's dynamic programme
over subsets, O(n^2 2^n), up to EXACT_MAX shots; beyond, 2-opt and Or-opt local search from
nearest neighbour's order and from random ones, so never longer than nearest neighbour. (LKH-3,
through elkai, is free for non-commercial use only: not a dependency of a product integrators
ship; OR-Tools' routing would bring pandas and protobuf and, limited by time, an order that
depends on the machine's load.)"""
from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

Positions = tuple[np.ndarray, np.ndarray | None]    # (camera, lamp) in the cell frame [m]; the lamp's may be unknown

EXACT_MAX = 12              # 2^12 subsets x 12^2 in NumPy: about 4 ms (15 shots: 0.1 s; each shot more doubles it)
RESTARTS = 8                # random starts of the local search besides nearest neighbour's


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
    return "exact" if n <= EXACT_MAX else "2-opt and Or-opt local search from nearest neighbour's and random orders"


def shortest_order(D: np.ndarray) -> tuple[int, ...]:
    """The order (a tuple of stop indices) of the shortest open path from the start through every
    stop of travel_matrix D: exact (held_karp) for up to EXACT_MAX stops, heuristic_order beyond."""
    return held_karp(D) if len(D) - 1 <= EXACT_MAX else heuristic_order(D)


def heuristic_order(D: np.ndarray) -> tuple[int, ...]:
    """The shortest of local_search's optima from nearest neighbour's order and from RESTARTS
    random orders (a fixed seed: the same matrix gives the same order): never longer than nearest
    neighbour, since the search only shortens its start."""
    rng = np.random.default_rng(0)
    starts = [nearest_neighbour(D)] + [tuple(rng.permutation(len(D) - 1)) for _ in range(RESTARTS)]
    return min((local_search(D, order) for order in starts), key=lambda order: length(D, order))


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


def local_search(D: np.ndarray, order: Sequence[int]) -> tuple[int, ...]:
    """`order` improved by 2-opt and Or-opt moves until none shortens the path (a local optimum):
    each pass takes the best of every 2-opt move (reverse the stops i..j) and every Or-opt move
    (a run of 1-3 stops moved elsewhere, its direction kept). The open path is closed by an end
    node whose legs cost nothing, so both ends stay fixed and no move needs a special case; a
    reversed run's legs are read from the matrix's transpose, so asymmetric travel is exact."""
    n = len(D) - 1
    ext = np.zeros((n + 2, n + 2))
    ext[:n + 1, :n + 1] = D
    path = np.array([0, *(i + 1 for i in order), n + 1])
    i, j = np.triu_indices(n + 1, 1)
    two = (i >= 1) & (j <= n)
    i, j = i[two], j[two]
    while n >= 2:
        legs, back = ext[path[:-1], path[1:]], ext[path[1:], path[:-1]]
        F, B = np.concatenate([[0.0], np.cumsum(legs)]), np.concatenate([[0.0], np.cumsum(back)])
        p = path
        flip = (ext[p[i - 1], p[j]] + ext[p[i], p[j + 1]] - legs[i - 1] - legs[j]
                + (B[j] - B[i]) - (F[j] - F[i]))
        best, move = 0.0, None                      # move (a, e, c): stops a..e moved after c; c -1: reversed
        if len(flip):
            f = int(np.argmin(flip))
            best, move = float(flip[f]), (int(i[f]), int(j[f]), -1)
        k = np.arange(n + 1)
        for length_ in (1, 2, 3):
            for a in range(1, n - length_ + 2):
                e = a + length_ - 1
                gain = legs[a - 1] + legs[e] - ext[p[a - 1], p[e + 1]]
                where = (k < a - 1) | (k > e)
                cost = ext[p[k], p[a]] + ext[p[e], p[k + 1]] - legs[k] - gain
                cost[~where] = np.inf
                c = int(np.argmin(cost))
                if cost[c] < best:
                    best, move = float(cost[c]), (a, e, c)
        if move is None or best >= -1e-12 * max(float(F[-1]), 1e-300):
            break
        a, e, c = move
        if c < 0:
            path = np.concatenate([p[:a], p[a:e + 1][::-1], p[e + 1:]])
        else:
            run, rest = p[a:e + 1], np.concatenate([p[:a], p[e + 1:]])
            at = c + 1 if c < a else c + 1 - len(run)       # c's position in rest, the run after it
            path = np.concatenate([rest[:at], run, rest[at:]])
    return tuple(int(x) - 1 for x in path[1:-1])


def nearest_neighbour(D: np.ndarray) -> tuple[int, ...]:
    """From the start, always to the nearest stop not yet visited."""
    left, here, order = set(range(len(D) - 1)), 0, []
    while left:
        here = min(left, key=lambda i: D[here, i + 1]) + 1
        order.append(here - 1)
        left.remove(here - 1)
    return tuple(order)
