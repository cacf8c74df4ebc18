"""``greedy+``: the paper's greedy followed by local search until no move improves.

Problem 1 (maximise Σ w·P). For a fixed placement the best settings of the nodes on one
computer are a multiple-choice knapsack, solved exactly by dynamic programming over CPU
units (:func:`best_settings`); that covers "re-upgrade with freed capacity" and
"downgrade one node to upgrade another". The moves (:class:`Improver`): re-optimise one
computer's settings; relocate a coresidence group; swap two groups; move two groups joined
by an edge together; the best split of two computers' groups; the best assignment of three
computers' groups; a pair of moves. Each is valued by the knapsack optimum of the computers
involved; the best improving one is applied if CPU and bandwidth still hold. A last pass
of Algorithm 2 uses any capacity left. Then :func:`kick` (a seeded iterated local search).

Problem 2 (minimise server capacity) uses the same moves with minus the server load as the
value (settings are fixed; servers may grow up to ``max_capacity``).

When the greedy finds no plan, a bounded depth-first search for any feasible placement
(most constrained group first) gives the local search a start.
"""

from __future__ import annotations

import heapq
import itertools
import math
import random
import time
from collections.abc import Iterable, Iterator

import numpy as np

from perfros_bag.solver.fleetmoves import fleet_moves
from perfros_bag.solver.greedy import run_greedy, upgrade
from perfros_bag.solver.state import EPS, State
from perfros_bag.system.plan import Method, Plan
from perfros_bag.system.types import Choice, Problem, System

MAX_ROUNDS = 500
DP_CELLS = 200_000
DP_WORK = 30_000_000  # levels x CPU cells of the whole instance, above which no knapsack tables
MOVES_LIMIT = 5_000  # groups x computers above which only settings are re-optimised
SWAPS_LIMIT = 150  # groups above which no swaps
DEPTH2_LIMIT = 60  # groups above which no pairs of moves
KICKS = 30  # perturbations of the iterated local search
KICKS_IDLE = 12  # stop after this many perturbations without improvement
KICK_LIMIT = 600  # groups x computers above which no perturbations
TIME_BUDGET_S = 60.0  # safety net: stop improving after this long (the plan stays feasible)
SEARCH_BUDGET = 20_000
#: above MOVES_LIMIT (Problem 1), the share of the search's time for the fleet's relocation
#: moves (:mod:`perfros_bag.solver.fleetmoves`); the rest re-sets settings
FLEET_SHARE = 0.85


def solve_greedy_plus(system: System, problem: Problem, choices: dict[str, list[Choice]], *,
                      time_budget: float | None = None) -> Plan:
    """The greedy, then local search. ``time_budget`` (seconds, default
    :data:`TIME_BUDGET_S`) bounds the whole search: the plan found by then is returned
    (the exact solver's dispatcher uses it to get a MIP start on big instances)."""
    found = run_greedy_plus(system, problem, choices, time_budget=time_budget)
    if isinstance(found, str):
        return Plan.infeasible(problem, Method.GREEDY_PLUS, found, system=system.source)
    return found.s.plan(Method.GREEDY_PLUS)


def run_greedy_plus(system: System, problem: Problem, choices: dict[str, list[Choice]], *,
                    time_budget: float | None = None, start: State | None = None) -> Improver | str:
    """:func:`solve_greedy_plus`'s search, its improver (its state the plan) returned for
    more moves (the data flow's rate moves, :mod:`perfros_bag.solver.flow`); or why the
    greedy found no plan and no feasible start was found either. ``start``: the greedy's
    final state on ``choices`` when the caller ran it already (it is changed in place)."""
    deadline = time.monotonic() + (TIME_BUDGET_S if time_budget is None else max(time_budget, 0.0))
    state, reason = (start, None) if start is not None else run_greedy(system, problem, choices)
    if reason is not None:
        found = feasible_start(system, problem, choices)
        if found is None:
            return reason
        state = found
        if problem == Problem.PERFORMANCE:
            upgrade(state, [n for n in state.nodes if len(state.ladder[n]) > 1])
    if problem == Problem.SERVER_CAPACITY:
        for c in state.computers:
            if state.kind[c] == "server":
                state.cap[c] = state.maxcap[c]
    improver = Improver(state, deadline=deadline)
    fleet = len(state.groups) * len(state.computers) > MOVES_LIMIT and problem == Problem.PERFORMANCE
    if fleet:  # the relocations Improver leaves out at this size, in most of the time
        now = time.monotonic()
        fleet_moves(state, now + FLEET_SHARE * max(improver.stop() - now, 0.0))
    improver.run()
    if fleet:
        consolidate(improver)
    kick(improver)
    return improver


