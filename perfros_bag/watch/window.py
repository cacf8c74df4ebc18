"""One window of a watch: the counters' differences as statistics eq 10 takes, and its JSON.

A window's topic rate is its messages over the seconds between the two readings (every
publisher of the topic summed, as a recording would hold them), its bandwidth its payload
bytes over the same seconds. They go into a :class:`~perfros_bag.ingest.stats.RecordingStats`
whose topics answer with those numbers, so validation's own eq 10
(:func:`perfros_bag.validation.eq10.check_run`, with the system's link loads) judges the
window exactly as it judges a recording. A node's CPU is its CPU seconds' difference over
the same seconds, given to eq 10 in the units its computer is planned in.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.ingest.stats import RecordingStats, TopicStats
from perfros_bag.watch.counters import window_counts

if TYPE_CHECKING:
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.types import System
    from perfros_bag.validation.eq10 import TracedCpu, Validation
    from perfros_bag.watch.observe import Reading

WINDOW_FORMAT = "perfros-bag/watch-window@1"


@dataclass
class WindowTopic(TopicStats):
    """A topic over one window: its rate and bandwidth are its counts over the window's
    seconds (not over the span between its first and last message, which a window does not see)."""

    window_s: float = 0.0

    @property
    def span_s(self) -> float:
        return self.window_s

    @property
    def frequency_hz(self) -> float:
        return self.messages / self.window_s if self.window_s > 0 else 0.0

    @property
    def rate_note(self) -> str | None:
        return None if self.window_s > 0 else "an empty window"

    @property
    def bandwidth_kBps(self) -> float:
        return self.bytes / self.window_s / 1000.0 if self.window_s > 0 else 0.0


def window_stats(before: Reading, after: Reading, types: dict[str, str], name: str = "window") -> RecordingStats:
    """The topics counted between two readings (topics whose publishers counted nothing, and
    :func:`unreadable_topics`, are absent). A topic's seconds are those between its
    publisher's two answers (the mean over its publishers): each publisher answers at its own
    moment, and one unread at the window's start counts from its last answer."""
    sums: dict[str, list[float]] = {}
    unread = unreadable_topics(before, after)
    for key, counters in after.topics.items():
        if key[0] in unread:
            continue
        m, b = window_counts(before.topics.get(key), counters)
        seconds = after.stamps.get(key, after.t) - before.stamps.get(key, before.t)
        s = sums.setdefault(key[0], [0, 0, 0.0, 0])
        s[0] += m
        s[1] += b
        s[2] += seconds
        s[3] += 1
    topics: dict[str, TopicStats] = {
        t: WindowTopic(t, types.get(t, ""), int(m), int(b), window_s=secs / n)
        for t, (m, b, secs, n) in sums.items() if m > 0}
    return RecordingStats(Path(name), "ros1-live", topics, "getBusStats")


def unreadable_topics(before: Reading, after: Reading) -> set[str]:
    """Topics a window cannot count: a publisher of theirs did not answer in time at its end
    (:attr:`Reading.unread`), or had never answered at its start (no counters to count from).
    A publisher that answers again counts from its last answer, over the seconds since."""
    out = {topic for topic, _pub in after.unread}
    out.update(topic for key in before.unread if key not in before.topics for topic in [key[0]])
    return out


def window_cpu(before: Reading, after: Reading, plan: Plan, units_per_core: float | None) -> dict[str, TracedCpu]:
    """Each measured node's CPU over the window, for eq 10: ``percent`` of one core as a
    trace of this machine gives it; with ``units_per_core`` (a deploy's emulated computers)
    scaled as :func:`perfros_bag.rosrun.cgroups.emulated_trace` scales a deploy's trace,
    so that eq 10 reads ``percent / 100 * units_per_core`` units."""
    from perfros_bag.validation.eq10 import TracedCpu

    n = os.cpu_count() or 1
    out: dict[str, TracedCpu] = {}
    for node, used in after.cpu_s.items():
        if node not in before.cpu_s or node not in plan.nodes \
                or before.cpu_pid.get(node) != after.cpu_pid.get(node):  # restarted meanwhile: no difference
            continue
        seconds = after.cpu_t.get(node, after.t) - before.cpu_t.get(node, before.t)
        if seconds <= 0:
            continue
        percent = max(0.0, used - before.cpu_s[node]) / seconds * 100.0
        cap = plan.computers[plan.nodes[node].computer].capacity if plan.nodes[node].computer in plan.computers \
            else None
        if units_per_core is not None and cap:
            percent = percent * n * units_per_core / cap
        out[node] = TracedCpu(percent, n, "live")
    return out


def cgroup_cpu_s(folder: str | Path) -> dict[int, float] | None:
    """CPU seconds so far of each process in a cgroup (its ``cgroup.procs``, psutil's
    user + system of each PID: the same on cgroup v1, whose ``cpu`` hierarchy need not
    account usage, and v2); None when the group cannot be read."""
    import psutil

    try:
        pids = [int(x) for x in (Path(folder) / "cgroup.procs").read_text().split()]
    except (OSError, ValueError):
        return None
    out: dict[int, float] = {}
    for pid in pids:
        try:
            ct = psutil.Process(pid).cpu_times()
        except psutil.Error:
            continue
        out[pid] = float(ct.user + ct.system)
    return out


def _group_delta(before: dict[int, float], after: dict[int, float], since: float) -> float:
    """CPU seconds a group's processes used between two readings: each process present at
    the second, from its first reading (one started after ``since``: all of its CPU)."""
    import psutil

    total = 0.0
    for pid, used in after.items():
        if pid in before:
            total += max(0.0, used - before[pid])
            continue
        try:
            born = psutil.Process(pid).create_time()
        except psutil.Error:
            continue
        if born >= since:
            total += used
    return total


