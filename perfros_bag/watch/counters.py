"""What ROS 1 already counts: the publishers' ``getBusStats``, as per-topic counters.

A publisher counts, per subscriber connection, the messages and payload bytes it sent on it
(roscpp: ``[topic, [[id, bytes, message_bytes, messages, _], ...]]``; rospy: ``[topic,
message_bytes, [[id, bytes with headers, messages, connected], ...]]``). Every connection
of a topic receives every message, so a window's messages on a topic are the largest
difference of one connection's counter between two readings (a connection that appeared
meanwhile counts from 0); its payload bytes likewise (rospy: the topic's own total). roscpp
sends its counters as 32-bit XML-RPC integers: a counter that went down wrapped once.
Reading them subscribes to nothing, so no message is copied for the watcher.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

WRAP = 2 ** 32


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
    """Per published topic, its counters in one node's ``getBusStats`` answer (anything
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


def _diff(now: int, before: int) -> int:
    d = now - before
    return d + WRAP if d < 0 else d


def window_counts(before: TopicCounters | None, after: TopicCounters) -> tuple[int, int]:
    """(messages, payload bytes) one topic's publisher sent between two readings."""
    old = before.connections if before is not None else {}
    messages = 0
    nbytes = 0
    for cid, (m, b) in after.connections.items():
        m0, b0 = old.get(cid, (0, 0))
        messages = max(messages, _diff(m, m0))
        nbytes = max(nbytes, _diff(b, b0))
    if after.total_bytes is not None:
        nbytes = _diff(after.total_bytes, before.total_bytes or 0) if before is not None else after.total_bytes
    return messages, nbytes
