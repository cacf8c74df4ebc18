"""The ``perfros-bag`` command line: a thin typer layer over the library.

Each verb lives in its own module of this package (``solve.py``, ``info.py``, ...),
registering itself on :data:`app` with :func:`perfros_bag.cli._app.command`. The modules are
imported on demand, one per run (``_lazy.VERBS`` lists them), so ``--help`` starts fast.
User errors print one line on stderr and exit 2 (see ``_app``).
"""

from __future__ import annotations

from perfros_bag.cli._app import app, main

__all__ = ["app", "main"]
