"""``perfros-bag fit``: system.yaml + characterisation.csv -> model.json (+ PNG plots)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from perfros_bag.cli._app import command, err, out


@command("fit")
def fit(
    system: Annotated[Path, typer.Argument(
        help="system.yaml: nodes, settings with the expert's performance levels, weights.")],
    characterisation: Annotated[Path, typer.Argument(
        help="characterisation.csv written by `perfros-bag characterise`.")],
    out_path: Annotated[Path, typer.Option(
        "--out", "-o", help="model.json to write (atomically).")] = Path("model.json"),
    plots: Annotated[Path | None, typer.Option(
        "--plots", help="Directory for one PNG per fitted node (Fig 3/4).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the model.json document on stdout (only).")] = False,
    cpu: Annotated[str, typer.Option(
        "--cpu", help="A setting's CPU: 'mean' of its samples, or 'p95' (room for bursts).")] = "mean",
) -> None:
    """Fit parameter -> CPU/performance/frequency/bandwidth and CPU -> performance per configurable node."""
    from rich.table import Table

    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import write_model

    result = build_model(system, characterisation, cpu=cpu)
    write_model(out_path, result.document)
    written: list[Path] = []
    if plots is not None:
        from perfros_bag.report.fit_plots import plot_model

        written = plot_model(result.system.node, result.fits, plots, result.document.driven)

    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(result.document.to_json(), indent=None))
        return
    table = Table(title=f"fits -> {out_path}")
    for col in ("node", "relation", "form", "R²", "LOO RMSE", "points", "domain"):
        table.add_column(col, justify="right" if col in ("R²", "LOO RMSE", "points") else "left")
    for node, fits in result.fits.items():
        for rel, f in fits.items():
            loo = "-" if f.loo_rmse is None else f"{f.loo_rmse:.3g}"
            r2 = f"{f.r2:.4f}" if f.r2 >= 0.9 else f"[yellow]{f.r2:.4f}[/]"
            table.add_row(node, rel.replace("parameter", "param"), f.form, r2, loo, str(len(f.points)),
                          f"[{f.domain[0]:.4g}, {f.domain[1]:.4g}]")
    out.print(table)
    for node, settings in result.document.driven.items():
        for d in settings:
            if d.source == "measured":
                at = "" if d.value is None else f" {d.value:g}"
                r2 = "one input rate" if d.r2 is None else f"R² {d.r2:.4f}"
                out.print(f"{node}{at}: CPU = {d.cpu:.4g} + {d.cpu_per_hz:.4g} x input Hz ({r2}, "
                          f"{len(d.points)} recording(s))")
        grid = sum(d.source == "grid" for d in settings)
        if grid:
            out.print(f"{node}: {grid} more setting(s) between the measured ones, from the curves over its parameter")
    for node, n in result.system.node.items():
        if n.curve is not None and node in result.fits:
            lo, hi = n.curve.domain
            out.print(f"{node}: solver's CPU range [{lo:g}, {hi:g}], performance "
                      f"{n.curve(lo):.1f} -> {n.curve(hi):.1f}")
    if not result.fits:
        err.print("[yellow]no node was fitted: model.json holds the measured numbers only[/]")
    out.print(f"wrote {out_path}" + (f" and {len(written)} plot(s) in {plots}" if plots is not None else ""))