def foreign_cpu(before: Reading, after: Reading, groups_before: dict[str, dict[int, float] | None],
                groups_after: dict[str, dict[int, float] | None], where: dict[str, str],
                units_per_core: float) -> dict[str, float]:
    """Per emulated computer, CPU units its cgroup spent over the window beyond its launched
    nodes' own (another process inside it: a hog; ``where``: plan node -> computer); a
    computer with a node restarted in the window, or whose group cannot be read, is left out."""
    seconds = after.t - before.t
    out: dict[str, float] = {}
    if seconds <= 0:
        return out
    for computer, b in groups_before.items():
        a = groups_after.get(computer)
        if a is None or b is None:
            continue
        nodes_s = 0.0
        for node, at in where.items():
            if at != computer:
                continue
            if node not in before.cpu_s or node not in after.cpu_s \
                    or before.cpu_pid.get(node) != after.cpu_pid.get(node):
                nodes_s = math.nan
                break
            nodes_s += after.cpu_s[node] - before.cpu_s[node]
        if math.isnan(nodes_s):
            continue
        used = _group_delta(b, a, before.t)
        out[computer] = round(max(0.0, (used - nodes_s) / seconds * units_per_core), 3)
    return out


def evaluate(stats: RecordingStats, plan: Plan, system: System | None, cpu: dict[str, TracedCpu],
             tolerance: float) -> Validation:
    """Eq 10 of one window (validation's own check, links included with the system)."""
    from perfros_bag.validation.eq10 import check_run

    return check_run(stats, plan, tolerance=tolerance, system=system, node_cpu=cpu, cpu_traces=["live"])


def _mean(xs: list[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def planned_chains(plan: Plan) -> list[dict[str, Any]]:
    """plan.json's ``chains`` that have a prediction (``predicted_ms``) and topics."""
    chains = getattr(plan, "chains", None) or plan.extra.get("chains") or []
    return [c for c in chains if isinstance(c, dict) and isinstance(c.get("predicted_ms"), dict)
            and isinstance(c.get("topics"), list) and c["topics"]]


def window_document(k: int, t: float, seconds: float, v: Validation, plan: Plan, alive_of: dict[str, bool],
                    measured_cpu: set[str], alarms: list[dict[str, Any]],
                    latency: dict[str, dict[str, Any] | None] | None = None,
                    restarting: set[str] | None = None, unreadable: set[str] | None = None,
                    unlistened: dict[str, str] | None = None) -> dict[str, Any]:
    """The window's JSON object (docs/formats.md "watch --json"); a node not alive is
    ``restarting`` when in ``restarting`` (a deploy restarting it), else ``dead``. A topic in
    ``unreadable`` (:func:`unreadable_topics`) has no measured rate (None, never 0 Hz); a
    running node none of whose topics could be read is ``unreadable``, its ``measured_hz`` None.
    A chain in ``unlistened`` (its last topic not subscribed to) says why in ``not_listened``."""
    unread = unreadable or set()
    nodes: dict[str, Any] = {}
    for n in v.nodes:
        alive = alive_of.get(n.node, False)
        readable = [tc for tc in n.topics if tc.topic not in unread]
        state = ("running" if readable or not n.topics else "unreadable") if alive \
            else "restarting" if n.node in (restarting or ()) else "dead"
        rated = [tc for tc in n.topics if tc.f_expected]
        rated_read = [tc for tc in readable if tc.f_expected]
        nodes[n.node] = {
            "expected_hz": _mean([float(tc.f_expected or 0.0) for tc in rated]),
            "measured_hz": _mean([tc.f_measured for tc in rated_read]) if rated
            else _mean([tc.f_measured for tc in readable]),
            **({"cpu": n.cpu_measured} if n.node in measured_cpu and n.cpu_measured is not None else {}),
            "cpu_expected": n.cpu_expected, "computer": n.computer, "alive": alive, "state": state,
            "p_expected": n.p_expected, "p_measured": n.p_measured, "deviation_pct": n.deviation_pct,
            "topics": {tc.topic: {"expected_hz": tc.f_expected,
                                  "measured_hz": None if tc.topic in unread else tc.f_measured,
                                  "kBps": None if tc.topic in unread else tc.bandwidth_kBps,
                                  "messages": None if tc.topic in unread else tc.messages} for tc in n.topics},
        }
    chains = [{"chain": c.get("name"), "topic": c["topics"][-1], "predicted_ms": c.get("predicted_ms"),
               "measured_ms": (latency or {}).get(str(c.get("name")))} for c in planned_chains(plan)]
    for chain in chains:
        if str(chain["chain"]) in (unlistened or {}):
            chain["not_listened"] = (unlistened or {})[str(chain["chain"])]
    return {
        "format": WINDOW_FORMAT, "window": k, "t": t, "seconds": seconds,
        "overall": {"expected": v.overall_expected, "measured": v.overall_measured, "deviation_pct": v.deviation_pct},
        "nodes": nodes,
        "computers": {c.name: {"capacity": c.capacity, "cpu_expected": c.cpu_expected, "cpu": c.cpu_measured,
                               "overloaded": c.overloaded} for c in v.computers},
        "links": [{"between": list(lc.between), "capacity_kBps": lc.capacity_kBps, "expected_kBps": lc.expected_kBps,
                   "measured_kBps": lc.measured_kBps, "overloaded": lc.overloaded} for lc in v.links],
        "chains": chains,
        "unmeasured": sorted(n for n in plan.nodes if n not in measured_cpu),
        "alarms": alarms,
    }
