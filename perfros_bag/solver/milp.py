"""A tiny sparse MILP builder (rows kept row-wise, passed to HiGHS in one call) and the one
place a HiGHS model is made (:func:`quiet_highs`): the options every solve of the exact
methods runs with, and stdout kept clean of HiGHS's banner (``--json``)."""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["BIG_MODEL", "HIGHS_OPTIONS", "Milp", "quiet_highs"]

_INF = math.inf
LOG = False  # HiGHS log on stdout (debugging)
# Measured (docs/solvers.md): on the case study these root heuristics cost more than they
# find, since the x-form's LP is tight; switching them off sped Table II instance 6 up 2.7x.
# Above this many columns HiGHS's MIP presolve (probing) costs more than it saves: 23 s of
# a 40 s run on 200 nodes x 20 computers (80,000 columns), against 0.2 s with it off.
BIG_MODEL = 20_000
HIGHS_OPTIONS: dict[str, Any] = {
    "mip_heuristic_run_rins": False,
    "mip_heuristic_run_rens": False,
    "mip_heuristic_run_root_reduced_cost": False,
}


@contextlib.contextmanager
def _stdout_silenced(silence: bool = True) -> Iterator[None]:
    """File descriptor 1 points to /dev/null inside (C and C++ code writing to stdout, such as
    HiGHS's banner, write nothing there); stdout is restored, C stdio flushed, on exit.
    ``--json`` output must be the document only."""
    if not silence:
        yield
        return
    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    try:
        saved = os.dup(1)
    except OSError:  # no stdout at all: nothing to protect
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        libc.fflush(None)  # what the C library buffered goes to /dev/null, not the restored stdout
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def quiet_highs() -> Any:
    """A new ``highspy.Highs()`` with nothing written to stdout: HiGHS >= 1.12 prints its
    banner when one is made, before any option can be set (every HiGHS model of the solvers
    is made here)."""
    import highspy  # lazy: keeps the CLI's start-up fast

    with _stdout_silenced(not LOG):
        return highspy.Highs()


# ---------------------------------------------------------------------------------------------
# A tiny sparse model builder (rows kept row-wise, passed to HiGHS in one call)


@dataclass
class Milp:
    cost: list[float] = field(default_factory=list)
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)
    integer: list[int] = field(default_factory=list)
    row_lo: list[float] = field(default_factory=list)
    row_hi: list[float] = field(default_factory=list)
    start: list[int] = field(default_factory=lambda: [0])
    index: list[int] = field(default_factory=list)
    value: list[float] = field(default_factory=list)

    def var(self, lo: float, hi: float, cost: float = 0.0, integer: bool = False) -> int:
        self.cost.append(cost)
        self.lower.append(lo)
        self.upper.append(hi)
        self.integer.append(1 if integer else 0)
        return len(self.cost) - 1

    def row(self, terms: Iterable[tuple[int, float]], lo: float, hi: float) -> int:
        merged: dict[int, float] = {}
        for j, a in terms:
            merged[j] = merged.get(j, 0.0) + a
        for j, a in merged.items():
            if a != 0.0:
                self.index.append(j)
                self.value.append(a)
        self.row_lo.append(lo)
        self.row_hi.append(hi)
        self.start.append(len(self.index))
        return len(self.row_lo) - 1

    def solve(self, maximise: bool, *, time_limit: float | None, mip_gap: float,
              start: dict[int, float] | None = None, relax: bool = False) -> Any:
        """Run HiGHS (``relax``: the LP relaxation); returns the Highs object. ``time_limit``
        counts from this call: passing a big model to HiGHS takes a while (~0.3 s at 1,000 x
        100), which HiGHS's own clock does not count."""
        import highspy  # lazy: keeps the CLI's start-up fast

        entered = time.perf_counter()
        h = quiet_highs()
        h.setOptionValue("output_flag", LOG)
        h.setOptionValue("mip_rel_gap", float(mip_gap))
        h.setOptionValue("mip_abs_gap", 1e-7)
        h.setOptionValue("random_seed", 0)
        for name, value in HIGHS_OPTIONS.items():
            h.setOptionValue(name, value)
        if len(self.cost) > BIG_MODEL:
            h.setOptionValue("presolve", "off")
        if time_limit is not None:
            h.setOptionValue("time_limit", float(max(time_limit, 0.01)))
        inf = highspy.kHighsInf
        fix = np.vectorize(lambda v: inf if v == _INF else (-inf if v == -_INF else v), otypes=[float])
        n_col, n_row = len(self.cost), len(self.row_lo)
        h.passModel(
            n_col, n_row, len(self.index), int(highspy.MatrixFormat.kRowwise),
            int(highspy.ObjSense.kMaximize if maximise else highspy.ObjSense.kMinimize), 0.0,
            np.asarray(self.cost, dtype=np.float64),
            fix(np.asarray(self.lower, dtype=np.float64)) if n_col else np.zeros(0),
            fix(np.asarray(self.upper, dtype=np.float64)) if n_col else np.zeros(0),
            fix(np.asarray(self.row_lo, dtype=np.float64)) if n_row else np.zeros(0),
            fix(np.asarray(self.row_hi, dtype=np.float64)) if n_row else np.zeros(0),
            np.asarray(self.start[:-1] if n_row else [], dtype=np.int32),
            np.asarray(self.index, dtype=np.int32), np.asarray(self.value, dtype=np.float64),
            np.zeros(n_col, dtype=np.int32) if relax else np.asarray(self.integer, dtype=np.int32),
        )
        if start:
            idx = np.fromiter(start.keys(), dtype=np.int32, count=len(start))
            val = np.fromiter(start.values(), dtype=np.float64, count=len(start))
            h.setSolution(len(start), idx, val)
        if time_limit is not None:
            h.setOptionValue("time_limit", float(max(time_limit - (time.perf_counter() - entered), 0.01)))
        h.run()
        return h

