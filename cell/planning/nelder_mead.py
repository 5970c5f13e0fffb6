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
    initial simplex's points come together, each step first asks its reflection and its inside
    contraction together (the centroid and the worst vertex fix both before either is evaluated;
    the inside contraction is the step's most frequent second point: 802 of the 1407 steps of a
    3-feature part's refinements, against 259 expansions, 94 outside contractions and 252
    reflections kept alone), and a shrink its N moved vertices together; the step then takes
    the values scipy's step reads, in its order, and counts only those against maxfev: the same
    search, result and count, in fewer rounds (each asked point costs its own evaluation, so
    the expansion and the outside contraction, rarer, are asked when needed), for an objective
    whose value at a point is its own whatever else is evaluated with it."""
    sim = np.asarray(np.atleast_2d(initial_simplex).copy(), dtype=float)
    n = sim.shape[1]
    calls = 0
    known: dict[bytes, float] = {}      # values asked ahead, by their point's bytes, each taken once

    def ask(points: np.ndarray) -> Generator[np.ndarray, Sequence[float], None]:
        if len(points):
            values = yield points.copy()
            known.update(zip((p.tobytes() for p in points), (float(v) for v in values)))

    def evaluate(x: np.ndarray) -> Generator[np.ndarray, Sequence[float], float]:
        nonlocal calls
        if calls >= maxfev:
            raise _Exhausted
        calls += 1
        if x.tobytes() not in known:
            yield from ask(x[None])
        return known.pop(x.tobytes())

    fsim = np.full((n + 1,), np.inf, dtype=float)
    if ahead:
        yield from ask(sim[:maxfev])
    try:
        for k in range(n + 1):
            fsim[k] = yield from evaluate(sim[k])
    except _Exhausted:
        pass
    for _ in range(2):                  # scipy sorts twice before its loop
        ind = np.argsort(fsim)
        sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    while calls < maxfev:
        try:
            if (np.max(np.ravel(np.abs(sim[1:] - sim[0]))) <= xatol
                    and np.max(np.abs(fsim[0] - fsim[1:])) <= fatol):
                break
            xbar = np.add.reduce(sim[:-1], 0) / n
            xr = (1 + RHO) * xbar - RHO * sim[-1]
            if ahead:
                known.clear()
                yield from ask(np.array([xr, (1 - PSI) * xbar + PSI * sim[-1]]))
            fxr = yield from evaluate(xr)
            if fxr < fsim[0]:
                xe = (1 + RHO * CHI) * xbar - RHO * CHI * sim[-1]
                fxe = yield from evaluate(xe)
                sim[-1], fsim[-1] = (xe, fxe) if fxe < fxr else (xr, fxr)
            elif fxr < fsim[-2]:
                sim[-1], fsim[-1] = xr, fxr
            else:
                shrink = False
                if fxr < fsim[-1]:
                    xc = (1 + PSI * RHO) * xbar - PSI * RHO * sim[-1]
                    fxc = yield from evaluate(xc)
                    if fxc <= fxr:
                        sim[-1], fsim[-1] = xc, fxc
                    else:
                        shrink = True
                else:
                    xcc = (1 - PSI) * xbar + PSI * sim[-1]
                    fxcc = yield from evaluate(xcc)
                    if fxcc < fsim[-1]:
                        sim[-1], fsim[-1] = xcc, fxcc
                    else:
                        shrink = True
                if shrink:
                    if ahead:
                        known.clear()
                        yield from ask(np.array([sim[0] + SIGMA * (sim[j] - sim[0])
                                                 for j in range(1, n + 1)][:maxfev - calls]).reshape(-1, n))
                    for j in range(1, n + 1):
                        sim[j] = sim[0] + SIGMA * (sim[j] - sim[0])
                        fsim[j] = yield from evaluate(sim[j])
        except _Exhausted:
            pass
        ind = np.argsort(fsim)
        sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    return sim[0], float(np.min(fsim)), calls
