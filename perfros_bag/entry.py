"""Console-script entry point: Ctrl-C while the CLI is still importing exits quietly, and
SIGUSR1 prints every thread's stack to stderr while the process goes on (``kill -USR1 PID``:
where a run that does not stop is waiting; the Ctrl-C tests ask for it before they give up
on one)."""

from __future__ import annotations

import sys


def main() -> None:
    import faulthandler
    import signal

    if hasattr(signal, "SIGUSR1") and sys.stderr is not None:
        try:
            faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)
        except (AttributeError, OSError, ValueError):  # a stderr with no file descriptor
            pass
    try:
        from perfros_bag.cli import main as cli_main
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    cli_main()
