"""``perfros-bag report``: one HTML page (and PNGs) from whatever outputs are given."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from perfros_bag.cli._app import command, err


@command("report")
def report(
    out_dir: Annotated[Path, typer.Option("--out", help="Directory for index.html and its PNGs.")],
    characterisation: Annotated[Path | None, typer.Option(
        "--characterisation", help="characterisation.csv from characterise.")] = None,
    model: Annotated[Path | None, typer.Option("--model", help="model.json from fit (regression plots).")] = None,
    plan: Annotated[Path | None, typer.Option("--plan", help="plan.json from solve.")] = None,
    validation: Annotated[Path | None, typer.Option(
        "--validation", help="The JSON of validate --json.")] = None,
    frontier: Annotated[Path | None, typer.Option(
        "--frontier", help="frontier.json from solve --pareto (or the JSON of --pareto-budget).")] = None,
    tune: Annotated[Path | None, typer.Option("--tune", help="tune.json from tune (the loop's rounds).")] = None,
    watch: Annotated[Path | None, typer.Option(
        "--watch", help="The --out folder of watch (windows, alarms, re-plans).")] = None,
) -> None:
    """Write an HTML report; anything not given is left out."""
    from perfros_bag.report.html import build_report

    index = build_report(out_dir, characterisation=characterisation, model=model, plan=plan,
                         validation=validation, frontier=frontier, tune=tune, watch=watch)
    err.print(f"wrote {escape(str(index))}", highlight=False)
