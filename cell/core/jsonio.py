"""JSON as every file of a run is written: strict (a number that is not finite becomes null,
since JSON has no NaN or Infinity; the data say where, e.g. bench rows' `finite`) and numpy
values as plain numbers and lists."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def plain(value: Any) -> Any:
    """value with numpy arrays and scalars made Python, tuples made lists, NaN/inf made None."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dumps(value: Any, indent: int | None = None) -> str:
    """Strict JSON text of value (see plain); anything else JSON lacks (a path) as its text."""
    return json.dumps(plain(value), indent=indent, allow_nan=False, default=str)
