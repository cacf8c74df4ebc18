"""The typer app, the shared consoles and the error handling every verb goes through."""

from __future__ import annotations

import functools
import re
import warnings
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import typer
from rich.console import Console, ConsoleOptions, ConsoleRenderable, RenderHook
from rich.markup import escape
from rich.segment import Segment
from rich.table import Table
from typer._click.globals import get_current_context

from perfros_bag.cli._lazy import LazyVerbGroup
from perfros_bag.cli._numbers import check_numbers
from perfros_bag.errors import PerfrosError


def _no_group_options() -> None:
    """No options before the verb (a callback keeps the app a group with 0 or 1 verbs loaded)."""


#: The verbs register here (:func:`command`); ``--help`` lists them all without importing them.
app = typer.Typer(
    name="perfros-bag",
    cls=LazyVerbGroup,
    callback=_no_group_options,
    help="Characterise ROS recordings, fit regressions, solve placement and settings, validate runs.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

#: C0 and C1 control characters but newline and tab: shown escaped, never sent raw
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def printable(text: str) -> str:
    """``text`` with every control character shown as its escape (ESC -> ``\\x1b``): a name
    or message from a hostile file cannot move the cursor, recolour or retitle the terminal."""
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


#: the widest a table is drawn when the output is not a terminal (a file, a pipe, CI's log)
MAX_PIPED_WIDTH = 1000


def _unsqueezed(table: Table, console: Console, options: ConsoleOptions) -> tuple[Table, ConsoleOptions]:
    """Into a file or pipe, rich draws at 80 columns and cuts names to ``navigat…``: there,
    a table is drawn as wide as its content needs (up to :data:`MAX_PIPED_WIDTH`), and a
    cell that still does not fit folds onto more lines instead of losing its end."""
    for column in table.columns:
        if column.overflow == "ellipsis":
            column.overflow = "fold"
    if table.expand:  # a table that fills its width keeps the console's
        return table, options
    return table, options.update(width=max(options.max_width, MAX_PIPED_WIDTH))  # it takes what it needs


class _Escaped:
    """A renderable whose text segments carry no raw control character (rich passes ESC
    through); rich's own control segments (cursor moves of live displays) stay as they are.
    Not on a terminal, a table is widened to its content (:func:`_unsqueezed`)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> Iterator[Segment]:
        inner = self.inner
        if isinstance(inner, Table) and not console.is_terminal:
            inner, options = _unsqueezed(inner, console, options)
        for seg in console.render(inner, options):
            if seg.control is None and _CONTROL.search(seg.text):
                yield Segment(printable(seg.text), seg.style)
            else:
                yield seg


class _EscapeHook(RenderHook):
    def process_renderables(self, renderables: list[ConsoleRenderable]) -> list[ConsoleRenderable]:
        return [_Escaped(r) for r in renderables]


class _Console(Console):
    """rich's Console, but into a file or pipe the lines of a widened table are not cut
    back to the console's width (:func:`_unsqueezed`)."""

    def print(self, *objects: Any, **kwargs: Any) -> None:
        if not self.is_terminal:
            kwargs.setdefault("crop", False)
        super().print(*objects, **kwargs)


#: stdout carries only the JSON document with --json; tables go to stdout otherwise.
out = _Console()
#: progress bars, warnings and errors go to stderr.
err = _Console(stderr=True)
for _console in (out, err):
    _console.push_render_hook(_EscapeHook())

F = TypeVar("F", bound=Callable[..., Any])


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    err.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False, markup=True, soft_wrap=True)


def command(*args: Any, group: typer.Typer | None = None, interrupted: str = "interrupted",
            **kwargs: Any) -> Callable[[F], F]:
    """``@app.command`` (or ``group.command`` for a sub-command group) plus: every number flag
    is checked first (:func:`~perfros_bag.cli._numbers.check_numbers`: finite, in its range);
    a PerfrosError becomes one line on stderr and its exit code (2); Ctrl-C prints
    ``interrupted`` and exits 130."""

    def decorate(func: F) -> F:
        @functools.wraps(func)
        def wrapper(*a: Any, **kw: Any) -> Any:
            warnings.showwarning = _show_warning
            try:
                ctx = get_current_context(silent=True)
                if ctx is not None:  # every number flag finite and in range, before anything starts
                    check_numbers(ctx, kw)
                return func(*a, **kw)
            except PerfrosError as exc:
                err.print(f"[red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True, markup=True)
                raise typer.Exit(exc.exit_code) from None
            except KeyboardInterrupt:
                err.print(f"[red]{escape(interrupted)}[/]")
                raise typer.Exit(130) from None

        (group or app).command(*args, **kwargs)(wrapper)
        return func

    return decorate


#: True when the verb is this process (the console script, ``python -m perfros_bag``), not
#: a call into the app from another program (a test's CliRunner): then a whole-process
#: budget (``solve --time-limit``) counts from the process's start
WHOLE_PROCESS = False


def main() -> None:
    """Console-script entry point."""
    global WHOLE_PROCESS
    WHOLE_PROCESS = True
    app(prog_name="perfros-bag")
