"""Recordings (+ CPU traces, manifest, system) -> the characterisation table.

:func:`characterise` runs :func:`~perfros_bag.characterisation.recording.characterise_recording`
over the entries, in this process or on Dask (:mod:`perfros_bag.characterisation.cluster`);
:func:`table_one` is the paper's Table I of the rows. The file is written by
:mod:`perfros_bag.characterisation.csvfile`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.characterisation.manifest import (
    RecordingEntry,
    SettingValue,
    default_cpu_path,
    load_manifest,
)
from perfros_bag.characterisation.recording import characterise_recording, reporting
from perfros_bag.characterisation.settings import by_setting, mean
from perfros_bag.errors import InputError, PerfrosError
from perfros_bag.fileio import file_kind
from perfros_bag.system.types import System


@dataclass(frozen=True)
class Failure:
    recording: str
    message: str


@dataclass
class Result:
    rows: list[Row]
    failures: list[Failure]
    recordings: int  # how many were attempted
    #: each container's CPU split among its nodes (perfros_bag.characterisation.containers)
    splits: list[Any] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """0 all good, 1 some recordings failed, 2 none could be read."""
        if not self.failures:
            return 0
        return 2 if len(self.failures) >= self.recordings else 1



# --------------------------------------------------------------------------- a directory


def find_entries(directory: str | Path, manifest: str | Path | None = None) -> tuple[list[RecordingEntry], Path | None]:
    """The recordings to characterise and the manifest's system path (if any).

    With a manifest (given, or ``DIR/manifest.yaml``): its entries. Otherwise every
    recording discovered in DIR, each with its ``<stem>.cpu.csv`` when present."""
    d = Path(directory)
    if not d.exists():
        raise InputError(d, "directory not found")
    mpath = Path(manifest) if manifest is not None else None
    kind = file_kind(d) if mpath is None else None
    if kind is not None:
        raise InputError(d, f"this is {kind}, expected a folder of recordings or one recording")
    if mpath is None and d.is_dir() and (d / "manifest.yaml").is_file():
        mpath = d / "manifest.yaml"
    if mpath is not None:
        m = load_manifest(mpath)
        return list(m.recordings), m.system
    from perfros_bag.ingest.discover import find_recordings

    entries = []
    for path in find_recordings(d):
        try:
            name = str(path.relative_to(d)) if d.is_dir() else path.name
        except ValueError:
            name = str(path)
        entries.append(RecordingEntry(path, name, default_cpu_path(path)))
    return entries, None


def check_settings(entries: Iterable[RecordingEntry], system: System, source: str | Path) -> None:
    """Manifest settings must name nodes of the system, and computers its computers unless
    the entry gives its own ``units_per_core`` (then the computer only says where it was
    measured: the robot the system describes may be another machine)."""
    for e in entries:
        for node in e.settings:
            if node not in system.node:
                raise InputError(source, f"recording {e.name!r}: settings name unknown node {node!r}")
        if e.computer is not None and e.units_per_core is None and e.computer not in system.computer:
            raise InputError(source, f"recording {e.name!r}: unknown computer {e.computer!r}")


def characterise(entries: Sequence[RecordingEntry], system: System | None = None, *, fast: bool = True,
                 on_done: Callable[[RecordingEntry, Failure | None], None] | None = None,
                 scheduler: str | None = None, workers: int | None = None,
                 latency: bool = False) -> Result:
    """Characterise every entry; a failing recording becomes a :class:`Failure`, not an abort.

    In this process by default; with ``scheduler`` (a dask.distributed address) or
    ``workers`` (a LocalCluster of that many processes) the per-recording work runs on
    Dask through :func:`perfros_bag.characterisation.distributed.run_distributed`. Rows keep entry order.
    ``latency``: also the ``latency_*`` columns (on Dask too: a split recording's parts
    bring their stamps, merged before the percentiles).
    """
    if scheduler is not None or workers is not None:
        return _characterise_dask(entries, system, fast, on_done, scheduler, workers, latency)
    rows: list[Row] = []
    failures: list[Failure] = []
    for entry in entries:
        failure = None
        try:
            with reporting(entry):
                rows.extend(characterise_recording(entry, system, fast=fast, latency=latency))
        except PerfrosError as exc:
            failure = Failure(entry.name, str(exc))
        if failure is not None:
            failures.append(failure)
        if on_done is not None:
            on_done(entry, failure)
    return _split(Result(rows, failures, len(entries)), entries, system)


def _split(result: Result, entries: Sequence[RecordingEntry], system: System | None) -> Result:
    """Containers' CPU split among the nodes they host (system.yaml ``container``), each
    fit's problem a warning; the standalone runs' rows left out."""
    if system is None or not (system.containers or any(e.standalone for e in entries)):
        return result
    import warnings

    from perfros_bag.characterisation.containers import split_containers
    from perfros_bag.errors import PerfrosWarning

    rows, splits = split_containers(result.rows, system, entries)
    for s in splits:
        for note in s.notes:
            warnings.warn(PerfrosWarning(note), stacklevel=3)
    return Result(rows, result.failures, result.recordings, splits)


def _characterise_dask(entries: Sequence[RecordingEntry], system: System | None, fast: bool,
                       on_done: Callable[[RecordingEntry, Failure | None], None] | None,
                       scheduler: str | None, workers: int | None, latency: bool = False) -> Result:
    # the Dask back end: loaded only when asked for
    from perfros_bag.characterisation.cluster import characterise_on_dask
    from perfros_bag.characterisation.distributed import Outcome

    by_name = {e.name: e for e in entries}

    def progress(outcome: Outcome[Any]) -> None:
        if on_done is not None:
            fail = None if outcome.ok else Failure(outcome.label, str(outcome.error))
            on_done(by_name[outcome.label], fail)

    # large ROS 1 bags / MCAP files are split into chunk-range tasks (perfros_bag/characterisation/cluster.py)
    outcomes = characterise_on_dask(entries, system, fast=fast, scheduler=scheduler,
                                    workers=workers, progress=progress, latency=latency)
    rows: list[Row] = []
    failures: list[Failure] = []
    for o in outcomes:
        if o.ok and o.value is not None:
            rows.extend(o.value)
        elif not o.ok:
            failures.append(Failure(o.label, str(o.error)))
    return _split(Result(rows, failures, len(entries)), entries, system)


# --------------------------------------------------------------------------- output


def rows_json(rows: Iterable[Row]) -> list[dict[str, Any]]:
    from perfros_bag.characterisation.csvfile import OPTIONAL_COLUMNS, columns_for

    rows = list(rows)
    absent = set(OPTIONAL_COLUMNS) - set(columns_for(rows))  # as in the CSV: only when some row has it
    out = []
    for r in rows:
        d = asdict(r)
        out.append({k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()
                    if k not in absent})
    return out


@dataclass(frozen=True)
class TableRow:
    """One line of the paper's Table I: a node at one setting, averaged over recordings."""

    node: str
    parameter: str | None
    value: SettingValue | None
    recordings: int
    cpu: float | None
    frequency_hz: float | None
    bandwidth_kBps: float | None


def table_one(rows: Sequence[Row]) -> list[TableRow]:
    """Per (node, setting): mean CPU over recordings, mean topic frequency, summed topic
    bandwidth (averaged over recordings). Rows without a node are left out."""
    return [TableRow(s.node, s.parameter, s.value, len(s.recordings), mean(s.cpus()), mean(s.frequencies()),
                     mean(s.bandwidths())) for s in by_setting(rows)]
