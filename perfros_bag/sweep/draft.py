"""``init``: draft a system.yaml from a sweep's folder (graph.yaml, manifest.yaml, recordings).

- one node per ROS node the launch file started (``/rosout`` and the tool's recorders left
  out), named without the leading slash, with the topics it publishes at a rate
  (``/rosout``, ``dynamic_reconfigure`` and latched one-message topics left out), a
  ``process`` pattern matching its label in the sweep's CPU traces, and, when the sweep
  varied it, its parameter (name and unit from the sweep's copy of space.yaml);
- edges from the subscriptions the master saw (graph.yaml); without graph.yaml the nodes and
  topics come from the recordings (ROS 1 ``callerid``, ``/rosout`` in ROS 1 and 2, a ROS 2
  topic going to the node named as its namespace) and there are no edges;
- one setting per measured value: CPU, frequency and bandwidth measured (the mean over the
  runs at that value; the characterisation of every run with a skeleton of this system);
- a node whose output followed the rate of a topic it subscribes to as driven (``input:``,
  per setting ``cpu`` + ``cpu_per_hz`` x the input's rate, ``out_per_in``, ``bytes_per_msg``:
  :mod:`perfros_bag.sweep.driven`), a throttle of that topic likewise with its value as
  ``max_frequency_hz`` (and ``step: period`` for topic_tools' rule); the node publishing that
  topic keeps its settings;
- what only the user knows, as a stated default and a comment: weights equal; performance
  ``100 x`` the node's measured output frequency ``/`` its highest (eq 10 measures
  performance through the output frequency);
- this machine as one computer of ``cores x units_per_core`` units (the manifest's scale, 100 =
  one core as ``sweep`` records), a commented robot +
  server example.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.characterisation.manifest import SWEEP_UNITS_PER_CORE, load_manifest
from perfros_bag.characterisation.table import characterise, check_settings, table_one
from perfros_bag.cpu.trace import read_cpu_trace
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fileio import atomic_write_text
from perfros_bag.ingest import read_recording
from perfros_bag.ingest.rosgraph import read_graph as read_recording_graph
from perfros_bag.sweep.driven import find_inputs, per_run, rated_topics
from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic, read_graph
from perfros_bag.sweep.runner import computer_name
from perfros_bag.sweep.space import Space, load_space
from perfros_bag.system.names import NameKind, name_problem, system_node_name
from perfros_bag.system.systemfile import parse_system

if TYPE_CHECKING:
    from perfros_bag.characterisation.manifest import Manifest
    from perfros_bag.characterisation.table import Row
    from perfros_bag.sweep.driven import Follow, RunMeasure

#: Nodes that are not the application's: roscore's, the tool's own recorders, rosbag's
#: recorders (ROS 1 ``record_<pid>``, ROS 2 ``rosbag2_recorder``) and the ros2 command line's.
NOT_APP = re.compile(r"^/(rosout|perfros_[a-z_]+|rosbag2_recorder|record_\d+|_ros2cli_\d+)$")
#: Message types that are not a node's output (logs, reconfiguration).
NOT_OUTPUT = re.compile(r"^(rosgraph_msgs|dynamic_reconfigure|bond)/")  # bond: a nodelet's tie to its manager
MIN_CPU = 0.1  # a setting's CPU must be > 0: what a node measured at 0 gets


def node_name(ros_name: str) -> str:
    """``ros_name`` as system.yaml names it; an error when no valid name can be made of it
    (names from a recording or graph are checked before they go into a system.yaml)."""
    name = system_node_name(ros_name)
    problem = name_problem(NameKind.NODE, name)
    if problem is not None:
        raise InputError(None, f"ROS node {ros_name!r} cannot be a system.yaml node: {name!r} {problem}")
    return name


@dataclass(frozen=True)
class Draft:
    """What :func:`draft_system` wrote: the text and the drafted nodes' names."""

    text: str
    nodes: tuple[str, ...]


