"""Console-script entry point: Ctrl-C while the CLI is still importing exits quietly."""

from __future__ import annotations

import sys


def main() -> None:
    try:
        from perfros_bag.cli import main as cli_main
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    cli_main()
