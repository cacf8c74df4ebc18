"""Drifts and alarms.

A window drifts on a node's rate when its topics' measured rate (the mean over its topics
with an expectation, as the window's ``measured_hz``) is further from the plan's than
``tolerance`` % plus one message per window (a count over a short window is whole
messages: 10 Hz over 2 s is 20 +- 1), and on a chain's latency when its measured p95
exceeds the plan's predicted p95 by more than ``latency_tolerance`` % (``watch
--latency-tolerance``, default ``tolerance``). A drift of the same node or
chain and quantity, in the same direction for a rate, in ``persist`` windows in a row is an
alarm; a node that died is an alarm at once, a node a deploy is restarting (``state:
restarting``) none. A node the deploy watched runs at a value other than the plan's (an
operator's change, the window's ``pinned``) is an alarm at once too (``quantity: value``):
the deploy says so, no count is needed to tell it from noise. An alarm stays listed while its
drift lasts.

A rate drift can also move between the nodes of one computer (a CPU hog there slows one
node in one window, another in the next): per computer, the windows in a row in which any of
its nodes drifts in the same direction are counted too, and at ``persist`` such windows,
with no node alarm of that computer and direction standing, the alarm names the node that
drifts most in that window (``computer`` in its object says which computer's count raised it).

Other processes in an emulated computer's cgroup (a CPU hog: the window's ``foreign`` CPU,
with ``watch --deployment``) drift when they take more than the CPU the plan left free there
(capacity less the planned nodes' CPU, at least :data:`FOREIGN_FLOOR` units): the plan's
nodes no longer have their CPU, whether or not their rates have fallen yet. Its alarm
(``quantity: foreign_cpu``, ``planned`` the CPU left free, ``measured`` the other processes')
names the computer's node with the most planned CPU and carries ``computer``. The window in
which other processes appeared there (more than :data:`FOREIGN_FLOOR` after a window with
less), if still within what the plan left free, counts as the first of the drift's windows in
a row: a hog that starts late in one window reads as a fraction of itself there, though the
reading is not noise (a steady cgroup reads 0-0.2), so with ``persist`` 2 the window after it
raises the alarm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Drift:
    kind: str  # "node" | "chain"
    name: str
    quantity: str  # "rate_hz" | "alive" | "latency_p95_ms" | "value"
    planned: float
    measured: float
    immediate: bool = False  # an alarm without waiting for persistence (a node that died)
    computer: str | None = None  # where the node runs (a rate drift's), for the per-computer count

    @property
    def key(self) -> tuple[str, str, str, int]:
        """What persists: the node or chain, the quantity and the drift's direction (a rate
        above its plan in one window and below in the next is a plan held on average, not a
        drift that lasts)."""
        direction = (self.measured > self.planned) - (self.measured < self.planned) if self.quantity == "rate_hz" else 0
        return (self.kind, self.name, self.quantity, direction)


@dataclass(frozen=True)
class Alarm:
    drift: Drift
    windows: int  # windows in a row it has drifted (its computer's, for a per-computer alarm)
    new: bool  # raised in this window
    computer: str | None = None  # raised by this computer's count of drifting windows

    def line(self) -> str:
        d = self.drift
        if d.quantity == FOREIGN:
            return (f"alarm: computer {d.computer}: other processes take {d.measured:.4g} CPU units, the plan left "
                    f"{d.planned:.4g} free (its node {d.name} the heaviest)")
        return f"alarm: {d.kind} {d.name}: {d.quantity} planned {d.planned:.4g}, measured {d.measured:.4g}"

    def to_dict(self) -> dict[str, Any]:
        d = self.drift
        out = {d.kind: d.name, "quantity": d.quantity, "planned": d.planned, "measured": d.measured,
               "windows": self.windows, "new": self.new, "line": self.line()}
        where = self.computer if self.computer is not None else (d.computer if d.quantity == FOREIGN else None)
        if where is not None:
            out["computer"] = where
        return out


#: a quantity: CPU of other processes in a computer's cgroup beyond what the plan left free
FOREIGN = "foreign_cpu"
#: the least foreign CPU (units) that drifts, whatever the plan left free: the watcher's own
#: reading of an idle cgroup moves by a few tenths (measured: 0-0.2 over a steady 5 minutes)
FOREIGN_FLOOR = 1.0


def foreign_drifts(window: dict[str, Any]) -> list[Drift]:
    """Per computer of one window's JSON object (its ``computers`` with ``foreign``,
    ``capacity`` and ``cpu_expected``, and its ``nodes``), a drift when other processes take
    more CPU than the plan left free there (and more than :data:`FOREIGN_FLOOR`)."""
    return _foreign(window, within_free=False)


def foreign_present(window: dict[str, Any]) -> list[Drift]:
    """Per computer of one window, where other processes take more than
    :data:`FOREIGN_FLOOR` units, whether or not the plan left room for them: the drift
    :func:`foreign_drifts` would give there (same key). :meth:`Persistence.update` tells from
    them the window other processes appeared in."""
    return _foreign(window, within_free=True)


def _foreign(window: dict[str, Any], within_free: bool) -> list[Drift]:
    out: list[Drift] = []
    for computer, c in (window.get("computers") or {}).items():
        foreign, cap, planned = c.get("foreign"), c.get("capacity"), c.get("cpu_expected")
        if foreign is None or cap is None or planned is None:
            continue
        free = max(0.0, float(cap) - float(planned))
        if float(foreign) <= (FOREIGN_FLOOR if within_free else max(free, FOREIGN_FLOOR)):
            continue
        mine = [(float(n.get("cpu_expected") or 0.0), name) for name, n in window["nodes"].items()
                if n.get("computer") == computer]
        if mine:
            out.append(Drift("node", max(mine)[1], FOREIGN, round(free, 3), float(foreign), computer=str(computer)))
    return out


def rate_drifts(window: dict[str, Any], tolerance: float, latency_tolerance: float | None = None) -> list[Drift]:
    """The node and chain drifts of one window's JSON object (its ``nodes``, ``chains`` and
    ``seconds``); a chain's p95 is judged with ``latency_tolerance`` (default ``tolerance``)."""
    lat_tol = tolerance if latency_tolerance is None else latency_tolerance
    seconds = float(window["seconds"])
    slack = 1.0 / seconds if seconds > 0 else 0.0
    out: list[Drift] = []
    for name, n in window["nodes"].items():
        if n.get("state") == "restarting":  # a deploy restarts it for a new plan: neither dead nor drifting
            continue
        if not n.get("alive", True):
            out.append(Drift("node", name, "alive", 1.0, 0.0, immediate=True))
            continue
        exp, meas = n.get("expected_hz"), n.get("measured_hz")
        if exp and meas is not None and abs(meas - exp) > tolerance / 100.0 * exp + slack:
            where = n.get("computer")
            out.append(Drift("node", name, "rate_hz", float(exp), float(meas),
                             computer=str(where) if where is not None else None))
    out += foreign_drifts(window)
    for c in window.get("chains", []):
        pred = (c.get("predicted_ms") or {}).get("p95")
        meas = (c.get("measured_ms") or {}).get("p95") if c.get("measured_ms") else None
        if pred and meas is not None and meas > pred * (1.0 + lat_tol / 100.0):
            out.append(Drift("chain", str(c["chain"]), "latency_p95_ms", float(pred), float(meas)))
    return out


