"""Node names and parameter values a recording holds, for recordings without a manifest.

* node names: ``/rosout`` (``rcl_interfaces/msg/Log`` in ROS 2, ``rosgraph_msgs/Log`` in
  ROS 1: the ``name`` field) and, in ROS 1, the publishers' ``callerid``;
* parameter values (ROS 2): ``/parameter_events`` (``rcl_interfaces/msg/ParameterEvent``:
  the node's new and changed parameters, each with a typed value).

Both topics are decoded by the libraries (:mod:`perfros_bag.ingest.decode`). A parameter
whose value changes during the recording is *flagged*: :meth:`RecordingGraph.value` gives
the value in force for the longest part of the recording and a warning names the node, the
parameter and every value it took (the recording is not split).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.cpu.trace import match_label
from perfros_bag.errors import PerfrosError, PerfrosWarning
from perfros_bag.ingest.decode import Undecodable, decoded_messages
from perfros_bag.ingest.stats import RecordingStats

ROSOUT = "/rosout"
PARAMETER_EVENTS = "/parameter_events"
Value = bool | int | float | str

# rcl_interfaces/msg/ParameterType: the scalar types a setting can take
_SCALAR_FIELD = {1: "bool_value", 2: "integer_value", 3: "double_value", 4: "string_value"}


@dataclass
class RecordingGraph:
    """What a recording says about its nodes: their names and, per node, each parameter's
    values over time ``(log time ns, value)`` in time order."""

    nodes: list[str] = field(default_factory=list)
    parameters: dict[str, dict[str, list[tuple[int, Value]]]] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None

    def ros_node(self, node: str, process: str | None = None) -> str | None:
        """The recorded node that is system node ``node`` (same name, a namespace ignored;
        or the node's ``process`` regex), among the nodes with parameters."""
        return next((n for n in self.parameters if match_label(n, "", node, process)), None)

    def value(self, node: str, parameter: str, where: str = "") -> Value | None:
        """The value of ``parameter`` of recorded node ``node`` in force for the longest part
        of the recording (a warning when it changed); None when never set."""
        history = self.parameters.get(node, {}).get(parameter)
        if not history:
            return None
        distinct = list(dict.fromkeys(v for _, v in history))
        if len(distinct) == 1:
            return distinct[0]
        start = self.start_ns if self.start_ns is not None else history[0][0]
        end = self.end_ns if self.end_ns is not None else history[-1][0]
        held: dict[Value, int] = {}
        for (t, v), nxt in zip(history, [*(t for t, _ in history[1:]), end], strict=True):
            held[v] = held.get(v, 0) + max(min(nxt, end) - max(t, start), 0)
        chosen = max(distinct, key=lambda v: held.get(v, 0))
        warnings.warn(f"{where}node {node} parameter {parameter} changed during the recording "
                      f"({' -> '.join(map(str, (v for _, v in history)))}): flagged, the value held "
                      f"longest ({chosen}) is used", PerfrosWarning, stacklevel=2)
        return chosen


def _scalar(parameter_value: Any) -> Value | None:
    name = _SCALAR_FIELD.get(int(parameter_value.type))
    return None if name is None else getattr(parameter_value, name)


def read_graph(path: str | Path, stats: RecordingStats | None = None) -> RecordingGraph:
    """Node names (``/rosout``, ROS 1 ``callerid`` from ``stats``) and parameter histories
    (``/parameter_events``) of a recording; a topic that does not decode is a warning."""
    p = Path(path)
    graph = RecordingGraph()
    names: dict[str, None] = {}
    if stats is not None:
        graph.start_ns, graph.end_ns = stats.start_ns, stats.end_ns
        for ts in stats.topics.values():
            names.update(dict.fromkeys(ts.publishers))
    wanted = [t for t in (ROSOUT, PARAMETER_EVENTS)
              if stats is None or (t in stats.topics and stats.topics[t].messages)]
    if wanted:
        try:
            for topic, log_ns, msg in sorted(decoded_messages(p, wanted), key=lambda m: m[1]):
                if topic == ROSOUT:
                    names[_absolute(str(msg.name))] = None
                    continue
                node = _absolute(str(msg.node))
                names[node] = None
                params = graph.parameters.setdefault(node, {})
                for param in [*msg.new_parameters, *msg.changed_parameters]:
                    value = _scalar(param.value)
                    if value is not None:
                        params.setdefault(str(param.name), []).append((log_ns, value))
        except (Undecodable, PerfrosError) as exc:
            warnings.warn(f"{p}: node names and parameters not read: {exc}", PerfrosWarning, stacklevel=2)
    graph.nodes = [n for n in names if n]
    return graph


def _absolute(name: str) -> str:
    """ROS 2's /rosout gives names without the leading slash (``talker``), parameter events
    with it (``/talker``): one spelling, with it."""
    return name if not name or name.startswith("/") else "/" + name


def settings_from_graph(graph: RecordingGraph, nodes: Sequence[tuple[str, str, str | None]],
                        where: str = "") -> dict[str, Value]:
    """(system node, parameter name, process regex) -> the recorded value, for the nodes
    whose parameter the recording's parameter events set."""
    out: dict[str, Value] = {}
    for node, parameter, process in nodes:
        ros = graph.ros_node(node, process)
        value = None if ros is None else graph.value(ros, parameter, where)
        if value is not None:
            out[node] = value
    return out