def consolidate(improver: Improver) -> None:
    """On instances too big for relocation moves (:data:`MOVES_LIMIT`): bring groups home
    from the servers, largest first, to a robot that holds them at their settings (their
    performance unchanged, the servers' CPU freed for the groups that can only run there),
    then re-optimise every computer's settings; kept only when Σ w·P rose."""
    s = improver.s
    before, snap = improver.current(s.nodes), s.snapshot()
    away = [gi for gi in range(len(s.groups)) if s.kind[s.place[s.groups[gi][0]] or ""] == "server"
            and any(s.kind[c] == "robot" for c in s.group_allowed[gi])]
    moved = 0
    for gi in sorted(away, key=lambda gi: (-s.group_cpu(gi), gi)):
        if improver.late():
            break
        for c in s.group_allowed[gi]:
            if s.kind[c] == "robot" and s.move_group(gi, c) is None:
                moved += 1
                break
    if not moved:
        return
    improver.run()
    if improver.current(s.nodes) <= before + 1e-9:
        s.restore(snap)


def kick(improver: Improver, *, seed: int = 0) -> None:
    """Iterated local search: move a few random groups (at their lowest settings) to
    random allowed computers, search again, keep the result only when it is better.
    The generator is seeded, so the outcome is deterministic."""
    s = improver.s
    movable = [gi for gi in range(len(s.groups)) if len(s.group_allowed[gi]) > 1]
    size = len(s.groups) * len(s.computers)
    if not movable or size > KICK_LIMIT:
        return
    rng = random.Random(seed)
    improver.trios = False
    best = improver.current(s.nodes)
    snap = s.snapshot()
    stop = improver.stop()
    bound = _bound(s)
    idle = 0
    for _ in range(KICKS):
        if time.monotonic() > stop or idle >= KICKS_IDLE or best >= bound - 1e-9:
            break
        idle += 1
        for gi in rng.sample(movable, min(len(movable), rng.randint(2, 4))):
            targets = [c for c in s.group_allowed[gi] if c != s.place[s.groups[gi][0]]]
            rng.shuffle(targets)
            for c in targets:
                if s.change({n: (c, 0) for n in s.groups[gi]}) is None:
                    break
        improver.run()
        value = improver.current(s.nodes)
        if value > best + 1e-9:
            best, snap, idle = value, s.snapshot(), 0
        else:
            s.restore(snap)
    improver.trios = True
    improver.run()  # a last full search from the best point


def _bound(s: State) -> float:
    """A bound no plan can beat, in the improver's sense (bigger is better): every node at
    its best setting (Problem 1); minus the CPU that cannot fit on the robots (Problem 2)."""
    if s.problem == Problem.PERFORMANCE:
        return sum(s.weight[n] * s.ladder[n][-1].performance for n in s.nodes)
    robots = [c for c in s.computers if s.kind[c] == "robot"]
    total = sum(s.cpu(n) for n in s.nodes)
    server_only = sum(s.group_cpu(gi) for gi in range(len(s.groups)) if not set(s.group_allowed[gi]) & set(robots))
    return -max(server_only, total - sum(s.cap[c] for c in robots))


