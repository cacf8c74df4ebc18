"""The ``perfros-bag`` command line: a thin typer layer over the library.

Each verb lives in its own module of this package (``solve.py``, ``ingest.py``, ...),
registering itself on :data:`app` with :func:`perfros_bag.cli._app.command`; this module
imports them all. User errors print one line on stderr and exit 2 (see ``_app``).
"""

from __future__ import annotations

import importlib
import pkgutil

from perfros_bag.cli._app import app, main, out

for _mod in sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")):
    importlib.import_module(f"{__name__}.{_mod}")


@app.command("version")
def version() -> None:
    """Print perfros-bag's version."""
    from perfros_bag import __version__

    out.print(__version__)

__all__ = ["app", "main"]
