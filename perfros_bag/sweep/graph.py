"""``graph.yaml``: the ROS graph as the master saw it during a run (format
``perfros-bag/graph@1``)::

    format: perfros-bag/graph@1
    run: camera-publish_rate-5__detector-canny_threshold-100   # the run it was taken in
    nodes:
      - {name: /detector, pid: 4242, executable: /usr/lib/opencv_apps/hough_circles, launched: true}
    topics:
      - {name: /detector/circles, type: opencv_apps/CircleArrayStamped,
         publishers: [/detector], subscribers: [/viewer]}

``launched``: the node is one of the launch file's (``/rosout``, started by roscore, is not).
Under space.yaml ``replay:`` a replaced node is not started: the ``rosbag play`` standing in
for it runs under its name (so it is ``launched``, with the player's PID and executable) and
carries ``replay: {recording: robot_day1.bag, factor: 2.0}`` (the recording as space.yaml
names it, the run's play-rate factor). A nodelet (``nodelet load PKG/TYPE MANAGER``) carries
``container: /MANAGER`` and ``nodelet: PKG/TYPE``: its PID is its loader's, and the topics the
manager carries for it list the nodelet as their publisher or subscriber
(:mod:`perfros_bag.sweep.nodelets`).
:func:`capture_graph` asks the master (getSystemState, getTopicTypes, lookupNode) and each
node (getPid); the tool's own nodes are left out.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from perfros_bag.doccheck import Doc
from perfros_bag.errors import PerfrosError
from perfros_bag.fileio import atomic_write_text, read_yaml
from perfros_bag.rosrun.master import master_call, master_state, node_call

GRAPH_FORMAT = "perfros-bag/graph@1"
_INTERPRETERS = ("python", "python3", "sh", "bash", "perl", "ruby", "node")


@dataclass(frozen=True)
class Replayed:
    """What a player standing in for a replaced node plays: the recording, at a factor."""

    recording: str
    factor: float


@dataclass(frozen=True)
class GraphNode:
    name: str
    pid: int | None
    executable: str | None
    launched: bool = True
    replay: Replayed | None = None  # a rosbag play standing in for this launch-file node
    container: str | None = None  # a nodelet: the manager that hosts it
    nodelet: str | None = None  # a nodelet: its PKG/TYPE


@dataclass(frozen=True)
class GraphTopic:
    name: str
    type: str | None
    publishers: tuple[str, ...]
    subscribers: tuple[str, ...]


@dataclass(frozen=True)
class Graph:
    nodes: tuple[GraphNode, ...]
    topics: tuple[GraphTopic, ...]
    run: str | None = None

    def node(self, name: str) -> GraphNode | None:
        return next((n for n in self.nodes if n.name == name), None)

    def to_dict(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"format": GRAPH_FORMAT}
        if self.run is not None:
            doc["run"] = self.run
        doc["nodes"] = [_node_dict(n) for n in self.nodes]
        doc["topics"] = [{"name": t.name, "type": t.type, "publishers": list(t.publishers),
                          "subscribers": list(t.subscribers)} for t in self.topics]
        return doc


def _node_dict(n: GraphNode) -> dict[str, Any]:
    out: dict[str, Any] = {"name": n.name, "pid": n.pid, "executable": n.executable, "launched": n.launched}
    if n.replay is not None:
        out["replay"] = {"recording": n.replay.recording, "factor": n.replay.factor}
    if n.container is not None:
        out["container"] = n.container
    if n.nodelet is not None:
        out["nodelet"] = n.nodelet
    return out


def executable_of(pid: int) -> str | None:
    """The program a process runs: the script for an interpreter, else the binary."""
    import psutil

    try:
        proc = psutil.Process(pid)
        cmdline = proc.cmdline()
        exe = proc.exe()
    except (psutil.Error, OSError):
        return None
    if cmdline and Path(cmdline[0]).name.rstrip("0123456789.") in _INTERPRETERS:
        script = next((a for a in cmdline[1:] if not a.startswith("-")), None)
        if script is not None:
            return script
    return exe or (cmdline[0] if cmdline else None)


def capture_graph(uri: str, launched: Collection[str], own: Collection[str], run: str | None = None) -> Graph:
    """The graph the master at ``uri`` knows, without the nodes named in ``own``.
    ``launched``: the launch file's node names."""
    state = master_state(uri)
    types_reply = master_call(uri, "getTopicTypes")
    if state is None or types_reply is None:
        raise PerfrosError(f"the ROS master at {uri} did not answer")
    types = {str(t): str(ty) for t, ty in types_reply}
    pubs = {str(t): sorted(str(n) for n in who if n not in own) for t, who in state[0]}
    subs = {str(t): sorted(str(n) for n in who if n not in own) for t, who in state[1]}
    names = set(launched)
    for who in (*pubs.values(), *subs.values()):
        names.update(who)
    nodes = []
    for name in sorted(names - set(own)):
        node_uri = master_call(uri, "lookupNode", name)
        pid = node_call(node_uri, "getPid") if isinstance(node_uri, str) else None
        pid = pid if isinstance(pid, int) and not isinstance(pid, bool) else None
        nodes.append(GraphNode(name, pid, executable_of(pid) if pid else None, name in launched))
    topics = []
    for topic in sorted(set(pubs) | set(subs)):
        p, s = pubs.get(topic, []), subs.get(topic, [])
        if p or s:
            topics.append(GraphTopic(topic, types.get(topic), tuple(p), tuple(s)))
    return Graph(tuple(nodes), tuple(topics), run)


