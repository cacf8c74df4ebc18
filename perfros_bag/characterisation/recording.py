"""One recording (+ its CPU trace, manifest entry, system) -> its characterisation.csv rows.

:func:`characterise_recording` is a pure top-level function of picklable arguments (a
:class:`~perfros_bag.characterisation.manifest.RecordingEntry` and a
:class:`~perfros_bag.system.types.System`), so the local loop
(:mod:`perfros_bag.characterisation.table`) and the Dask back end
(:mod:`perfros_bag.characterisation.cluster`) both run it; :func:`reporting` gives both the
same words for a recording that fails.

Rows are one per (recording, node, topic), design.md's ``characterisation.csv``:

- a topic belongs to the system node listing it in ``topics``; else to its publisher
  (ROS 1 ``callerid``) when that names a system node; else node = publisher (or empty);
- a node's CPU comes from the processes the CPU trace attributes to it (the node's
  ``process`` regex on the trace's node label / process name, or its name), summed per
  sample, aligned with the recording's window, normalised with the measurement's own
  ``units_per_core`` when the manifest gives it (the system's computers then play no part),
  else with the capacity of the manifest's ``computer``;
- a node with CPU but no topic in the recording gets one row with an empty topic;
- settings the manifest does not give (no manifest, or silent about a node) come from the
  recording's ``/parameter_events`` (ROS 2; :mod:`perfros_bag.ingest.rosgraph`);
- a system node with a ``metric`` carries its value (:func:`perfros_bag.ingest.contents.read_metric`)
  in ``metric_value`` on every one of its rows; ``latency_*`` only when asked for.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.characterisation.manifest import RecordingEntry, SettingValue
from perfros_bag.cpu.trace import NodeCpu, match_label, node_cpu, read_cpu_trace
from perfros_bag.errors import InputError, PerfrosError, PerfrosWarning
from perfros_bag.ingest.stats import RecordingStats
from perfros_bag.system.types import System

if TYPE_CHECKING:
    from perfros_bag.ingest.contents import TopicLatency

#: CPU units of a computer that the system does not describe: 100 = the whole machine.
DEFAULT_CAPACITY = 100.0


#: What a reader may raise on a case it did not foresee (read_recording turns everything it
#: knows into an InputError); the recording is reported as unreadable, never a traceback.
UNFORESEEN: tuple[type[Exception], ...] = (OSError, ValueError, KeyError, IndexError, EOFError)


@contextmanager
def reporting(entry: RecordingEntry) -> Iterator[None]:
    """Turn an unforeseen exception raised while characterising ``entry`` into the
    :class:`PerfrosError` the user sees. The one conversion: the local loop and the Dask
    tasks (:mod:`perfros_bag.characterisation.cluster`, on the workers) both run inside it, so a recording fails
    with the same words whether or not ``--workers``/``--scheduler`` is given."""
    try:
        yield
    except PerfrosError:
        raise
    except UNFORESEEN as exc:
        raise PerfrosError(f"{entry.path}: cannot read: {type(exc).__name__}: {exc}") from None


def characterise_recording(entry: RecordingEntry, system: System | None = None, *,
                           fast: bool = True, stats: RecordingStats | None = None,
                           latency: bool = False,
                           delays: Mapping[str, TopicLatency | None] | None = None) -> list[Row]:
    """The rows of one recording. Raises :class:`PerfrosError` when it cannot be read.

    ``stats``: the recording's statistics when already read (the fleet merges a large
    recording's chunk-range parts, perfros_bag/characterisation/cluster.py); else read here.
    ``latency``: also read the headers of the stamped topics (the ``latency_*`` columns;
    with the statistics in one pass, :func:`perfros_bag.ingest.contents.read_with_latency`),
    unless ``delays`` gives them already (merged from the parts)."""
    from perfros_bag.ingest import read_recording

    if not entry.path.exists():
        raise InputError(entry.path, "recording not found")
    if latency and delays is None:
        from perfros_bag.ingest.contents import read_latency, read_with_latency

        if stats is None:
            stats, delays = read_with_latency(entry.path, fast=fast)
        else:
            delays = read_latency(entry.path, fast=fast)
    if stats is None:
        stats = read_recording(entry.path, fast=fast)
    delays = delays or {}
    start, end = stats.start_ns, stats.end_ns
    cpu: dict[str, NodeCpu] = {}
    speed = entry.speed_factor  # recorded on every row, never applied (docs/benchmarks.md)
    if entry.cpu is not None:
        trace = read_cpu_trace(entry.cpu)
        speed = speed if speed is not None else trace.speed_factor
        capacity = _capacity(entry, system, trace.logical_cpus)
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
    metrics = _metrics(entry, system, stats)
    settings = _recorded_settings(entry, system, stats)
    for node in order:
        parameter, value = _setting(node, settings, system)
        metric = metrics.get(node)
        driven_by = system.node[node].input if system is not None and node in system.node else None
        input_hz = stats.topics[driven_by].frequency_hz if driven_by in stats.topics else None
        c = cpu.get(node) or (_cpu_for_publisher(node, cpu) if system is None else None)
        mean, p95, samples = (c.mean, c.p95, c.samples) if c is not None else (None, None, None)
        threads = c.threads if c is not None else None
        topics = by_node.get(node, [])
        if not topics:
            rows.append(Row(entry.name, node, parameter, value, None, None, None, span, None, None,
                            mean, p95, samples, metric_value=metric, input_hz=input_hz, speed_factor=speed,
                            threads=threads))
            continue
        for topic in topics:
            ts = stats.topics[topic]
            delay = delays.get(topic)
            rows.append(Row(entry.name, node, parameter, value, topic, ts.msgtype, ts.messages,
                            ts.span_s, ts.frequency_hz, ts.bandwidth_kBps, mean, p95, samples,
                            ts.median_rate_hz, ts.p95_gap_s, metric_value=metric,
                            latency_p50_s=delay.p50_s if delay else None,
                            latency_p95_s=delay.p95_s if delay else None,
                            latency_max_s=delay.max_s if delay else None, input_hz=input_hz,
                            speed_factor=speed, threads=threads))
    return rows


def _metrics(entry: RecordingEntry, system: System | None, stats: RecordingStats) -> dict[str, float | None]:
    """The value of each system node's ``metric`` in this recording (one pass over the
    messages of the metric topics, decoded only when a node has a metric)."""
    if system is None or not any(n.metric for n in system.nodes):
        return {}
    from perfros_bag.ingest.contents import read_metrics

    return read_metrics(entry.path, {n.name: n.metric for n in system.nodes if n.metric is not None}, stats)


def _recorded_settings(entry: RecordingEntry, system: System | None,
                       stats: RecordingStats) -> Mapping[str, SettingValue]:
    """The manifest's settings, completed from the recording's ``/parameter_events`` (ROS 2)
    for the system nodes with a parameter that the manifest does not set."""
    from perfros_bag.ingest.rosgraph import PARAMETER_EVENTS

    events = stats.topics.get(PARAMETER_EVENTS)
    if system is None or events is None or not events.messages:
        return entry.settings
    wanted = [(n.name, n.parameter.name, n.process) for n in system.nodes
              if n.parameter is not None and n.name not in entry.settings]
    if not wanted:
        return entry.settings
    from perfros_bag.ingest.rosgraph import read_graph, settings_from_graph

    found = settings_from_graph(read_graph(entry.path, stats), wanted, f"{entry.name}: ")
    recorded = {n: (int(v) if isinstance(v, bool) else v) for n, v in found.items()}
    return {**recorded, **entry.settings}


def _cpu_owned(label: str, nodes: Sequence[str]) -> bool:
    """A trace label already reported under a publisher's name (no-system mode)."""
    return any(n and match_label(label, "", n.rsplit("/", 1)[-1], None) for n in nodes)


