"""``tune.json`` (format ``perfros-bag/tune@1``, docs/formats.md): the one reader and writer.

The document is plain JSON written atomically after every finished round, so a run that is
interrupted or fails keeps every round it finished, and a new start resumes after them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import DOCUMENT_KINDS, atomic_write_json, expect_kind, read_json
from perfros_bag.limits import tree_problem

TUNE_FORMAT = "perfros-bag/tune@1"
#: why the loop stopped (``stopped.reason``)
STOP_REASONS = ("within tolerance", "plan unchanged", "rounds")
_ROUND_KEYS = ("round", "dir", "values", "placement", "expected", "measured", "deviation_pct",
               "within_tolerance", "nodes", "computers")


def write_tune(path: str | Path, document: dict[str, Any]) -> None:
    """Write tune.json atomically (a reader never sees half of it)."""
    atomic_write_json(path, document)


def read_tune(path: str | Path) -> dict[str, Any]:
    """Read tune.json, checking what the loop, its table and the report rely on."""
    data = read_json(path)
    kind = DOCUMENT_KINDS[TUNE_FORMAT]
    expect_kind(path, data, kind, {kind})
    if not isinstance(data, dict) or data.get("format") != TUNE_FORMAT:
        raise InputError(path, f"not a perfros-bag tune document (expected format {TUNE_FORMAT!r})")
    rounds = data.get("rounds")
    if not isinstance(rounds, list):
        raise InputError(path, "'rounds' must be a list")
    for i, r in enumerate(rounds):
        where = f"rounds[{i}]"
        if not isinstance(r, dict):
            raise InputError(path, f"{where}: must be an object")
        missing = [k for k in _ROUND_KEYS if k not in r]
        if missing:
            raise InputError(path, f"{where}: missing {', '.join(map(repr, missing))}")
        if r["round"] != i + 1:
            raise InputError(path, f"{where}: 'round' must be {i + 1}, got {r['round']!r}")
        if not isinstance(r["nodes"], dict) or not isinstance(r["computers"], dict):
            raise InputError(path, f"{where}: 'nodes' and 'computers' must be objects")
        problem = tree_problem(r, where)
        if problem is not None:
            raise InputError(path, problem)
    stopped = data.get("stopped")
    if stopped is not None and (not isinstance(stopped, dict) or stopped.get("reason") not in STOP_REASONS):
        raise InputError(path, f"'stopped' must be null or name a reason ({', '.join(STOP_REASONS)})")
    return data
