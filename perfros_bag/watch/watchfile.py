"""A ``watch --out DIR`` folder read back: its windows (``windows.jsonl``) and its re-plans
(``adapt.jsonl``), for the report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import read_text

WINDOWS_FILE = "windows.jsonl"


def _lines(path: Path) -> list[dict[str, Any]]:
    out = []
    for i, line in enumerate(read_text(path).splitlines(), 1):
        if not line.strip():
            continue
        try:
            doc = json.loads(line)
        except ValueError as exc:
            raise InputError(path, f"line {i}: not JSON ({exc})") from None
        if not isinstance(doc, dict):
            raise InputError(path, f"line {i}: expected a JSON object")
        out.append(doc)
    return out


def read_watch(folder: str | Path) -> dict[str, Any]:
    """``{"windows": [...], "replans": [...]}`` of a watch's ``--out`` folder."""
    from perfros_bag.watch.adapt import ADAPT_LOG
    from perfros_bag.watch.window import WINDOW_FORMAT

    root = Path(folder)
    windows = _lines(root / WINDOWS_FILE)
    for i, w in enumerate(windows, 1):
        if w.get("format") != WINDOW_FORMAT or not {"t", "overall", "nodes", "alarms"} <= set(w):
            raise InputError(root / WINDOWS_FILE, f"line {i}: not a watch window ({WINDOW_FORMAT})")
    replans = _lines(root / ADAPT_LOG) if (root / ADAPT_LOG).exists() else []
    return {"folder": str(root), "windows": windows, "replans": replans}
