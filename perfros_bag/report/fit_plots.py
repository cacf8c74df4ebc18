"""PNG plots of the fitted regressions, one file per node (the paper's Fig 3 and 4).

Each figure has four panels: parameter -> performance (Fig 3), CPU -> performance
(Fig 4, with the CPU range the solver uses shaded), parameter -> CPU (what Problem 2 and
the plan's parameter value come from) and parameter -> frequency / bandwidth. Points are
the data, the line the chosen form, and the legend gives the form and R².
matplotlib is imported lazily with the Agg backend (no display needed).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.fitting.regression import Fit
from perfros_bag.system.types import Node

_PANELS = (
    ("parameter->performance", "performance", "Fig 3: parameter vs performance"),
    ("cpu->performance", "performance", "Fig 4: CPU vs performance"),
    ("parameter->cpu", "CPU units", "parameter vs CPU"),
    ("parameter->frequency", "frequency (Hz)", "parameter vs frequency / bandwidth"),
)

_FORMULA = {
    "linear": "{0:.4g}·x + {1:.4g}",
    "log": "{0:.4g}·ln(x) + {1:.4g}",
    "quadratic": "{0:.4g}·x² + {1:.4g}·x + {2:.4g}",
    "power": "{0:.4g}·x^{1:.4g}",
}


def formula(fit: Fit) -> str:
    """The fitted equation, x = input / scale (as the paper prints them)."""
    text = _FORMULA[fit.form].format(*fit.coef).replace("+ -", "− ")
    return text if fit.scale == 1 else f"{text}, x = input/{fit.scale:g}"


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "node"


def _draw(ax: Any, fit: Fit, colour: str, label_prefix: str = "") -> None:
    lo, hi = fit.domain
    xs = np.linspace(lo, hi, 200)
    ys = [fit.curve(v) for v in xs]
    ax.plot(xs, ys, "-", color=colour, lw=2,
            label=f"{label_prefix}{fit.form}: {formula(fit)}  (R² = {fit.r2:.3f})")
    ax.plot(fit.x, fit.y, "o", color=colour, ms=7, mec="black", label=f"{label_prefix}data ({len(fit.x)} points)")


def plot_node(node: Node, fits: dict[str, Fit], path: str | Path) -> Path:
    """Write one node's figure to ``path`` (PNG); returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pname = node.parameter.name if node.parameter else "parameter"
    punit = f" ({node.parameter.unit})" if node.parameter and node.parameter.unit else ""
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))
    try:
        for ax, (rel, ylabel, title) in zip(axes.flat, _PANELS, strict=True):
            ax.set_title(title)
            ax.set_ylabel(ylabel)
            ax.set_xlabel("CPU units (100 = one robot)" if rel.startswith("cpu") else f"{pname}{punit}")
            ax.grid(alpha=0.3)
            fit = fits.get(rel)
            if fit is None:
                ax.text(0.5, 0.5, "not fitted", ha="center", va="center", transform=ax.transAxes)
                continue
            _draw(ax, fit, "tab:blue")
            if rel == "cpu->performance" and node.curve is not None:
                a, b = node.curve.domain
                ax.axvspan(a, b, color="tab:green", alpha=0.12, label=f"solver's range [{a:g}, {b:g}]")
            if rel == "parameter->frequency" and "parameter->bandwidth" in fits:
                twin = ax.twinx()
                twin.set_ylabel("bandwidth (kB/s)")
                _draw(twin, fits["parameter->bandwidth"], "tab:orange", "bandwidth ")
                ax.set_ylim(bottom=0)  # from 0: measurement noise on a flat rate looks like noise
                twin.set_ylim(bottom=0)
                h1, l1 = ax.get_legend_handles_labels()
                h2, l2 = twin.get_legend_handles_labels()
                ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="best")
                continue
            ax.legend(fontsize=7, loc="best")
        fig.suptitle(f"{node.name}: fitted regressions", fontsize=14)
        fig.tight_layout()
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp.png")
        fig.savefig(tmp, dpi=100)
        tmp.replace(out)
        return out
    finally:
        plt.close(fig)


def plot_model(system_nodes: dict[str, Node], fits: dict[str, dict[str, Fit]], out_dir: str | Path) -> list[Path]:
    """One PNG per fitted node in ``out_dir`` (``<node>.png``)."""
    d = Path(out_dir)
    return [plot_node(system_nodes[name], node_fits, d / f"{_safe(name)}.png")
            for name, node_fits in fits.items()]

