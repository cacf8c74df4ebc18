"""Validate a run against its plan: the paper's eq 10 plus CPU and bandwidth checks.

For every node of the plan and each of its planned topics, the measured frequency
``F_measured`` (``(n - 1) / span`` of the recording) is compared with the plan's
``F_expected``. A node's ratio is the mean of its topics' ``F_measured / F_expected``
and its measured performance is (eq 10)::

    P_measured = P_expected * ratio          (capped at P_expected with cap=True)

Choices documented in ``docs/formats.md`` ("validate --json"):

- a planned topic absent from the recording counts ``F_measured = 0`` (status ``missing``);
- a topic whose ``F_expected`` is 0 or unknown has no expectation (status
  ``no-expectation``) and is left out of the node's mean; a node with no topic that has an
  expectation keeps ``P_measured = P_expected`` (``counted: false``): it cannot deviate;
- recorded topics that are in no node of the plan are listed (``unplanned_topics``), not
  counted;
- deviations are absolute, in %: ``100 * |measured - expected| / expected``.

With CPU traces (``<stem>.cpu.csv``), each computer's measured load is the sum of its
nodes' mean CPU in normalised units (``cpu_percent / (100 * logical_cpus) * capacity``)
and ``overloaded`` where it exceeds the capacity. With the system (given, or the
plan's ``system`` path), each link's measured load is the measured bandwidth of the
publisher topics of the edges crossing it, and a node with a ``metric`` gets its measured
value, on the 0-100 scale of the metric's ``range``, beside P_measured (``p_metric``).
A driven node (system.yaml ``input``) gets its input rate, the plan's against the run's;
an overloaded plan the rates it keeps (:mod:`perfros_bag.validation.kept`). A topic with
too few messages for a rate (:attr:`TopicStats.rate_note`) is said to have none.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.ingest.stats import RecordingStats, TopicStats
from perfros_bag.system.plan import Plan
from perfros_bag.system.types import System
from perfros_bag.validation import DEFAULT_TOLERANCE
from perfros_bag.validation.kept import KeptRates, overloaded_capacities, predict_kept

if TYPE_CHECKING:
    from perfros_bag.ingest.chains import ChainLatency
    from perfros_bag.ingest.contents import TopicLatency

VALIDATION_FORMAT = "perfros-bag/validation@1"


# ---------------------------------------------------------------------------------------
# results


class TopicStatus(StrEnum):
    """A planned topic in the run: compared, absent (F = 0), or nothing to compare with."""

    OK = "ok"
    MISSING = "missing"
    NO_EXPECTATION = "no-expectation"


@dataclass
class TopicCheck:
    topic: str
    f_expected: float | None
    f_measured: float
    ratio: float | None  # F_measured / F_expected; None without an expectation
    deviation_pct: float | None
    bandwidth_kBps: float  # measured
    messages: int
    status: TopicStatus
    #: the recording has too few messages of it for a rate: f_measured is then its messages
    #: over the recording's span (:func:`_measured_rate`), and this says why
    rate_note: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "topic": self.topic, "status": str(self.status), "f_expected": self.f_expected,
            "f_measured": self.f_measured, "ratio": self.ratio, "deviation_pct": self.deviation_pct,
            "bandwidth_kBps": self.bandwidth_kBps, "messages": self.messages, "rate_note": self.rate_note,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> TopicCheck:
        """A topic of validation.json ``nodes[].topics`` (what :meth:`to_dict` wrote)."""
        return cls(d["topic"], d["f_expected"], d["f_measured"], d["ratio"], d["deviation_pct"], d["bandwidth_kBps"],
                   d["messages"], TopicStatus(d["status"]), d.get("rate_note"))


@dataclass
class NodeCheck:
    node: str
    computer: str
    weight: float
    p_expected: float
    p_measured: float
    ratio: float  # mean of the topics' ratios (1 when not counted), before the cap
    deviation_pct: float
    counted: bool  # False: no topic with an expected frequency; P_measured = P_expected
    topics: list[TopicCheck] = field(default_factory=list)
    parameter: str | None = None
    value: float | None = None
    cpu_expected: float | None = None
    cpu_measured: float | None = None  # normalised units, from the CPU trace
    note: str | None = None
    # the node's metric (system.yaml ``metric``) measured in the run, beside eq 10
    metric_value: float | None = None
    p_metric: float | None = None  # metric_value on the 0-100 scale of the metric's range
    metric_deviation_pct: float | None = None  # p_metric against p_expected
    # a driven node (system.yaml ``input``): its input topic, the rate the plan propagated to
    # it and the run's rate of that topic (None: not recorded, or too few messages: the note)
    input: str | None = None
    input_hz_expected: float | None = None
    input_hz_measured: float | None = None
    input_rate_note: str | None = None

    @property
    def flagged(self) -> bool:
        return any(t.status == TopicStatus.MISSING for t in self.topics)

    def to_dict(self) -> dict[str, Any]:
        return {
            "node": self.node, "computer": self.computer, "weight": self.weight,
            "parameter": self.parameter, "value": self.value,
            "p_expected": self.p_expected, "p_measured": self.p_measured, "ratio": self.ratio,
            "deviation_pct": self.deviation_pct, "counted": self.counted, "flagged": self.flagged,
            "cpu_expected": self.cpu_expected, "cpu_measured": self.cpu_measured, "note": self.note,
            "metric_value": self.metric_value, "p_metric": self.p_metric,
            "metric_deviation_pct": self.metric_deviation_pct,
            "input": self.input, "input_hz_expected": self.input_hz_expected,
            "input_hz_measured": self.input_hz_measured,
            "input_deviation_pct": self.input_deviation_pct, "input_rate_note": self.input_rate_note,
            "topics": [t.to_dict() for t in self.topics],
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> NodeCheck:
        """A node of validation.json ``nodes`` (``flagged`` and ``input_deviation_pct`` follow
        from the rest)."""
        return cls(d["node"], d["computer"], d["weight"], d["p_expected"], d["p_measured"], d["ratio"],
                   d["deviation_pct"], d["counted"], [TopicCheck.from_json(t) for t in d.get("topics") or []],
                   d.get("parameter"), d.get("value"), d.get("cpu_expected"), d.get("cpu_measured"), d.get("note"),
                   d.get("metric_value"), d.get("p_metric"), d.get("metric_deviation_pct"), d.get("input"),
                   d.get("input_hz_expected"), d.get("input_hz_measured"), d.get("input_rate_note"))

    @property
    def input_deviation_pct(self) -> float | None:
        """100 x |measured - expected| / expected of a driven node's input rate."""
        if self.input_hz_expected is None or self.input_hz_measured is None:
            return None
        return _deviation(self.input_hz_measured, self.input_hz_expected)


