"""PNG plots of the fitted regressions (the paper's Fig 3 and 4), from the fits as
model.json keeps them (:class:`~perfros_bag.fitting.modelfile.FittedRelation`).

:func:`plot_model` (``fit --plots``): one file per node with four panels: parameter ->
performance (Fig 3), CPU -> performance (Fig 4, with the CPU range the solver uses
shaded), parameter -> CPU (what Problem 2 and the plan's parameter value come from) and
parameter -> frequency / bandwidth; a driven node (system.yaml ``input:``) instead shows its
CPU against its input rate, one line per setting (:func:`plot_driven_node`).
:func:`plot_relations` (the HTML report): every
relation of a node, one panel each. Points are the data, the line the chosen form, and
the legend gives the form and R².
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.fitting.modelfile import DrivenSetting, FittedRelation
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


def _twin(ax: Any, left: FittedRelation | None, right: FittedRelation | None, right_label: str) -> None:
    """Two relations on one panel, the second on a twin axis, one legend."""
    if left is not None:
        _draw(ax, left, "tab:blue")
    if right is None:
        if left is not None:
            ax.legend(fontsize=7, loc="best")
        return
    twin = ax.twinx()
    twin.set_ylabel(right_label)
    _draw(twin, right, "tab:orange", f"{right_label} ")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = twin.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="best")


def plot_driven_node(node: Node, fits: Mapping[str, FittedRelation], settings: list[DrivenSetting],
                     path: str | Path) -> Path:
    """A driven node's figure: CPU against input rate (one line cpu + cpu_per_hz x F_in per
    measured setting through its recordings; settings evaluated from the curves as thin
    grey lines), and over the parameter: base CPU and CPU per Hz, performance, output per
    input and bytes per message."""
    pname = node.parameter.name if node.parameter else "parameter"
    punit = f" ({node.parameter.unit})" if node.parameter and node.parameter.unit else ""
    rates = [f for d in settings for f, _ in d.points]
    top = max(rates, default=1.0) * 1.1 or 1.0
    xs = np.linspace(0.0, top, 50)
    with subplots(2, 2, figsize=(12, 8.5)) as (fig, axes):
        ax = axes[0, 0]
        ax.set_title(f"CPU vs input rate ({node.input})")
        ax.set_xlabel("input rate (Hz)")
        ax.set_ylabel("CPU units")
        colours = iter(f"C{i}" for i in range(10_000))
        for d in settings:
            name = "" if d.value is None else f"{pname}={d.value:g}: "
            if d.source == "grid":
                ax.plot(xs, d.cpu + d.cpu_per_hz * xs, "-", color="0.75", lw=0.8)
                continue
            colour = next(colours)
            r2 = "" if d.r2 is None else f", R² = {d.r2:.3f}"
            ax.plot(xs, d.cpu + d.cpu_per_hz * xs, "-", color=colour, lw=2,
                    label=f"{name}{d.cpu:.3g} + {d.cpu_per_hz:.3g}·F_in{r2}")
            if d.points:
                ax.plot([p[0] for p in d.points], [p[1] for p in d.points], "o", color=colour, ms=6, mec="black")
        if any(d.source == "grid" for d in settings):
            ax.plot([], [], "-", color="0.75", lw=0.8, label="settings from the curves")
        ax.grid(alpha=0.3)
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=7, loc="best")
        panels = ((axes[0, 1], "base CPU and CPU per Hz", "base CPU units", "parameter->cpu_base",
                   "parameter->cpu_per_hz", "CPU per Hz"),
                  (axes[1, 0], "parameter vs performance", "performance", "parameter->performance", None, ""),
                  (axes[1, 1], "output per input and bytes per message", "output msgs per input msg",
                   "parameter->out_per_in", "parameter->bytes_per_msg", "bytes per message"))
        for pax, title, ylabel, left, right, right_label in panels:
            pax.set_title(title)
            pax.set_xlabel(f"{pname}{punit}")
            pax.set_ylabel(ylabel)
            pax.grid(alpha=0.3)
            lf, rf = fits.get(left), fits.get(right) if right else None
            if lf is None and rf is None:
                pax.text(0.5, 0.5, "not fitted", ha="center", va="center", transform=pax.transAxes)
                continue
            _twin(pax, lf, rf, right_label)
        fig.suptitle(f"{node.name}: driven by {node.input}", fontsize=14)
        fig.tight_layout()
        return save_png(fig, path)


def plot_model(system_nodes: Mapping[str, Node], fits: Mapping[str, Mapping[str, FittedRelation]],
               out_dir: str | Path, driven: Mapping[str, list[DrivenSetting]] | None = None) -> list[Path]:
    """One PNG per fitted node in ``out_dir`` (``<node>.png``); a driven node (``driven``:
    its settings as model.json's ``driven`` part gives them) by :func:`plot_driven_node`."""
    d = Path(out_dir)
    driven = driven or {}
    out = [plot_node(system_nodes[name], node_fits, d / f"{_safe(name)}.png")
           for name, node_fits in fits.items() if name not in driven]
    return out + [plot_driven_node(system_nodes[name], fits.get(name, {}), settings, d / f"{_safe(name)}.png")
                  for name, settings in driven.items() if settings]


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
