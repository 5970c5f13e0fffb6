"""Numbers as a person reads them: fixed decimals and a unit, "unlimited" for inf, "over
1,000,000" beyond LARGE; never an exponent, never a 430-digit number. Every sentence a person
reads (cell.report.words, the requirements' explanations) prints its numbers through `number`."""

from __future__ import annotations

import math
from typing import SupportsFloat

LARGE = 1e6          # numbers beyond are said as "over 1,000,000", never in exponent form


def number(x: SupportsFloat, unit: str = "", digits: int = 1) -> str:
    """x with `digits` decimals and its unit; "unlimited" for inf, "over 1,000,000" beyond LARGE,
    "unknown" for NaN."""
    x = float(x)
    if math.isnan(x):
        return "unknown"
    if math.isinf(x):
        return "unlimited" if x > 0 else "none"
    if abs(x) >= LARGE:
        return f"{'over' if x > 0 else 'below'} {'-' * (x < 0)}{LARGE:,.0f}{unit}"
    return f"{x:.{digits}f}{unit}"
