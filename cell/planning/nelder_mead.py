"""scipy.optimize.minimize(method="Nelder-Mead") as a generator: it yields each point whose
value it needs and is sent that value, so that several searches can run in lockstep in one
thread (cell.planning.lockstep.drive: one batched evaluation a round, no thread handing the
GIL to another for every point, which costs more than a cheap objective).

The same arithmetic, step for step, as scipy 1.17's _minimize_neldermead without bounds, not
adaptive, with an initial simplex and maxfev (maxiter unlimited): reflection, expansion, outside
and inside contraction and shrink with rho = 1, chi = 2, psi = 0.5, sigma = 0.5; the simplex
sorted by np.argsort after each step; an evaluation past maxfev ends the step where it stands
(a shrink keeps the vertices it moved before it). The same points are asked in the same order
and the result is the same bit for bit (tests/test_lockstep.py holds it to scipy's). `batches`
is the same search asking its points in batches, with `ahead` every point a step may need at
once (the lamp search's refinement: a round of its objective costs about a millisecond whatever
a few more poses add, and half the rounds go).
"""

from __future__ import annotations

from collections.abc import Generator, Sequence

import numpy as np
from numpy.typing import ArrayLike

Search = Generator[np.ndarray, float, tuple[np.ndarray, float, int]]
Batches = Generator[np.ndarray, Sequence[float], tuple[np.ndarray, float, int]]

RHO, CHI, PSI, SIGMA = 1, 2, 0.5, 0.5


class _Exhausted(Exception):
    """An evaluation asked beyond maxfev (scipy's _MaxFuncCallError)."""


def minimize(initial_simplex: ArrayLike, xatol: float, fatol: float, maxfev: int) -> Search:
    """Nelder-Mead from `initial_simplex` (N + 1, N) until the simplex is within xatol of its
    best vertex and its values within fatol of the best, or maxfev evaluations: yields each point
    (a copy) to be sent its value; returns (x, f(x), evaluations), scipy's res.x, res.fun, res.nfev."""
    search = batches(initial_simplex, xatol, fatol, maxfev, ahead=False)
    try:
        points = next(search)
        while True:
            values = []
            for x in points:
                values.append((yield x))
            points = search.send(values)
    except StopIteration as stop:
        return stop.value


