"""``perfros-bag sweep APP.launch --space space.yaml --out DIR``: record one run per setting."""

from __future__ import annotations

from pathlib import Path

import typer

from perfros_bag.cli._app import command, err


@command("sweep", interrupted="interrupted: finished runs are kept in the manifest; nothing is left running")
def sweep_cmd(
    launch: Path = typer.Argument(..., metavar="APP.launch", help="Your ROS 1 launch file."),  # noqa: B008
    space: Path = typer.Option(..., "--space", help="space.yaml: what to vary and how it reaches the launch file."),  # noqa: B008
    out_dir: Path = typer.Option(  # noqa: B008
        ..., "--out", "-o", help="Folder for <run>.bag, <run>.cpu.csv, manifest.yaml, graph.yaml."),
    duration: float | None = typer.Option(
        None, "--duration", "-d", help="Seconds recorded per run (default: space.yaml's duration_s)."),
    interval: float = typer.Option(0.5, "--interval", "-i", help="Seconds between CPU samples (>= 0.05)."),
    repeat_off_speed: int | None = typer.Option(
        None, "--repeat-off-speed",
        help="Then record again, up to N (1-5) times, each run made while the machine's speed reference "
             "(record-cpu) was more than 15 % off the sweep's median; the recording nearer the median is kept."),
) -> None:
    """Run APP.launch once per setting of space.yaml; record every topic and the nodes' CPU."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from perfros_bag.sweep.runner import sweep

    columns = [TextColumn("sweep"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("ETA"),
               TimeRemainingColumn(), TextColumn("{task.description}")]
    with Progress(*columns, console=err, transient=True) as progress:
        task = progress.add_task("", total=None)

        def show(i: int, runs: int, name: str, stage: str, frac: float) -> None:
            progress.update(task, total=runs, completed=i + frac, description=f"{name}: {stage}")

        result = sweep(launch, space, out_dir, duration=duration, interval=interval, progress=show,
                       repeat_off_speed=repeat_off_speed or 0)
    done = len(result.recorded)
    again = f", {len(result.repeated)} recorded again nearer the sweep's speed" if repeat_off_speed else ""
    err.print(f"{done} run(s) recorded, {len(result.skipped)} already there{again} -> {out_dir}/manifest.yaml, "
              f"{out_dir}/graph.yaml", highlight=False)
