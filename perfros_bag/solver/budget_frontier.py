"""Performance against one chain's latency budget (``solve --pareto RANGE --pareto-budget
CHAIN[:p50|p95]``): for each budget level, Problem 1's best plan with that chain's budget
(its p95 by default) set to the level, every other budget kept; the plan's Σ w·P and the
chain's predicted latency in it.

- The default range (``auto``) runs from the chain's lower bound over every plan
  (:func:`~perfros_bag.system.latency.fastest_bound`: below it no plan exists) to its
  predicted latency in the best plan without its budget (above it the budget no longer
  binds: performance stops rising).
- Each point is a solve by ``method`` (exact: proven optimal within the budgets, the lazy
  cuts of :mod:`perfros_bag.solver.budgets`).
- The frontier never falls as the budget grows: a plan within a budget is within every
  larger one, so a point whose plan is worse than one found at a smaller budget takes that
  plan (``carried_from``: the budget it was found at, its predicted latency with it).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import atomic_write_text
from perfros_bag.solver.candidates import fixed_choices
from perfros_bag.solver.dispatch import solve
from perfros_bag.system.latency import chain_hops, fastest_bound
from perfros_bag.system.plan import Plan, Status
from perfros_bag.system.types import Budget, Chain, Problem, System

__all__ = ["CSV_COLUMNS", "FORMAT", "BudgetPoint", "budget_frontier", "budget_frontier_csv",
           "budget_frontier_document", "budget_range", "parse_target", "read_budget_frontier", "with_budget",
           "write_budget_frontier"]

FORMAT = "perfros-bag budget frontier 1"
QUANTILES = ("p50", "p95")
CSV_COLUMNS = ("budget_ms", "status", "objective", "bound", "predicted_p50_ms", "predicted_p95_ms", "solve_s",
               "carried_from")


def parse_target(system: System, text: str) -> tuple[Chain, str]:
    """``--pareto-budget CHAIN[:p50|p95]``: the chain (by name) and the quantile (p95 by
    default); an :class:`InputError` naming what is wrong otherwise."""
    name, sep, quantile = text.strip().rpartition(":") if ":" in text else (text.strip(), "", "p95")
    quantile = quantile.strip() or "p95"
    if quantile not in QUANTILES:
        raise InputError(None, f"--pareto-budget {text!r}: the quantile must be p50 or p95, got {quantile!r}")
    chain = next((c for c in system.chains if c.name == name.strip()), None)
    if chain is None:
        have = ", ".join(repr(c.name) for c in system.chains) or "none"
        raise InputError(system.source, f"--pareto-budget: no chain {name.strip()!r} (the system's chains: {have})")
    hops = chain_hops(system, chain)
    if isinstance(hops, str):  # a chain without a budget may be one the model cannot follow
        raise InputError(system.source, f"--pareto-budget: chain {chain.name!r}: its latency cannot be predicted, "
                                        f"so it cannot have a budget: {hops}")
    return chain, quantile


def with_budget(system: System, chain: str, quantile: str, ms: float | None) -> System:
    """The system with ``chain``'s ``quantile`` bound set to ``ms`` (None: removed; the chain's
    other bound and every other chain's budget kept)."""
    def budget(c: Chain) -> Budget | None:
        bounds = dict(c.budget_ms.items()) if c.budget_ms is not None else {}
        bounds.pop(quantile, None)
        if ms is not None:
            bounds[quantile] = ms
        return Budget(bounds.get("p50"), bounds.get("p95")) if bounds else None

    chains = tuple(dataclasses.replace(c, budget_ms=budget(c)) if c.name == chain else c for c in system.chains)
    return dataclasses.replace(system, chains=chains)


