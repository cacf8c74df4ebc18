"""``perfros-bag export PLAN --format roslaunch|ros2-params --out FILE``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from perfros_bag.cli._app import command, err


@command("export")
def export(
    plan: Annotated[Path, typer.Argument(help="plan.json to deploy.")],
    fmt: Annotated[str, typer.Option("--format", help="roslaunch (ROS 1 launch XML) or ros2-params (YAML).")],
    out_path: Annotated[Path, typer.Option("--out", help="File to write (atomically).")],
    system: Annotated[Path | None, typer.Option(
        "--system", help="system.yaml: launch: fields (package, type, param, name, namespace) and machines:.")] = None,
) -> None:
    """Write a plan as a ROS 1 launch file or a ROS 2 parameters file."""
    from perfros_bag.export.writers import export_plan

    export_plan(plan, fmt, out_path, system)
    err.print(f"wrote {escape(str(out_path))} ({escape(fmt)})", highlight=False)