@dataclass
class ComputerCheck:
    name: str
    capacity: float | None
    cpu_expected: float
    cpu_measured: float | None  # None: no CPU trace covers any of its nodes
    overloaded: bool | None
    unmatched_nodes: list[str] = field(default_factory=list)  # its nodes not found in the trace

    def to_dict(self) -> dict[str, Any]:
        return {
            "computer": self.name, "capacity": self.capacity, "cpu_expected": self.cpu_expected,
            "cpu_measured": self.cpu_measured, "overloaded": self.overloaded,
            "unmatched_nodes": self.unmatched_nodes,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ComputerCheck:
        return cls(d["computer"], d["capacity"], d["cpu_expected"], d["cpu_measured"], d["overloaded"],
                   list(d.get("unmatched_nodes") or []))


@dataclass
class LinkCheck:
    between: tuple[str, str]
    capacity_kBps: float
    expected_kBps: float | None
    measured_kBps: float
    overloaded: bool
    medium: str | None = None
    edges: list[str] = field(default_factory=list)  # "src->dst" crossing it

    def to_dict(self) -> dict[str, Any]:
        return {
            "between": list(self.between), "medium": self.medium, "capacity_kBps": self.capacity_kBps,
            "expected_kBps": self.expected_kBps, "measured_kBps": self.measured_kBps,
            "overloaded": self.overloaded, "edges": self.edges,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> LinkCheck:
        """A link or medium of validation.json ``links``/``media``."""
        a, b = d["between"]
        return cls((a, b), d["capacity_kBps"], d["expected_kBps"], d["measured_kBps"], d["overloaded"], d.get("medium"),
                   list(d.get("edges") or []))


@dataclass
class NetworkCheck:
    """A topic the plan sends across the network (an edge whose ends it puts on different
    computers): the transfer delay per message its route adds, predicted from the run's mean
    message size and the links' bandwidths, beside the topic's measured header.stamp latency."""

    edge: str  # "src->dst"
    topic: str
    links: list[tuple[str, str]]  # the route, link by link
    message_bytes: float | None  # mean payload bytes per message in the run; None: not recorded
    predicted_delay_s: float | None  # Σ over the route's links of message_bytes / (1000 × bandwidth_kBps)
    latency_p50_s: float | None = None  # measured receive/log time - header.stamp (stamped topics)
    latency_p95_s: float | None = None
    latency_max_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"edge": self.edge, "topic": self.topic, "links": [list(b) for b in self.links],
                "message_bytes": self.message_bytes, "predicted_delay_s": self.predicted_delay_s,
                "latency_p50_s": self.latency_p50_s, "latency_p95_s": self.latency_p95_s,
                "latency_max_s": self.latency_max_s}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> NetworkCheck:
        return cls(d["edge"], d["topic"], [(a, b) for a, b in d["links"]], d["message_bytes"], d["predicted_delay_s"],
                   d.get("latency_p50_s"), d.get("latency_p95_s"), d.get("latency_max_s"))


@dataclass
class UnplannedTopic:
    topic: str
    msgtype: str
    messages: int
    f_measured: float | None  # None: too few messages for a rate (``rate_note`` says so)
    bandwidth_kBps: float
    rate_note: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"topic": self.topic, "msgtype": self.msgtype, "messages": self.messages,
                "f_measured": self.f_measured, "bandwidth_kBps": self.bandwidth_kBps, "rate_note": self.rate_note}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> UnplannedTopic:
        return cls(d["topic"], d["msgtype"], d["messages"], d["f_measured"], d["bandwidth_kBps"], d.get("rate_note"))


