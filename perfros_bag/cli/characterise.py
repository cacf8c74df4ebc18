"""``perfros-bag characterise DIR``: recordings + CPU traces -> characterisation.csv."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from perfros_bag.cli._app import command, err, out

if TYPE_CHECKING:
    from perfros_bag.characterisation.manifest import RecordingEntry
    from perfros_bag.characterisation.table import Failure


@contextmanager
def _progress_bar(total: int) -> Iterator[Callable[[RecordingEntry, Failure | None], None] | None]:
    """A progress bar on stderr when it is a terminal; elsewhere none (no blank line left on a
    pipe, and rich.progress is not even imported)."""
    if not err.is_terminal:
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("characterise"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("{task.description}"), console=err, transient=True) as progress:
        task = progress.add_task("", total=total)

        def done(entry: RecordingEntry, failure: Failure | None) -> None:
            progress.update(task, advance=1, description=entry.name)

        yield done


def _fmt(v: float | None, digits: int = 1) -> str:
    return "" if v is None else f"{v:.{digits}f}"


@command("characterise")
def characterise_cmd(
    directory: Path = typer.Argument(..., metavar="DIR", help="Directory of recordings (or one recording)."),  # noqa: B008
    manifest: Path | None = typer.Option(  # noqa: B008
        None, "--manifest", "-m", help="manifest.yaml (default: DIR/manifest.yaml when present)."),
    system_path: Path | None = typer.Option(  # noqa: B008
        None, "--system", "-s", help="system.yaml: nodes' topics and process patterns, computers' capacities."),
    out_path: Path | None = typer.Option(None, "--out", "-o", help="characterisation.csv to write."),  # noqa: B008
    as_json: bool = typer.Option(False, "--json", help="Print the rows as a JSON array on stdout (only)."),
    slow: bool = typer.Option(False, "--slow", help="Stream every message instead of reading the indexes."),
    scheduler: str | None = typer.Option(None, "--scheduler", help="Run on a dask.distributed cluster (tcp://HOST:PORT)."),
    workers: int | None = typer.Option(None, "--workers", help="Run on a local Dask cluster of N worker processes."),
    latency: bool = typer.Option(
        False, "--latency",
        help="Also the latency_* columns: receive time - header.stamp of the topics with a std_msgs/Header."),
    plot: Path | None = typer.Option(  # noqa: B008
        None, "--plot", help="Also write a PNG: CPU and frequency per setting of each configurable node."),
) -> None:
    """Characterise every recording in DIR: per node and topic, frequency, bandwidth and CPU."""
    from rich.markup import escape
    from rich.table import Table

    from perfros_bag.characterisation.csvfile import write_characterisation
    from perfros_bag.characterisation.table import (
        characterise,
        check_settings,
        find_entries,
        rows_json,
        table_one,
    )
    from perfros_bag.errors import PerfrosError

    if out_path is None and not as_json:
        raise PerfrosError("characterise needs --out FILE or --json")
    for target in (out_path, plot):
        if target is not None and target.is_dir():
            raise PerfrosError(f"{target}: is a directory, expected a file to write")
    entries, manifest_system = find_entries(directory, manifest)
    sys_file = system_path or manifest_system
    system = None
    if sys_file is not None:
        from perfros_bag.system.systemfile import load_system

        system = load_system(sys_file)
    if system is not None and entries:
        check_settings(entries, system, manifest or directory / "manifest.yaml")
    if not entries:
        raise PerfrosError(f"{directory}: no recordings found")

    with _progress_bar(len(entries)) as done:
        result = characterise(entries, system, fast=not slow, on_done=done, scheduler=scheduler, workers=workers,
                               latency=latency)

    for f in result.failures:
        err.print(f"[red]error:[/] {escape(f.message)}", highlight=False, soft_wrap=True)
    if result.exit_code == 2:  # nothing could be read: the error lines only, no output file
        raise typer.Exit(2)
    if out_path is not None:  # an empty result is a header-only file
        write_characterisation(out_path, result.rows)
    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(rows_json(result.rows), indent=1))
    if plot is not None and result.rows:
        from perfros_bag.report.characterisation_plots import plot_characterisation

        if not plot_characterisation(result.rows, plot):
            err.print(f"no node with two or more settings: {plot} not written", highlight=False)

    table = Table(title="characterisation (Table I)", title_justify="left")
    for col, just in (("node", "left"), ("setting", "left"), ("recordings", "right"), ("CPU", "right"),
                      ("freq Hz", "right"), ("kB/s", "right")):
        table.add_column(col, justify=just)  # type: ignore[arg-type]
    for t in table_one(result.rows):
        value = "" if t.value is None else f"{t.value:g}" if isinstance(t.value, int | float) else str(t.value)
        setting = f"{t.parameter}={value}" if t.parameter and value else value
        table.add_row(t.node, setting, str(t.recordings), _fmt(t.cpu), _fmt(t.frequency_hz, 2),
                      _fmt(t.bandwidth_kBps, 3))
    (err if as_json else out).print(table)
    summary = f"{len(result.rows)} rows from {result.recordings - len(result.failures)}/{result.recordings} recordings"
    if out_path is not None:
        summary += f" -> {out_path}"
    err.print(summary, highlight=False)
    if result.exit_code:
        raise typer.Exit(result.exit_code)