def batches(initial_simplex: ArrayLike, xatol: float, fatol: float, maxfev: int, ahead: bool = True) -> Batches:
    """minimize's search asking its points in batches: yields (K, N) points and is sent their K
    values. Without `ahead` each batch is the one point scipy evaluates next. With `ahead`, the
    initial simplex's points come together, each step first asks its reflection, its inside
    contraction and its expansion together (the centroid and the worst vertex fix all three
    before any is evaluated; of the 1407 steps of a 3-feature part's refinements 802 took the
    inside contraction and 259 the expansion, against 94 outside contractions and 252
    reflections kept alone), and a shrink its N moved vertices together; the step then takes
    the values scipy's step reads, in its order, and counts only those against maxfev: the same
    search, result and count, in fewer rounds, for an objective whose value at a point is its
    own whatever else is evaluated with it. The lamp's refinement evaluates a round of poses for
    about 0.4 ms whatever their number and some 30 us more a pose (its requirements' NumPy
    passes, one kernel launch): the expansion asked ahead takes 18 % of the rounds away for 32 %
    more poses (6 features' refinements: 846 -> 692 rounds, 5155 -> 6791 poses; refine_all's CPU
    time 2-22 % less in 6 alternating pairs, median 11 %, at load 21); the outside contraction,
    rarer, is asked when needed.

    The vertices are lists of Python floats, their arithmetic scipy's element by element (IEEE
    double either way: a NumPy call on a 3-vector costs more than its sums), the centroid's sum
    in NumPy's order (np.add.reduce over the rows starts from +0.0 and adds them in turn: rows
    of -0.0 sum to +0.0, where adding them without the +0.0 gives -0.0), the simplex ordered by
    np.argsort of the values (its order among equal values is NumPy's, which Python's sort need
    not share)."""
    sim = [[float(v) for v in row] for row in np.atleast_2d(np.asarray(initial_simplex, dtype=float))]
    n = len(sim[0])
    calls = 0

    def ask(points: list[list[float]]) -> Generator[np.ndarray, Sequence[float], list[float]]:
        if not points:
            return []
        values = yield np.array(points, dtype=float)
        return [float(v) for v in values]

    def evaluate(x: list[float], asked: float | None) -> Generator[np.ndarray, Sequence[float], float]:
        """One evaluation counted against maxfev: its value asked ahead, or asked now."""
        nonlocal calls
        if calls >= maxfev:
            raise _Exhausted
        calls += 1
        if asked is not None:
            return asked
        return (yield from ask([x]))[0]

    def ordered(fsim: list[float]) -> tuple[list[list[float]], list[float]]:
        order = np.argsort(np.array(fsim)).tolist()
        return [sim[k] for k in order], [fsim[k] for k in order]

    fsim = [np.inf] * (n + 1)
    first = (yield from ask(sim[:maxfev])) if ahead else []
    try:
        for k in range(n + 1):
            fsim[k] = yield from evaluate(sim[k], first[k] if k < len(first) else None)
    except _Exhausted:
        pass
    for _ in range(2):                  # scipy sorts twice before its loop
        sim, fsim = ordered(fsim)
    while calls < maxfev:
        try:
            best, worst = sim[0], sim[-1]
            if (all(abs(a - b) <= xatol for row in sim[1:] for a, b in zip(row, best))      # np.max(...) <= xatol,
                    and all(abs(fsim[0] - f) <= fatol for f in fsim[1:])):                  # NaN failing it as there
                break
            total = [0.0] * n                       # scipy's np.add.reduce(sim[:-1], 0): from +0.0, a row at a time
            for row in sim[:-1]:
                total = [t + x for t, x in zip(total, row)]
            xbar = [t / n for t in total]
            xr = [(1 + RHO) * a - RHO * w for a, w in zip(xbar, worst)]
            xcc = [(1 - PSI) * a + PSI * w for a, w in zip(xbar, worst)]
            xe = [(1 + RHO * CHI) * a - RHO * CHI * w for a, w in zip(xbar, worst)]
            fxr_ahead, fxcc_ahead, fxe_ahead = (yield from ask([xr, xcc, xe])) if ahead else (None, None, None)
            fxr = yield from evaluate(xr, fxr_ahead)
            if fxr < fsim[0]:
                fxe = yield from evaluate(xe, fxe_ahead)
                sim[-1], fsim[-1] = (xe, fxe) if fxe < fxr else (xr, fxr)
            elif fxr < fsim[-2]:
                sim[-1], fsim[-1] = xr, fxr
            else:
                shrink = False
                if fxr < fsim[-1]:
                    xc = [(1 + PSI * RHO) * a - PSI * RHO * w for a, w in zip(xbar, worst)]
                    fxc = yield from evaluate(xc, None)
                    if fxc <= fxr:
                        sim[-1], fsim[-1] = xc, fxc
                    else:
                        shrink = True
                else:
                    fxcc = yield from evaluate(xcc, fxcc_ahead)
                    if fxcc < fsim[-1]:
                        sim[-1], fsim[-1] = xcc, fxcc
                    else:
                        shrink = True
                if shrink:
                    moved = [[b + SIGMA * (a - b) for a, b in zip(sim[j], best)] for j in range(1, n + 1)]
                    shrunk = (yield from ask(moved[:maxfev - calls])) if ahead else []
                    for j in range(1, n + 1):
                        sim[j] = moved[j - 1]
                        fsim[j] = yield from evaluate(sim[j], shrunk[j - 1] if j - 1 < len(shrunk) else None)
        except _Exhausted:
            pass
        sim, fsim = ordered(fsim)
    return np.array(sim[0]), float(np.min(fsim)), calls
