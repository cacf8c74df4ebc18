"""``perfros-bag init DIR --out system.yaml``: draft the system from a sweep's folder."""

from __future__ import annotations

from pathlib import Path

import typer

from perfros_bag.cli._app import command, err


@command("init")
def init_cmd(
    directory: Path = typer.Argument(..., metavar="DIR", help="The folder `sweep` recorded into."),  # noqa: B008
    out_path: Path = typer.Option(..., "--out", "-o", help="The system.yaml to write."),  # noqa: B008
) -> None:
    """Draft system.yaml from DIR's graph.yaml, manifest and recordings (loads, fits and solves as it is)."""
    from perfros_bag.errors import PerfrosError
    from perfros_bag.sweep.draft import draft_system

    if out_path.is_dir():
        raise PerfrosError(f"{out_path}: is a directory, expected the system.yaml to write")
    draft = draft_system(directory, out_path)
    err.print(f"wrote {out_path}: {len(draft.nodes)} node(s); review the lines marked REPLACE", highlight=False)
