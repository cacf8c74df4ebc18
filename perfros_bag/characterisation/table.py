"""Recordings (+ CPU traces, manifest, system) -> the characterisation table.

The per-recording work, :func:`characterise_recording`, is a pure top-level function of
picklable arguments (a :class:`~perfros_bag.characterisation.manifest.RecordingEntry` and a
:class:`~perfros_bag.system.types.System`), so a fleet can ship it to workers; the aggregation
(:func:`characterise`, :func:`table_one`, :func:`write_csv`) is separate.

Rows are one per (recording, node, topic), design.md's ``characterisation.csv``:

- a topic belongs to the system node listing it in ``topics``; else to its publisher
  (ROS 1 ``callerid``) when that names a system node; else node = publisher (or empty);
- a node's CPU comes from the processes the CPU trace attributes to it (the node's
  ``process`` regex on the trace's node label / process name, or its name), summed per
  sample, aligned with the recording's window, normalised with the capacity of the
  manifest's ``computer``;
- a node with CPU but no topic in the recording gets one row with an empty topic.
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from perfros_bag.characterisation.manifest import (
    RecordingEntry,
    SettingValue,
    default_cpu_path,
    load_manifest,
)
from perfros_bag.cpu.trace import NodeCpu, match_label, node_cpu, read_cpu_trace
from perfros_bag.errors import InputError, PerfrosError, PerfrosWarning
from perfros_bag.ingest.stats import RecordingStats
from perfros_bag.system.types import System

#: CPU units of a computer that the system does not describe: 100 = the whole machine.
DEFAULT_CAPACITY = 100.0


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


COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(Row))


@dataclass(frozen=True)
class Failure:
    recording: str
    message: str


@dataclass
class Result:
    rows: list[Row]
    failures: list[Failure]
    recordings: int  # how many were attempted

    @property
    def exit_code(self) -> int:
        """0 all good, 1 some recordings failed, 2 none could be read."""
        if not self.failures:
            return 0
        return 2 if len(self.failures) >= self.recordings else 1


# --------------------------------------------------------------------------- per recording


#: What a reader may raise on a case it did not foresee (read_recording turns everything it
#: knows into an InputError); the recording is reported as unreadable, never a traceback.
UNFORESEEN: tuple[type[Exception], ...] = (OSError, ValueError, KeyError, IndexError, EOFError)


@contextmanager
def reporting(entry: RecordingEntry) -> Iterator[None]:
    """Turn an unforeseen exception raised while characterising ``entry`` into the
    :class:`PerfrosError` the user sees. The one conversion: the local loop and the Dask
    tasks (perfros_bag/characterisation/cluster.py, on the workers) both run inside it, so a recording fails
    with the same words whether or not ``--workers``/``--scheduler`` is given."""
    try:
        yield
    except PerfrosError:
        raise
    except UNFORESEEN as exc:
        raise PerfrosError(f"{entry.path}: cannot read: {type(exc).__name__}: {exc}") from None


def characterise_recording(entry: RecordingEntry, system: System | None = None, *,
                           fast: bool = True, stats: RecordingStats | None = None) -> list[Row]:
    """The rows of one recording. Raises :class:`PerfrosError` when it cannot be read.

    ``stats``: the recording's statistics when already read (the fleet merges a large
    recording's chunk-range parts, perfros_bag/characterisation/cluster.py); else read here."""
    from perfros_bag.ingest import read_recording

    if not entry.path.exists():
        raise InputError(entry.path, "recording not found")
    if stats is None:
        stats = read_recording(entry.path, fast=fast)
    start, end = stats.start_ns, stats.end_ns
    cpu: dict[str, NodeCpu] = {}
    if entry.cpu is not None:
        trace = read_cpu_trace(entry.cpu)
        capacity = _capacity(entry, system)
        patterns = None if system is None else {n.name: n.process for n in system.nodes}
        cpu = node_cpu(trace, capacity, start_ns=start, end_ns=end, nodes=patterns)
        if trace.time.size and start is not None and end is not None and not cpu:
            lo, hi = float(trace.time.min()), float(trace.time.max())
            if hi < start / 1e9 or lo > end / 1e9:  # other clocks (sim time?): the whole trace
                warnings.warn(f"{entry.cpu}: no sample inside the recording's time window "
                              f"({start / 1e9:.3f}-{end / 1e9:.3f} s; the trace covers {lo:.3f}-{hi:.3f} s); "
                              "using the whole trace", PerfrosWarning, stacklevel=2)
                cpu = node_cpu(trace, capacity, nodes=patterns)

    owner: dict[str, str] = {}
    if system is not None:
        for n in system.nodes:
            for t in n.topics:
                owner.setdefault(t, n.name)
    names = [n.name for n in system.nodes] if system is not None else []

    rows: list[Row] = []
    by_node: dict[str, list[str]] = {}
    for topic in sorted(stats.topics):
        ts = stats.topics[topic]
        node = owner.get(topic)
        if node is None:
            pubs = list(ts.publishers)
            node = pubs[0] if len(pubs) == 1 else ";".join(pubs)
            if system is not None and len(pubs) == 1:
                node = next((n for n in names if match_label(pubs[0], "", n, None)), node)
        by_node.setdefault(node, []).append(topic)

    # system nodes first (system order), then other publishers, then CPU-only trace labels
    order = [n for n in names if n in by_node or n in cpu]
    order += [n for n in by_node if n not in order]
    order += [n for n in cpu if n not in order and not _cpu_owned(n, order)]
    span = (end - start) / 1e9 if start is not None and end is not None else None
    for node in order:
        parameter, value = _setting(node, entry.settings, system)
        c = cpu.get(node) or (_cpu_for_publisher(node, cpu) if system is None else None)
        mean, p95, samples = (c.mean, c.p95, c.samples) if c is not None else (None, None, None)
        topics = by_node.get(node, [])
        if not topics:
            rows.append(Row(entry.name, node, parameter, value, None, None, None, span, None, None,
                            mean, p95, samples))
            continue
        for topic in topics:
            ts = stats.topics[topic]
            rows.append(Row(entry.name, node, parameter, value, topic, ts.msgtype, ts.messages,
                            ts.span_s, ts.frequency_hz, ts.bandwidth_kBps, mean, p95, samples,
                            ts.median_rate_hz, ts.p95_gap_s))
    return rows


