"""Requirement costs of sec. 2.1 / 5 and the log-sum-exp objective (eq. 1, 22-23), with the
erratum of eq. (25): feasibility is max_i f_i <= 1 over the requirement values themselves."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike


EXP_LIMIT = 700.0   # exp(700) ~ 1e304: reported requirement values stay finite however far they miss

# The requirements are computed as ln f_i, uncapped, so that the objective (eq. 22 over ln f_i)
# still ranks poses that miss by e^1000 or by e^100000; only the reported f_i is capped.


def ln_f_max(x: ArrayLike, x_max: float | np.ndarray) -> np.ndarray:
    """ln of eq. (1)'s f_max = exp(x / x_max - 1): <= 0 iff x <= x_max (x_max > 0)."""
    return np.asarray(x, dtype=float) / x_max - 1.0


def ln_f_min(x: ArrayLike, x_min: float | np.ndarray) -> np.ndarray:
    """ln of eq. (1)'s f_min = exp(1 - x / x_min): <= 0 iff x >= x_min (x_min > 0)."""
    return 1.0 - np.asarray(x, dtype=float) / x_min


def ln_count_cost(count: ArrayLike) -> np.ndarray:
    """ln of a requirement that no item fails (shadowed sample, unseen sample), f = 0.5 + count:
    met (<= 1) exactly when count is 0, and never at the boundary 1 when met."""
    return np.log(0.5 + np.asarray(count, dtype=float))


def value(ln_f: ArrayLike) -> np.ndarray:
    """The requirement value f_i = exp(ln f_i) as reported, capped at exp(EXP_LIMIT)."""
    return np.exp(np.minimum(ln_f, EXP_LIMIT))


def log_sum_exp(x: ArrayLike, axis: int = -1) -> np.ndarray:
    """Eq. (22) ln sum exp(x_i) with the max shifted out; max <= lse <= max + ln N (eq. 23)."""
    x = np.asarray(x, dtype=float)
    m = np.max(x, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(over="ignore"):       # a pose missing by more than e^709 sums to inf: worst, as it is
        out = m + np.log(np.sum(np.exp(x - m), axis=axis, keepdims=True))
    return np.squeeze(out, axis=axis)


@dataclass(frozen=True)
class Amount:
    """What a requirement compares, in its own unit, for words a person reads: `actual` against
    `limit`, met when actual <= limit (`at_most`) or actual >= limit (at least); `unit` printed
    after each number ("mm", "deg", "" for a gray level or an f-number), with `digits` decimals."""

    actual: float
    limit: float
    unit: str
    at_most: bool
    digits: int = 1


@dataclass(frozen=True)
class RequirementValue:
    """One requirement's value f_i for a chosen pose (met when <= 1), a sentence a person can act
    on, and where the requirement compares a quantity, that Amount (not in plan.json)."""

    name: str
    value: float
    detail: str = ""
    amount: Amount | None = field(default=None, compare=False)

    @property
    def met(self) -> bool:
        return bool(self.value <= 1.0)


@dataclass(frozen=True)
class Verdict:
    feasible: bool
    binding: str
    miss: float          # max_i f_i - 1: how far the binding requirement misses (<= 0 when met)
    objective: float     # eq. (22) over the log-values ln f_i


def verdict(requirements: Sequence[RequirementValue]) -> Verdict:
    """Feasibility from max_i f_i <= 1 (erratum eq. 25), the binding (largest) requirement and
    the smooth objective lse(ln f_i) that the optimizer minimises."""
    values = np.array([r.value for r in requirements], dtype=float)
    worst = int(np.argmax(values))
    logs = np.log(np.maximum(values, np.finfo(float).tiny))
    return Verdict(feasible=bool(values[worst] <= 1.0), binding=requirements[worst].name,
                   miss=float(values[worst] - 1.0), objective=float(log_sum_exp(logs)))
