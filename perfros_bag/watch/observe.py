"""The live system, read without perturbing it.

One :meth:`Observer.read` asks the master who publishes each planned topic
(``getSystemState``, one call), every such publisher for its ``getBusStats`` (one call per
node) and psutil for each local node's CPU time, by the PID the node's own XML-RPC
``getPid`` gave when the watch attached. No topic is subscribed to. A node is local when
its XML-RPC address is one of this machine's (loopback, its host names and interfaces) or
when the watch attached to a deploy (every emulated computer is a namespace here); other
nodes are unmeasured (their ``cpu`` is absent). A node is dead when its process is gone
(local) or its XML-RPC no longer answers ``getPid``.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from perfros_bag.rosrun.master import bus_stats, master_call, node_call
from perfros_bag.system.names import system_node_name
from perfros_bag.watch.counters import TopicCounters, parse_bus_stats


@dataclass
class WatchedNode:
    """A planned node found running: its ROS name, XML-RPC URI and PID."""

    plan_name: str
    ros_name: str
    uri: str
    pid: int | None
    local: bool
    created: float | None = None  # the process's start time (a reused PID is not the node)


@dataclass
class Reading:
    """Everything counted at one moment (``t``: seconds since the epoch)."""

    t: float
    #: (topic, publisher ROS name) -> its counters
    topics: dict[tuple[str, str], TopicCounters] = field(default_factory=dict)
    #: (topic, publisher) -> when its publisher answered (the middle of the call)
    stamps: dict[tuple[str, str], float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)  # plan node -> CPU seconds so far (local)
    cpu_t: dict[str, float] = field(default_factory=dict)  # plan node -> when its CPU time was read
    cpu_pid: dict[str, int] = field(default_factory=dict)  # plan node -> the PID it was read of
    alive: dict[str, bool] = field(default_factory=dict)  # plan node -> alive
    master_up: bool = True


def local_hosts() -> set[str]:
    """Names and addresses of this machine (its own network namespace)."""
    import psutil

    hosts = {"localhost", socket.gethostname(), socket.getfqdn()}
    for addrs in psutil.net_if_addrs().values():
        hosts.update(a.address.split("%")[0] for a in addrs if a.family in (socket.AF_INET, socket.AF_INET6))
    return hosts


def _is_local(uri: str, hosts: set[str]) -> bool:
    host = urlsplit(uri).hostname or ""
    return host in hosts or host.startswith("127.") or host == "::1"


def _create_time(pid: int) -> float | None:
    import psutil

    try:
        return float(psutil.Process(pid).create_time())
    except psutil.Error:
        return None


def _running(node: WatchedNode) -> bool:
    import psutil

    try:
        p = psutil.Process(node.pid or 0)
        return (node.created is None or abs(p.create_time() - node.created) < 0.01) \
            and p.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


class Observer:
    """Reads the running plan's nodes through the master at ``master_uri``."""

    def __init__(self, master_uri: str, planned_topics: Mapping[str, list[str]], *, all_local: bool = False) -> None:
        self.master_uri = master_uri
        self.planned_topics = {n: list(ts) for n, ts in planned_topics.items()}  # plan node -> its topics
        self.all_local = all_local
        self.nodes: dict[str, WatchedNode] = {}  # plan node -> found
        self.publishers: dict[str, list[str]] = {}  # topic -> ROS publishers (last known)
        self.types: dict[str, str] = {}  # topic -> message type
        self.uris: dict[str, str] = {}  # ROS node -> XML-RPC URI (cached)

    def _state(self) -> tuple[list[Any], list[Any], list[Any]] | None:
        reply = master_call(self.master_uri, "getSystemState")
        if not isinstance(reply, list) or len(reply) != 3:
            return None
        return list(reply[0]), list(reply[1]), list(reply[2])

    def _uri(self, ros_name: str) -> str | None:
        if ros_name not in self.uris:
            uri = master_call(self.master_uri, "lookupNode", ros_name)
            if not isinstance(uri, str):
                return None
            self.uris[ros_name] = uri
        return self.uris[ros_name]

    def attach(self) -> list[str]:
        """Find every planned node; returns the planned nodes not running (in plan order)."""
        state = self._state()
        names: set[str] = set()
        if state is not None:
            for section in state:
                for entry in section:
                    if isinstance(entry, list) and len(entry) == 2 and isinstance(entry[1], list):
                        names.update(str(x) for x in entry[1])
            self._publishers(state)
        types = master_call(self.master_uri, "getTopicTypes")
        if isinstance(types, list):
            self.types = {str(t[0]): str(t[1]) for t in types if isinstance(t, list) and len(t) == 2}
        by_plan: dict[str, str] = {}
        for ros in sorted(names):
            by_plan.setdefault(system_node_name(ros), ros)
        hosts = set() if self.all_local else local_hosts()
        missing = []
        for plan_name in self.planned_topics:
            found = by_plan.get(plan_name)
            uri = None if found is None else self._uri(found)
            pid = None if uri is None else node_call(uri, "getPid")
            if found is None or uri is None or not isinstance(pid, int):
                missing.append(plan_name)
                continue
            local = self.all_local or _is_local(uri, hosts)
            self.nodes[plan_name] = WatchedNode(plan_name, found, uri, pid if local else None, local,
                                                _create_time(pid) if local else None)
        return missing

    def _again(self, node: WatchedNode) -> None:
        """Follow a node that was restarted under the same name: its new URI and PID."""
        self.uris.pop(node.ros_name, None)
        uri = self._uri(node.ros_name)
        pid = None if uri is None else node_call(uri, "getPid")
        if uri is not None and isinstance(pid, int) and pid != node.pid:
            node.uri, node.pid, node.created = uri, pid, _create_time(pid)

    def _publishers(self, state: tuple[list[Any], list[Any], list[Any]]) -> None:
        self.publishers = {str(e[0]): [str(x) for x in e[1]] for e in state[0]
                           if isinstance(e, list) and len(e) == 2 and isinstance(e[1], list)}

    def read(self) -> Reading:
        """One reading of every counter (see the module's doc)."""
        import psutil

        state = self._state()
        reading = Reading(time.time(), master_up=state is not None)
        if state is not None:
            self._publishers(state)
        wanted = {t for n in self.nodes for t in self.planned_topics[n]}
        stats: dict[str, dict[str, TopicCounters]] = {}
        answered: dict[str, float] = {}  # ROS node -> when it answered getBusStats
        for topic in sorted(wanted):
            for pub in self.publishers.get(topic, []):
                if pub not in stats:
                    uri = self.uris.get(pub) or (self._uri(pub) if state is not None else None)
                    t0 = time.time()
                    reply = bus_stats(uri) if uri else None
                    if reply is None and state is not None and pub in self.uris:  # restarted: a new address
                        del self.uris[pub]
                        uri = self._uri(pub)
                        t0 = time.time()
                        reply = bus_stats(uri) if uri else None
                    stats[pub] = parse_bus_stats(reply)
                    if reply is not None:
                        answered[pub] = (t0 + time.time()) / 2
                if topic in stats[pub]:
                    reading.topics[(topic, pub)] = stats[pub][topic]
                    reading.stamps[(topic, pub)] = answered[pub]
        for name, node in self.nodes.items():
            if node.local and node.pid is not None and state is not None and not _running(node):
                self._again(node)  # a node restarted under its name (a deploy applying a new plan) goes on
            if node.local and node.pid is not None:
                alive = _running(node)
                if alive:
                    try:
                        ct = psutil.Process(node.pid).cpu_times()
                        reading.cpu_s[name] = float(ct.user + ct.system)
                        reading.cpu_t[name] = time.time()
                        reading.cpu_pid[name] = node.pid
                    except psutil.Error:
                        alive = False
            else:
                alive = True
            # a local node: its process runs (an XML-RPC call a loaded machine answers late is no
            # death); else its XML-RPC answers: getBusStats did this time, else ask getPid
            reading.alive[name] = alive and (node.local or node.ros_name in answered
                                             or isinstance(node_call(node.uri, "getPid"), int))
        reading.t = time.time()
        return reading