def write_graph(path: str | Path, graph: Graph) -> None:
    import yaml

    atomic_write_text(path, yaml.safe_dump(graph.to_dict(), sort_keys=False, default_flow_style=None, width=100))


def read_graph(path: str | Path) -> Graph:
    p = Path(path)
    data = read_yaml(p)
    fail = Doc(p).fail
    if not isinstance(data, dict) or data.get("format") != GRAPH_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise fail("", f"not a graph.yaml (format {got!r}, expected {GRAPH_FORMAT!r})")
    nodes = []
    for i, raw in enumerate(data.get("nodes") or []):
        if not isinstance(raw, dict) or not isinstance(raw.get("name"), str) or not raw["name"]:
            raise fail(f"nodes[{i}]", f"expected {{name, pid, executable}}, got {raw!r}")
        pid = raw.get("pid")
        if pid is not None and (isinstance(pid, bool) or not isinstance(pid, int)):
            raise fail(f"nodes[{i}].pid", f"must be a whole number, got {pid!r}")
        exe = raw.get("executable")
        replay = raw.get("replay")
        replayed = None
        if replay is not None:
            factor = replay.get("factor") if isinstance(replay, dict) else None
            if not isinstance(replay, dict) or not isinstance(replay.get("recording"), str) \
                    or isinstance(factor, bool) or not isinstance(factor, int | float) or not factor > 0:
                raise fail(f"nodes[{i}].replay", f"expected {{recording, factor > 0}}, got {replay!r}")
            replayed = Replayed(replay["recording"], float(factor))
        member = {}
        for key in ("container", "nodelet"):
            if raw.get(key) is not None:
                if not isinstance(raw[key], str) or not raw[key]:
                    raise fail(f"nodes[{i}].{key}", f"must be a name, got {raw[key]!r}")
                member[key] = raw[key]
        nodes.append(GraphNode(raw["name"], pid, None if exe is None else str(exe), bool(raw.get("launched", True)),
                               replayed, **member))
    topics = []
    for i, raw in enumerate(data.get("topics") or []):
        if not isinstance(raw, dict) or not isinstance(raw.get("name"), str) or not raw["name"]:
            raise fail(f"topics[{i}]", f"expected {{name, type, publishers, subscribers}}, got {raw!r}")
        lists = {}
        for key in ("publishers", "subscribers"):
            val = raw.get(key) or []
            if not isinstance(val, list) or not all(isinstance(x, str) for x in val):
                raise fail(f"topics[{i}].{key}", f"must be a list of node names, got {val!r}")
            lists[key] = tuple(val)
        ty = raw.get("type")
        topics.append(GraphTopic(raw["name"], None if ty is None else str(ty),
                                 lists["publishers"], lists["subscribers"]))
    run = data.get("run")
    return Graph(tuple(nodes), tuple(topics), None if run is None else str(run))