def _cpu_owned(label: str, nodes: Sequence[str]) -> bool:
    """A trace label already reported under a publisher's name (no-system mode)."""
    return any(n and match_label(label, "", n.rsplit("/", 1)[-1], None) for n in nodes)


def _cpu_for_publisher(publisher: str, cpu: Mapping[str, NodeCpu]) -> NodeCpu | None:
    """No system: a ROS 1 publisher ``/ns/tracker1`` takes the CPU of trace label ``tracker1``."""
    if not publisher:
        return None
    short = publisher.rsplit("/", 1)[-1]
    return cpu.get(publisher) or cpu.get(short)


def _capacity(entry: RecordingEntry, system: System | None) -> float:
    if entry.computer is None:
        if system is not None:
            warnings.warn(f"{entry.name}: no 'computer' in the manifest: CPU normalised to "
                          f"{DEFAULT_CAPACITY:g} = the whole traced machine", PerfrosWarning, stacklevel=3)
        return DEFAULT_CAPACITY
    if system is None:
        raise InputError(entry.cpu, f"computer {entry.computer!r} given but no system.yaml to find its capacity "
                                    "(pass --system or set 'system:' in the manifest)")
    comp = system.computer.get(entry.computer)
    if comp is None:
        raise InputError(entry.cpu, f"unknown computer {entry.computer!r} (the system has "
                                    f"{', '.join(c.name for c in system.computers)})")
    if comp.capacity is None or comp.capacity <= 0:
        raise InputError(entry.cpu, f"computer {entry.computer!r} has no capacity to normalise the CPU trace with")
    return comp.capacity


def _setting(node: str, settings: Mapping[str, SettingValue], system: System | None) -> tuple[str | None, SettingValue | None]:
    value = settings.get(node)
    parameter = None
    if system is not None and node in system.node:
        n = system.node[node]
        if n.parameter is not None:
            parameter = n.parameter.name
        elif value is None and len(n.settings) == 1 and n.settings[0].value is not None:
            value = n.settings[0].value
    return parameter, _norm_value(value)


def _norm_value(value: SettingValue | None) -> SettingValue | None:
    """A whole number is written as one (``10``, not ``10.0``)."""
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
        return int(value)
    return value


# --------------------------------------------------------------------------- a directory


def find_entries(directory: str | Path, manifest: str | Path | None = None) -> tuple[list[RecordingEntry], Path | None]:
    """The recordings to characterise and the manifest's system path (if any).

    With a manifest (given, or ``DIR/manifest.yaml``): its entries. Otherwise every
    recording discovered in DIR, each with its ``<stem>.cpu.csv`` when present."""
    d = Path(directory)
    if not d.exists():
        raise InputError(d, "directory not found")
    mpath = Path(manifest) if manifest is not None else None
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
    """Manifest settings and computers must name nodes/computers of the system."""
    for e in entries:
        for node in e.settings:
            if node not in system.node:
                raise InputError(source, f"recording {e.name!r}: settings name unknown node {node!r}")
        if e.computer is not None and e.computer not in system.computer:
            raise InputError(source, f"recording {e.name!r}: unknown computer {e.computer!r}")


