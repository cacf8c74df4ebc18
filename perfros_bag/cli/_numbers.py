"""The one check of every numeric flag: a finite number in its range, before the verb starts.

Every verb goes through :func:`perfros_bag.cli._app.command`, whose wrapper calls
:func:`check_numbers` with the parsed flags before the verb's body runs (before any file
is read or any process started). A number flag is ``> 0`` unless :data:`RANGES` says
otherwise; NaN and infinity are refused everywhere (``nan <= 0`` is False, so a plain
``<= 0`` test lets them through).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import InputError

if TYPE_CHECKING:
    from typer import _click as click


@dataclass(frozen=True)
class Range:
    """A closed or left-open interval ``low .. high`` (no ``high``: unbounded above)."""

    low: float = 0.0
    low_open: bool = True
    high: float | None = None
    text: str | None = None  # how the message says it, when not "a finite number ..."

    def admits(self, x: float) -> bool:
        if not math.isfinite(x):
            return False
        if x < self.low or (self.low_open and x == self.low):
            return False
        return self.high is None or x <= self.high

    def describe(self, whole: bool = False) -> str:
        """``a finite number > 0`` (``a whole number ...`` for an integer flag), or its text."""
        if self.text is not None:
            return self.text
        low = f"{'>' if self.low_open else '>='} {self.low:g}"
        kind = "a whole number" if whole else "a finite number"
        return f"{kind} {low}" + ("" if self.high is None else f" and <= {self.high:g}")


#: The default range of a number flag.
POSITIVE = Range()

#: Number flags whose range is not ``> 0``: ``"VERB --flag"`` (``"casestudy run --flag"``
#: for a sub-command) or ``"--flag"`` for every verb that has it.
RANGES: Mapping[str, Range] = {
    "--tolerance": Range(0.0, low_open=False),  # a deviation in %: 0 passes only a perfect run
    "--latency-tolerance": Range(0.0, low_open=False),  # watch: a chain's p95 drift in %
    "solve --problem": Range(1, low_open=False, high=2, text="1 or 2"),
    "record-cpu --duration": Range(0.0, low_open=False),
    "record-cpu --interval": Range(0.01, low_open=False),
    "sweep --interval": Range(0.05, low_open=False),
    "sweep --repeat-off-speed": Range(1, low_open=False, high=5),
    "casestudy run --duration": Range(1.0, low_open=False),
    "casestudy run --units-per-core": Range(1.0, low_open=False),
    "casestudy run --headroom": Range(0.05, low_open=False, high=2.0),
}


def flag_range(verb: str, flag: str) -> Range:
    """The range of ``flag`` of ``verb`` (``"casestudy run"`` for a sub-command)."""
    return RANGES.get(f"{verb} {flag}") or RANGES.get(flag) or POSITIVE


def check_numbers(ctx: click.Context, values: Mapping[str, Any]) -> None:
    """Raise an :class:`InputError` naming the first number flag of ``ctx``'s command whose
    value in ``values`` (the parsed keyword arguments) is not finite or out of its range."""
    verb = " ".join((ctx.command_path or "").split()[1:])  # without the program's name
    for param in ctx.command.params:
        given = values.get(param.name or "")
        items = given if isinstance(given, list | tuple) else [given]
        for value in items:
            if not isinstance(value, int | float) or isinstance(value, bool):
                continue
            flag = max(param.opts, key=len)
            allowed = flag_range(verb, flag)
            if not allowed.admits(value):
                raise InputError(None, f"{flag} must be {allowed.describe(isinstance(value, int))}, got {value!r}")