def draft_system(directory: str | Path, out: str | Path) -> Draft:
    """Write the drafted system.yaml to ``out``; returns its text and nodes."""
    d = Path(directory)
    manifest = _manifest(d)
    values = _values(manifest)
    graph_path = d / "graph.yaml"
    graph = read_graph(graph_path) if graph_path.exists() else _graph_from_recordings(manifest)
    space = load_space(d / "space.yaml") if (d / "space.yaml").exists() else None  # the sweep's copy
    if space is not None:  # topics the sweep did not record (its exclude) have no measurement
        graph = replace(graph, topics=tuple(t for t in graph.topics if space.recorded(t.name)))
    parameters = _parameters(space)
    machine = _computer(manifest)
    app = [n for n in graph.nodes if n.launched and not NOT_APP.match(n.name)]
    if not app:
        raise InputError(graph_path, "no node of the application in the graph")
    named: dict[str, str] = {}
    for n in app:
        other = named.setdefault(node_name(n.name), n.name)
        if other != n.name:
            raise InputError(graph_path, f"ROS nodes {other} and {n.name} would both be named "
                             f"{node_name(n.name)!r} in system.yaml: rename one of them")
    unknown = sorted(set(values) - {node_name(n.name) for n in app})
    if unknown:
        raise InputError(manifest.path, f"settings name node(s) {', '.join(unknown)} that the graph does not have")
    skeleton = _skeleton(app, graph, values, parameters, machine)
    check_settings(manifest.recordings, skeleton, manifest.path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        result = characterise(manifest.recordings, skeleton)
    if result.failures:
        raise InputError(result.failures[0].recording, result.failures[0].message)
    _warn_members(skeleton, result.splits)
    by_run = per_run(result.rows)
    follows = find_inputs(skeleton.nodes, graph, by_run, {node_name(n.name): n.name for n in app})
    prices = {s.container: s.copy_per_MBps for s in result.splits if s.copy_per_MBps is not None}
    text = _render(d, graph, skeleton, result.rows, values, machine, graph_path.exists(), follows, by_run, prices)
    _check_loads(text, Path(out))
    atomic_write_text(out, text)
    return Draft(text, tuple(n.name for n in skeleton.nodes))


def _manifest(d: Path) -> Manifest:
    if not d.is_dir():
        raise InputError(d, "not a directory (expected the folder sweep recorded into)")
    path = d / "manifest.yaml"
    if not path.exists():
        raise InputError(d, "no manifest.yaml: not a folder of recorded runs (a sweep writes one)")
    manifest = load_manifest(path)
    if not manifest.recordings:
        raise InputError(path, "lists no recording")
    return manifest


def _values(manifest: Manifest) -> dict[str, list[float]]:
    """node -> the numeric values the runs set, in ascending order."""
    out: dict[str, set[float]] = {}
    for e in manifest.recordings:
        for node, value in e.settings.items():
            if isinstance(value, str):
                raise InputError(manifest.path, f"recording {e.name!r}: node {node}: value {value!r} is not a "
                                 "number (system.yaml settings are numbers)")
            out.setdefault(node, set()).add(value)
    return {n: sorted(v) for n, v in out.items()}


@dataclass(frozen=True)
class _Machine:
    """Where the runs were measured: the manifest's computer, its logical CPUs (the CPU
    traces') and the measurement's CPU units per core (the manifest's ``units_per_core``)."""

    name: str
    cores: int
    units_per_core: float
    own_scale: bool  # every run gives units_per_core: the system's computers cannot rescale the data

    @property
    def capacity(self) -> float:
        return _norm(self.cores * self.units_per_core)


def _computer(manifest: Manifest) -> _Machine:
    """This machine, as the runs measured it."""
    names = {e.computer for e in manifest.recordings if e.computer}
    if len(names) > 1:
        raise InputError(manifest.path, f"the runs name several computers ({', '.join(sorted(names))}): "
                         "init drafts one machine")
    units = {e.units_per_core for e in manifest.recordings if e.units_per_core is not None}
    if len(units) > 1:
        raise InputError(manifest.path, f"the runs were measured in several scales (units_per_core "
                         f"{', '.join(f'{u:g}' for u in sorted(units))}): init drafts one machine")
    name = names.pop() if names else computer_name()
    trace = next((e.cpu for e in manifest.recordings if e.cpu is not None and e.cpu.exists()), None)
    if trace is None:
        raise InputError(manifest.path, "no CPU trace beside the recordings (expected <run>.cpu.csv)")
    own = all(e.units_per_core is not None for e in manifest.recordings)
    return _Machine(name, read_cpu_trace(trace).logical_cpus, units.pop() if units else float(SWEEP_UNITS_PER_CORE),
                    own)


def _parameters(space: Space | None) -> dict[str, tuple[str, str | None]]:
    """node -> (parameter name, unit) from the sweep's copy of space.yaml (when there)."""
    if space is None:
        return {}
    return {name: (p.name, p.unit) for name, p in space.parameters().items()}  # replay: a replaced node's rate


def _graph_from_recordings(manifest: Manifest) -> Graph:
    """Nodes and topics from the recordings themselves (no graph.yaml, no subscriptions):
    nodes from the publishers' ROS 1 ``callerid`` and the ``/rosout`` names (ROS 1 and 2,
    :func:`perfros_bag.ingest.rosgraph.read_graph`) of every recording; a topic no callerid
    names (ROS 2 records none) goes to the node whose name is its namespace (``/detector``
    publishes ``/detector/circles``; the longest such name)."""
    names: dict[str, None] = {}
    types: dict[str, str] = {}
    publishers: dict[str, set[str]] = {}
    for e in manifest.recordings:
        stats = read_recording(e.path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PerfrosWarning)  # a parameter changed: not init's business
            names.update(dict.fromkeys(read_recording_graph(e.path, stats).nodes))
        for t in stats.topics.values():
            types.setdefault(t.topic, t.msgtype)
            publishers.setdefault(t.topic, set()).update(t.publishers)
    for topic, pubs in publishers.items():
        owner = max((n for n in names if topic.startswith(n.rstrip("/") + "/")), key=len, default=None)
        if not pubs and owner is not None:
            pubs.add(owner)
    if not names:
        raise InputError(manifest.recordings[0].path,
                         "no graph.yaml beside it and no node in the recordings (no callerid, no /rosout)")
    topics = tuple(GraphTopic(t, types[t], tuple(sorted(publishers[t])), ()) for t in sorted(publishers))
    return Graph(tuple(GraphNode(n, None, None, True) for n in sorted(names)), topics)


def _output_topics(node: GraphNode, graph: Graph) -> tuple[str, ...]:
    return tuple(t.name for t in graph.topics
                 if node.name in t.publishers and t.name not in ("/rosout", "/rosout_agg")
                 and not NOT_OUTPUT.match(t.type or ""))


def _skeleton(app: Sequence[GraphNode], graph: Graph, values: Mapping[str, list[float]],
              parameters: Mapping[str, tuple[str, str | None]], machine: _Machine) -> Any:
    """The system the runs are characterised with: the nodes, their topics and patterns."""
    nodes = []
    for n in app:
        name = node_name(n.name)
        entry: dict[str, Any] = {"name": name, "weight": 1.0, "process": f"^{re.escape(n.name)}$",
                                 "settings": [{"cpu": 1, "performance": 1}]}
        topics = _output_topics(n, graph)
        if topics:
            entry["topics"] = list(topics)
        if n.container is not None:
            entry["container"] = node_name(n.container)
        if name in values:
            pname, unit = parameters.get(name, ("value", None))
            entry["parameter"] = {"name": pname} if unit is None else {"name": pname, "unit": unit}
        nodes.append(entry)
    doc: dict[str, Any] = {"computers": [{"name": machine.name, "kind": "robot", "capacity": machine.capacity}],
                           "nodes": nodes}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        system = parse_system(doc, "<skeleton>")
        if not system.containers:
            return system
        doc["edges"] = _edges(graph, system.nodes)  # what a container's copy price is measured on
        return parse_system(doc, "<skeleton>")


def _topic_means(rows: Sequence[Row]) -> dict[tuple[str, str, str], tuple[float | None, float | None]]:
    """(node, value, topic) -> mean frequency and bandwidth over the recordings."""
    acc: dict[tuple[str, str, str], list[tuple[float | None, float | None]]] = {}
    for r in rows:
        if r.node and r.topic:
            acc.setdefault((r.node, repr(r.value), r.topic), []).append((r.frequency_hz, r.bandwidth_kBps))
    out = {}
    for key, pairs in acc.items():
        f = [p[0] for p in pairs if p[0] is not None]
        b = [p[1] for p in pairs if p[1] is not None]
        out[key] = (sum(f) / len(f) if f else None, sum(b) / len(b) if b else None)
    return out


def _r(x: float, digits: int = 4) -> float:
    return float(f"{x:.{digits}g}")


def _render(d: Path, graph: Graph, skeleton: Any, rows: Sequence[Row], values: Mapping[str, list[float]],
            machine: _Machine, from_graph: bool, follows: Mapping[str, Follow],
            by_run: Mapping[str, Mapping[str, RunMeasure]], prices: Mapping[str, float] | None = None) -> str:
    import yaml

    def flow(obj: Any) -> str:  # one line of YAML, names quoted where YAML needs it
        return yaml.safe_dump([obj], default_flow_style=True, sort_keys=False, width=1 << 20).strip()[1:-1]

    per_value = {(t.node, repr(t.value)): t for t in table_one(rows)}
    topic_means = _topic_means(rows)
    nodes = skeleton.nodes
    weight = 1.0 / len(nodes)
    runs = len({r.recording for r in rows})
    lines = [
        f"# system.yaml drafted by `perfros-bag init` from {d}: "
        + ("graph.yaml, " if from_graph else "the recordings' callerids and /rosout (no graph.yaml: no edges), ")
        + f"manifest.yaml and {runs} run(s).",
        "# It loads, fits and solves as it is. Lines marked REPLACE hold stated defaults that only you",
        "# can know better: the nodes' weights and performance.",
        f"cpu_unit: {flow(f'{machine.units_per_core:g} = one core of {machine.name} (the machine the sweep ran on)')}",
        "computers:",
        f"  # this machine: {machine.cores} logical CPUs x {machine.units_per_core:g}"
        + (". The measured CPU figures keep the runs' own scale (manifest.yaml units_per_core):\n"
           "  # edit this computer, or describe your robots below, and the plan changes, never the data."
           if machine.own_scale else " (it also normalises the CPU traces: manifest.yaml has no units_per_core)"),
        f"  - {flow({'name': machine.name, 'kind': 'robot', 'capacity': machine.capacity})}",
        "  # where the nodes may run instead, e.g. a robot and a server on Wi-Fi (then add links:)",
        "  # - {name: robot1, kind: robot, capacity: 100}",
        "  # - {name: server, kind: server, capacity: 400}",
        "# links:",
        "#   - {between: [robot1, server], bandwidth_kBps: 37500, medium: wifi}",
        "# media:",
        "#   - {name: wifi, bandwidth_kBps: 37500}",
        "nodes:",
    ]
    for node in nodes:
        ros = graph.node("/" + node.name)
        exe = ros.executable if ros is not None and ros.executable else "executable unknown"
        keys = [_norm(v) for v in values.get(node.name, [])] if node.parameter else [None]
        if node.name in follows:
            lines += _render_driven(node, exe, keys, weight, follows[node.name], by_run[node.name], flow, ros)
            continue
        measured = [_measured(node, key, per_value, topic_means) for key in keys]
        freqs = [m.frequency_hz for m in measured if m.frequency_hz]
        top = max(freqs) if freqs else None
        lines.append(f"  # /{node.name} ({exe})")
        lines.append(f"  - name: {flow(node.name)}")
        lines.append(f"    weight: {weight!r}  # REPLACE: every node weighs the same (a stated default)")
        lines += _process_lines(node, ros, flow, prices)
        if top:
            lines.append(f"    # performance: REPLACE. A stated default: 100 x the measured output frequency / "
                         f"its highest ({_r(top)} Hz)")
        else:
            lines.append("    # performance: REPLACE. A stated default: 100 (the node publishes no output at a rate)")
        lines.append("    settings:")
        lines += [f"      - {flow(_setting(m, top))}" for m in measured]
    edges = _edges(graph, nodes)
    if edges:
        lines.append("edges:")
        lines += [f"  - {flow(e)}" for e in edges]
    elif not from_graph:
        lines.append("# edges: unknown without graph.yaml: add {from: NODE, to: NODE, topic: TOPIC} per subscription")
    lines += _render_chains(nodes, follows, flow)
    return "\n".join(lines) + "\n"


def _process_lines(node: Any, ros: GraphNode | None, flow: Callable[[Any], str],
                   prices: Mapping[str, float] | None = None) -> list[str]:
    """A node's parameter, topics, container and process lines (every drafted node has them);
    a container's measured copy price (``prices``: container -> CPU units per MB/s)."""
    lines = []
    if prices and node.name in prices:
        lines.append(f"    copy_cpu_per_MBps: {_r(prices[node.name])}  # CPU units per MB/s of copies its nodes "
                     "would add run standalone (its standalone run against its runs at the same values)")
    if node.parameter is not None:
        lines.append(f"    parameter: {flow(_parameter(node.parameter))}")
    if node.topics:
        lines.append(f"    topics: {flow(list(node.topics))}")
    lines += _container_lines(node, ros)
    lines.append(f"    process: {flow(node.process)}  # its ROS name in the sweep's CPU traces")
    return lines


def _container_lines(node: Any, ros: GraphNode | None) -> list[str]:
    """A hosted node's ``container:`` (its CPU: its share of the container's, fitted)."""
    if node.container is None:
        return []
    kind = f"nodelet {ros.nodelet}" if ros is not None and ros.nodelet else "hosted"
    return [f"    container: {node.container}  # {kind}: runs in {node.container}'s process; its CPU is its share "
            "of that process's, fitted over the runs (docs/formats.md, Nodelets)"]


def _render_chains(nodes: Sequence[Any], follows: Mapping[str, Follow], flow: Callable[[Any], str]) -> list[str]:
    """One chain per driven node fed by a node on its own clock: its input, then its first
    topic, on through the driven nodes each one feeds (their first topics); its budget is
    left for the user to state (docs/formats.md, ``budget_ms``)."""
    topics_of = {n.name: list(n.topics) for n in nodes}
    fed_by = {f.topic: name for name, f in follows.items()}
    chains: list[tuple[str, list[str]]] = []
    for name, f in follows.items():
        if f.publisher in follows or not topics_of.get(name):
            continue
        path, at = [f.topic, topics_of[name][0]], name
        while (nxt := fed_by.get(path[-1])) is not None and nxt not in path and topics_of.get(nxt):
            path.append(topics_of[nxt][0])
            at = nxt
        chains.append((at, path))
    if not chains:
        return []
    lines = ["# the data flow's chains: their latency is measured (validate) and predicted (solve);",
             "# a budget_ms makes every plan keep its predicted latency within it",
             "chains:"]
    for at, path in chains:
        lines += [f"  - name: {flow(at)}", f"    topics: {flow(path)}",
                  "    # budget_ms: {p95: 250}  # REPLACE: the most its latency may be, in ms (p50 and/or p95)"]
    return lines


def _render_driven(node: Any, exe: str, keys: Sequence[int | float | None], weight: float, follow: Follow,
                   runs: Mapping[str, RunMeasure], flow: Callable[[Any], str],
                   ros: GraphNode | None = None) -> list[str]:
    """A driven node's lines (perfros_bag/sweep/driven.py: the rule and the numbers)."""
    from perfros_bag.sweep.driven import (
        INPUT_VARIED,
        RATIO_TOLERANCE,
        draft_settings,
        draft_throttle,
    )

    drafted = (draft_settings if follow.throttle is None else draft_throttle)(node.topics, runs, follow)
    missing = [k for k in keys if repr(k) not in drafted]
    if missing:
        raise InputError(None, f"node {node.name}: no run measured it at value {missing[0]}")
    settings = [drafted[repr(k)] for k in keys]
    top = max(s.out_per_in for s in settings)
    if follow.throttle is not None:  # its performance follows what it lets through, as a paper node's
        f_out = _throttle_output(node.topics, runs)
        perf = {repr(k): 100.0 * f_out[repr(k)] / max(f_out.values()) for k in keys}
        how = ("the step F_in / ceil(F_in / value) (a message passes once 1/value s have elapsed since the last)"
               if follow.throttle == "period" else "min(F_in, value)")
        said = [f"    # driven, a throttle: its output moved with its value, never above {follow.topic}'s rate, and",
                f"    # every run gave {how}, the worst {100 * follow.spread:.1f} % off (max_frequency_hz = its value)"]
    else:
        said = [f"    # driven: its output kept one rate per message of {follow.topic} (within "
                f"{100 * (RATIO_TOLERANCE - 1):.0f} %) while that rate varied by more than "
                f"{100 * (INPUT_VARIED - 1):.0f} %"]
        if follow.overloaded:
            worst = max(follow.overloaded, key=lambda r: 1 - follow.overloaded[r] / follow.input_hz[r])
            share = 100 * (1 - follow.overloaded[worst] / follow.input_hz[worst])
            note = (f"overloaded in {len(follow.overloaded)} run(s) (dropped up to {share:.0f} % of its input, "
                    f"in {worst}): their ratio left out, their CPU counted at the rate it processed")
            said.append(f"    # {note}")
            warnings.warn(PerfrosWarning(f"node {node.name}: {note}"), stacklevel=2)
    lines = [f"  # /{node.name} ({exe})",
             f"  - name: {flow(node.name)}",
             f"    weight: {weight!r}  # REPLACE: every node weighs the same (a stated default)",
             *said,
             f"    input: {flow(follow.topic)}"]
    lines += _process_lines(node, ros, flow)
    lines.append("    # cpu + cpu_per_hz x input rate: least squares over the runs at each setting; "
                 "performance: REPLACE.")
    if follow.throttle is not None:
        lines.append("    # A stated default: 100 x its measured output rate / the highest")
    else:
        lines.append(f"    # A stated default: 100 x its out_per_in / the highest ({_r(top)})")
    lines.append("    settings:")
    for s in settings:
        entry: dict[str, Any] = {} if s.value is None else {"value": _norm(s.value)}
        entry.update(cpu=_r(s.cpu), cpu_per_hz=_r(s.cpu_per_hz),
                     performance=_r(100.0 * s.out_per_in / top) if top > 0 else 100.0,
                     out_per_in=_r(s.out_per_in), bytes_per_msg=_r(s.bytes_per_msg))
        if follow.throttle is not None:
            entry["performance"] = _r(perf[repr(s.value)])
            entry["max_frequency_hz"] = _norm(s.value)
            if follow.throttle == "period":
                entry["step"] = "period"
        note = ""
        if s.clipped is not None:
            note = f"  # {s.clipped}"
        elif s.scaled_from is not None:
            note = (f"  # input rate not varied here: the line at value {_norm(s.scaled_from)} scaled by "
                    "this setting's CPU")
        lines.append(f"      - {flow(entry)}{note}")
    return lines


def _throttle_output(topics: Sequence[str], runs: Mapping[str, RunMeasure]) -> dict[str, float]:
    """own value (``repr``) -> a throttle's mean output rate over its rated topics and runs."""
    rated = rated_topics(topics, runs)
    acc: dict[str, list[float]] = {}
    for m in runs.values():
        acc.setdefault(repr(m.value), []).extend(m.rate(t) for t in rated)
    return {k: sum(v) / len(v) for k, v in acc.items()}


def _norm(v: float) -> float | int:
    return int(v) if float(v).is_integer() else v


def _parameter(p: Any) -> dict[str, Any]:
    return {"name": p.name} if p.unit is None else {"name": p.name, "unit": p.unit}


@dataclass(frozen=True)
class _Measured:
    """A node at one value: CPU (mean over the runs), and over its output topics the mean
    frequency, the summed bandwidth and each topic's own."""

    value: int | float | None
    cpu: float
    frequency_hz: float | None
    bandwidth_kBps: float | None
    topics: dict[str, dict[str, float]]


def _measured(node: Any, value: int | float | None, per_value: Mapping[tuple[str, str], Any],
              topic_means: Mapping[tuple[str, str, str], tuple[float | None, float | None]]) -> _Measured:
    row = per_value.get((node.name, repr(value)))
    if row is None:
        raise InputError(None, f"node {node.name}: no run measured it at value {value}")
    cpu = row.cpu if row.cpu is not None and math.isfinite(row.cpu) else 0.0
    topics: dict[str, dict[str, float]] = {}
    for t in node.topics:
        f, b = topic_means.get((node.name, repr(value), t), (None, None))
        rate = {k: x for k, x in (("frequency_hz", f), ("bandwidth_kBps", b)) if x is not None}
        if rate:
            topics[t] = rate
    freqs = [r["frequency_hz"] for r in topics.values() if "frequency_hz" in r]
    bws = [r["bandwidth_kBps"] for r in topics.values() if "bandwidth_kBps" in r]
    return _Measured(value, cpu, sum(freqs) / len(freqs) if freqs else None, sum(bws) if bws else None, topics)


def _setting(m: _Measured, top: float | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if m.value is not None:
        out["value"] = m.value
    out["cpu"] = max(MIN_CPU, _r(m.cpu))
    out["performance"] = _r(100.0 * (m.frequency_hz or 0.0) / top) if top else 100.0
    if m.frequency_hz is not None:
        out["frequency_hz"] = _r(m.frequency_hz)
    if m.bandwidth_kBps is not None:
        out["bandwidth_kBps"] = _r(m.bandwidth_kBps)
    if m.topics:
        out["topics"] = {t: {k: _r(x) for k, x in rate.items()} for t, rate in m.topics.items()}
    return out


def _edges(graph: Graph, nodes: Sequence[Any]) -> list[dict[str, str]]:
    names = {n.name for n in nodes}
    out = []
    for n in nodes:
        for t in n.topics:
            topic = next((g for g in graph.topics if g.name == t), None)
            for sub in topic.subscribers if topic is not None else ():
                dst = node_name(sub)
                if dst in names and dst != n.name:
                    out.append({"from": n.name, "to": dst, "topic": t})
    return out


def _warn_members(skeleton: Any, splits: Sequence[Any]) -> None:
    """Never silent about what a process hosts: a nodelet with no topic of its own (only its
    bond) and each container fit's problem are warnings naming the node and what was done."""
    for n in skeleton.nodes:
        if n.container is not None and not n.topics:
            warnings.warn(PerfrosWarning(f"node {n.name}: a nodelet of {n.container} whose only published topic is "
                                         "its bond: drafted with no topics (performance 100, no rate)"), stacklevel=3)
    for s in splits:
        for note in s.notes:
            warnings.warn(PerfrosWarning(note), stacklevel=3)
        for k in s.cpu:
            lo = min(s.cpu[k].values())
            if lo <= 0:
                warnings.warn(PerfrosWarning(f"node {k}: its share of {s.container}'s CPU fitted to 0 at some value: "
                                             f"drafted at {MIN_CPU} there"), stacklevel=3)


def _check_loads(text: str, out: Path) -> None:
    """The draft must load as a system.yaml (a bug here, not the user's input)."""
    import yaml

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        parse_system(yaml.safe_load(text), str(out))
