"""``characterisation.csv``: its row type, the writer and the (checked) reader.

One row per (recording, node, topic); column order = :class:`Row`'s field order; empty
cells are ``None``; floats are written with ``repr`` (non-finite ones as empty cells);
whole-number setting values are written as integers. Format: ``docs/formats.md``.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from perfros_bag.characterisation.manifest import SettingValue
from perfros_bag.errors import InputError
from perfros_bag.fileio import CHARACTERISATION_KIND, atomic_write_text, read_text, text_kind
from perfros_bag.limits import number_problem


@dataclass(frozen=True)
class Row:
    """One row of characterisation.csv (column order = field order)."""

    recording: str
    node: str
    parameter: str | None
    value: SettingValue | None
    topic: str | None
    msgtype: str | None
    messages: int | None
    duration_s: float | None
    frequency_hz: float | None
    bandwidth_kBps: float | None
    cpu_units_mean: float | None
    cpu_units_p95: float | None
    cpu_samples: int | None
    median_rate_hz: float | None = None
    p95_gap_s: float | None = None
    # message contents (perfros_bag/ingest/contents.py): empty unless read
    metric_value: float | None = None
    latency_p50_s: float | None = None
    latency_p95_s: float | None = None
    latency_max_s: float | None = None
    # the data flow: the measured rate of the node's input topic (system.yaml ``input``) in
    # this recording; empty for a node without one
    input_hz: float | None = None
    # the machine's speed in the row's recording (perfros_bag.cpu.speed: manifest entry's
    # ``speed_factor``, else the CPU trace's ``# speed_factor=``); recorded, never applied
    speed_factor: float | None = None
    # the node's busy threads in the row's recording (the CPU trace's optional ``threads``
    # column, its mean over the samples where the node ran); empty without it
    threads: float | None = None


#: Columns written only when some row has a value (appended after the others, in this order).
OPTIONAL_COLUMNS: tuple[str, ...] = ("speed_factor", "threads")
#: The columns always written, in order.
COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(Row) if f.name not in OPTIONAL_COLUMNS)
ALL_COLUMNS: tuple[str, ...] = COLUMNS + OPTIONAL_COLUMNS
#: The columns a characterisation.csv must have (the others came later: optional).
REQUIRED_COLUMNS = ("recording", "node", "value", "topic", "frequency_hz", "bandwidth_kBps", "cpu_units_mean")
_INT_COLUMNS = frozenset({"messages", "cpu_samples"})
_TEXT_COLUMNS = frozenset({"parameter", "topic", "msgtype"})


# --------------------------------------------------------------------------- writing


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    return str(v)


def columns_for(rows: Iterable[Row]) -> tuple[str, ...]:
    """:data:`COLUMNS`, then each of :data:`OPTIONAL_COLUMNS` that some row fills."""
    rows = list(rows)
    return COLUMNS + tuple(c for c in OPTIONAL_COLUMNS if any(getattr(r, c) is not None for r in rows))


def rows_csv(rows: Iterable[Row], columns: tuple[str, ...] | None = None, *, header: bool = True) -> str:
    """The file's text: the header (unless ``header`` is false), then one line per row, in
    ``columns`` (default :func:`columns_for` the rows)."""
    rows = list(rows)
    columns = columns_for(rows) if columns is None else columns
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    if header:
        w.writerow(columns)
    for r in rows:
        w.writerow([_cell(getattr(r, c)) for c in columns])
    return buf.getvalue()


def write_characterisation(path: str | Path, rows: Iterable[Row]) -> None:
    """Write characterisation.csv atomically; a path that cannot be written is an InputError."""
    if Path(path).is_dir():
        raise InputError(path, "is a directory, expected the output CSV file")
    try:
        atomic_write_text(path, rows_csv(rows))
    except OSError as exc:
        raise InputError(path, f"cannot write: {exc.strerror or exc}") from None


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class CharacterisationFile:
    """A read characterisation.csv: the typed rows, and the file as written (its header
    and string cells, for display) with each row's line number (for error messages)."""

    path: Path
    columns: tuple[str, ...]
    cells: list[dict[str, str]]
    lines: list[int]
    rows: list[Row]