# ---- a feasible start when the greedy fails -------------------------------------------
def feasible_start(system: System, problem: Problem, choices: dict[str, list[Choice]]) -> State | None:
    """Any feasible placement at the lowest settings (bounded depth-first search)."""
    state = State(system, problem, choices)
    if problem == Problem.SERVER_CAPACITY:
        for c in state.computers:
            state.cap[c] = state.maxcap[c]
    # the most constrained first: fewest computers, then the heaviest traffic (a group that
    # would fill an access point is placed while its peers' computer still has room), then CPU
    traffic = [max((state.edge_bw[ei][0] for n in g for ei in state.incident[n]
                    if state.group_of[state.edges[ei].src] != state.group_of[state.edges[ei].dst]), default=0.0)
               for g in state.groups]
    order = sorted(range(len(state.groups)),
                   key=lambda gi: (len(state.group_allowed[gi]), -traffic[gi], -state.group_cpu(gi), gi))
    budget = SEARCH_BUDGET

    def levels(gi: int) -> list[dict[str, int]]:
        """The lowest settings, and for a lone node the one sending the least traffic."""
        out = [{n: 0 for n in state.groups[gi]}]
        if len(state.groups[gi]) == 1:
            n = state.groups[gi][0]
            sends = [ei for ei in state.incident[n] if state.edges[ei].src == n]
            if sends:
                k = min(range(len(state.ladder[n])), key=lambda k: (sum(state.edge_bw[ei][k] for ei in sends), k))
                if k:
                    out.append({n: k})
        return out

    robots_first = problem == Problem.SERVER_CAPACITY  # a server's every unit counts against Problem 2

    def candidates(gi: int) -> Iterator[tuple[str, dict[str, int]]]:
        """Where and at which levels group ``gi`` may go, the freest computer first (as the
        state is now); for Problem 2 the robots first."""
        comps = sorted(state.group_allowed[gi], key=lambda c: (robots_first and state.kind[c] == "server",
                                                               -state.free(c), state.computers.index(c)))
        return iter([(c, lv) for c in comps for lv in levels(gi)])

    # depth-first search with an explicit stack (a fleet has thousands of groups: no recursion)
    if not order:
        return state
    stack = [candidates(order[0])]
    applied: list[dict[str, int]] = []  # the levels placed at each depth of the stack
    while stack:
        if len(applied) == len(stack):  # the deeper search failed: undo this depth's placement
            state.change({n: (None, 0) for n in applied.pop()})
        for c, lv in stack[-1]:
            budget -= 1
            if budget < 0:
                return None
            if state.change({n: (c, k) for n, k in lv.items()}) is None:
                applied.append(lv)
                break
        else:
            stack.pop()
            continue
        if len(stack) == len(order):
            return state
        stack.append(candidates(order[len(stack)]))
    return None


# ---- Problem 1 ------------------------------------------------------------------------
def on_grid(cpus: Iterable[float], scale: float) -> bool:
    """Every CPU value times ``scale`` is an integer (to 1e-6): the knapsack DP's grid."""
    return all(abs(u * scale - round(u * scale)) < 1e-6 for u in cpus)


def _grid_scale(state: State) -> float | None:
    """A factor that makes every CPU value an integer (None: none small enough)."""
    cpus = [ch.cpu for lad in state.ladder.values() for ch in lad]
    biggest = max((state.cap[c] for c in state.computers), default=0.0)
    for scale in (1, 2, 4, 5, 10, 20, 50, 100):
        if biggest * scale > DP_CELLS or biggest * scale * len(cpus) > DP_WORK:
            return None
        if on_grid(cpus, scale):
            return float(scale)
    return None


Plan_ = dict[str, list[str]]  # computer -> the nodes it would hold