def _cpu_for_publisher(publisher: str, cpu: Mapping[str, NodeCpu]) -> NodeCpu | None:
    """No system: a ROS 1 publisher ``/ns/tracker1`` takes the CPU of trace label ``tracker1``."""
    if not publisher:
        return None
    short = publisher.rsplit("/", 1)[-1]
    return cpu.get(publisher) or cpu.get(short)


def _capacity(entry: RecordingEntry, system: System | None, logical_cpus: int) -> float:
    """The capacity R the trace is normalised with (``cpu_percent / (100 N) x R``): the
    measurement's own ``units_per_core x N`` when the manifest gives it, else the capacity
    of the manifest's computer in the system (100 without a computer)."""
    if entry.units_per_core is not None:
        return entry.units_per_core * logical_cpus
    if entry.computer is None:
        if system is not None:
            warnings.warn(f"{entry.name}: no 'computer' in the manifest: CPU normalised to "
                          f"{DEFAULT_CAPACITY:g} = the whole traced machine", PerfrosWarning, stacklevel=3)
        return DEFAULT_CAPACITY
    if system is None:
        raise InputError(entry.cpu, f"computer {entry.computer!r} given but no system.yaml to find its capacity "
                                    "(none was given and the manifest names none)")
    comp = system.computer.get(entry.computer)
    if comp is None:
        raise InputError(entry.cpu, f"unknown computer {entry.computer!r} (the system has "
                                    f"{', '.join(c.name for c in system.computers)})")
    if comp.capacity is None or comp.capacity <= 0:
        raise InputError(entry.cpu, f"computer {entry.computer!r} has no capacity to normalise the CPU trace with")
    return comp.capacity


def _setting(node: str, settings: Mapping[str, SettingValue],
             system: System | None) -> tuple[str | None, SettingValue | None]:
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
