"""The live system, read without perturbing it.

One :meth:`Observer.read` asks the master who publishes each planned topic
(``getSystemState``, one call), every such publisher for its ``getBusStats`` (one call per
node, all at once on a small pool of threads) and psutil for each local node's CPU time, by
the PID the node's own XML-RPC ``getPid`` gave when the watch attached. No topic is
subscribed to. A reading waits at most ``call_budget_s`` for the publishers' answers (the
loop gives it a share of the window): a publisher that has not answered by then (a node
behind a throttled link, RQ4 saw 46 s windows of calls made one after the other) is
*unreadable* in this reading: its topics keep the counters and times of its last answer,
listed in :attr:`Reading.unread`, and it is not asked again while its call is under way, so a
window keeps its cadence and the next answer counts from the last one. A node is local when
its XML-RPC address is one of this machine's (loopback, its host names and interfaces) or
when the watch attached to a deploy (every emulated computer is a namespace here); other
nodes are unmeasured (their ``cpu`` is absent). A node is dead when its process is gone
(local) or its XML-RPC no longer answers ``getPid``.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from perfros_bag.rosrun.master import CALL_TIMEOUT_S, bus_stats, master_call, node_call
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
    #: (topic, publisher) whose publisher did not answer within the reading's budget: its
    #: counters and stamp in ``topics``/``stamps`` are those of its last answer (absent
    #: when it never answered)
    unread: set[tuple[str, str]] = field(default_factory=set)


#: threads a reading asks publishers on at most
CALL_THREADS = 8


def _ask(uri: str) -> tuple[Any, float]:
    """One ``getBusStats`` and when it was answered (the middle of the call)."""
    t0 = time.time()
    reply = bus_stats(uri)
    return reply, (t0 + time.time()) / 2


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


def _pid_at(uri: str) -> tuple[str, Any]:
    return uri, node_call(uri, "getPid")


class Observer:
    """Reads the running plan's nodes through the master at ``master_uri``."""

    def __init__(self, master_uri: str, planned_topics: Mapping[str, list[str]], *, all_local: bool = False,
                 call_budget_s: float = CALL_TIMEOUT_S) -> None:
        self.master_uri = master_uri
        self.call_budget_s = call_budget_s  # seconds a reading waits for the publishers' answers
        self._pool: ThreadPoolExecutor | None = None
        #: ROS node (``getPid <node>`` for :meth:`_again`) -> its call not answered yet
        self._under_way: dict[str, Future[Any]] = {}
        self._last: Reading | None = None
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
        """Follow a node that was restarted under the same name: its new URI and PID. Its
        ``getPid`` is waited for at most the reading's budget (a node behind a slow link
        answers a later reading: the call is not made again meanwhile)."""
        key = f"getPid {node.ros_name}"
        fut = self._under_way.pop(key, None)
        if fut is None:
            self.uris.pop(node.ros_name, None)
            uri = self._uri(node.ros_name)
            if uri is None:
                return
            fut = self._pool_of().submit(_pid_at, uri)
            wait_for([fut], timeout=self.call_budget_s)
        if not fut.done():
            self._under_way[key] = fut
            return
        uri, pid = fut.result()
        if isinstance(pid, int) and pid != node.pid:
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
        pubs = list(dict.fromkeys(p for t in sorted(wanted) for p in self.publishers.get(t, [])))
        replies, late = self._ask_all(pubs, state is not None)
        stats = {pub: parse_bus_stats(reply) for pub, (reply, _t) in replies.items()}
        answered = {pub: t for pub, (reply, t) in replies.items() if reply is not None}
        last = self._last
        for topic in sorted(wanted):
            for pub in self.publishers.get(topic, []):
                key = (topic, pub)
                if pub in late:  # no answer in time: its last answer (if any) stands, marked unread
                    reading.unread.add(key)
                    if last is not None and key in last.topics:
                        reading.topics[key] = last.topics[key]
                        reading.stamps[key] = last.stamps[key]
                elif topic in stats.get(pub, {}):
                    reading.topics[key] = stats[pub][topic]
                    reading.stamps[key] = answered[pub]
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
            # (a remote node whose call is still under way is no death either: its link is slow)
            reading.alive[name] = alive and (node.local or node.ros_name in answered or node.ros_name in late
                                             or isinstance(node_call(node.uri, "getPid"), int))
        reading.t = time.time()
        self._last = reading
        return reading

    def _ask_all(self, pubs: list[str], master_up: bool) -> tuple[dict[str, tuple[Any, float]], set[str]]:
        """Every publisher's ``getBusStats`` at once, waited for until the reading's budget:
        (publisher -> (its reply, when it answered), the publishers that did not answer in
        time). A reply of None that comes in time (refused: the node restarted under a new
        address, or is gone) is asked once more at the address the master gives now."""
        deadline = time.time() + self.call_budget_s
        replies: dict[str, tuple[Any, float]] = {}
        late: set[str] = set()
        asked: dict[str, Future[tuple[Any, float]]] = {}
        for pub in pubs:
            if pub in self._under_way:
                if not self._under_way[pub].done():  # still waiting from an earlier reading
                    late.add(pub)
                    continue
                del self._under_way[pub]
            uri = self.uris.get(pub) or (self._uri(pub) if master_up else None)
            if uri is None:
                replies[pub] = (None, time.time())
                continue
            asked[pub] = self._submit(uri)
        for attempt in (1, 2):
            wait_for(list(asked.values()), timeout=max(0.0, deadline - time.time()))
            again: dict[str, Future[tuple[Any, float]]] = {}
            for pub, fut in asked.items():
                if not fut.done():
                    late.add(pub)
                    self._under_way[pub] = fut
                    continue
                reply, t = fut.result()
                if reply is None and attempt == 1 and master_up and pub in self.uris:  # restarted: a new address?
                    old = self.uris.pop(pub)
                    uri = self._uri(pub)
                    if uri is not None and uri != old:
                        again[pub] = self._submit(uri)
                        continue
                replies[pub] = (reply, t)
            asked = again
        return replies, late

    def _pool_of(self) -> ThreadPoolExecutor:
        if self._pool is None:  # made by the reading thread: its threads share its network namespace
            self._pool = ThreadPoolExecutor(CALL_THREADS, thread_name_prefix="perfros-watch-call")
        return self._pool

    def _submit(self, uri: str) -> Future[tuple[Any, float]]:
        return self._pool_of().submit(_ask, uri)

    def close(self) -> None:
        """Let the calls under way end by their own timeout, without waiting for them."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        self._under_way.clear()
