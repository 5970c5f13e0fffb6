"""The fewest shots covering every feature: a set cover by integer programming
(scipy.optimize.milp, HiGHS's branch and bound, solved to optimality).

  minimise  sum_s x_s (1 + w_s),   w_s = travel_s / (sum_t travel_t + 1) / S
  s.t.      sum_s A_fs x_s >= 1    for every coverable feature f (a row of A with some shot),
            x_s in {0, 1}

A_fs: shot s covers feature f. The tie-break w_s of any selection sums to less than 1 / S, so it
never trades a shot: among the selections with the fewest shots it picks the least travel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import Bounds, LinearConstraint, milp


@dataclass(frozen=True)
class Cover:
    """The chosen shots (ascending indices), the coverable features, the objective."""

    chosen: tuple[int, ...]
    coverable: tuple[int, ...]
    objective: float


def tie_break(travel: ArrayLike) -> np.ndarray:
    """w_s of the module's objective: travel scaled so that all of them sum to less than 1 / S."""
    travel = np.asarray(travel, float)
    return travel / (travel.sum() + 1.0) / max(len(travel), 1)


def fewest_shots(covers: ArrayLike, travel: ArrayLike) -> Cover:
    """Cover of the (F, S) bool matrix `covers` (feature f covered by shot s) with per-shot
    travel (S,) >= 0 [m] breaking ties."""
    covers = np.asarray(covers, bool)
    coverable = np.flatnonzero(covers.any(axis=1))
    cost = 1.0 + tie_break(travel)
    if len(coverable) == 0:
        return Cover((), (), 0.0)
    A = covers[coverable].astype(float)
    res = milp(cost, constraints=LinearConstraint(A, lb=1.0), integrality=np.ones(covers.shape[1]),
               bounds=Bounds(0, 1), options={"mip_rel_gap": 0.0})
    if not res.success:                  # a coverable feature always has a shot: a solver failure
        raise RuntimeError(f"set cover: milp failed: {res.message}")
    chosen = tuple(int(s) for s in np.flatnonzero(res.x > 0.5))
    return Cover(chosen, tuple(int(f) for f in coverable), float(cost[list(chosen)].sum()))
