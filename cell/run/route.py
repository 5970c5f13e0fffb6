"""The order in which a run visits its shots: the shortest open path from the start pose through
every shot once, a leg's travel the camera's distance plus the lamp's (straight lines in the cell
frame: a stand-in for the arm's and the servos' motion). Exact by Held-Karp's dynamic programme
over subsets, O(n^2 2^n), up to EXACT_MAX shots; nearest neighbour beyond."""
from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

Positions = tuple[np.ndarray, np.ndarray | None]    # (camera, lamp) in the cell frame [m]; the lamp's may be unknown

EXACT_MAX = 10              # 2^10 subsets x 10^2: a few ms; the planner's shots are far fewer


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


def shortest_order(D: np.ndarray) -> tuple[int, ...]:
    """The order (a tuple of stop indices) of the shortest open path from the start through every
    stop of travel_matrix D: Held-Karp for up to EXACT_MAX stops, else nearest neighbour."""
    n = len(D) - 1
    if n <= 1:
        return tuple(range(n))
    if n > EXACT_MAX:
        return nearest_neighbour(D)
    # cost[mask][j]: the shortest path from the start over the stops in mask, ending at j (in mask)
    cost = np.full((1 << n, n), np.inf)
    last = np.zeros((1 << n, n), int)
    for j in range(n):
        cost[1 << j, j] = D[0, j + 1]
    for mask in range(1, 1 << n):
        for j in range(n):
            if not mask >> j & 1 or not np.isfinite(cost[mask, j]):
                continue
            for i in range(n):
                if mask >> i & 1:
                    continue
                c = cost[mask, j] + D[j + 1, i + 1]
                if c < cost[mask | 1 << i, i]:
                    cost[mask | 1 << i, i], last[mask | 1 << i, i] = c, j
    mask, j = (1 << n) - 1, int(np.argmin(cost[(1 << n) - 1]))
    order = []
    while mask:
        order.append(j)
        mask, j = mask ^ 1 << j, int(last[mask, j])
    return tuple(reversed(order))


def nearest_neighbour(D: np.ndarray) -> tuple[int, ...]:
    """From the start, always to the nearest stop not yet visited."""
    left, here, order = set(range(len(D) - 1)), 0, []
    while left:
        here = min(left, key=lambda i: D[here, i + 1]) + 1
        order.append(here - 1)
        left.remove(here - 1)
    return tuple(order)
