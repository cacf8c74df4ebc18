"""``perfros-bag tune APP.launch --space space.yaml --system system.yaml --out DIR [--base CSV]``: the loop."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from perfros_bag.cli._app import command, err

if TYPE_CHECKING:
    from perfros_bag.tune.tunefile import TuneRound


def _f(x: Any, nd: int = 1) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def render_rounds(rounds: list[TuneRound]) -> None:
    """Each round's plan, prediction, measurement and the fit's change, as tables on stderr."""
    from rich.table import Table

    table = Table(title="tune: rounds", title_justify="left")
    for col in ("round", "values deployed", "expected Σ w·P", "measured Σ w·P", "deviation %", "starved"):
        table.add_column(col, justify="left" if col in ("values deployed", "starved") else "right")
    for r in rounds:
        starved = [c for c, v in r.computers.items() if v.starved]
        table.add_row(str(r.round), ", ".join(f"{n}={v}" for n, v in r.values.items()), _f(r.expected, 2),
                      _f(r.measured, 2), _f(r.deviation_pct, 2), ", ".join(starved) or "-")
    err.print(table)
    nodes = Table(title="tune: per node, CPU units (model: fit before -> after the round)", title_justify="left")
    for col in ("round", "node", "computer", "value", "planned", "measured", "kept rate", "need", "model before",
                "model after", "refit"):
        nodes.add_column(col, justify="left" if col in ("node", "computer", "refit") else "right")
    for r in rounds:
        for name, n in r.nodes.items():
            nodes.add_row(str(r.round), name, n.computer, "-" if n.value is None else f"{n.value:g}"
                          if isinstance(n.value, int | float) else str(n.value), _f(n.cpu_planned),
                          _f(n.cpu_measured), "-" if n.kept_ratio is None else f"{100 * n.kept_ratio:.0f} %",
                          _f(n.cpu_need), _f(n.model_cpu_before), _f(n.model_cpu_after), n.refit)
    err.print(nodes)


@command("tune", interrupted="interrupted: finished rounds are kept in tune.json; nothing is left running")
def tune_cmd(
    launch: Path = typer.Argument(..., metavar="APP.launch", help="Your ROS 1 launch file."),  # noqa: B008
    space: Path = typer.Option(..., "--space", help="space.yaml: what to vary and how it reaches the launch file."),  # noqa: B008
    system: Path = typer.Option(  # noqa: B008
        ..., "--system", help="system.yaml: your computers, links and nodes (init drafts one)."),
    out_dir: Path = typer.Option(  # noqa: B008
        ..., "--out", "-o", help="Folder for sweep/, round-K/, model-K.json, tune.json, tune.png."),
    rounds: int = typer.Option(3, "--rounds", "-n", help="Most deployments (rounds) to run."),
    tolerance: float | None = typer.Option(
        None, "--tolerance",
        help="A round whose overall deviation (eq 10) is at most this % ends the loop (default 5)."),
    method: str = typer.Option("exact", "--method", "-m", help="Solver: greedy, greedy+, exact, bruteforce."),
    headroom: str = typer.Option(
        "0", "--headroom", metavar="H|auto",
        help="Share of every computer's capacity each plan keeps free, in [0, 1), "
             "or auto: each node's measured CPU error (solve --headroom)."),
    duration: float | None = typer.Option(
        None, "--duration", "-d",
        help="Seconds recorded per sweep run and deployment (default: space.yaml's duration_s)."),
    units_per_core: float = typer.Option(100.0, "--units-per-core", help="CPU units of one core (init drafts 100)."),
    net: bool = typer.Option(True, "--net/--no-net", help="Emulate the system's links in each deployment (root)."),
    base: Path | None = typer.Option(  # noqa: B008
        None, "--base", metavar="CHARACTERISATION.csv",
        help="Start from this characterisation instead of sweeping: model 0 is fitted on it, "
             "each refit on it plus the rounds' recordings (same CPU scale as --units-per-core)."),
) -> None:
    """Sweep, fit, solve and deploy APP.launch, then refit on each deployment until its plan holds."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from perfros_bag.cli.solve import parse_headroom
    from perfros_bag.report.tune_plots import plot_tune
    from perfros_bag.tune.loop import tune

    kept = parse_headroom(headroom, check_range=False)  # tune() says what is wrong with a number
    with Progress(SpinnerColumn(), TextColumn("tune"), TimeElapsedColumn(), TextColumn("{task.description}"),
                  console=err, transient=True) as progress:
        task = progress.add_task("", total=None)

        def show(stage: str) -> None:
            progress.update(task, description=stage)

        def finished(r: TuneRound) -> None:
            progress.console.print(f"round {r.round}: expected {_f(r.expected, 2)} measured "
                                   f"{_f(r.measured, 2)} ({_f(r.deviation_pct, 2)} %)", highlight=False)

        result = tune(launch, space, system, out_dir, rounds=rounds, tolerance=tolerance, method=method,
                      headroom=kept, duration=duration, units_per_core=units_per_core, net=net,
                      progress=show, on_round=finished, base=base, plot=plot_tune)
    doc = result.document
    if result.rounds:
        render_rounds(result.rounds)
    stopped = doc["stopped"]
    err.print(f"{result.ran} round(s) run, {result.resumed} resumed; stopped: {stopped['reason']} after round "
              f"{stopped['after_round']}; wrote {out_dir}/tune.json" + (", tune.png" if doc["rounds"] else ""),
              highlight=False)
    if stopped["reason"] != "within tolerance":
        raise typer.Exit(1)
