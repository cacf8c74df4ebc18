"""PNG plots of the fitted regressions (the paper's Fig 3 and 4), from the fits as
model.json keeps them (:class:`~perfros_bag.fitting.modelfile.FittedRelation`).

:func:`plot_model` (``fit --plots``): one file per node with four panels: parameter ->
performance (Fig 3), CPU -> performance (Fig 4, with the CPU range the solver uses
shaded), parameter -> CPU (what Problem 2 and the plan's parameter value come from) and
parameter -> frequency / bandwidth. :func:`plot_relations` (the HTML report): every
relation of a node, one panel each. Points are the data, the line the chosen form, and
the legend gives the form and R².
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.fitting.modelfile import FittedRelation
from perfros_bag.report.figures import label, png_bytes, save_png, subplots
from perfros_bag.system.types import CurveForm, Node

_PANELS = (
    ("parameter->performance", "performance", "Fig 3: parameter vs performance"),
    ("cpu->performance", "performance", "Fig 4: CPU vs performance"),
    ("parameter->cpu", "CPU units", "parameter vs CPU"),
    ("parameter->frequency", "frequency (Hz)", "parameter vs frequency / bandwidth"),
)

_FORMULA: dict[CurveForm, str] = {
    "linear": "{0:.4g}·x + {1:.4g}",
    "log": "{0:.4g}·ln(x) + {1:.4g}",
    "quadratic": "{0:.4g}·x² + {1:.4g}·x + {2:.4g}",
    "power": "{0:.4g}·x^{1:.4g}",
}


def formula(fit: FittedRelation) -> str:
    """The fitted equation, x = input / scale (as the paper prints them)."""
    text = _FORMULA[fit.form].format(*fit.coef).replace("+ -", "− ")
    return text if fit.scale == 1 else f"{text}, x = input/{fit.scale:g}"


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "node"


def _draw(ax: Any, fit: FittedRelation, colour: str, label_prefix: str = "") -> None:
    lo, hi = fit.domain
    xs = np.linspace(lo, hi, 200) if hi > lo else np.array([lo])
    ys = [fit.curve(float(v)) for v in xs]
    ax.plot(xs, ys, "-", color=colour, lw=2, label=f"{label_prefix}{fit.form}: {formula(fit)}  (R² = {fit.r2:.3f})")
    if fit.points:
        ax.plot([p[0] for p in fit.points], [p[1] for p in fit.points], "o", color=colour, ms=7, mec="black",
                label=f"{label_prefix}data ({len(fit.points)} points)")


def plot_node(node: Node, fits: Mapping[str, FittedRelation], path: str | Path) -> Path:
    """Write one node's figure to ``path`` (PNG); returns the path."""
    pname = node.parameter.name if node.parameter else "parameter"
    punit = f" ({node.parameter.unit})" if node.parameter and node.parameter.unit else ""
    with subplots(2, 2, figsize=(12, 8.5)) as (fig, axes):
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
        return save_png(fig, path)


def plot_model(system_nodes: Mapping[str, Node], fits: Mapping[str, Mapping[str, FittedRelation]],
               out_dir: str | Path) -> list[Path]:
    """One PNG per fitted node in ``out_dir`` (``<node>.png``)."""
    d = Path(out_dir)
    return [plot_node(system_nodes[name], node_fits, d / f"{_safe(name)}.png")
            for name, node_fits in fits.items()]


def plot_relations(node: str, fits: Mapping[str, FittedRelation]) -> bytes:
    """Every fitted relation of ``node``, a panel each, three to a row (PNG bytes)."""
    n = len(fits)
    ncols = min(n, 3)
    nrows = (n + ncols - 1) // ncols
    with subplots(nrows, ncols, figsize=(4.2 * ncols, 3.4 * nrows), squeeze=False) as (fig, axes):
        flat = [ax for row in axes for ax in row]
        for ax in flat[n:]:
            ax.set_visible(False)
        for ax, (rel, fit) in zip(flat, fits.items(), strict=False):
            _draw(ax, fit, "tab:blue")
            src, _, dst = rel.partition("->")
            ax.set_xlabel(label(src or "input"))
            ax.set_ylabel(label(dst or rel))
            ax.set_title(label(f"{node}: {rel}", 60), fontsize=9)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.tight_layout()
        return png_bytes(fig)