def value_drifts(pinned: dict[str, float] | None, planned: dict[str, float | None]) -> list[Drift]:
    """A drift at once per node the deploy runs at a value other than its plan's: ``pinned``
    (the window's, node -> value running) against ``planned`` (node -> the plan's value)."""
    return [Drift("node", n, "value", float(planned[n] or 0.0), float(v), immediate=True)
            for n, v in sorted((pinned or {}).items()) if planned.get(n) is not None]


class Persistence:
    """Counts each drift's windows in a row, and each computer's windows in a row with a rate
    drift of one direction on any of its nodes; a drift missing from a window starts again at 0."""

    def __init__(self, persist: int) -> None:
        if persist < 1:
            raise ValueError("persist must be >= 1")
        self.persist = persist
        self.updates = 0
        self.present: set[tuple[str, str, str, int]] = set()  # the last window's foreign_present keys
        self.count: dict[tuple[str, str, str, int], int] = {}
        self.raised: set[tuple[str, str, str, int]] = set()
        self.computer_count: dict[tuple[str, int], int] = {}  # (computer, direction) -> windows in a row
        self.computer_raised: set[tuple[str, int]] = set()

    def update(self, drifts: list[Drift], present: list[Drift] | None = None) -> list[Alarm]:
        """The alarms of this window, given its drifts and (:func:`foreign_present`) the
        computers where other processes take CPU: where they appeared in this window (not in
        the one before, nor in the first window, which has none before it to tell), a window
        within what the plan left free counts as the first of their drift's run."""
        now = {d.key: d for d in drifts}
        seen = {d.key for d in present or []}
        appeared = seen - self.present if self.updates else set()
        self.present, self.updates = seen, self.updates + 1
        self.count = {k: (self.count.get(k, 0) + 1) for k in now} | {k: 1 for k in appeared if k not in now}
        self.raised &= set(now)
        alarms = []
        for k, d in now.items():
            if d.immediate or self.count[k] >= self.persist:
                alarms.append(Alarm(d, self.count[k], k not in self.raised))
                self.raised.add(k)
        # per computer: the rate drifts of its nodes, whichever node drifts in each window
        where: dict[tuple[str, int], list[Drift]] = {}
        for k, d in now.items():
            if d.quantity == "rate_hz" and d.computer is not None:
                where.setdefault((d.computer, k[3]), []).append(d)
        self.computer_count = {g: self.computer_count.get(g, 0) + 1 for g in where}
        self.computer_raised &= set(where)
        for g, ds in sorted(where.items()):
            if self.computer_count[g] < self.persist or any(a.drift in ds for a in alarms):
                continue  # not yet, or a node alarm of this computer and direction says it already
            worst = max(ds, key=lambda d: (abs(d.measured - d.planned) / d.planned if d.planned else 0.0, d.name))
            alarms.append(Alarm(worst, self.computer_count[g], g not in self.computer_raised, computer=g[0]))
            self.computer_raised.add(g)
        return alarms
