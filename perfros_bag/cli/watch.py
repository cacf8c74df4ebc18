"""``perfros-bag watch PLAN``: the running plan checked live, window by window (eq 10, CPU,
links), alarms when a drift persists; ``--adapt`` re-plans."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import typer
from rich import box
from rich.markup import escape
from rich.table import Table

from perfros_bag.cli._app import command, err, out
from perfros_bag.validation import DEFAULT_TOLERANCE


def _f(x: Any, fmt: str = ".3g") -> str:
    return "-" if x is None else format(x, fmt)


def window_table(doc: dict[str, Any]) -> Table:
    """One window as a rich table: per node its rates, CPU and eq 10."""
    o = doc["overall"]
    t = Table(title=f"window {doc['window']} ({doc['seconds']:.1f} s): Σ w·P expected {o['expected']:.4g}, "
                    f"measured {o['measured']:.4g} ({o['deviation_pct']:.1f} %)", box=box.SIMPLE_HEAD)
    for col in ("node", "computer", "Hz exp", "Hz meas", "cpu exp", "cpu", "dev%", "state"):
        t.add_column(col, justify="left" if col in ("node", "computer", "state") else "right")
    alarmed = {a.get("node") for a in doc["alarms"]}
    for name, n in doc["nodes"].items():
        state = "[yellow]restarting[/]" if n.get("state") == "restarting" else "[red]dead[/]" if not n["alive"] \
            else "[red]alarm[/]" if name in alarmed else "[yellow]unreadable[/]" if n.get("state") == "unreadable" \
            else "ok"
        t.add_row(escape(name), escape(n["computer"]), _f(n["expected_hz"]), _f(n["measured_hz"]),
                  _f(n["cpu_expected"]), _f(n.get("cpu")) if "cpu" in n else "[dim]unmeasured[/]",
                  _f(n["deviation_pct"], ".1f"), state)
    for link in doc["links"]:
        t.add_row(f"link {escape(' - '.join(link['between']))}", "", "", "", "", "", "",
                  f"{link['measured_kBps']:.1f} of {link['capacity_kBps']:.4g} kB/s"
                  f" (planned {_f(link['expected_kBps'], '.1f')})")
    return t


@command("watch", interrupted="interrupted: watch started nothing, nothing is left running")
def watch_cmd(
    plan: Path = typer.Argument(..., metavar="PLAN", help="The plan.json that runs."),  # noqa: B008
    deployment: Path | None = typer.Option(  # noqa: B008
        None, "--deployment",
        help="Attach to `deploy --out DIR` in progress (its master, namespaces, cgroups)."),
    master: str | None = typer.Option(None, "--master", help="The ROS master's URI (default: ROS_MASTER_URI)."),
    system: Path | None = typer.Option(  # noqa: B008
        None, "--system", help="The plan's system.yaml, for link loads (default: the plan's)."),
    window: float = typer.Option(5.0, "--window", help="Seconds per window (positive, finite)."),
    tolerance: float = typer.Option(
        DEFAULT_TOLERANCE, "--tolerance",
        help="Drift in % (of a node's planned rate, a chain's predicted p95) beyond which a window drifts."),
    latency_tolerance: float | None = typer.Option(
        None, "--latency-tolerance",
        help="Drift in % of a chain's predicted p95 beyond which a window drifts (default: --tolerance)."),
    latency_alarms: bool = typer.Option(
        True, "--latency-alarms/--no-latency-alarms",
        help="Alarm on chains' latency; --no-latency-alarms reports it without alarms."),
    persist: int = typer.Option(2, "--persist", help="Windows in a row a drift must last to raise an alarm."),
    partial: bool = typer.Option(False, "--partial", help="Watch the planned nodes that run when some do not."),
    windows: int | None = typer.Option(
        None, "--windows", help="Stop after N windows (default: until Ctrl-C or the master/deploy ends)."),
    json_out: bool = typer.Option(False, "--json", help="One JSON object per window on stdout."),
    out_dir: Path | None = typer.Option(  # noqa: B008
        None, "--out", "-o",
        help="Folder for windows.jsonl, characterisation.csv (a row per window, node, topic) and the re-plans."),
    adapt: bool = typer.Option(
        False, "--adapt",
        help="On a new alarm, refit with the live windows, re-solve and write the new plan (needs --out); "
             "with --deployment the deploy applies it, else nothing is restarted."),
    launch: Path | None = typer.Option(  # noqa: B008
        None, "--launch", help="With --adapt: your launch file, to write each new plan's planned.launch."),
    space: Path | None = typer.Option(None, "--space", help="With --adapt and --launch: the space.yaml of the sweep."),  # noqa: B008
) -> None:
    """Watch a running plan live: rates, CPU, links and eq 10 per window; alarms on persisting drift.

    Exit code: 0 no alarm, 1 an alarm was raised, 2 bad input."""
    from perfros_bag.errors import InputError
    from perfros_bag.fileio import json_text
    from perfros_bag.watch.loop import check_window, watch

    check_window(window)
    if windows is not None and windows < 1:
        raise InputError(None, f"--windows must be >= 1, got {windows}")
    adapter = None
    if adapt:
        if out_dir is None:
            raise InputError(None, "--adapt needs --out DIR (where the new plans and their log go)")
        from perfros_bag.watch.adapt import Adapter

        adapter = Adapter(out_dir, plan, launch, space, deployment)
    live_ctx: Any = None
    if not json_out and out.is_terminal:
        from rich.live import Live

        live_ctx = Live(console=out, auto_refresh=False)
        live_ctx.start()

    def show(doc: dict[str, Any], new: list[dict[str, Any]]) -> None:
        if json_out:
            out.file.write(json_text(doc, indent=None) + "\n")
            out.file.flush()
        elif live_ctx is not None:
            live_ctx.update(window_table(doc), refresh=True)
        else:
            out.print(window_table(doc))
        # above the live table when there is one (rich keeps it below), else on stderr
        say = live_ctx.console if live_ctx is not None else err
        for a in new:
            say.print(f"[red]{escape(a['line'])}[/]", highlight=False)
        if "replan" in doc:
            r = doc["replan"]
            say.print(f"re-planned: {escape(r['plan'])} ({len(r['changes'])} change(s))", highlight=False)

    try:
        result = watch(plan, master_uri=master, deployment=deployment, system_path=system, window_s=window,
                       tolerance=tolerance, persist=persist, partial=partial, windows=windows, out=out_dir,
                       adapt=adapter,
                       latency_tolerance=latency_tolerance if latency_alarms else math.inf, on_window=show)
    finally:
        if live_ctx is not None:
            live_ctx.stop()
    if result.ended:
        err.print(f"watch ended: {escape(result.ended)}", highlight=False)
    err.print(f"{result.windows} window(s), {len(result.alarms)} alarm(s)", highlight=False)
    if result.alarms:
        raise typer.Exit(1)
