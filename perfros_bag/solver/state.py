"""The mutable assignment the heuristics work on: placement, setting levels, loads.

Every change goes through :meth:`State.change`, which checks CPU (eq 3), bandwidth per
link and per shared medium (eq 4) and residence (eq 8) before applying it, so a state is
feasible at every step. Coresidence (eq 9) is kept by moving whole groups.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.rules import build_plan
from perfros_bag.system.types import Choice, Problem, System

EPS = 1e-9


def ladder(choices: list[Choice]) -> list[Choice]:
    """The upgrade ladder of a node: its choices by increasing CPU, keeping only those whose
    performance beats every cheaper one (a dearer, no-better setting is never an upgrade)."""
    out: list[Choice] = []
    for ch in sorted(choices, key=lambda c: (c.cpu, -c.performance, c.index)):
        if out and math.isclose(ch.cpu, out[-1].cpu, abs_tol=EPS):
            continue
        if not out or ch.performance > out[-1].performance + EPS:
            out.append(ch)
    return out


class State:
    def __init__(self, system: System, problem: Problem, choices: Mapping[str, list[Choice]]) -> None:
        self.system = system
        self.problem = problem
        self.nodes = [n.name for n in system.nodes]
        self.order = {n: i for i, n in enumerate(self.nodes)}
        self.weight = {n.name: n.weight for n in system.nodes}
        self.ladder = {n: (ladder(choices[n]) if problem == Problem.PERFORMANCE else list(choices[n][:1]))
                       for n in self.nodes}
        self.level = dict.fromkeys(self.nodes, 0)
        self.place: dict[str, str | None] = dict.fromkeys(self.nodes)
        self.computers = [c.name for c in system.computers]
        self.kind = {c.name: c.kind for c in system.computers}
        # Problem 2: servers start at 0 and grow up to max_capacity; robots (and Problem 1) fixed
        self.maxcap: dict[str, float] = system.capacities(problem)
        self.cap: dict[str, float] = {
            c: 0.0 if problem == Problem.SERVER_CAPACITY and self.kind[c] == "server" else self.maxcap[c]
            for c in self.computers}
        self.proven = False  # set when a failure is a proof of infeasibility
        self.load = dict.fromkeys(self.computers, 0.0)
        self.members: dict[str, set[str]] = {c: set() for c in self.computers}
        self.groups: list[tuple[str, ...]] = list(system.coresidence_groups)
        self.group_of = {n: gi for gi, g in enumerate(self.groups) for n in g}
        self.group_allowed: list[list[str]] = [list(a) for a in system.group_computers]
        # network: per edge the bandwidth at each of its publisher's ladder levels
        self.edges = list(system.edges)
        self.pub_bw = {n: [ch.bandwidth_kBps or 0.0 for ch in self.ladder[n]] for n in self.nodes}
        self.edge_bw = [self.pub_bw[e.src] if e.bandwidth_kBps is None and not e.topic
                        else [system.edge_bandwidth(e, ch) for ch in self.ladder[e.src]] for e in self.edges]
        self.incident: dict[str, list[int]] = {n: [] for n in self.nodes}
        for i, e in enumerate(self.edges):
            self.incident[e.src].append(i)
            if e.dst != e.src:
                self.incident[e.dst].append(i)
        self.neighbours: dict[str, set[str]] = {n: set() for n in self.nodes}
        for e in self.edges:
            self.neighbours[e.src].add(e.dst)
            self.neighbours[e.dst].add(e.src)
        # per publisher: its edges that cross the network now, as link multiplicities for the
        # edges that carry the publisher's own bandwidth, and the rest edge by edge
        self._out: dict[str, tuple[dict[int, int], list[tuple[int, tuple[int, ...]]]]] = {}
        self.links = list(system.links)
        self.link_load = [0.0] * len(self.links)
        self.media = list(system.media)
        self.allowed_set = {n: set(system.allowed(n)) for n in self.nodes}

    # ---- reading -------------------------------------------------------------------
    def choice(self, n: str) -> Choice:
        return self.ladder[n][self.level[n]]

    def cpu(self, n: str) -> float:
        return self.ladder[n][self.level[n]].cpu

    def free(self, c: str) -> float:
        return self.cap[c] - self.load[c]

    def at_max(self, n: str) -> bool:
        return self.level[n] >= len(self.ladder[n]) - 1

    def step(self, n: str) -> tuple[float, float]:
        """(CPU, weighted performance) of the next upgrade of ``n``."""
        lad, k = self.ladder[n], self.level[n]
        return lad[k + 1].cpu - lad[k].cpu, self.weight[n] * (lad[k + 1].performance - lad[k].performance)

    def gradient(self, n: str) -> float:
        """Weighted performance gained per CPU unit by the next upgrade (0 at the top)."""
        if self.at_max(n):
            return 0.0
        du, dp = self.step(n)
        return dp / du if du > EPS else math.inf

    def on(self, c: str) -> list[str]:
        return sorted(self.members[c], key=self.order.__getitem__)

    def value(self) -> float:
        if self.problem == Problem.PERFORMANCE:
            return sum(self.weight[n] * self.choice(n).performance for n in self.nodes)
        return sum(self.load[c] for c in self.computers if self.kind[c] == "server")

    def group_cpu(self, gi: int) -> float:
        return sum(self.cpu(n) for n in self.groups[gi])

    # ---- changing ------------------------------------------------------------------
    def _crossing(self, n: str) -> tuple[dict[int, int], list[tuple[int, tuple[int, ...]]]]:
        hit = self._out.get(n)
        if hit is None:
            mult: dict[int, int] = {}
            special: list[tuple[int, tuple[int, ...]]] = []
            a = self.place[n]
            for ei in self.incident[n]:
                e = self.edges[ei]
                if e.src != n:
                    continue
                b = self.place[e.dst]
                if a is None or b is None or a == b:
                    continue
                route = self.system.route(a, b) or ()
                if self.edge_bw[ei] is self.pub_bw[n]:
                    for li in route:
                        mult[li] = mult.get(li, 0) + 1
                else:
                    special.append((ei, route))
            hit = (mult, special)
            self._out[n] = hit
        return hit

    def _level_delta(self, n: str, new: int) -> dict[int, float]:
        """Link load deltas when only ``n``'s level changes."""
        mult, special = self._crossing(n)
        old = self.level[n]
        delta: dict[int, float] = {}
        d = self.pub_bw[n][new] - self.pub_bw[n][old]
        if d:
            for li, k in mult.items():
                delta[li] = k * d
        for ei, route in special:
            de = self.edge_bw[ei][new] - self.edge_bw[ei][old]
            if de:
                for li in route:
                    delta[li] = delta.get(li, 0.0) + de
        return delta

    def _net_delta(self, changes: Mapping[str, tuple[str | None, int]]) -> tuple[dict[int, float], str | None]:
        if len(changes) == 1:
            (n, (c, lvl)), = changes.items()
            if c == self.place[n] and c is not None:
                return self._level_delta(n, lvl), None
        edges: set[int] = set()
        for n in changes:
            edges.update(self.incident[n])
        delta: dict[int, float] = {}
        place, level, route_of = self.place, self.level, self.system.route
        for ei in edges:
            e = self.edges[ei]
            oa, ob = place[e.src], place[e.dst]
            ca, cb = changes.get(e.src), changes.get(e.dst)
            na = ca[0] if ca is not None else oa
            nb = cb[0] if cb is not None else ob
            if oa is not None and ob is not None and oa != ob:
                bw = self.edge_bw[ei][level[e.src]]
                if bw:
                    for li in route_of(oa, ob) or ():
                        delta[li] = delta.get(li, 0.0) - bw
            if na is not None and nb is not None and na != nb:
                route = route_of(na, nb)
                if route is None:
                    return delta, f"no network path between {na} and {nb} (edge {e.src}->{e.dst})"
                bw = self.edge_bw[ei][ca[1] if ca is not None else level[e.src]]
                if bw:
                    for li in route:
                        delta[li] = delta.get(li, 0.0) + bw
        return delta, None

    def check(self, changes: Mapping[str, tuple[str | None, int]]
              ) -> tuple[str | None, dict[int, float], dict[str, float]]:
        """Whether ``changes`` (node -> (computer, level)) keeps the state feasible: the
        reason it does not (or None), the link load deltas and the computer load deltas."""
        dload: dict[str, float] = {}
        for n, (c, lvl) in changes.items():
            old = self.place[n]
            if old is not None:
                dload[old] = dload.get(old, 0.0) - self.cpu(n)
            if c is not None:
                if c not in self.allowed_set[n]:
                    return f"{n} may not run on {c} (residence)", {}, {}
                dload[c] = dload.get(c, 0.0) + self.ladder[n][lvl].cpu
        for c, d in dload.items():
            if d > EPS and self.load[c] + d > self.cap[c] + EPS * max(1.0, self.cap[c]):
                return f"{c} has {fmt_units(self.free(c))} CPU free", {}, {}
        delta, why = self._net_delta(changes)
        if why is not None:
            return why, {}, {}
        for li, d in delta.items():
            lk = self.links[li]
            if d > EPS and self.link_load[li] + d > lk.bandwidth_kBps + EPS * max(1.0, lk.bandwidth_kBps):
                return (f"link {lk.between[0]}-{lk.between[1]} would carry {fmt_units(self.link_load[li] + d)} "
                        f"> {fmt_units(lk.bandwidth_kBps)} kB/s"), {}, {}
        if self.media:
            dm: dict[str, float] = {}
            for li, d in delta.items():
                med = self.links[li].medium
                if med is not None:
                    dm[med] = dm.get(med, 0.0) + d
            for name, d in dm.items():
                if d > EPS:
                    m = self.system.medium[name]
                    now = self.system.medium_load(self.link_load, name)
                    if now + d > m.bandwidth_kBps + EPS * max(1.0, m.bandwidth_kBps):
                        return (f"medium {name} would carry {fmt_units(now + d)} "
                                f"> {fmt_units(m.bandwidth_kBps)} kB/s", {}, {})
        return None, delta, dload

    def change(self, changes: Mapping[str, tuple[str | None, int]]) -> str | None:
        """Apply ``changes`` if feasible; else return why not (and change nothing)."""
        why, delta, dload = self.check(changes)
        if why is not None:
            return why
        for li, d in delta.items():
            self.link_load[li] += d
        for comp, d in dload.items():
            self.load[comp] += d
        for n, (target, lvl) in changes.items():
            old = self.place[n]
            if old != target:
                if old is not None:
                    self.members[old].discard(n)
                if target is not None:
                    self.members[target].add(n)
                self._out.pop(n, None)
                for m in self.neighbours[n]:
                    self._out.pop(m, None)
            self.place[n] = target
            self.level[n] = lvl
        return None

    def set_ladder(self, n: str, choices: list[Choice]) -> None:
        """Give unplaced node ``n`` other choices (along a data flow: those at another input
        rate), its level reset to 0; its outgoing edges' traffic follows."""
        assert self.place[n] is None, "a node's choices change only while it is off every computer"
        self.ladder[n] = ladder(choices) if self.problem == Problem.PERFORMANCE else list(choices[:1])
        self.level[n] = 0
        self.pub_bw[n] = [ch.bandwidth_kBps or 0.0 for ch in self.ladder[n]]
        for ei in self.incident[n]:
            e = self.edges[ei]
            if e.src == n:
                self.edge_bw[ei] = (self.pub_bw[n] if e.bandwidth_kBps is None and not e.topic
                                    else [self.system.edge_bandwidth(e, ch) for ch in self.ladder[n]])
        self._out.pop(n, None)

    def move_group(self, gi: int, c: str | None) -> str | None:
        return self.change({n: (c, self.level[n]) for n in self.groups[gi]})

    def snapshot(self) -> tuple[dict[str, str | None], dict[str, int], dict[str, float]]:
        return dict(self.place), dict(self.level), dict(self.cap)

    def restore(self, snap: tuple[dict[str, str | None], dict[str, int], dict[str, float]]) -> None:
        """Return to a snapshot, recomputing the loads from scratch."""
        self.place, self.level, self.cap = dict(snap[0]), dict(snap[1]), dict(snap[2])
        self.recompute()

    def recompute(self) -> None:
        self._out.clear()
        self.members = {c: set() for c in self.computers}
        for n in self.nodes:
            c = self.place[n]
            if c is not None:
                self.members[c].add(n)
        self.load = dict.fromkeys(self.computers, 0.0)
        for n in self.nodes:
            c = self.place[n]
            if c is not None:
                self.load[c] += self.cpu(n)
        self.link_load = self.system.link_loads(self.place, {n: self.choice(n) for n in self.nodes})

    # ---- output --------------------------------------------------------------------
    def plan(self, method: Method, status: Status = Status.FEASIBLE) -> Plan:
        placement = {n: c for n, c in self.place.items() if c is not None}
        assert len(placement) == len(self.nodes), "every node must be placed"
        capacities: dict[str, float] = {}
        if self.problem == Problem.SERVER_CAPACITY:
            capacities = {c: self.load[c] for c in self.computers if self.kind[c] == "server"}
        return build_plan(self.system, Assignment(placement, {n: self.choice(n) for n in self.nodes}, capacities),
                          problem=self.problem, method=method, status=status)


def fmt_units(x: float) -> str:
    return f"{x:.6g}"
