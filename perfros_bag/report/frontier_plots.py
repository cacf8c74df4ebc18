"""The frontiers of ``solve --pareto`` as pictures: performance per server capacity, and
per latency budget of a chain (``--pareto-budget``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from perfros_bag.report.figures import png_bytes, subplots


def plot_frontier(points: Sequence[Mapping[str, Any]]) -> bytes:
    """Σ w·P of the best plan per total server capacity, with each point's bound (a
    frontier document's ``points``); points without a plan are left out (PNG). Only proven
    bounds are in a frontier document (a heuristic's points have none): the bound line is
    drawn, as "proven bound", only through points that have one."""
    solved = [p for p in points if p.get("objective") is not None]
    with subplots(figsize=(6.4, 3.8)) as (fig, ax):
        xs = [float(p["server_capacity"]) for p in solved]
        ax.plot(xs, [float(p["objective"]) for p in solved], "o-", label="best plan found")
        bounds = [(float(p["server_capacity"]), float(p["bound"])) for p in solved if p.get("bound") is not None]
        if bounds and any(p.get("status") != "optimal" for p in solved):
            ax.plot([b[0] for b in bounds], [b[1] for b in bounds], "v--", color="grey", label="proven bound")
        ax.set_xlabel("total server capacity (CPU units)")
        ax.set_ylabel("Σ w·P (Problem 1)")
        ax.set_title("what server capacity buys: performance frontier")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        return png_bytes(fig)


def plot_budget_frontier(doc: Mapping[str, Any]) -> bytes:
    """A budget frontier document (``solve --pareto-budget``) as two panels: Σ w·P of the
    best plan per budget of the chain, and the chain's predicted latency in that plan against
    the budget (never above the line ``predicted = budget``); points without a plan are left
    out (PNG)."""
    quantile = str(doc.get("quantile", "p95"))
    solved = [p for p in doc.get("points", []) if p.get("objective") is not None]
    with subplots(1, 2, figsize=(9.6, 3.8)) as (fig, (left, right)):
        xs = [float(p["budget_ms"]) for p in solved]
        left.plot(xs, [float(p["objective"]) for p in solved], "o-", label="best plan found")
        left.set_xlabel(f"chain {doc.get('chain')}: {quantile} budget (ms)")
        left.set_ylabel("Σ w·P (Problem 1)")
        left.set_title("what latency costs: performance per budget")
        for q, style in (("p50", "s--"), ("p95", "o-")):
            got = [(float(p["budget_ms"]), float(p["predicted_ms"][q])) for p in solved
                   if isinstance(p.get("predicted_ms"), Mapping) and p["predicted_ms"].get(q) is not None]
            if got:
                right.plot([g[0] for g in got], [g[1] for g in got], style, label=f"predicted {q}")
        if xs:
            right.plot([min(xs), max(xs)], [min(xs), max(xs)], ":", color="grey", label="= budget")
        right.set_xlabel(f"{quantile} budget (ms)")
        right.set_ylabel("predicted latency of the plan (ms)")
        right.set_title("the best plan's latency")
        for ax in (left, right):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        fig.tight_layout()
        return png_bytes(fig)
