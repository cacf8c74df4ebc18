"""``perfros-bag export PLAN --format roslaunch|ros2-params --out FILE [--launch APP.launch --space space.yaml]``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from perfros_bag.cli._app import command, err


@command("export")
def export(
    plan: Annotated[Path, typer.Argument(help="plan.json to deploy.")],
    fmt: Annotated[str, typer.Option(
        "--format",
        help="roslaunch (ROS 1 launch XML) or ros2-params (YAML, and a ROS 2 launch file per computer beside it).")],
    out_path: Annotated[Path, typer.Option("--out", help="File to write (atomically).")],
    system: Annotated[Path | None, typer.Option(
        "--system", help="system.yaml: launch: fields (package, type, param, name, namespace) and machines:.")] = None,
    launch: Annotated[Path | None, typer.Option(
        "--launch", help="roslaunch: your own ROS 1 launch file; the plan is written into it (needs --space).")] = None,
    space: Annotated[Path | None, typer.Option(
        "--space",
        help="with --launch: the sweep's space.yaml (how each node's value reaches the launch file).")] = None,
) -> None:
    """Write a plan as a ROS 1 launch file (yours, with --launch) or ROS 2 files."""
    from perfros_bag.errors import InputError

    if (launch is None) != (space is None):
        raise InputError(None, "--launch and --space go together: your launch file and the sweep's space.yaml")
    if launch is not None and fmt != "roslaunch":
        raise InputError(None, f"--launch writes a ROS 1 launch file: use it with --format roslaunch, not {fmt!r}")
    if launch is not None and space is not None:
        from perfros_bag.export.planned import export_planned

        export_planned(plan, launch, space, out_path, system)
        err.print(f"wrote {escape(str(out_path))} ({escape(str(launch))}, planned)", highlight=False)
        return
    from perfros_bag.export.writers import export_plan

    export_plan(plan, fmt, out_path, system)
    err.print(f"wrote {escape(str(out_path))} ({escape(fmt)})", highlight=False)