@dataclass
class Validation:
    recording: str
    recording_format: str
    plan: str | None
    tolerance_pct: float
    cap: bool
    overall_expected: float
    overall_measured: float
    deviation_pct: float
    nodes: list[NodeCheck]
    computers: list[ComputerCheck] = field(default_factory=list)
    links: list[LinkCheck] = field(default_factory=list)
    media: list[LinkCheck] = field(default_factory=list)
    unplanned_topics: list[UnplannedTopic] = field(default_factory=list)
    cpu_traces: list[str] = field(default_factory=list)
    system: str | None = None
    notes: list[str] = field(default_factory=list)
    network: list[NetworkCheck] = field(default_factory=list)
    chains: list[ChainLatency] = field(default_factory=list)
    kept: KeptRates | None = None  # the rates an overloaded plan keeps (None: nothing capped)
    #: the plan's chains (plan.json ``chains``): their predicted latency, set beside the measured
    predicted_chains: list[dict[str, Any]] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return self.deviation_pct <= self.tolerance_pct

    @property
    def missing_topics(self) -> list[str]:
        return [t.topic for n in self.nodes for t in n.topics if t.status == TopicStatus.MISSING]

    @property
    def overloaded_computers(self) -> list[str]:
        return [c.name for c in self.computers if c.overloaded]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": VALIDATION_FORMAT,
            "recording": self.recording, "recording_format": self.recording_format,
            "plan": self.plan, "system": self.system, "cpu_traces": self.cpu_traces,
            "tolerance_pct": self.tolerance_pct, "cap": self.cap,
            "overall": {
                "expected": self.overall_expected, "measured": self.overall_measured,
                "ratio": _ratio(self.overall_measured, self.overall_expected),
                "deviation_pct": self.deviation_pct, "passed": self.passed,
            },
            "nodes": [n.to_dict() for n in self.nodes],
            "missing_topics": self.missing_topics,
            "unplanned_topics": [t.to_dict() for t in self.unplanned_topics],
            "computers": [c.to_dict() for c in self.computers],
            "overloaded": self.overloaded_computers,
            "links": [link.to_dict() for link in self.links],
            "media": [m.to_dict() for m in self.media],
            "network": [c.to_dict() for c in self.network],
            "chains": chains_beside_predicted([c.to_dict() for c in self.chains], self.predicted_chains),
            "kept": None if self.kept is None else self.kept.to_dict(),
            "notes": self.notes,
        }


