"""``perfros-bag casestudy run|cleanup``: the paper's case study on real ROS 1."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer
from rich.markup import escape

from perfros_bag.cli._app import app, command, err, out
from perfros_bag.cli._lazy import QuickHelpGroup

casestudy_app = typer.Typer(cls=QuickHelpGroup,
                            help="The paper's case study on real ROS 1 nodes (roscore, rospy, rosbag).",
                            no_args_is_help=True)
app.add_typer(casestudy_app, name="casestudy")

_CLEANED = "interrupted (every process and cgroup of the run was removed)"


def _parse_overrides(items: list[str]) -> dict[str, float]:
    from perfros_bag.errors import InputError

    found: dict[str, float] = {}
    for item in items:
        name, sep, raw = item.partition("=")
        try:
            if not sep or not name.strip():
                raise ValueError
            found[name.strip()] = float(raw)
        except ValueError:
            raise InputError(None, f"--set {item!r}: expected NODE=VALUE (a number)") from None
    return found


@command("run", group=casestudy_app, interrupted=_CLEANED)
def run_cmd(
    system: Path = typer.Option(..., "--system", "-s", help="system.yaml whose settings (Table I) the nodes emulate."),  # noqa: B008
    plan: Path = typer.Option(..., "--plan", "-p", help="plan.json: each node's setting and computer."),  # noqa: B008
    out_dir: Path = typer.Option(..., "--out", "-o", help="Run folder: run.bag, run.cpu.csv, manifest.yaml, run.json."),  # noqa: B008
    duration: float = typer.Option(30.0, "--duration", "-d", help="Seconds of recording (>= 1)."),
    override: list[str] | None = typer.Option(  # noqa: B008
        None, "--set", help="NODE=VALUE: force a parameter above/below the plan (RQ3); repeatable."),
    units_per_core: float = typer.Option(400.0, "--units-per-core",
                                         help="CPU units per core (400: a robot of 100 = 0.25 core; >= 1)."),
    headroom: float = typer.Option(0.85, "--headroom",
                                   help="Nodes do this fraction of their Table I CPU (0.05 to 2)."),
    cap: bool = typer.Option(True, "--cap/--no-cap", help="Cap each computer's CPU with a cgroup."),
    as_json: bool = typer.Option(False, "--json", help="Print run.json on stdout (only)."),
) -> None:
    """Deploy PLAN on real ROS 1 for DURATION seconds: roscore, nodes (in cgroups), rosbag record,
    CPU trace; then stop everything and remove the cgroups."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from perfros_bag.casestudy.launcher import RunConfig, run_plan
    from perfros_bag.system.planfile import load_plan
    from perfros_bag.system.systemfile import load_system

    sys_ = load_system(system)
    pl = load_plan(plan)
    pl.require_feasible(plan, "deploy")
    cfg = RunConfig(duration=duration, units_per_core=units_per_core, headroom=headroom, cap=cap)
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeRemainingColumn(),
                  console=err, transient=True) as bar:
        task = bar.add_task("calibrating", total=None)

        def progress(stage: str, done: float, total: float) -> None:
            label = {"recording": f"recording {duration:g} s"}.get(stage, f"starting {stage}")
            if stage == "stopping":
                label = "stopping"
            bar.update(task, description=label, completed=done if stage == "recording" else None,
                       total=total if stage == "recording" else None)

        record = run_plan(sys_, pl, out_dir, cfg, overrides=_parse_overrides(override or []),
                          progress=progress, system_path=system)
    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(record, indent=None))
        return
    _summary(record, out_dir)


def _summary(record: dict[str, Any], out_dir: Path) -> None:
    from rich.table import Table

    cap = record["cpu_cap"]
    if cap["mode"] == "uncapped":
        err.print(f"[yellow]UNCAPPED run[/]: {escape(cap['reason'])}")
    table = Table(title=f"run {record['run_id']} ({cap['mode']}, {record['duration_s']:g} s)")
    for col in ("computer", "capacity", "cores", "CPU measured", "throttled periods"):
        table.add_column(col, justify="right" if col != "computer" else "left")
    loads = record.get("loads", {}).get("computers", {})
    for comp, cores in cap["cores"].items():
        thr = record.get("throttling", {}).get(comp, {})
        frac = (f"{thr['nr_throttled'] / thr['nr_periods']:.0%}" if thr.get("nr_periods") else "-")
        table.add_row(comp, f"{cores * cap['units_per_core']:g}", f"{cores:g}",
                      f"{loads.get(comp, {}).get('cpu', float('nan')):.1f}", frac)
    out.print(table)
    out.print(f"wrote {out_dir}/run.bag, run.cpu.csv, manifest.yaml, plan.json, run.json; "
              f"check it with: perfros-bag validate {out_dir}/run.bag {out_dir}/plan.json", highlight=False)


@command("cleanup", group=casestudy_app, interrupted=_CLEANED)
def cleanup_cmd(
    run: str | None = typer.Option(None, "--run", help="Only this run id (run.json's run_id); default: every run."),
) -> None:
    """Kill processes and remove cgroups left by a case-study run that was itself killed (-9)."""
    from perfros_bag.rosrun.cgroups import leftover_groups
    from perfros_bag.rosrun.processes import kill_stale

    pids, groups = kill_stale(run), leftover_groups(run_id=run)
    removed = []
    for g in groups:
        try:
            g.rmdir()
            removed.append(g)
        except OSError as exc:
            err.print(f"[yellow]warning:[/] cannot remove {g}: {exc}")
    out.print(f"killed {len(pids)} processes, removed {len(removed)} cgroups", highlight=False)
