"""Each setting's CPU error, written by ``fit`` into model.json's ``system`` part (the rule:
docs/solvers.md, "Headroom"; how ``solve --headroom auto`` uses it:
:mod:`perfros_bag.system.cpuerror`).

A **measured** value (its recordings, one per run; x = each run's CPU statistic, the mean or
the p95 as ``fit --cpu`` says):

- burst: the mean over the runs of ``cpu_units_p95 - x`` (0 under ``--cpu p95``), at least 0;
- spread: the runs' residuals from the setting's own CPU (their mean; a driven node's line
  ``cpu + cpu_per_hz x F_in`` at each run's input rate), ``sqrt(Σ r² / (n - 1))``, 0 with one run;
- gap: ``|fitted CPU at the value - measured mean|`` when the model's CPU there comes from a
  fitted curve (a curve node's ``parameter->cpu``; a driven node's line at its mean input rate).

error = burst + spread + gap. An **unmeasured** value between measured ones (a setting
without a recording, a driven node's grid setting) carries the burst + spread interpolated
(linearly, by value) from its measured neighbours plus the leave-one-out RMSE of the fit its
CPU comes from (0 when the fit has none: two points). A curve node also gets
``cpu_error_between`` = its ``parameter->cpu`` fit's leave-one-out RMSE, for the CPU levels
between its settings. Every error is at least :data:`~perfros_bag.system.cpuerror.FAIR_SHARE`
x the setting's CPU; a setting neither measured nor between measured values gets no
``cpu_error`` (solve applies the floor to it). A driven node states it as ``cpu_error_share``: the error over its CPU at
its measured input rate (the LOO term: ``(rmse(cpu_base) + rmse(cpu_per_hz) x F) / CPU(F)`` at
F = the mean input rate of its recordings).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from perfros_bag.fitting.modelfile import DrivenSetting, FittedRelation, round9, same_value
from perfros_bag.system.cpuerror import FAIR_SHARE


@dataclass(frozen=True)
class Runs:
    """One measured value of a node: per run its CPU statistic ``x``, its p95 (None when the
    row has none) and, for a driven node, its input rate."""

    value: float | None
    x: tuple[float, ...]
    p95: tuple[float | None, ...]
    input_hz: tuple[float, ...] = ()


def burst(runs: Runs) -> float:
    """The mean over the runs of p95 - x (runs with a p95), at least 0."""
    diffs = [p - x for x, p in zip(runs.x, runs.p95, strict=True) if p is not None]
    return max(0.0, sum(diffs) / len(diffs)) if diffs else 0.0


def spread(residuals: Sequence[float]) -> float:
    """``sqrt(Σ r² / (n - 1))`` of the runs' residuals; 0 with fewer than 2 runs."""
    n = len(residuals)
    return math.sqrt(sum(r * r for r in residuals) / (n - 1)) if n > 1 else 0.0


def interpolate(points: Sequence[tuple[float, float]], x: float) -> float | None:
    """The straight line between the two ``points`` (by x) around ``x``; None when ``x`` is
    not strictly between the lowest and the highest."""
    pts = sorted(points)
    if len(pts) < 2 or not pts[0][0] < x < pts[-1][0]:
        return None
    for (x0, y0), (x1, y1) in zip(pts, pts[1:], strict=False):
        if x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0) if x1 > x0 else y1
    return None  # pragma: no cover - x < the last point's x


def _find(runs: Sequence[Runs], value: float | None, single: bool) -> Runs | None:
    match = next((r for r in runs if same_value(r.value, value)), None)
    if match is None and single and len(runs) == 1:
        return runs[0]
    return match


def _loo(fit: FittedRelation | None) -> float:
    return 0.0 if fit is None or fit.loo_rmse is None or not math.isfinite(fit.loo_rmse) else fit.loo_rmse


def node_errors(raw: dict[str, Any], runs: Sequence[Runs], p2c: FittedRelation | None) -> None:
    """A node without ``input``: write ``cpu_error`` on each of ``raw``'s settings (and, with a
    fitted ``parameter->cpu`` ``p2c`` making it a curve node, ``cpu_error_between``)."""
    settings = raw.get("settings") or []
    measured = [(r.value, burst(r) + spread([x - sum(r.x) / len(r.x) for x in r.x])) for r in runs if r.x]
    known = [(v, e) for v, e in measured if v is not None]
    for rs in settings:
        value = rs.get("value")
        value = None if value is None else float(value)
        cpu = float(rs["cpu"])
        r = _find(runs, value, len(settings) == 1)
        if r is not None and r.x:
            mean = sum(r.x) / len(r.x)
            gap = abs(p2c.curve(value) - mean) if p2c is not None and value is not None else 0.0
            err = burst(r) + spread([x - mean for x in r.x]) + gap
        else:
            between = None if value is None else interpolate(known, value)
            if between is None:
                continue  # nothing measured says more than the floor solve applies anyway
            err = between + _loo(p2c)
        rs["cpu_error"] = round9(max(err, FAIR_SHARE * cpu))
    if p2c is not None and p2c.loo_rmse is not None and math.isfinite(p2c.loo_rmse):
        raw["cpu_error_between"] = round9(p2c.loo_rmse)


def driven_errors(raw: dict[str, Any], written: Sequence[DrivenSetting], runs: Sequence[Runs],
                  fits: dict[str, FittedRelation]) -> None:
    """A driven node: write ``cpu_error_share`` on each of ``raw``'s settings (``written``:
    the same settings, in order, with where each came from)."""
    settings = raw.get("settings") or []
    rates = [f for r in runs for f in r.input_hz]
    f_ref = sum(rates) / len(rates) if rates else 0.0
    shares: list[tuple[float, float]] = []  # (value, run part's share) of the measured settings
    share_of: dict[int, float] = {}
    for i, d in enumerate(written):
        r = _find(runs, d.value, len(written) == 1)
        if d.source != "measured" or r is None or not r.x:
            continue
        f_bar = sum(r.input_hz) / len(r.input_hz)
        level = d.cpu + d.cpu_per_hz * f_bar
        if level <= 0:
            continue
        runs_part = burst(r) + spread([x - (d.cpu + d.cpu_per_hz * f) for x, f in zip(r.x, r.input_hz, strict=True)])
        gap = abs(level - sum(r.x) / len(r.x))
        share_of[i] = (runs_part + gap) / level
        if d.value is not None:
            shares.append((d.value, runs_part / level))
    loo_base, loo_k = _loo(fits.get("parameter->cpu_base")), _loo(fits.get("parameter->cpu_per_hz"))
    for i, (rs, d) in enumerate(zip(settings, written, strict=True)):
        share = share_of.get(i)
        if share is None:
            between = None if d.value is None else interpolate(shares, d.value)
            at_ref = d.cpu + d.cpu_per_hz * f_ref
            fit_part = (loo_base + loo_k * f_ref) / at_ref if at_ref > 0 else 0.0
            if between is None:
                continue  # nothing measured says more than the floor solve applies anyway
            share = between + fit_part
        rs["cpu_error_share"] = round9(max(share, FAIR_SHARE))
