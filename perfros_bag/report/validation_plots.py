"""The validation's picture (the paper's Fig 5): expected vs measured performance per node
and overall, from the JSON of ``validate --json``."""

from __future__ import annotations

import math
from typing import Any

from perfros_bag.report.figures import label, png_bytes, subplots

#: a figure shows at most this many nodes (the largest deviations).
MAX_PLOT_NODES = 40


def number(x: Any) -> float | None:
    """A finite JSON number as a float; anything else (null, text, bool, NaN) None."""
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(float(x)):
        return None
    return float(x)


def plot_validation(v: dict[str, Any]) -> bytes:
    """The paper's Fig 5 for one run: expected vs measured performance per node and overall
    (the overall panel normalised to expected = 1)."""
    nodes = [n for n in v["nodes"] if isinstance(n, dict)]
    title = "per node (eq 10)"
    if len(nodes) > MAX_PLOT_NODES:  # keep the figure readable: the largest deviations
        nodes = sorted(nodes, key=lambda n: -(number(n.get("deviation_pct")) or 0.0))[:MAX_PLOT_NODES]
        title = f"per node (eq 10), the {MAX_PLOT_NODES} largest deviations"
    with subplots(1, 2, figsize=(max(6.0, 0.8 * len(nodes) + 4), 3.8),
                  gridspec_kw={"width_ratios": [max(1, len(nodes)), 1.2]}) as (fig, (ax, ax2)):
        xs = range(len(nodes))
        pe = [number(n.get("p_expected")) or 0.0 for n in nodes]
        pm = [number(n.get("p_measured")) or 0.0 for n in nodes]
        ax.bar([x - 0.2 for x in xs], pe, 0.4, label="Expected", color="tab:blue")
        ax.bar([x + 0.2 for x in xs], pm, 0.4, label="Measured", color="tab:orange")
        ax.set_xticks(list(xs), [label(str(n.get("node", "")), 14) for n in nodes], rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("performance")
        ax.set_title(title)
        ax.set_ylim(0, max([*pe, *pm, 1e-9]) * 1.25)  # room for the legend above the bars
        ax.legend(fontsize=8, ncol=2, loc="upper right")
        ov = v["overall"]
        e, m = number(ov.get("expected")) or 0.0, number(ov.get("measured")) or 0.0
        ax2.bar([0], [1.0], 0.4, color="tab:blue", label="Expected")
        ax2.bar([0.45], [m / e if e else 0.0], 0.4, color="tab:orange", label="Measured")
        ax2.set_xticks([0.225], ["overall Σ w·P"])
        ax2.set_ylim(0, max(1.2, (m / e if e else 0) * 1.1))
        dev = number(ov.get("deviation_pct"))
        ax2.set_title("overall (normalised)" + ("" if dev is None else f", dev {dev:.1f} %"), fontsize=9)
        fig.tight_layout()
        return png_bytes(fig)
