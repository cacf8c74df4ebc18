"""A ROS 1 master of our own, and what it and the nodes answer over XML-RPC.

:func:`start_roscore` starts ``roscore`` on a free loopback port and makes sure the master
answering there is ours. :func:`master_call` / :func:`node_call` are one XML-RPC call that
answers None on any failure (not up yet, or another program on the port).
"""

from __future__ import annotations

import functools
import socket
import xmlrpc.client
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.errors import PerfrosError
from perfros_bag.rosrun.processes import Processes, Started, wait_for

ROSCORE = "roscore"
#: The caller id our own XML-RPC calls use.
CALLER_ID = "/perfros_launcher"
#: Seconds an XML-RPC call may take before it counts as no answer.
CALL_TIMEOUT_S = 5.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _TimeoutTransport(xmlrpc.client.Transport):
    def make_connection(self, host: Any) -> Any:
        conn = super().make_connection(host)
        conn.timeout = CALL_TIMEOUT_S
        return conn


def _call(uri: str, method: str, *args: Any) -> Any:
    try:
        proxy = xmlrpc.client.ServerProxy(uri, transport=_TimeoutTransport())
        return getattr(proxy, method)(CALLER_ID, *args)
    except Exception:  # noqa: BLE001 - whatever answers on the port, it is not a ROS peer
        return None


def _value(reply: Any) -> Any:
    """The value of a ``[code, message, value]`` reply; None unless code is 1 (success)."""
    try:
        code, _msg, value = reply
    except (TypeError, ValueError):
        return None
    return value if code == 1 else None


def master_call(uri: str, method: str, *args: Any) -> Any:
    """One ROS master XML-RPC call; None on any failure (not up yet, or not a ROS master:
    another program may have taken the port)."""
    return _value(_call(uri, method, *args))


def node_call(uri: str, method: str, *args: Any) -> Any:
    """One call of a node's XML-RPC API (``getPid``...); None on failure."""
    return _value(_call(uri, method, *args))


def bus_stats(uri: str) -> Any:
    """A node's ``getBusStats``: ``[publish, subscribe, service]`` statistics. roscpp
    answers them bare, not as ``[code, message, value]``; both are accepted."""
    reply = _call(uri, "getBusStats")
    if isinstance(reply, list) and len(reply) == 3 and isinstance(reply[0], int):
        return _value(reply)
    return reply


@dataclass(frozen=True)
class TopicCounters:
    """One publisher's counters of one topic at one reading."""

    #: connection id -> (messages, payload bytes) sent on it so far
    connections: dict[int, tuple[int, int]] = field(default_factory=dict)
    #: the topic's payload bytes as one total (rospy), else None
    total_bytes: int | None = None


def _int(x: Any) -> int | None:
    return x if isinstance(x, int) and not isinstance(x, bool) else None


def parse_bus_stats(stats: Any) -> dict[str, TopicCounters]:
    """Per published topic, its counters in one node's :func:`bus_stats` answer: roscpp
    ``[topic, [[id, bytes, message_bytes, messages, _], ...]]``; rospy ``[topic,
    message_bytes, [[id, bytes with headers, messages, connected], ...]]`` (anything
    malformed is left out: a peer that answers oddly is read as counting nothing)."""
    out: dict[str, TopicCounters] = {}
    if not isinstance(stats, list) or not stats or not isinstance(stats[0], list):
        return out
    for entry in stats[0]:
        if not isinstance(entry, list) or len(entry) < 2 or not isinstance(entry[0], str):
            continue
        conns: dict[int, tuple[int, int]] = {}
        if _int(entry[1]) is not None and len(entry) > 2 and isinstance(entry[2], list):  # rospy
            for c in entry[2]:
                if isinstance(c, list) and len(c) > 2 and _int(c[0]) is not None and _int(c[2]) is not None:
                    conns[c[0]] = (c[2], 0)
            out[entry[0]] = TopicCounters(conns, entry[1])
        elif isinstance(entry[1], list):  # roscpp
            for c in entry[1]:
                if isinstance(c, list) and len(c) > 3 and all(_int(c[i]) is not None for i in (0, 2, 3)):
                    conns[c[0]] = (c[3], c[2])
            out[entry[0]] = TopicCounters(conns)
    return out


def master_state(uri: str) -> tuple[list[Any], list[Any]] | None:
    """(publishers, subscribers) of getSystemState: lists of ``[topic, [node, ...]]``."""
    reply = master_call(uri, "getSystemState")
    if reply is None:
        return None
    return list(reply[0]), list(reply[1])


def _exited(st: Started) -> str | None:
    return st.name if st.popen.poll() is not None else None


def start_roscore(procs: Processes, out: Path, timeout: float, host: str = "127.0.0.1") -> str:
    """roscore on a free port (logs in ``out``), reached at ``host`` (an address of the
    calling thread's network namespace); retried on another port when the port was taken
    meanwhile. The master must be ours: its PID is a descendant of the roscore we started.
    Sets ``ROS_MASTER_URI`` in ``procs.env`` and returns it."""
    import psutil

    for attempt in range(3):
        port = free_port()
        uri = f"http://{host}:{port}"
        procs.env["ROS_MASTER_URI"] = uri
        core = procs.start(f"roscore{attempt or ''}", [ROSCORE, "-p", str(port)],
                           out / f"roscore{attempt or ''}.log", cwd=out)

        def ours(uri: str = uri, core: Started = core) -> bool:
            pid = master_call(uri, "getPid")
            if pid is None:
                return False
            try:
                return pid in {c.pid for c in psutil.Process(core.popen.pid).children(recursive=True)}
            except psutil.Error:
                return False

        try:
            wait_for("roscore", ours, timeout, functools.partial(_exited, core))
            return uri
        except PerfrosError:
            procs.stop([core.name])
            if attempt == 2:
                raise
    raise AssertionError("unreachable")


def port_of(uri: str) -> int:
    """The port of a master URI ``http://HOST:PORT``."""
    return int(uri.rstrip("/").rsplit(":", 1)[1])