def characterise(entries: Sequence[RecordingEntry], system: System | None = None, *, fast: bool = True,
                 on_done: Callable[[RecordingEntry, Failure | None], None] | None = None,
                 scheduler: str | None = None, workers: int | None = None) -> Result:
    """Characterise every entry; a failing recording becomes a :class:`Failure`, not an abort.

    In this process by default; with ``scheduler`` (a dask.distributed address) or
    ``workers`` (a LocalCluster of that many processes) the per-recording work runs on
    Dask through :func:`perfros_bag.characterisation.distributed.run_distributed`. Rows keep entry order.
    """
    if scheduler is not None or workers is not None:
        return _characterise_dask(entries, system, fast, on_done, scheduler, workers)
    rows: list[Row] = []
    failures: list[Failure] = []
    for entry in entries:
        failure = None
        try:
            with reporting(entry):
                rows.extend(characterise_recording(entry, system, fast=fast))
        except PerfrosError as exc:
            failure = Failure(entry.name, str(exc))
        if failure is not None:
            failures.append(failure)
        if on_done is not None:
            on_done(entry, failure)
    return Result(rows, failures, len(entries))


def _characterise_dask(entries: Sequence[RecordingEntry], system: System | None, fast: bool,
                       on_done: Callable[[RecordingEntry, Failure | None], None] | None,
                       scheduler: str | None, workers: int | None) -> Result:
    from perfros_bag.characterisation.cluster import characterise_on_dask
    from perfros_bag.characterisation.distributed import Outcome

    by_name = {e.name: e for e in entries}

    def progress(outcome: Outcome[Any]) -> None:
        if on_done is not None:
            fail = None if outcome.ok else Failure(outcome.label, str(outcome.error))
            on_done(by_name[outcome.label], fail)

    # large ROS 1 bags / MCAP files are split into chunk-range tasks (perfros_bag/characterisation/cluster.py)
    outcomes = characterise_on_dask(entries, system, fast=fast, scheduler=scheduler,
                                    workers=workers, progress=progress)
    rows: list[Row] = []
    failures: list[Failure] = []
    for o in outcomes:
        if o.ok and o.value is not None:
            rows.extend(o.value)
        elif not o.ok:
            failures.append(Failure(o.label, str(o.error)))
    return Result(rows, failures, len(entries))


# --------------------------------------------------------------------------- output


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    return str(v)


def rows_csv(rows: Iterable[Row]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow([_cell(getattr(r, c)) for c in COLUMNS])
    return buf.getvalue()


def write_csv(path: str | Path, rows: Iterable[Row]) -> None:
    """Write characterisation.csv atomically; a path that cannot be written is an InputError."""
    from perfros_bag.fileio import atomic_write_text

    if Path(path).is_dir():
        raise InputError(path, "is a directory, expected the output CSV file")
    try:
        atomic_write_text(path, rows_csv(rows))
    except OSError as exc:
        raise InputError(path, f"cannot write: {exc.strerror or exc}") from None


def rows_json(rows: Iterable[Row]) -> list[dict[str, Any]]:
    out = []
    for r in rows:
        d = asdict(r)
        out.append({k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()})
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
    groups: dict[tuple[str, str], list[Row]] = {}
    for r in rows:
        if not r.node:
            continue
        groups.setdefault((r.node, "" if r.value is None else repr(r.value)), []).append(r)
    first: dict[str, int] = {}
    for r in rows:
        first.setdefault(r.node, len(first))
    out: list[TableRow] = []
    for (node, _), rs in groups.items():
        recs: dict[str, list[Row]] = {}
        for r in rs:
            recs.setdefault(r.recording, []).append(r)
        cpus, freqs, bws = [], [], []
        for rr in recs.values():
            if rr[0].cpu_units_mean is not None:
                cpus.append(rr[0].cpu_units_mean)
            f = [r.frequency_hz for r in rr if r.topic and r.frequency_hz is not None]
            b = [r.bandwidth_kBps for r in rr if r.topic and r.bandwidth_kBps is not None]
            if f:
                freqs.append(sum(f) / len(f))
            if b:
                bws.append(sum(b))
        out.append(TableRow(node, rs[0].parameter, rs[0].value, len(recs), _mean(cpus), _mean(freqs), _mean(bws)))
    return sorted(out, key=lambda t: (first[t.node], _sort_value(t.value)))


def _sort_value(v: SettingValue | None) -> tuple[int, float, str]:
    if v is None:
        return (0, 0.0, "")
    if isinstance(v, int | float):
        return (1, float(v), "")
    return (2, 0.0, v)


def _mean(xs: Sequence[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None