@dataclass
class BudgetPoint:
    budget_ms: float
    status: Status
    objective: float | None  # Σ w·P of the best plan found within the budget
    bound: float | None  # proven: no plan within this budget does better (None: none proven)
    predicted_ms: dict[str, float] | None  # the chain's predicted {p50, p95} in that plan
    solve_s: float
    carried_from: float | None = None  # the smaller budget whose (better) plan this is

    def to_json(self) -> dict[str, Any]:
        """The point as the document holds it (docs/formats.md, the one place)."""
        return {"budget_ms": round(self.budget_ms, 9), "status": str(self.status), "objective": self.objective,
                "bound": self.bound, "predicted_ms": self.predicted_ms, "solve_s": round(self.solve_s, 6),
                "carried_from": None if self.carried_from is None else round(self.carried_from, 9)}


def _predicted(plan: Plan, chain: str) -> dict[str, float] | None:
    said = next((c for c in plan.chains if c.get("name") == chain), None)
    got = None if said is None else said.get("predicted_ms")
    return None if not isinstance(got, dict) else {q: float(got[q]) for q in QUANTILES if got.get(q) is not None}


def budget_range(system: System, chain: Chain, quantile: str, *, resolution: float = 1.0,
                 time_limit: float | None = None, headroom: float | str = 0.0) -> tuple[float, float]:
    """The budgets worth asking about: from the chain's lower bound over every plan (below it
    none exists) to its predicted ``quantile`` in Problem 1's exact optimum without its own
    bound (above it the bound does not bind); a flat frontier (that optimum at the bound)
    gets twice the bound as its top."""
    free = with_budget(system, chain.name, quantile, None)
    bound = fastest_bound(free, chain, fixed_choices(free, Problem.PERFORMANCE, None, resolution))
    if bound is None:  # pragma: no cover - parse_target refuses a chain whose hops cannot be followed
        raise InputError(system.source, f"--pareto-budget: chain {chain.name!r} cannot be followed hop by hop")
    low = bound[QUANTILES.index(quantile)]
    plan = solve(free, Problem.PERFORMANCE, "exact", resolution=resolution, time_limit=time_limit,
                 headroom=headroom)
    if plan.status == Status.INFEASIBLE:
        raise InputError(system.source, f"--pareto-budget: Problem 1 without chain {chain.name!r}'s {quantile} "
                                        f"bound has no plan: {plan.reason}")
    got = _predicted(plan, chain.name)
    high = got.get(quantile) if got else None
    if high is None or not math.isfinite(high):
        raise InputError(system.source, f"--pareto-budget: chain {chain.name!r}'s latency cannot be predicted")
    return low, high if high > low * (1 + 1e-9) else 2 * low


def budget_frontier(system: System, chain: Chain, quantile: str, *, low: float | None = None,
                    high: float | None = None, points: int = 21, resolution: float = 1.0, method: str = "exact",
                    time_limit: float | None = None, headroom: float | str = 0.0) -> list[BudgetPoint]:
    """Problem 1 at ``points`` budgets of ``chain``'s ``quantile`` evenly spaced from ``low``
    to ``high`` (default :func:`budget_range`); ``time_limit`` is per point."""
    from perfros_bag.solver.frontier import MAX_POINTS

    if points < 2:
        raise InputError(None, f"a frontier needs at least 2 points, got {points}")
    if points > MAX_POINTS:
        raise InputError(None, f"a frontier takes at most {MAX_POINTS:,} points (each one a solve), got {points:,}")
    if low is None or high is None:
        lo, hi = budget_range(system, chain, quantile, resolution=resolution, time_limit=time_limit,
                              headroom=headroom)
        low = lo if low is None else low
        high = hi if high is None else high
    if not (math.isfinite(low) and math.isfinite(high)) or low <= 0 or high <= low:
        raise InputError(system.source, f"--pareto-budget: the budget range {low:g} to {high:g} ms is empty, "
                                        "inverted or not above 0")
    out: list[BudgetPoint] = []
    for i in range(points):
        level = low + (high - low) * i / (points - 1)
        t0 = time.perf_counter()
        plan = solve(with_budget(system, chain.name, quantile, level), Problem.PERFORMANCE, method,
                     resolution=resolution, time_limit=time_limit, headroom=headroom)
        found = plan.status != Status.INFEASIBLE
        out.append(BudgetPoint(level, plan.status, plan.objective if found else None, plan.bound if found else None,
                               _predicted(plan, chain.name) if found else None, time.perf_counter() - t0))
    return carried(out)


