"""What the pipelines share: running a shown command, and writing results into a docs page."""

from __future__ import annotations

import csv
import shlex
import shutil
import signal
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console

from perfros_bag.fileio import atomic_write_text


def read_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """A CSV file's columns and rows (a characterisation.csv the pipeline copies per instance)."""
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        return list(reader.fieldnames or []), list(reader)


def write_rows(path: Path, fields: list[str], rows: list[dict[str, str]]) -> None:
    """Write ``rows`` as a CSV file with the columns ``fields``."""
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


def run_shown(args: Sequence[object], *, root: Path, program: Path, commands: list[str], console: Console,
              ok: tuple[int, ...] = (0,)) -> subprocess.CompletedProcess[str]:
    """Run ``args``; show it (paths relative to ``root``, ``program`` as ``perfros-bag``) on
    ``console`` and append it to ``commands`` (for the results page); a ``SystemExit`` naming
    it and the end of its stderr when its exit code is not in ``ok``."""
    shown = " ".join(shlex.quote(str(a)) for a in args).replace(str(program), "perfros-bag")
    shown = shown.replace(str(root) + "/", "")
    commands.append(shown)
    console.print(f"[dim]$ {shown}[/]", highlight=False)
    done = run_to_end([str(a) for a in args])
    if done.returncode not in ok:
        raise SystemExit(f"error: `{shown}` failed ({done.returncode}): {done.stderr.strip()[-1500:]}")
    return done


#: seconds a step is given to clean up (stop its nodes, remove its cgroups and namespaces) after
#: the pipeline is interrupted, before it is killed
CLEANUP_S = 120.0


def run_to_end(args: list[str], cleanup_s: float = CLEANUP_S) -> subprocess.CompletedProcess[str]:
    """Run one pipeline step, its output captured. The step runs in a session of its own, so an
    interrupt reaches it once, from here: on Ctrl-C (or SIGTERM, see ``interrupt_on_sigterm``) it
    gets one SIGINT and up to ``cleanup_s`` seconds to clean up, then the interrupt goes on.
    (``subprocess.run`` would SIGKILL it: a deploy's nodes, cgroups and namespaces would stay.)"""
    with subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          start_new_session=True) as proc:
        try:
            out, err = proc.communicate()
        except KeyboardInterrupt:
            proc.send_signal(signal.SIGINT)
            try:
                proc.communicate(timeout=cleanup_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
            raise
    return subprocess.CompletedProcess(args, proc.returncode, out, err)


def interrupt_on_sigterm() -> None:
    """A pipeline stopped from outside (SIGTERM) cleans up as on Ctrl-C."""

    def interrupted(_sig: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupted)


def write_section(docs: Path, name: str, section: str, out: Path, images: tuple[str, ...], title: str) -> None:
    """Replace what stands between ``<!-- NAME-results:begin -->`` and ``...:end -->`` in
    ``docs`` with ``section`` (the markers are appended, or the page made with ``title``,
    when missing); copy ``images`` that exist in ``out`` into ``docs``'s folder ``NAME/``."""
    begin, end = f"<!-- {name}-results:begin -->", f"<!-- {name}-results:end -->"
    text = docs.read_text() if docs.exists() else f"# {title}\n\n{begin}\n{end}\n"
    if begin not in text:
        text += f"\n{begin}\n{end}\n"
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    atomic_write_text(docs, f"{head}{begin}\n{section}\n{end}{tail}")
    img = docs.parent / name
    img.mkdir(exist_ok=True)
    for image in images:
        if (out / image).exists():
            shutil.copyfile(out / image, img / image)