class Improver:
    """Best-improvement local search over relocations and swaps of coresidence groups, each
    computer's value being its best settings (Problem 1) or minus its server load (Problem 2).
    When no single move improves, the groups of every pair of computers are redistributed
    between them (all splits, when at most :data:`REPARTITION` groups could go either way);
    then a pair of moves (the first among the best :data:`DEPTH2` single moves) is tried.

    Problem 1 values come from knapsack tables: ``table(c, S)[x]`` is the best Σ w·P of the
    nodes ``S`` within ``x`` CPU (on the integer grid), so adding a node to a known table
    costs one maximum over its levels."""

    DEPTH2 = 4
    REPARTITION = 10
    TRIO_LIMIT = 20_000

    def __init__(self, state: State, *, deadline: float | None = None) -> None:
        self.s = state
        self.deadline = deadline  # time.monotonic() after which no search starts
        self.scale = _grid_scale(state) if state.problem == Problem.PERFORMANCE else None
        self.tables: dict[tuple[str, frozenset[str]], np.ndarray] = {}
        self.items: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.values: dict[tuple[str, frozenset[str]], float] = {}
        self.trios = True  # try three-computer reassignments (off during perturbations)
        self.subsets: dict[tuple[str, frozenset[str], tuple[int, ...]], list[float]] = {}
        self.sig = [self._sig(gi) for gi in range(len(state.groups))]
        if self.scale is not None:
            for n in state.nodes:
                self.items[n] = self._item(n, state.ladder[n])

    def _item(self, n: str, lad: list[Choice]) -> tuple[np.ndarray, np.ndarray]:
        """Node ``n`` at ladder ``lad`` as a knapsack item: CPU in grid units, w·P per level."""
        assert self.scale is not None
        return (np.array([int(round(ch.cpu * self.scale)) for ch in lad]),
                np.array([self.s.weight[n] * ch.performance for ch in lad]))

    def _sig(self, gi: int) -> tuple[object, ...]:
        """What makes two groups interchangeable (no swap between them is tried)."""
        s = self.s
        return tuple(sorted((s.weight[n], tuple((c.cpu, c.performance) for c in s.ladder[n]),
                             tuple(s.system.allowed(n))) for n in s.groups[gi]))

    def relevel(self, nodes: Iterable[str]) -> None:
        """Nodes whose ladders changed (:meth:`State.set_ladder`): their knapsack items
        rebuilt, every cached value that holds them dropped."""
        s, changed = self.s, set(nodes)
        if self.scale is not None:
            for n in changed:
                self.items[n] = self._item(n, s.ladder[n])
        for gi in {s.group_of[n] for n in changed}:
            self.sig[gi] = self._sig(gi)
        self.tables = {k: v for k, v in self.tables.items() if not k[1] & changed}
        self.values = {k: v for k, v in self.values.items() if not k[1] & changed}
        self.subsets = {k: v for k, v in self.subsets.items()
                        if not k[1] & changed and not any(set(s.groups[gi]) & changed for gi in k[2])}

    # ---- values --------------------------------------------------------------------
    def _cap(self, comp: str) -> int:
        assert self.scale is not None
        return int(math.floor(self.s.cap[comp] * self.scale + 1e-6))

    def table(self, comp: str, nodes: frozenset[str]) -> np.ndarray:
        """The knapsack table of ``nodes`` on ``comp``, built from its longest cached prefix
        (the nodes in :attr:`State.order`), every prefix cached on the way (no recursion)."""
        key = (comp, nodes)
        t = self.tables.get(key)
        if t is not None:
            return t
        ordered = sorted(nodes, key=self.s.order.__getitem__)
        prefixes = [frozenset(ordered[:k]) for k in range(len(ordered) + 1)]
        k = next((k for k in range(len(ordered), -1, -1) if (comp, prefixes[k]) in self.tables), -1)
        if k < 0:
            t = self.tables[(comp, prefixes[0])] = np.zeros(self._cap(comp) + 1)
            k = 0
        else:
            t = self.tables[(comp, prefixes[k])]
        for j in range(k, len(ordered)):
            t = combine_tables(t, *self.items[ordered[j]])[0]
            self.tables[(comp, prefixes[j + 1])] = t
        return t

    def value(self, comp: str, base: Iterable[str], extra: Iterable[str] = ()) -> float:
        """The best value of ``base`` + ``extra`` on ``comp`` (-inf: they do not fit)."""
        s = self.s
        nodes = frozenset(base)
        more = [n for n in extra if n not in nodes]
        key = (comp, nodes | frozenset(more))
        hit = self.values.get(key)
        if hit is not None:
            return hit
        if s.problem == Problem.SERVER_CAPACITY or self.scale is None:
            ordered = sorted(key[1], key=s.order.__getitem__)
            if s.problem == Problem.SERVER_CAPACITY:
                load = sum(s.ladder[n][0].cpu for n in ordered)
                fits = load <= s.cap[comp] + EPS * max(1.0, s.cap[comp])
                v = (-load if s.kind[comp] == "server" else 0.0) if fits else -math.inf
            else:
                v = _marginal(s, s.cap[comp], ordered)[0]
        else:
            t = self.table(comp, nodes)
            for n in more[:-1]:
                t = combine_tables(t, *self.items[n])[0]
            if more:
                us, vs = self.items[more[-1]]
                ok = us <= len(t) - 1
                v = float(np.max(t[len(t) - 1 - us[ok]] + vs[ok])) if ok.any() else -math.inf
            else:
                v = float(t[-1])
        self.values[key] = v
        return v

    def trial_value(self, comp: str, base: Iterable[str], extra: dict[str, list[Choice]]) -> float:
        """The best value (Problem 1) on ``comp`` of ``base`` at their ladders plus the nodes
        of ``extra`` at the ladders it gives them (a move that changes their choices: the
        data flow's rate moves); -inf when they do not fit. Nothing is cached or changed."""
        s = self.s
        if self.scale is not None and on_grid([ch.cpu for lad in extra.values() for ch in lad], self.scale):
            t = self.table(comp, frozenset(base))
            for n, lad in extra.items():
                t = combine_tables(t, *self._item(n, lad))[0]
            return float(t[-1])
        saved = {n: s.ladder[n] for n in extra}
        try:  # Algorithm 2's rule reads the state's ladders: lent the trial ones for the call
            s.ladder.update(extra)
            return _marginal(s, s.cap[comp], sorted([*base, *extra], key=s.order.__getitem__))[0]
        finally:
            s.ladder.update(saved)

    def levels(self, comp: str, nodes: list[str]) -> dict[str, int]:
        s = self.s
        ordered = sorted(nodes, key=s.order.__getitem__)
        if s.problem == Problem.SERVER_CAPACITY:
            return dict.fromkeys(ordered, 0)
        return best_settings(s, s.cap[comp], ordered, self.scale)[1]

    def current(self, nodes: Iterable[str]) -> float:
        s = self.s
        if s.problem == Problem.SERVER_CAPACITY:
            return -sum(s.cpu(n) for n in nodes if s.kind[s.place[n] or ""] == "server")
        return sum(s.weight[n] * s.choice(n).performance for n in nodes)

    # ---- search --------------------------------------------------------------------
    def stop(self) -> float:
        """When a search starting now must stop (:data:`TIME_BUDGET_S`, or the deadline)."""
        stop = time.monotonic() + TIME_BUDGET_S
        return stop if self.deadline is None else min(stop, self.deadline)

    def late(self) -> bool:
        """Past the deadline: a search in progress stops where it is (every change applied
        was checked, so the state stays feasible)."""
        return self.deadline is not None and time.monotonic() > self.deadline

    def run(self) -> None:
        s = self.s
        stop = self.stop()
        for _ in range(MAX_ROUNDS):
            if time.monotonic() > stop or not self._step():
                break
        if s.problem == Problem.PERFORMANCE:
            upgrade(s, [n for n in s.nodes if len(s.ladder[n]) > 1])

    def _apply(self, plan: Plan_) -> bool:
        """Place nodes on computers at their best levels there, in one checked change."""
        changes: dict[str, tuple[str | None, int]] = {}
        for comp, nodes in plan.items():
            for n, lvl in self.levels(comp, nodes).items():
                changes[n] = (comp, lvl)
        return self.s.change(changes) is None

    def moves(self) -> list[tuple[float, int, Plan_]]:
        """Every settings re-optimisation, relocation and swap with its gain, best first."""
        s = self.s
        on = {c: s.on(c) for c in s.computers}
        cur = {c: self.current(on[c]) for c in s.computers}
        out: list[tuple[float, int, Plan_]] = []
        if s.problem == Problem.PERFORMANCE:
            for c in s.computers:
                out.append((self.value(c, on[c]) - cur[c], len(out), {c: on[c]}))
        if len(s.groups) * len(s.computers) > MOVES_LIMIT:
            out.sort(key=lambda m: (-m[0], m[1]))
            return out
        groups_on = {c: sorted({s.group_of[n] for n in on[c]}) for c in s.computers}
        for src in s.computers:
            for gi in groups_on[src]:
                if self.late():
                    break
                g = s.groups[gi]
                rest = [n for n in on[src] if n not in g]
                v_src = self.value(src, rest)
                if v_src == -math.inf:
                    continue
                for dst in s.group_allowed[gi]:
                    if dst != src:
                        v_dst = self.value(dst, on[dst], g)
                        if v_dst != -math.inf:
                            out.append((v_src + v_dst - cur[src] - cur[dst], len(out),
                                        {src: rest, dst: on[dst] + list(g)}))
        comps = s.computers if len(s.groups) <= SWAPS_LIMIT else []
        for i, a in enumerate(comps):
            for b in comps[i + 1:]:
                for ga in groups_on[a]:
                    if b not in s.group_allowed[ga] or self.late():
                        continue
                    rest_a = [n for n in on[a] if s.group_of[n] != ga]
                    for gb in groups_on[b]:
                        if a not in s.group_allowed[gb] or self.sig[ga] == self.sig[gb]:
                            continue  # not allowed, or two identical groups
                        rest_b = [n for n in on[b] if s.group_of[n] != gb]
                        va = self.value(a, rest_a, s.groups[gb])
                        if va == -math.inf:
                            continue
                        vb = self.value(b, rest_b, s.groups[ga])
                        if vb != -math.inf:
                            out.append((va + vb - cur[a] - cur[b], len(out),
                                        {a: rest_a + list(s.groups[gb]), b: rest_b + list(s.groups[ga])}))
        # two groups joined by an edge move together (bandwidth may forbid moving one alone)
        pairs = sorted({tuple(sorted((s.group_of[e.src], s.group_of[e.dst]))) for e in s.edges
                        if s.group_of[e.src] != s.group_of[e.dst]})
        for ga, gb in pairs:
            if self.late():
                break
            members = list(s.groups[ga]) + list(s.groups[gb])
            homes = {s.place[n] or "" for n in members}
            for dst in s.group_allowed[ga]:
                if dst not in s.group_allowed[gb] or homes == {dst}:
                    continue
                plan: Plan_ = {c: [n for n in on[c] if n not in members] for c in homes if c != dst}
                plan[dst] = [n for n in on[dst] if n not in members] + members
                vals = [self.value(c, nodes) for c, nodes in plan.items()]
                if -math.inf not in vals:
                    out.append((sum(vals) - sum(cur[c] for c in plan), len(out), plan))
        out.sort(key=lambda m: (-m[0], m[1]))
        return out

    def _step(self) -> bool:
        s = self.s
        moves = self.moves()
        for gain, _, plan in moves:
            if gain <= 1e-9:
                break
            if self._apply(plan):
                return True
            if self.late():
                return False
        if len(s.groups) * len(s.computers) > MOVES_LIMIT or self.late():
            return False
        if self._repartition() or (self.trios and self._repartition3()):
            return True
        if len(s.groups) > DEPTH2_LIMIT:
            return False
        before = self.current(s.nodes)
        tried = 0
        for gain, _, plan in moves:
            if tried >= self.DEPTH2 or self.late():
                break
            if len(plan) == 1 and gain <= 1e-9:
                continue  # re-optimising one computer's settings changes nothing
            snap = s.snapshot()
            if not self._apply(plan):
                continue
            tried += 1
            for gain2, _, plan2 in self.moves():
                if gain2 <= 1e-9:
                    break
                if gain + gain2 > 1e-9 and self._apply(plan2):
                    if self.current(s.nodes) > before + 1e-9:
                        return True
                    break
            s.restore(snap)
        return False

    def _repartition(self) -> bool:
        """The best split of two computers' groups between them, applied when it improves."""
        s = self.s
        on = {c: s.on(c) for c in s.computers}
        best: tuple[float, Plan_] | None = None
        for i, a in enumerate(s.computers):
            if self.late():
                break
            for b in s.computers[i + 1:]:
                groups = sorted({s.group_of[n] for n in on[a] + on[b]})
                both = [gi for gi in groups if a in s.group_allowed[gi] and b in s.group_allowed[gi]]
                if not both or len(both) > self.REPARTITION:
                    continue
                fixed_a = [n for n in on[a] if s.group_of[n] not in both]
                fixed_b = [n for n in on[b] if s.group_of[n] not in both]
                cur = self.current(on[a] + on[b])
                side_a = self._subset_values(a, fixed_a, both)
                side_b = self._subset_values(b, fixed_b, both)
                full = (1 << len(both)) - 1
                for mask in range(full + 1):
                    gain = side_a[mask] + side_b[full ^ mask] - cur
                    if gain > 1e-9 and (best is None or gain > best[0] + 1e-12):
                        na = fixed_a + [n for j, gi in enumerate(both) if mask >> j & 1 for n in s.groups[gi]]
                        nb = fixed_b + [n for j, gi in enumerate(both) if not mask >> j & 1 for n in s.groups[gi]]
                        best = (gain, {a: na, b: nb})
        return best is not None and self._apply(best[1])

    def _repartition3(self) -> bool:
        """The best assignment of three computers' groups among them (every one, when at
        most :data:`TRIO_LIMIT` assignments), applied when it improves."""
        s = self.s
        on = {c: s.on(c) for c in s.computers}
        best: tuple[float, Plan_] | None = None
        for trio in itertools.combinations(s.computers, 3):
            if self.late():
                break
            nodes = [n for c in trio for n in on[c]]
            groups = sorted({s.group_of[n] for n in nodes})
            opts = {gi: [c for c in trio if c in s.group_allowed[gi]] for gi in groups}
            movable = [gi for gi in groups if len(opts[gi]) > 1]
            if not movable or math.prod(len(opts[gi]) for gi in movable) > self.TRIO_LIMIT:
                continue
            fixed = {c: [n for n in on[c] if s.group_of[n] not in movable] for c in trio}
            cand = {c: [gi for gi in movable if c in opts[gi]] for c in trio}
            vals = {c: self._subset_values(c, fixed[c], cand[c]) for c in trio}
            bit = {c: {gi: 1 << j for j, gi in enumerate(cand[c])} for c in trio}
            cur = self.current(nodes)
            for combo in itertools.product(*(opts[gi] for gi in movable)):
                masks = dict.fromkeys(trio, 0)
                for gi, c in zip(movable, combo, strict=True):
                    masks[c] |= bit[c][gi]
                gain = sum(vals[c][masks[c]] for c in trio) - cur
                if gain > 1e-9 and (best is None or gain > best[0] + 1e-12):
                    plan = {c: list(fixed[c]) for c in trio}
                    for gi, c in zip(movable, combo, strict=True):
                        plan[c] += list(s.groups[gi])
                    best = (gain, plan)
        return best is not None and self._apply(best[1])

    def _subset_values(self, comp: str, fixed: list[str], groups: list[int]) -> list[float]:
        """The value on ``comp`` of ``fixed`` plus each subset (bit mask) of ``groups``."""
        key = (comp, frozenset(fixed), tuple(groups))
        hit = self.subsets.get(key)
        if hit is None:
            hit = self.subsets[key] = self._subset_values_uncached(comp, fixed, groups)
        return hit

    def _subset_values_uncached(self, comp: str, fixed: list[str], groups: list[int]) -> list[float]:
        s = self.s
        k = len(groups)
        if s.problem == Problem.SERVER_CAPACITY or self.scale is None:
            return [self.value(comp, fixed, [n for j, gi in enumerate(groups) if m >> j & 1 for n in s.groups[gi]])
                    for m in range(1 << k)]
        tabs: list[np.ndarray] = [self.table(comp, frozenset(fixed))]
        for m in range(1, 1 << k):
            low = (m & -m).bit_length() - 1
            t = tabs[m & (m - 1)]
            for n in s.groups[groups[low]]:
                t = combine_tables(t, *self.items[n])[0]
            tabs.append(t)
        return [float(t[-1]) for t in tabs]


