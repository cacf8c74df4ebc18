"""The performance / server-capacity frontier (``solve --pareto``) as a picture."""

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
