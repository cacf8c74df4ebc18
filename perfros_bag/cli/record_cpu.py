"""``perfros-bag record-cpu``: a psutil CPU trace of the matching processes."""

from __future__ import annotations

from pathlib import Path

import typer

from perfros_bag.cli._app import command, err


@command("record-cpu")
def record_cpu_cmd(
    command_args: list[str] | None = typer.Argument(  # noqa: B008
        None, metavar="[-- COMMAND ...]", help="Run COMMAND, trace it and its children, stop when it exits."),
    match: list[str] | None = typer.Option(  # noqa: B008
        None, "--match", "-m", help="Regex on a process's ROS node name, process name or command line (repeatable)."),
    interval: float = typer.Option(0.5, "--interval", "-i", help="Seconds between samples (>= 0.01)."),
    out_path: Path = typer.Option(..., "--out", "-o", help="The CPU trace to write (<stem>.cpu.csv)."),  # noqa: B008
    duration: float | None = typer.Option(None, "--duration", "-d", help="Stop after S seconds."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No live status on stderr."),
    speed: bool = typer.Option(True, "--speed/--no-speed",
                               help="Measure the machine's speed first (~0.2 s of CPU): "
                                    "'# speed_factor=' in the trace."),
    ready: Path | None = typer.Option(None, "--ready", hidden=True,  # noqa: B008
                                      help="Create this file once the first sample is taken (a caller waits on it)."),
) -> None:
    """Sample CPU % and RSS of matching processes until the duration ends, Ctrl-C, or COMMAND exits."""
    import time

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from perfros_bag.cpu.record import record_cpu

    seen = [0]
    columns = [TextColumn("record-cpu"), BarColumn() if duration else TextColumn(""), TimeElapsedColumn(),
               TextColumn("{task.description}")]
    with Progress(*columns, console=err, transient=True, disable=quiet or not err.is_terminal) as progress:
        task = progress.add_task("starting", total=duration or None)
        t0 = time.monotonic()

        def status(rnd: int, rows: int) -> None:
            if rnd == 0 and ready is not None:
                ready.touch()
            seen[0] += rows
            progress.update(task, completed=time.monotonic() - t0,
                            description=f"{rows} processes, {seen[0]} rows -> {out_path}")

        rc = record_cpu(out_path, list(match or []), interval, duration=duration,
                        command=list(command_args or []) or None, on_round=status, speed=speed)
    if not quiet:
        err.print(f"wrote {out_path} ({seen[0]} samples)", highlight=False)
    if rc:
        raise typer.Exit(rc)