class _BadCell(ValueError):
    """A cell that is not what its column holds (the reader adds file, line and column)."""


def _number(text: str) -> float:
    """A numeric cell: a finite number >= 0 within :data:`~perfros_bag.limits.MAX_MAGNITUDE`."""
    try:
        v = float(text)
    except ValueError:
        raise _BadCell(f"{text!r} is not a number") from None
    problem = number_problem(v, nonneg=True)
    if problem is not None:
        raise _BadCell(f"{text!r}: {problem}")
    return v


def _integer(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        f = _number(text)
        if not f.is_integer():
            raise _BadCell(f"{text!r} is not a whole number") from None
        return int(f)
    problem = number_problem(v, nonneg=True)
    if problem is not None:
        raise _BadCell(f"{text[:40]!r}: {problem}")
    return v


def parse_value(text: str) -> SettingValue | None:
    """A setting value cell: empty -> None, an integer, a float, else the text (a setting
    may be named). A number that is not finite or beyond
    :data:`~perfros_bag.limits.MAX_MAGNITUDE` is a ``ValueError``."""
    if not text:
        return None
    number: int | float
    try:
        number = int(text)
    except ValueError:
        try:
            number = float(text)
        except ValueError:
            return text
    problem = number_problem(number)
    if problem is not None:
        raise _BadCell(f"{text[:40]!r}: {problem}")
    return number


def _row(cells: dict[str, str]) -> Row:
    kw: dict[str, Any] = {}
    for name in ALL_COLUMNS:
        text = cells.get(name, "").strip()
        try:
            if name in ("recording", "node"):
                kw[name] = text
            elif name == "value":
                kw[name] = parse_value(text)
            elif name in _TEXT_COLUMNS:
                kw[name] = text or None
            elif name in _INT_COLUMNS:
                kw[name] = _integer(text) if text else None
            else:
                kw[name] = _number(text) if text else None
        except _BadCell as exc:
            raise _BadCell(f"column {name}: {exc}") from None
    return Row(**kw)


def _uncommented(text: str, numbers: list[int]) -> Iterator[str]:
    """The lines that are not ``#`` comments; ``numbers[0]`` follows the file line number."""
    for n, line in enumerate(io.StringIO(text, newline=""), start=1):
        numbers[0] = n
        if not line.startswith("#"):
            yield line


def read_characterisation(path: str | Path) -> CharacterisationFile:
    """Read and check a characterisation.csv (``#`` lines are comments): the required
    columns must be there and at least one row. Cells that are not numbers where numbers
    are expected are an error, and so are numbers that are not finite, below 0 (all measured columns)
    or beyond :data:`~perfros_bag.limits.MAX_MAGNITUDE` (the ``value`` column may hold
    text, and any finite number within that limit). Every problem is an
    :class:`InputError` naming the file (and the line and column)."""
    p = Path(path)
    text = read_text(p, "characterisation CSV", newline="")
    line_no = [0]
    reader = csv.DictReader(_uncommented(text, line_no))
    try:
        header = [h.strip() for h in (reader.fieldnames or [])]
        if not header:
            raise InputError(p, "the file is empty (expected a characterisation.csv header)")
        missing = [c for c in REQUIRED_COLUMNS if c not in header]
        if missing:
            kind = text_kind(text)
            if kind is not None and kind != CHARACTERISATION_KIND:
                raise InputError(p, f"this is {kind}, expected a characterisation.csv")
            raise InputError(p, f"not a characterisation.csv: missing column(s) {', '.join(missing)}")
        cells: list[dict[str, str]] = []
        lines: list[int] = []
        for raw in reader:
            cells.append({(k or "").strip(): (v if isinstance(v, str) else "") for k, v in raw.items()})
            lines.append(line_no[0])
    except csv.Error as exc:
        raise InputError(p, f"invalid CSV: {exc}") from None
    if not cells:
        raise InputError(p, "has a header but no rows")
    rows: list[Row] = []
    for c, line in zip(cells, lines, strict=True):
        try:
            rows.append(_row(c))
        except _BadCell as exc:
            raise InputError(p, f"line {line}: {exc}") from None
    return CharacterisationFile(p, tuple(header), cells, lines, rows)
