"""``perfros-bag version``."""

from __future__ import annotations

from perfros_bag.cli._app import command, out


@command("version")
def version() -> None:
    """Print perfros-bag's version."""
    from perfros_bag import __version__

    out.print(__version__)
