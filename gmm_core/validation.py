"""Checks shared by the configuration sections: a bad value is a ValueError that names its field."""

from __future__ import annotations

import math
import numbers


def require_number(field: str, value, *, positive: bool) -> float:
    """`value` as a float if it is a finite number, > 0 when `positive` else >= 0."""
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not math.isfinite(value)
        or value < 0
        or (positive and value == 0)
    ):
        raise ValueError(f"{field}: must be a finite number {'> 0' if positive else '>= 0'}, got {value!r}")
    return float(value)


def require_count(field: str, value, minimum: int = 1) -> int:
    """`value` if it is an integer >= `minimum`."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{field}: must be an integer >= {minimum}, got {value!r}")
    return int(value)
