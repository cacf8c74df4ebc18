"""The stated limits on numbers read from the tool's files, and the one check of them.

Every number read from system.yaml, model.json, plan.json and characterisation.csv must
be finite and at most :data:`MAX_MAGNITUDE` in size: CPU units, frequencies (Hz),
bandwidths (kB/s), performance levels, weights and parameter values of real ROS systems
are many orders of magnitude smaller, and bigger numbers only come from damaged or
hostile files, where they overflow to infinity inside the fits and the solvers (or make
them run without end). Light module: no imports beyond the standard library.
"""

from __future__ import annotations

import math
from typing import Any

#: the largest magnitude a number in an input file may have (10^12).
MAX_MAGNITUDE = 1e12
#: the largest magnitude of a fitted curve's coefficient (the fit refuses bigger ones: a
#: curve whose coefficients cancel at that scale is numerically meaningless)
MAX_COEFFICIENT = 1e15


def as_number(obj: Any) -> float | None:
    """``obj`` as a float when it is an int or a float (not a bool) whose value a float can
    hold; None otherwise (a huge integer does not fit a float)."""
    if isinstance(obj, bool) or not isinstance(obj, int | float):
        return None
    try:
        return float(obj)
    except OverflowError:
        return None


def number_problem(obj: Any, *, positive: bool = False, nonneg: bool = False,
                   limit: float = MAX_MAGNITUDE) -> str | None:
    """What is wrong with ``obj`` as a number read from a file (None: nothing): not a
    number, not finite, bigger than ``limit`` in magnitude, or below 0 / not above 0
    when ``nonneg`` / ``positive``."""
    value = as_number(obj)
    if value is None or not math.isfinite(value):
        return f"must be a finite number, got {short_repr(obj)}"
    if abs(value) > limit:
        return f"must be at most {limit:g} in magnitude, got {value:g}"
    if positive and value <= 0:
        return f"must be > 0, got {obj!r}"
    if nonneg and value < 0:
        return f"must be >= 0, got {obj!r}"
    return None


def short_repr(obj: Any) -> str:
    """``repr(obj)``, shortened: a hostile file may hold a 5,000-digit number."""
    try:
        text = repr(obj)
    except ValueError:  # an int beyond Python's digit limit for str()
        return "an integer too long to print"
    return text if len(text) <= 40 else f"{text[:20]}...({len(text)} characters)"


def tree_problem(value: Any, where: str = "") -> str | None:
    """The first number of a JSON tree (dicts, lists, scalars) that :func:`number_problem`
    refuses, as ``place: problem`` (``nodes[2].cpu: must be ...``); None when all are fine."""
    if isinstance(value, dict):
        for key, item in value.items():
            found = tree_problem(item, f"{where}.{key}" if where else str(key))
            if found is not None:
                return found
    elif isinstance(value, list):
        for i, item in enumerate(value):
            found = tree_problem(item, f"{where}[{i}]")
            if found is not None:
                return found
    elif isinstance(value, float | int) and not isinstance(value, bool):
        problem = number_problem(value)
        if problem is not None:
            return f"{where}: {problem}"
    return None