def carried(points: list[BudgetPoint], rel_tol: float = 1e-6) -> list[BudgetPoint]:
    """``points`` (by increasing budget) made consistent with what a budget means: each
    objective at least the best found at a smaller budget (that plan keeps this budget too:
    its value and predicted latency are carried, ``carried_from`` its budget, status
    ``feasible`` unless this point's proven bound says it is optimal)."""
    out = sorted(points, key=lambda p: p.budget_ms)
    best: BudgetPoint | None = None
    for p in out:
        if best is None or best.objective is None or (p.objective is not None and p.objective >= best.objective):
            if p.objective is not None and (best is None or best.objective is None or p.objective > best.objective):
                best = p
            continue
        p.objective, p.predicted_ms = best.objective, best.predicted_ms
        p.carried_from = best.carried_from if best.carried_from is not None else best.budget_ms
        proven = p.bound is not None and p.bound - p.objective <= rel_tol * max(1.0, abs(p.objective))
        p.status = Status.OPTIMAL if proven else Status.FEASIBLE
    return out


def budget_frontier_document(system: System, chain: Chain, quantile: str, points: list[BudgetPoint], method: str,
                             headroom: float | str = 0.0) -> dict[str, Any]:
    """The frontier as JSON-ready data (docs/formats.md, budget frontier)."""
    return {"format": FORMAT, "system": system.source, "method": method, "headroom": headroom,
            "chain": chain.name, "topics": list(chain.topics), "quantile": quantile,
            "points": [p.to_json() for p in points]}


def budget_frontier_csv(doc: dict[str, Any]) -> str:
    """The document's points as CSV (:data:`CSV_COLUMNS`; empty cells for null)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for p in doc["points"]:
        pred = p.get("predicted_ms") or {}
        row = [p["budget_ms"], p["status"], p["objective"], p["bound"], pred.get("p50"), pred.get("p95"),
               p["solve_s"], p["carried_from"]]
        writer.writerow(["" if v is None else v for v in row])
    return buf.getvalue()


def write_budget_frontier(path: str | Path, doc: dict[str, Any]) -> None:
    """The document as JSON at ``path`` and as CSV beside it (``.csv``), each written atomically."""
    atomic_write_text(Path(path).with_suffix(".csv"), budget_frontier_csv(doc))
    atomic_write_text(path, json.dumps(doc, indent=2) + "\n")


def read_budget_frontier(path: str | Path) -> dict[str, Any]:
    """A budget frontier document, checked field by field (the one reader): an
    :class:`InputError` naming the broken place otherwise."""
    from perfros_bag.solver.frontier import document_points

    doc, points = document_points(path, FORMAT, "budget frontier")
    if not isinstance(doc.get("chain"), str) or doc.get("quantile") not in QUANTILES:
        raise InputError(path, "budget frontier: 'chain' must be a name and 'quantile' p50 or p95")
    for where, p in points:
        if p.get("status") not in tuple(Status):
            raise InputError(path, f"{where}.status: one of {', '.join(Status)}")
        for key in ("budget_ms", "objective", "bound", "solve_s", "carried_from"):
            v = p.get(key)
            if (v is None and key != "budget_ms") or (not isinstance(v, bool) and isinstance(v, int | float)
                                                      and math.isfinite(v)):
                continue
            raise InputError(path, f"{where}.{key}: not a finite number" + ("" if key == "budget_ms" else " or null"))
        pred = p.get("predicted_ms")
        if pred is not None and not (isinstance(pred, dict) and all(
                q in QUANTILES and not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
                for q, v in pred.items())):
            raise InputError(path, f"{where}.predicted_ms: an object of finite p50/p95 or null")
    return doc