def combine_tables(table: np.ndarray, us: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Add one node (levels of CPU ``us`` and value ``vs``) to a knapsack table: the new
    table and, per budget, the level chosen (the cheapest among equals)."""
    size = len(table)
    pad = int(us.max())
    padded = np.concatenate([np.full(pad, -np.inf), table])
    idx = pad + np.arange(size)[None, :] - us[:, None]
    grid = padded[idx] + vs[:, None]
    arg = np.argmax(grid, axis=0)
    return grid[arg, np.arange(size)], arg


def best_settings(state: State, capacity: float, nodes: list[str], scale: float | None) -> tuple[float, dict[str, int]]:
    """The best Σ w·P of ``nodes`` on one computer of ``capacity`` and their levels
    (-inf when even the lowest settings do not fit). Exact on the integer grid ``scale``;
    without one, Algorithm 2's marginal rule on this computer alone."""
    if scale is None:
        return _marginal(state, capacity, nodes)
    size = int(math.floor(capacity * scale + 1e-6)) + 1
    table = np.zeros(size)
    steps: list[tuple[str, np.ndarray, np.ndarray]] = []
    for n in nodes:
        lad = state.ladder[n]
        us = np.array([int(round(ch.cpu * scale)) for ch in lad])
        vs = np.array([state.weight[n] * ch.performance for ch in lad])
        table, arg = combine_tables(table, us, vs)
        steps.append((n, us, arg))
    if not np.isfinite(table[-1]):
        return -math.inf, {}
    levels: dict[str, int] = {}
    x = size - 1
    for n, us, arg in reversed(steps):
        k = int(arg[x])
        levels[n] = k
        x -= int(us[k])
    return float(table[-1]), levels


def _marginal(state: State, capacity: float, nodes: list[str]) -> tuple[float, dict[str, int]]:
    """Algorithm 2's rule on one computer, from the lowest settings: the best gain per CPU
    unit first; a node whose next step does not fit stops."""
    levels = dict.fromkeys(nodes, 0)
    used = sum(state.ladder[n][0].cpu for n in nodes)
    if used > capacity + EPS:
        return -math.inf, {}

    def entry(n: str) -> tuple[float, int, str]:
        lad, k = state.ladder[n], levels[n]
        du = lad[k + 1].cpu - lad[k].cpu
        return -state.weight[n] * (lad[k + 1].performance - lad[k].performance) / max(du, EPS), state.order[n], n

    heap = [entry(n) for n in nodes if len(state.ladder[n]) > 1]
    heapq.heapify(heap)
    while heap:
        n = heapq.heappop(heap)[2]
        lad, k = state.ladder[n], levels[n]
        du = lad[k + 1].cpu - lad[k].cpu
        if used + du > capacity + EPS:
            continue
        used += du
        levels[n] = k + 1
        if k + 2 < len(lad):
            heapq.heappush(heap, entry(n))
    return sum(state.weight[n] * state.ladder[n][levels[n]].performance for n in nodes), levels
