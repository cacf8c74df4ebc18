"""What ROS 1 already counts: the publishers' ``getBusStats``, as per-topic counters.

A publisher counts, per subscriber connection, the messages and payload bytes it sent on it
(roscpp: ``[topic, [[id, bytes, message_bytes, messages, _], ...]]``; rospy: ``[topic,
message_bytes, [[id, bytes with headers, messages, connected], ...]]``). Every connection
of a topic receives every message, so a window's messages on a topic are the largest
difference of one connection's counter between two readings (a connection that appeared
meanwhile counts from 0); its payload bytes likewise (rospy: the topic's own total). roscpp
sends its counters as 32-bit XML-RPC integers: a counter that went down by more than half
their range wrapped once; one that went down by less was counted afresh (a connection re-made
under the same id: RQ4 saw one after a link drop), and counts from 0, never as a wrap (that
would be ~4e9 messages in one window).
Reading them subscribes to nothing, so no message is copied for the watcher.
"""

from __future__ import annotations

from perfros_bag.rosrun.master import TopicCounters, parse_bus_stats

__all__ = ["WRAP", "TopicCounters", "parse_bus_stats", "window_counts"]

WRAP = 2 ** 32


def _diff(now: int, before: int) -> int:
    d = now - before
    if d >= 0:
        return d
    if d <= -(WRAP // 2):
        return d + WRAP  # wrapped once
    return max(0, now)  # counted afresh


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