def chains_beside_predicted(measured: list[dict[str, Any]], predicted: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """validation.json ``chains``: each measured chain (``p50_s``/``p95_s``) with the plan's
    ``predicted_ms`` and ``budget_ms`` beside it (null when the plan has none), whether the
    measured latency held the budget (``budget_held``: each bound against the measured
    quantile; null without a budget or a measurement), and each hop's ``predicted_ms``."""
    by_name = {c.get("name"): c for c in predicted if isinstance(c, dict)}
    out = []
    for c in measured:
        p = by_name.get(c["name"], {})
        hops = {(h.get("from"), h.get("to")): h for h in p.get("hops") or [] if isinstance(h, dict)}
        budget = p.get("budget_ms")
        held: bool | None = None
        if isinstance(budget, dict) and budget:
            got = {"p50": c.get("p50_s"), "p95": c.get("p95_s")}
            seen = {q: got.get(q) for q in budget}
            if all(isinstance(v, int | float) for v in seen.values()):
                held = all(1000 * float(seen[q]) <= b for q, b in budget.items())  # type: ignore[arg-type]
        out.append({**c, "predicted_ms": p.get("predicted_ms"), "budget_ms": budget, "budget_held": held,
                    "hops": [{**h, "predicted_ms": hops.get((h["from"], h["to"]), {}).get("predicted_ms")}
                             for h in c["hops"]]})
    return out


def _ratio(measured: float, expected: float) -> float | None:
    return measured / expected if expected else None


def _deviation(measured: float, expected: float) -> float:
    """100 * |measured - expected| / expected; 0 when both are 0, and 100 (the most a
    vanished quantity can deviate) when only the expectation is 0."""
    if expected == 0:
        return 0.0 if measured == 0 else 100.0
    return 100.0 * abs(measured - expected) / abs(expected)


# ---------------------------------------------------------------------------------------
# CPU traces


@dataclass
class TracedCpu:
    """Mean CPU of one node from one trace: cpu_percent (100 = one core) and the trace's
    number of logical CPUs, to convert into its computer's units."""

    percent: float
    logical_cpus: int
    trace: str
    host: str | None = None  # the trace's "# host=" line


def node_cpu_from_trace(path: str | Path, plan: Plan, system: System | None,
                        start_ns: int | None = None, end_ns: int | None = None) -> dict[str, TracedCpu]:
    """Mean CPU per plan node in one trace, over the samples inside the recording's window
    (the whole trace, with a warning, when none is inside it). Rows are matched to plan
    nodes by name, else by the system's ``process`` regex
    (:func:`perfros_bag.cpu.trace.assign_nodes`)."""
    from perfros_bag.cpu import trace as cputrace

    trace = cputrace.read_cpu_trace(path)
    patterns: dict[str, str | None] = {
        n: (system.node[n].process if system is not None and n in system.node else None) for n in plan.nodes
    }
    full = 100.0 * trace.logical_cpus  # the capacity at which units == cpu_percent
    found = cputrace.node_cpu(trace, full, start_ns=start_ns, end_ns=end_ns, nodes=patterns)
    if not found and len(trace) and start_ns is not None:
        everything = cputrace.node_cpu(trace, full, nodes=patterns)
        if everything:
            warnings.warn(f"{path}: no CPU sample inside the recording's time window; using the whole trace",
                          PerfrosWarning, stacklevel=2)
            found = everything
    return {n: TracedCpu(c.mean, trace.logical_cpus, str(path), trace.host) for n, c in found.items()}


# ---------------------------------------------------------------------------------------
# the check


def _topic_key(stats: RecordingStats, topic: str) -> str | None:
    """The recording's name for a planned topic (a leading ``/`` may differ)."""
    if topic in stats.topics:
        return topic
    alt = topic.lstrip("/") if topic.startswith("/") else "/" + topic
    return alt if alt in stats.topics else None


def _find_topic(stats: RecordingStats, topic: str) -> TopicStats | None:
    key = _topic_key(stats, topic)
    return None if key is None else stats.topics[key]


def _measured_rate(stats: RecordingStats, ts: TopicStats) -> tuple[float, str | None]:
    """A topic's measured rate and, when it has too few messages for one
    (:attr:`TopicStats.rate_note`), why: then the rate is its messages over the whole
    recording's span (0 when that span is 0), not (n - 1) over its own."""
    note = ts.rate_note
    if note is None:
        return ts.frequency_hz, None
    start, end = stats.start_ns, stats.end_ns
    span = (end - start) / 1e9 if start is not None and end is not None else 0.0
    return (ts.messages / span if span > 0 else 0.0), note


def _check_topic(stats: RecordingStats, topic: str, f_expected: float | None) -> TopicCheck:
    ts = _find_topic(stats, topic)
    f_meas, note = _measured_rate(stats, ts) if ts is not None else (0.0, None)
    bw = ts.bandwidth_kBps if ts is not None else 0.0
    msgs = ts.messages if ts is not None else 0
    if not f_expected:  # 0 or None: nothing to compare with
        status = TopicStatus.MISSING if ts is None else TopicStatus.NO_EXPECTATION
        return TopicCheck(topic, f_expected, f_meas, None, None, bw, msgs, status, note)
    ratio = f_meas / f_expected
    status = TopicStatus.MISSING if ts is None else TopicStatus.OK
    return TopicCheck(topic, f_expected, f_meas, ratio, 100.0 * abs(ratio - 1.0), bw, msgs, status, note)


def check_run(stats: RecordingStats, plan: Plan, *, cap: bool = False,
              tolerance: float = DEFAULT_TOLERANCE, system: System | None = None,
              node_cpu: dict[str, TracedCpu] | None = None, cpu_traces: Iterable[str] = (),
              plan_path: str | None = None, metrics: Mapping[str, float | None] | None = None,
              latency: Mapping[str, TopicLatency | None] | None = None,
              chains: Sequence[ChainLatency] = ()) -> Validation:
    """Eq 10 for every node of ``plan`` against the recording's statistics. ``metrics``: the
    measured value of each node's ``metric`` in the run (:func:`measured_metrics`), compared
    with the plan's performance beside eq 10 (it does not change eq 10's numbers);
    ``latency``: the run's header.stamp latency per stamped topic, shown beside the network
    delay the plan adds; ``chains``: the system's chains measured in the run."""
    plan.require_feasible(plan_path, "validate")
    notes: list[str] = []
    nodes: list[NodeCheck] = []
    planned: set[str] = set()
    for name, pn in plan.nodes.items():
        topics = [_check_topic(stats, t, r.frequency_hz) for t, r in pn.topics.items()]
        planned.update(k for t in topics if (k := _topic_key(stats, t.topic)) is not None)
        ratios = [t.ratio for t in topics if t.ratio is not None]
        note = None
        if ratios:
            ratio = sum(ratios) / len(ratios)
            p_meas = pn.performance * ratio
            if cap:
                p_meas = min(p_meas, pn.performance)
            counted = True
            skipped = [t.topic for t in topics if t.ratio is None]
            if skipped:
                note = f"no expected frequency for {', '.join(skipped)}: left out of the mean"
        else:
            ratio, p_meas, counted = 1.0, pn.performance, False
            note = ("no planned topic: P_measured = P_expected" if not topics
                    else "no expected frequency on any topic: P_measured = P_expected")
            notes.append(f"node {name!r}: {note}")
        missing = [t.topic for t in topics if t.status == TopicStatus.MISSING]
        if missing:
            notes.append(f"node {name!r}: planned topic(s) not in the recording (F = 0): {', '.join(missing)}")
        for t in topics:
            if t.rate_note is not None:
                notes.append(f"node {name!r}: {t.topic}: {t.rate_note}: F_measured = its messages over the "
                             f"recording's span ({t.f_measured:.3g} Hz)")
        nodes.append(NodeCheck(
            node=name, computer=pn.computer, weight=pn.weight, p_expected=pn.performance,
            p_measured=p_meas, ratio=ratio, deviation_pct=_deviation(p_meas, pn.performance),
            counted=counted, topics=topics, parameter=pn.parameter, value=pn.value,
            cpu_expected=pn.cpu, note=note,
        ))
        if pn.input is not None:
            _check_input(nodes[-1], stats, pn.input, pn.input_hz, notes)

    for n in nodes:
        if metrics and n.node in metrics:
            _compare_metric(n, metrics[n.node], system, notes)

    if nodes and not any(n.counted for n in nodes):
        raise InputError(plan_path, "no node of the plan has a topic with an expected frequency: eq 10 has "
                                    "nothing to compare (the plan's topics need frequency_hz)")
    overall_e = sum(n.weight * n.p_expected for n in nodes)
    overall_m = sum(n.weight * n.p_measured for n in nodes)
    unplanned = [UnplannedTopic(t, ts.msgtype, ts.messages, None if ts.rate_note else ts.frequency_hz,
                                ts.bandwidth_kBps, ts.rate_note)
                 for t, ts in sorted(stats.topics.items()) if t not in planned]

    computers = _check_computers(plan, nodes, node_cpu, notes) if node_cpu is not None else []
    kept = _kept_rates(plan, system, nodes, computers)
    links, media = _check_links(plan, stats, system, notes) if system is not None else ([], [])
    network = _check_network(plan, stats, system, latency or {}) if system is not None else []
    return Validation(
        recording=str(stats.path), recording_format=stats.format, plan=plan_path,
        tolerance_pct=tolerance, cap=cap, overall_expected=overall_e, overall_measured=overall_m,
        deviation_pct=_deviation(overall_m, overall_e), nodes=nodes, computers=computers,
        links=links, media=media, unplanned_topics=unplanned, cpu_traces=list(cpu_traces),
        system=system.source if system is not None else None, notes=notes + (kept.notes if kept else []),
        network=network, chains=list(chains), kept=kept, predicted_chains=_predicted_chains(plan, system, chains),
    )


def _predicted_chains(plan: Plan, system: System | None, chains: Sequence[ChainLatency]) -> list[dict[str, Any]]:
    """The plan's predicted chains; a plan that states none (written before chains were
    predicted, or built by hand) predicted here from its own numbers when the system is known."""
    if plan.chains or system is None or not chains:
        return list(plan.chains)
    from perfros_bag.system.latency import plan_predictions

    return [p.to_dict() for p in plan_predictions(system, plan, warn=False)]


def _check_input(n: NodeCheck, stats: RecordingStats, topic: str, expected: float | None, notes: list[str]) -> None:
    """A driven node's input rate: the plan's against the run's (its input topic's rate)."""
    n.input, n.input_hz_expected = topic, expected
    ts = _find_topic(stats, topic)
    if ts is None:
        notes.append(f"node {n.node!r}: its input {topic} is not in the recording: no input rate to compare")
    elif ts.rate_note is not None:
        n.input_rate_note = ts.rate_note
        notes.append(f"node {n.node!r}: its input {topic}: {ts.rate_note}")
    else:
        n.input_hz_measured = ts.frequency_hz


def _kept_rates(plan: Plan, system: System | None, nodes: list[NodeCheck],
                computers: list[ComputerCheck]) -> KeptRates | None:
    """The rates the plan keeps (:mod:`perfros_bag.validation.kept`) when a computer is
    overloaded: measured (the CPU trace) or predicted (its nodes' planned CPU above the
    capacity of the system's computer, else the plan's). A node traced on a computer whose
    measured load exceeds its capacity needs what it was measured at when that is more than
    planned (calibration: measured over planned CPU). None when no computer is overloaded
    either way."""
    capacities = overloaded_capacities(plan, system)
    over = {c.name for c in computers if c.overloaded}
    # only where the run showed more: on a capped computer a node's measured CPU is what its
    # share gave it, not its need (taking it as the need would predict that nothing is lost)
    calibration = {n.node: n.cpu_measured / n.cpu_expected for n in nodes
                   if n.computer in over and n.cpu_measured is not None and n.cpu_expected
                   and n.cpu_measured > n.cpu_expected}
    kept = predict_kept(plan, system, capacities, calibration)
    if not over and not any(c.capped for c in kept.computers):
        return None
    measured = {n.node: [t.f_measured for t in n.topics if t.f_expected] for n in nodes}
    for k in kept.nodes:
        rates = measured.get(k.node) or []
        k.f_measured = sum(rates) / len(rates) if rates else None
    return kept


def _compare_metric(n: NodeCheck, value: float | None, system: System | None, notes: list[str]) -> None:
    """The node's measured metric on the 0-100 scale of its ``range`` against P_expected."""
    n.metric_value = value
    metric = system.node[n.node].metric if system is not None and n.node in system.node else None
    if value is None or metric is None:
        return
    if metric.range is None:
        notes.append(f"node {n.node!r}: metric {metric.topic} = {value:.6g}: no 'range' in the system "
                     "to put it on the performance scale, not compared")
        return
    n.p_metric = metric.performance(value)
    if n.p_metric is not None:
        n.metric_deviation_pct = _deviation(n.p_metric, n.p_expected)


def measured_metrics(run: Path, plan: Plan, system: System | None,
                     stats: RecordingStats) -> dict[str, float | None]:
    """The run's value of the ``metric`` of every plan node that has one (decoded by the
    libraries in one pass: :func:`perfros_bag.ingest.contents.read_metrics`)."""
    if system is None:
        return {}
    wanted = {n: system.node[n].metric for n in plan.nodes if n in system.node and system.node[n].metric}
    if not wanted:
        return {}
    from perfros_bag.ingest.contents import read_metrics

    return read_metrics(run, {n: m for n, m in wanted.items() if m is not None}, stats)


def _check_computers(plan: Plan, nodes: list[NodeCheck], node_cpu: dict[str, TracedCpu],
                     notes: list[str]) -> list[ComputerCheck]:
    out: list[ComputerCheck] = []
    for n in nodes:
        nc = node_cpu.get(n.node)
        if nc is not None and nc.host in plan.computers and nc.host != n.computer:
            notes.append(f"node {n.node!r} is planned on {n.computer!r} but its CPU trace {nc.trace} was "
                         f"recorded on {nc.host!r}: was the plan deployed?")
    for cname, pc in plan.computers.items():
        members = [n for n in nodes if n.computer == cname]
        total: float | None = None
        unmatched: list[str] = []
        for n in members:
            nc = node_cpu.get(n.node)
            if nc is None:
                unmatched.append(n.node)
                continue
            if pc.capacity is None or nc.logical_cpus <= 0:
                continue
            n.cpu_measured = nc.percent / (100.0 * nc.logical_cpus) * pc.capacity
            total = (total or 0.0) + n.cpu_measured
        overloaded = None if total is None or pc.capacity is None else total > pc.capacity
        out.append(ComputerCheck(cname, pc.capacity, pc.cpu, total, overloaded, unmatched))
    return out


def _measured_publisher_bw(stats: RecordingStats, plan: Plan, system: System, src: str, topic: str | None) -> float:
    """kB/s an edge carries in the run: its topic's, else all the publisher's topics'."""
    found = (_find_topic(stats, t) for t in _edge_topics(plan, system, src, topic))
    return sum(ts.bandwidth_kBps for ts in found if ts is not None)


def _check_links(plan: Plan, stats: RecordingStats, system: System,
                 notes: list[str]) -> tuple[list[LinkCheck], list[LinkCheck]]:
    loads = [0.0] * len(system.links)
    crossing: list[list[str]] = [[] for _ in system.links]
    # the plan's placement on the system's computers: edges with an end elsewhere are skipped
    placement = {n: pn.computer for n, pn in plan.nodes.items() if pn.computer in system.computer}
    edge_notes = [(ei, f"edge {e.src}->{e.dst}: a node is not in the plan, edge skipped")
                  for ei, e in enumerate(system.edges) if e.src not in plan.nodes or e.dst not in plan.nodes]
    for ei, edge, route in system.edge_routes(placement):
        if route is None:
            a, b = placement[edge.src], placement[edge.dst]
            edge_notes.append((ei, f"edge {edge.src}->{edge.dst}: no network route between {a!r} and {b!r}"))
            continue
        bw = _measured_publisher_bw(stats, plan, system, edge.src, edge.topic)
        for li in route:
            loads[li] += bw
            crossing[li].append(f"{edge.src}->{edge.dst}")
    notes.extend(note for _, note in sorted(edge_notes))
    planned = {frozenset(pl.between): pl.load_kBps for pl in plan.links}
    links = [
        LinkCheck(link.between, link.bandwidth_kBps, planned.get(frozenset(link.between)), load,
                  load > link.bandwidth_kBps, link.medium, crossing[i])
        for i, (link, load) in enumerate(zip(system.links, loads, strict=True))
    ]
    media: list[LinkCheck] = []
    for m in system.media:
        members = [links[li] for li in system.medium_links[m.name]]
        load = system.medium_load(loads, m.name)
        exp = [lc.expected_kBps for lc in members]
        expected = None if any(e is None for e in exp) else sum(e for e in exp if e is not None)
        media.append(LinkCheck((m.name, m.name), m.bandwidth_kBps, expected, load,
                               load > m.bandwidth_kBps, m.name, [e for lc in members for e in lc.edges]))
    return links, media


def _edge_topics(plan: Plan, system: System, src: str, topic: str | None) -> list[str]:
    """The topics an edge carries: its own, else every planned topic of its publisher."""
    if topic is not None:
        return [topic]
    return list(plan.nodes[src].topics if plan.nodes[src].topics else system.node[src].topics)


def _planned_routes(plan: Plan, system: System) -> list[tuple[Any, tuple[int, ...]]]:
    """(edge, links) of every edge the plan sends across at least one link."""
    placement = {n: pn.computer for n, pn in plan.nodes.items() if pn.computer in system.computer}
    return [(edge, route) for _, edge, route in system.edge_routes(placement) if route]


def _check_network(plan: Plan, stats: RecordingStats, system: System,
                   latency: Mapping[str, TopicLatency | None]) -> list[NetworkCheck]:
    """Per topic of every edge across links: predicted added transfer delay per message
    ``Σ_links mean_message_bytes / (1000 × bandwidth_kBps)`` and the measured latency."""
    out: list[NetworkCheck] = []
    for edge, route in _planned_routes(plan, system):
        for topic in _edge_topics(plan, system, edge.src, edge.topic):
            key = _topic_key(stats, topic)
            ts = None if key is None else stats.topics[key]
            size = ts.bytes / ts.messages if ts is not None and ts.messages else None
            delay = None if size is None else sum(size / (1000.0 * system.links[li].bandwidth_kBps) for li in route)
            lat = latency.get(key) if key is not None else None
            out.append(NetworkCheck(f"{edge.src}->{edge.dst}", topic, [system.links[li].between for li in route],
                                    size, delay, lat.p50_s if lat else None, lat.p95_s if lat else None,
                                    lat.max_s if lat else None))
    return out


def measured_latency(run: Path, plan: Plan, system: System | None
                     ) -> tuple[dict[str, TopicLatency | None], list[ChainLatency]]:
    """The run's header.stamp latency per stamped topic and its chains, read (one reading of
    the stamps) only when the system has chains or the plan sends a topic across a link."""
    if system is None or not (system.chains or _planned_routes(plan, system)):
        return {}, []
    from perfros_bag.ingest.chains import chain_latencies
    from perfros_bag.ingest.contents import read_contents_stamps, topic_latencies

    read = read_contents_stamps(run)
    return topic_latencies(run, read), chain_latencies(system.chains, read, where=f"{run}: ")


# ---------------------------------------------------------------------------------------
# files


def default_cpu_trace(run: str | Path) -> Path | None:
    """``<stem>.cpu.csv`` beside the recording (for a rosbag2 directory: ``<dir>.cpu.csv``
    beside it or inside it; for a ``.db3``/``.mcap`` inside a rosbag2 directory also the
    directory's trace)."""
    p = Path(run)
    candidates: list[Path] = []
    if p.is_dir():
        candidates += [p.parent / f"{p.name}.cpu.csv", p / f"{p.name}.cpu.csv"]
    else:
        candidates.append(p.with_name(f"{p.stem}.cpu.csv"))
        if (p.parent / "metadata.yaml").exists():
            d = p.parent
            candidates += [d.parent / f"{d.name}.cpu.csv", d / f"{d.name}.cpu.csv"]
    return next((c for c in candidates if c.is_file()), None)


def validate_files(run: str | Path, plan_path: str | Path, *, cpu: Sequence[str | Path] | None = None,
                   system_path: str | Path | None = None, tolerance: float = DEFAULT_TOLERANCE,
                   cap: bool = False, plan: Plan | None = None) -> Validation:
    """Read the recording, the plan, the CPU trace(s) and the system, then :func:`check_run`.
    ``plan``: ``plan_path`` already read (``deploy`` reads it once, for both)."""
    from perfros_bag.ingest import read_recording
    from perfros_bag.system.planfile import is_forced, load_plan, plan_system

    if not math.isfinite(tolerance) or tolerance < 0:
        raise InputError(None, f"the tolerance must be a number >= 0, got {tolerance}")
    run_p, plan_p = Path(run), Path(plan_path)
    if plan is None:
        plan = load_plan(plan_p)
    plan.require_feasible(plan_p, "validate")  # before the recording is read
    if not run_p.exists():
        raise InputError(run_p, "recording not found")
    system = plan_system(plan, plan_p, system_path)
    stats = read_recording(run_p)
    if not stats.topics or stats.messages == 0:
        raise InputError(run_p, "the recording has no messages")

    traces: list[Path] = [Path(c) for c in cpu] if cpu else []
    for t in traces:
        if not t.is_file():
            raise InputError(t, "CPU trace not found")
    if not traces:
        found = default_cpu_trace(run_p)
        traces = [found] if found is not None else []
    node_cpu: dict[str, TracedCpu] | None = None
    if traces:
        node_cpu = {}
        for t in traces:
            for node, nc in node_cpu_from_trace(t, plan, system, stats.start_ns, stats.end_ns).items():
                if node in node_cpu:
                    warnings.warn(f"{t}: node {node!r} also in {node_cpu[node].trace}; the later trace is used",
                                  PerfrosWarning, stacklevel=2)
                node_cpu[node] = nc
    latency, chains = measured_latency(run_p, plan, system)
    validation = check_run(stats, plan, cap=cap, tolerance=tolerance, system=system, node_cpu=node_cpu,
                           cpu_traces=[str(t) for t in traces], plan_path=str(plan_p),
                           metrics=measured_metrics(run_p, plan, system, stats), latency=latency, chains=chains)
    if is_forced(plan):
        validation.notes.append(FORCED_NOTE)
    slower = speed_note(system.source if system is not None else None, traces)
    if slower is not None:
        validation.notes.append(slower)
    return validation


def speed_note(model_path: str | None, traces: Sequence[Path]) -> str | None:
    """A note when the run's machine speed (its CPU traces' ``# speed_factor=``, their mean)
    is not the speed its model's recordings were made at (:func:`perfros_bag.cpu.speed.same_speed`)
    (model.json ``speed_factor``): the model's CPU per message, and the latency that follows
    from it, were measured on a machine of another speed. None when either is unknown."""
    from perfros_bag.cpu.speed import same_speed
    from perfros_bag.cpu.trace import trace_speed

    run = [s for t in traces if (s := trace_speed(t)) is not None]
    if not run or model_path is None or not model_path.endswith(".json"):
        return None
    from perfros_bag.fitting.modelfile import read_model

    try:
        model = read_model(model_path).speed_factor
    except InputError:
        return None  # a system.yaml saved as .json, or no model: nothing to compare
    here = sum(run) / len(run)
    if model is None or same_speed(here, model):
        return None
    return (f"the machine ran at speed {here:.2f} in this run and at {model:.2f} in the recordings {model_path} "
            f"was fitted on (record-cpu's reference workload, perfros_bag/cpu/speed.py): a node's CPU per message "
            f"is about {model / here:.2f}x what the model says, and its latency with it")


#: the note of a validation whose plan is forced (plan.json ``"forced": true``)
FORCED_NOTE = "the plan is forced (plan.json \"forced\": true): its loads may exceed its computers on purpose"
