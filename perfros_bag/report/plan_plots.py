"""The plan's picture: planned CPU per computer, stacked by node, against the capacities."""

from __future__ import annotations

from perfros_bag.report.figures import label, png_bytes, subplots
from perfros_bag.system.plan import Plan


def plot_plan_loads(plan: Plan) -> bytes:
    """Planned CPU per computer, stacked by node, with each capacity as a dashed line (PNG)."""
    names = list(plan.computers)
    with subplots(figsize=(min(24.0, max(4.0, 1.6 * len(names) + 2)), 3.6)) as (fig, ax):
        bottoms = [0.0] * len(names)
        loads = [sum(pn.cpu for pn in plan.nodes.values() if pn.computer == c) for c in names]
        caps = [plan.computers[c].capacity or 0.0 for c in names]
        top = max([*loads, *caps, 1e-9])
        for node, pn in plan.nodes.items():
            if pn.computer not in plan.computers:
                continue
            i = names.index(pn.computer)
            ax.bar(i, pn.cpu, bottom=bottoms[i], edgecolor="white")
            if pn.cpu >= 0.04 * top:  # label only the bars tall enough to hold it
                ax.text(i, bottoms[i] + pn.cpu / 2, label(node, 18), ha="center", va="center", fontsize=7)
            bottoms[i] += pn.cpu
        for i, c in enumerate(names):
            cap = plan.computers[c].capacity
            if cap is not None:
                ax.hlines(cap, i - 0.45, i + 0.45, colors="red", linestyles="--",
                          label="capacity" if i == 0 else None)
        ax.set_xticks(range(len(names)), [label(n, 20) for n in names])
        ax.set_ylabel("CPU (normalised units)")
        ax.set_title("planned CPU per computer (stacked by node)")
        if any(plan.computers[c].capacity is not None for c in names):
            ax.legend(fontsize=8)
        fig.tight_layout()
        return png_bytes(fig)
