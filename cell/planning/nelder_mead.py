"""scipy.optimize.minimize(method="Nelder-Mead") as a generator: it yields each point whose
value it needs and is sent that value, so that several searches can run in lockstep in one
thread (cell.planning.lockstep.drive: one batched evaluation a round, no thread handing the
GIL to another for every point, which costs more than a cheap objective).

The same arithmetic, step for step, as scipy 1.17's _minimize_neldermead without bounds, not
adaptive, with an initial simplex and maxfev (maxiter unlimited): reflection, expansion, outside
and inside contraction and shrink with rho = 1, chi = 2, psi = 0.5, sigma = 0.5; the simplex
sorted by np.argsort after each step; an evaluation past maxfev ends the step where it stands
(a shrink keeps the vertices it moved before it). The same points are asked in the same order
and the result is the same bit for bit (tests/test_lockstep.py holds it to scipy's).
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
from numpy.typing import ArrayLike

Search = Generator[np.ndarray, float, tuple[np.ndarray, float, int]]

RHO, CHI, PSI, SIGMA = 1, 2, 0.5, 0.5


class _Exhausted(Exception):
    """An evaluation asked beyond maxfev (scipy's _MaxFuncCallError)."""


def minimize(initial_simplex: ArrayLike, xatol: float, fatol: float, maxfev: int) -> Search:
    """Nelder-Mead from `initial_simplex` (N + 1, N) until the simplex is within xatol of its
    best vertex and its values within fatol of the best, or maxfev evaluations: yields each point
    (a copy) to be sent its value; returns (x, f(x), evaluations), scipy's res.x, res.fun, res.nfev."""
    sim = np.asarray(np.atleast_2d(initial_simplex).copy(), dtype=float)
    n = sim.shape[1]
    calls = 0

    def evaluate(x: np.ndarray) -> Generator[np.ndarray, float, float]:
        nonlocal calls
        if calls >= maxfev:
            raise _Exhausted
        calls += 1
        return (yield np.copy(x))

    fsim = np.full((n + 1,), np.inf, dtype=float)
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
                    for j in range(1, n + 1):
                        sim[j] = sim[0] + SIGMA * (sim[j] - sim[0])
                        fsim[j] = yield from evaluate(sim[j])
        except _Exhausted:
            pass
        ind = np.argsort(fsim)
        sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    return sim[0], float(np.min(fsim)), calls
