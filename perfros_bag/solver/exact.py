"""The exact solver: both problems as one mixed-integer linear program, solved by HiGHS.

Formulation (eq 1-9 of the paper; see docs/solvers.md for the measurements behind it):

- ``x[n,k,c]`` binary: node ``n`` runs choice ``k`` on computer ``c`` (the tight
  multiple-choice form: its LP relaxation is the concave envelope of each node's curve).
  Only allowed computers (residence, eq 8) and usable, non-dominated choices get a column.
- ``z[g,c]`` binary for a coresidence group ``g`` of two or more nodes (eq 9):
  ``Σ_k x[n,k,c] = z[g,c]`` for every member ``n``, ``Σ_c z[g,c] = 1``; a lone node has
  ``Σ_{k,c} x[n,k,c] = 1`` (eq 5).
- CPU (eq 3): ``Σ U·x[·,·,c] <= R_c``. Problem 2 makes ``R_c`` of every server a
  continuous variable in ``[0, max_capacity]`` and minimises ``Σ R_c`` (eq 2); robots keep
  their capacity.
- Bandwidth (eq 4): the traffic of edge ``e = s -> d`` is ``b_e(k)`` when ``s`` runs choice
  ``k``; it loads every link of ``system.route(c_s, c_d)``. For a link whose removal cuts the
  computers into ``S`` and the rest, and whose routes are exactly the pairs split by that
  cut (always true on a tree), one continuous ``t[e,l] >= |A_s(S) - A_d(S)|·b_e`` is exact
  (the cut form). Any other link gets the pair form: ``f[e,a,b] >= b_e·[s on a] - M·(1 -
  [d on b])`` for every pair of computers whose route crosses it. A shared medium caps the
  sum of its links' loads.

A MIP start (``start``, e.g. greedy+'s plan) is checked and mapped onto the pruned model;
when the LP relaxation's bound already proves it within ``mip_gap`` the solver stops
there, otherwise HiGHS gets it as its first incumbent.

An infeasible instance gets a reason naming the constraint: cheap checks first (a node or
coresidence group larger than every allowed computer, residence sums, totals, edges that
always cross a link), then, when the MILP itself is infeasible, an elastic copy of it
(capacity and bandwidth may overflow at a cost) names the constraints that overflow.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import sys
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from perfros_bag.errors import InputError
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.rules import build_plan, computer_loads, server_sizes
from perfros_bag.system.rules import objective as plan_objective
from perfros_bag.system.types import Choice, Edge, Problem, System

__all__ = ["solve_exact", "trivial_bound", "within_trivial_bound"]

EPS = 1e-9
_INF = math.inf
_LOG = False  # HiGHS log on stdout (debugging)
# Measured (docs/solvers.md): on the case study these root heuristics cost more than they
# find, since the x-form's LP is tight; switching them off sped Table II instance 6 up 2.7x.
# Above this many columns HiGHS's MIP presolve (probing) costs more than it saves: 23 s of
# a 40 s run on 200 nodes x 20 computers (80,000 columns), against 0.2 s with it off.
_BIG_MODEL = 20_000
#: the share of a time limit (at least RESERVE_S) not handed to HiGHS nor to building the
#: model: measured, a MILP run at 200 x 20 (80,000 columns) stops up to ~0.1 s after its
#: limit, and freeing a half-built 1,000 x 100 model takes ~0.12 s; the plan is built after
#: them (--time-limit is honoured within 5 %)
RESERVE_SHARE = 0.05
RESERVE_S = 0.2
_HIGHS_OPTIONS: dict[str, Any] = {
    "mip_heuristic_run_rins": False,
    "mip_heuristic_run_rens": False,
    "mip_heuristic_run_root_reduced_cost": False,
}


@contextlib.contextmanager
def _stdout_silenced(silence: bool = True) -> Iterator[None]:
    """File descriptor 1 points to /dev/null inside (C and C++ code writing to stdout, such as
    HiGHS's banner, write nothing there); stdout is restored, C stdio flushed, on exit.
    ``--json`` output must be the document only."""
    if not silence:
        yield
        return
    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    try:
        saved = os.dup(1)
    except OSError:  # no stdout at all: nothing to protect
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        libc.fflush(None)  # what the C library buffered goes to /dev/null, not the restored stdout
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def quiet_highs() -> Any:
    """A new ``highspy.Highs()`` with nothing written to stdout: HiGHS >= 1.12 prints its
    banner when one is made, before any option can be set (every HiGHS model of the solvers
    is made here)."""
    import highspy  # lazy: keeps the CLI's start-up fast

    with _stdout_silenced(not _LOG):
        return highspy.Highs()


# ---------------------------------------------------------------------------------------------
# A tiny sparse model builder (rows kept row-wise, passed to HiGHS in one call)


@dataclass
class _Milp:
    cost: list[float] = field(default_factory=list)
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)
    integer: list[int] = field(default_factory=list)
    row_lo: list[float] = field(default_factory=list)
    row_hi: list[float] = field(default_factory=list)
    start: list[int] = field(default_factory=lambda: [0])
    index: list[int] = field(default_factory=list)
    value: list[float] = field(default_factory=list)

    def var(self, lo: float, hi: float, cost: float = 0.0, integer: bool = False) -> int:
        self.cost.append(cost)
        self.lower.append(lo)
        self.upper.append(hi)
        self.integer.append(1 if integer else 0)
        return len(self.cost) - 1

    def row(self, terms: Iterable[tuple[int, float]], lo: float, hi: float) -> int:
        merged: dict[int, float] = {}
        for j, a in terms:
            merged[j] = merged.get(j, 0.0) + a
        for j, a in merged.items():
            if a != 0.0:
                self.index.append(j)
                self.value.append(a)
        self.row_lo.append(lo)
        self.row_hi.append(hi)
        self.start.append(len(self.index))
        return len(self.row_lo) - 1

    def solve(self, maximise: bool, *, time_limit: float | None, mip_gap: float,
              start: dict[int, float] | None = None, relax: bool = False) -> Any:
        """Run HiGHS (``relax``: the LP relaxation); returns the Highs object. ``time_limit``
        counts from this call: passing a big model to HiGHS takes a while (~0.3 s at 1,000 x
        100), which HiGHS's own clock does not count."""
        import highspy  # lazy: keeps the CLI's start-up fast

        entered = time.perf_counter()
        h = quiet_highs()
        h.setOptionValue("output_flag", _LOG)
        h.setOptionValue("mip_rel_gap", float(mip_gap))
        h.setOptionValue("mip_abs_gap", 1e-7)
        h.setOptionValue("random_seed", 0)
        for name, value in _HIGHS_OPTIONS.items():
            h.setOptionValue(name, value)
        if len(self.cost) > _BIG_MODEL:
            h.setOptionValue("presolve", "off")
        if time_limit is not None:
            h.setOptionValue("time_limit", float(max(time_limit, 0.01)))
        inf = highspy.kHighsInf
        fix = np.vectorize(lambda v: inf if v == _INF else (-inf if v == -_INF else v), otypes=[float])
        n_col, n_row = len(self.cost), len(self.row_lo)
        h.passModel(
            n_col, n_row, len(self.index), int(highspy.MatrixFormat.kRowwise),
            int(highspy.ObjSense.kMaximize if maximise else highspy.ObjSense.kMinimize), 0.0,
            np.asarray(self.cost, dtype=np.float64),
            fix(np.asarray(self.lower, dtype=np.float64)) if n_col else np.zeros(0),
            fix(np.asarray(self.upper, dtype=np.float64)) if n_col else np.zeros(0),
            fix(np.asarray(self.row_lo, dtype=np.float64)) if n_row else np.zeros(0),
            fix(np.asarray(self.row_hi, dtype=np.float64)) if n_row else np.zeros(0),
            np.asarray(self.start[:-1] if n_row else [], dtype=np.int32),
            np.asarray(self.index, dtype=np.int32), np.asarray(self.value, dtype=np.float64),
            np.zeros(n_col, dtype=np.int32) if relax else np.asarray(self.integer, dtype=np.int32),
        )
        if start:
            idx = np.fromiter(start.keys(), dtype=np.int32, count=len(start))
            val = np.fromiter(start.values(), dtype=np.float64, count=len(start))
            h.setSolution(len(start), idx, val)
        if time_limit is not None:
            h.setOptionValue("time_limit", float(max(time_limit - (time.perf_counter() - entered), 0.01)))
        h.run()
        return h


# ---------------------------------------------------------------------------------------------
# The instance after pruning


@dataclass
class Group:
    members: tuple[str, ...]
    allowed: tuple[str, ...]  # computers every member may use (eq 8) and that can hold it
    z: dict[str, int] = field(default_factory=dict)  # computer -> column (groups of >= 2)


@dataclass
class Instance:
    system: System
    problem: Problem
    original: dict[str, list[Choice]]  # the candidates as given
    choices: dict[str, list[Choice]]  # kept choices (usable, non-dominated)
    replace: dict[str, dict[int, int]]  # node -> original position -> kept position
    groups: list[Group]
    group_of: dict[str, Group]
    cap: dict[str, float]  # the most CPU a computer can ever hold (inf: unbounded server)
    min_cpu: dict[str, float]
    cut: dict[int, frozenset[str]]  # link -> one side, for links in the cut form
    pairs: dict[int, list[tuple[str, str]]]  # link -> ordered computer pairs routed over it
    active: set[int] | None = None  # active_links, once computed
    # edge (src, dst) -> links it always crosses, links it may cross (see _crossings)
    crossings: dict[tuple[str, str], tuple[frozenset[int], frozenset[int]]] = field(default_factory=dict)


def _prune_choices(system: System, problem: Problem, node: str, options: Sequence[Choice],
                   cpu_room: float) -> tuple[list[Choice], dict[int, int]]:
    """Drop choices that can never fit (``cpu > cpu_room``) and, for Problem 1, choices
    dominated by another (no more CPU, no less performance, no more traffic on any edge).
    Returns the kept choices and, for every original position, the kept position that can
    replace it (for MIP starts); unusable positions are absent."""
    usable = [i for i, ch in enumerate(options) if ch.cpu <= cpu_room + EPS]
    # a node of the data flow is no plain multiple-choice item: a driven node's choices are
    # tied to its input's rate, a publisher's rate loads everything it drives
    if problem != Problem.PERFORMANCE or len(usable) <= 1 or system.in_flow(node):
        return [options[i] for i in usable], {i: p for p, i in enumerate(usable)}
    out_edges = [e for e in system.edges if e.src == node]
    bws = {i: tuple(system.edge_bandwidth(e, options[i]) for e in out_edges) for i in usable}
    order = sorted(usable, key=lambda i: (options[i].cpu, -options[i].performance, bws[i]))
    kept: list[int] = []
    best_of: dict[int, int] = {}
    uniform = len({bws[i] for i in usable}) == 1
    best_perf = -_INF
    for i in order:
        ch = options[i]
        if uniform:
            if ch.performance > best_perf + EPS:
                kept.append(i)
                best_perf = ch.performance
            best_of[i] = kept[-1] if kept and options[kept[-1]].performance >= ch.performance - EPS else i
            continue
        dom = next((j for j in kept
                    if options[j].cpu <= ch.cpu + EPS and options[j].performance >= ch.performance - EPS
                    and all(a <= b + EPS for a, b in zip(bws[j], bws[i], strict=True))), None)
        if dom is None:
            kept.append(i)
            best_of[i] = i
        else:
            best_of[i] = dom
    kept.sort(key=lambda i: (options[i].cpu, -options[i].performance))
    pos = {i: p for p, i in enumerate(kept)}
    return [options[i] for i in kept], {i: pos[best_of[i]] for i in usable}


def _classify_links(system: System) -> tuple[dict[int, frozenset[str]], dict[int, list[tuple[str, str]]]]:
    """Per link, the cut form's side when the pairs routed over it are exactly those the
    link's removal splits, else those pairs (for the pair form)."""
    n_computers = len(system.computers)
    cut: dict[int, frozenset[str]] = {}
    pairs: dict[int, list[tuple[str, str]]] = {}
    adjacent: dict[str, list[tuple[str, int]]] = {c.name: [] for c in system.computers}
    for li, link in enumerate(system.links):
        a, b = link.between
        adjacent[a].append((b, li))
        adjacent[b].append((a, li))
    for li, link in enumerate(system.links):
        # the side of link.between[0] when the link is removed
        side = {link.between[0]}
        frontier = [link.between[0]]
        while frontier:
            cur = frontier.pop()
            for nxt, lj in adjacent[cur]:
                if lj != li and nxt not in side:
                    side.add(nxt)
                    frontier.append(nxt)
        crossing = system.link_pairs[li]
        # the pairs it splits are exactly the crossing ones: as many, and each crossing one split
        split_count = 2 * len(side) * (n_computers - len(side))
        if link.between[1] not in side and len(crossing) == split_count \
                and all((a in side) != (b in side) for a, b in crossing):
            cut[li] = frozenset(side)
        else:
            pairs[li] = list(crossing)
    return cut, pairs


def prepare_instance(system: System, problem: Problem, choices: dict[str, list[Choice]]) -> Instance | str:
    """Prune the instance; returns a reason string when it is infeasible on its face."""
    cap = system.capacities(problem)
    missing = [n.name for n in system.nodes if not choices.get(n.name)]
    if missing:
        raise InputError(system.source, f"node(s) {', '.join(map(repr, missing))} have no choice to solve with")
    min_cpu = {n: min(ch.cpu for ch in opts) for n, opts in choices.items()}
    groups: list[Group] = []
    for members in system.coresidence_groups:
        allowed = system.allowed_to_all(members)
        who = ", ".join(members)
        if not allowed:
            return f"coresidence: nodes {who} have no computer allowed for all of them"
        need = sum(min_cpu[n] for n in members)
        fits = [c for c in allowed if need <= cap[c] + EPS]
        if not fits:
            biggest = max(allowed, key=lambda c: cap[c])
            if len(members) > 1:
                return (f"coresidence: nodes {who} need {need:g} CPU together at their minimum settings "
                        f"but the largest computer allowed for them, {biggest}, has {cap[biggest]:g}")
            if len(allowed) == 1:
                why = "residence" if len(system.computers) > 1 else "the only computer"
                return f"{who} needs {need:g} CPU on {biggest} ({why}) but {biggest} has {cap[biggest]:g}"
            return (f"{who} needs {need:g} CPU at its minimum setting but the largest computer allowed "
                    f"for it, {biggest}, has {cap[biggest]:g}")
        groups.append(Group(tuple(members), tuple(fits)))
    group_of = {n: g for g in groups for n in g.members}

    # residence: nodes (groups) that can only go to one computer must fit on it together
    forced: dict[str, list[Group]] = {}
    for g in groups:
        if len(g.allowed) == 1:
            forced.setdefault(g.allowed[0], []).append(g)
    for comp, gs in forced.items():
        need = sum(min_cpu[n] for g in gs for n in g.members)
        if need > cap[comp] + EPS:
            names = [n for g in gs for n in g.members]
            verb = "needs" if len(names) == 1 else "need"
            why = "residence" if len(system.computers) > 1 else "the only computer"
            return f"{', '.join(names)} {verb} {need:g} CPU on {comp} ({why}) but {comp} has {cap[comp]:g}"
    total_cap = sum(cap.values())
    total_need = sum(min_cpu.values())
    if total_need > total_cap + EPS:
        return (f"CPU: the nodes need {total_need:g} CPU in total at their minimum settings but the "
                f"computers have {total_cap:g}")

    kept: dict[str, list[Choice]] = {}
    replace: dict[str, dict[int, int]] = {}
    for g in groups:
        room = max(cap[c] for c in g.allowed)
        for n in g.members:
            others = sum(min_cpu[m] for m in g.members if m != n)
            kept[n], replace[n] = _prune_choices(system, problem, n, choices[n], room - others)
    cut, pairs = _classify_links(system)
    inst = Instance(system, problem, choices, kept, replace, groups, group_of, cap, min_cpu, cut, pairs)
    return _network_precheck(inst) or inst


def _crossings(inst: Instance, edge: Edge) -> tuple[frozenset[int], frozenset[int]]:
    """The links the edge crosses wherever its ends go, and those it may cross (over every
    pair of computers its ends' groups may use: the intersection and the union of their
    routes). Cached on the instance."""
    key = (edge.src, edge.dst)
    hit = inst.crossings.get(key)
    if hit is None:
        gs, gd = inst.group_of[edge.src], inst.group_of[edge.dst]
        always: set[int] | None = None
        maybe: set[int] = set()
        if gs is not gd:
            for a in gs.allowed:
                for b in gd.allowed:
                    route = set(inst.system.route(a, b) or ())
                    maybe |= route
                    always = route if always is None else always & route
        hit = (frozenset(always or ()), frozenset(maybe))
        inst.crossings[key] = hit
    return hit


def _crossing_always(inst: Instance, edge: Edge, li: int) -> bool | None:
    """True when the edge crosses link ``li`` wherever its ends go, False when it never
    can, None otherwise."""
    always, maybe = _crossings(inst, edge)
    return True if li in always else (None if li in maybe else False)


def _link_name(system: System, li: int) -> str:
    a, b = system.links[li].between
    return f"link {a}-{b}"


def _network_precheck(inst: Instance) -> str | None:
    system = inst.system
    for e in system.edges:
        gs, gd = inst.group_of[e.src], inst.group_of[e.dst]
        if gs is gd or not system.links:
            continue
        if all(system.route(a, b) is None for a in gs.allowed for b in gd.allowed):
            return (f"network: edge {e.src} -> {e.dst} joins computers with no network path between them "
                    f"({e.src} on {'/'.join(gs.allowed)}, {e.dst} on {'/'.join(gd.allowed)})")
    forced_load, forced_edges = _load_bounds(inst, forced=True)
    for li, link in enumerate(system.links):
        if forced_load[li] > link.bandwidth_kBps + EPS:
            return (f"bandwidth: {_link_name(system, li)} carries at least {forced_load[li]:g} kB/s "
                    f"(edges {', '.join(forced_edges[li])} must cross it) but has {link.bandwidth_kBps:g}")
    for m in system.media:
        load = system.medium_load(forced_load, m.name)
        if load > m.bandwidth_kBps + EPS:
            return (f"bandwidth: medium {m.name} carries at least {load:g} kB/s on its links "
                    f"(edges that must cross them) but has {m.bandwidth_kBps:g}")
    return None


def _load_bounds(inst: Instance, *, forced: bool) -> tuple[list[float], list[list[str]]]:
    """Per link, a bound on its load and the edges (``src->dst``) in it: with ``forced``,
    the least load (the edges that cross it wherever their ends go, at their publishers'
    least traffic); otherwise the most (every edge that may cross it, at the most traffic)."""
    system = inst.system
    bound = [0.0] * len(system.links)
    edges: list[list[str]] = [[] for _ in system.links]
    for e in system.edges:
        always, maybe = _crossings(inst, e)
        links = always if forced else maybe
        if not links:
            continue
        traffic = [system.edge_bandwidth(e, ch) for ch in inst.choices[e.src]]
        bw = min(traffic) if forced else max(traffic)
        if bw <= 0:
            continue
        for li in sorted(links):
            bound[li] += bw
            edges[li].append(f"{e.src}->{e.dst}")
    return bound, edges


# ---------------------------------------------------------------------------------------------
# The MILP


@dataclass
class _Built:
    milp: _Milp
    x: dict[tuple[str, int, str], int]  # (node, kept position, computer) -> column
    server_cap: dict[str, int]  # Problem 2: server -> capacity column
    slack: dict[str, int]  # elastic copy: constraint label -> overflow column
    # compact nodes: (node, computer) -> (placed column, level column); level m is the
    # kept position (CPU = lo + r·m)
    compact: dict[tuple[str, str], tuple[int, int]] = field(default_factory=dict)


def active_links(inst: Instance) -> set[int]:
    """Links (by index) whose bandwidth, or whose medium's, could ever be exceeded: the
    others need no rows at all. Computed once per instance."""
    if inst.active is not None:
        return inst.active
    system = inst.system
    potential, _ = _load_bounds(inst, forced=False)
    active = {li for li, link in enumerate(system.links) if potential[li] > link.bandwidth_kBps + EPS}
    for m in system.media:
        if system.medium_load(potential, m.name) > m.bandwidth_kBps + EPS:
            active.update(system.medium_links[m.name])
    inst.active = active
    return active


def _modelled_edges(inst: Instance, active: set[int]) -> list[int]:
    system = inst.system
    out = []
    for ei, e in enumerate(system.edges):
        if inst.group_of[e.src] is inst.group_of[e.dst]:
            continue
        if max(system.edge_bandwidth(e, ch) for ch in inst.choices[e.src]) <= 0:
            continue
        if any(_crossing_always(inst, e, li) is not False for li in active):
            out.append(ei)
    return out


def _grid(inst: Instance, node: str, modelled: Sequence[int]) -> tuple[float, float] | None:
    """``(lo, step)`` when the node's kept choices are ``lo + step·m`` (m = 0..M), with a
    concave performance sequence and constant traffic on every modelled edge: then the
    compact form (a placement binary, an integer level and the concave envelope, which is
    the convex hull of the choices) replaces the node's x columns."""
    opts = inst.choices[node]
    if inst.problem != Problem.PERFORMANCE or len(opts) < 3:
        return None
    if inst.system.in_flow(node):
        return None  # tied to the data flow's rows by its x columns
    lo, step = opts[0].cpu, opts[1].cpu - opts[0].cpu
    if step <= EPS:
        return None
    tol = 1e-9 * max(1.0, abs(opts[-1].cpu))
    if any(abs(ch.cpu - (lo + step * k)) > tol for k, ch in enumerate(opts)):
        return None
    slopes = [b.performance - a.performance for a, b in zip(opts, opts[1:], strict=False)]
    if any(s2 > s1 + 1e-9 * max(1.0, abs(s1)) for s1, s2 in zip(slopes, slopes[1:], strict=False)):
        return None
    system = inst.system
    for ei in modelled:
        e = system.edges[ei]
        if e.src == node and len({system.edge_bandwidth(e, ch) for ch in opts}) > 1:
            return None
    return lo, step


class _OutOfTime(Exception):
    """Building the model passed its deadline."""


def _build(inst: Instance, *, elastic: bool = False, compact_form: bool = False,
           deadline: float | None = None) -> _Built:
    """The MILP of the instance. Past ``deadline`` (``time.perf_counter()``), raises
    :class:`_OutOfTime` (checked per node group, computer and edge: at 1,000 x 100 the whole
    build takes over a second)."""
    system, problem = inst.system, inst.problem

    def on_time() -> None:
        if deadline is not None and time.perf_counter() > deadline:
            raise _OutOfTime
    milp = _Milp()
    x: dict[tuple[str, int, str], int] = {}
    slack: dict[str, int] = {}
    compact: dict[tuple[str, str], tuple[int, int]] = {}
    active = active_links(inst) if system.links else set()
    modelled = _modelled_edges(inst, active) if active else []
    # per (node, computer): terms of "node sits there" and of its CPU there
    placed_terms: dict[tuple[str, str], list[tuple[int, float]]] = {}
    cpu_terms: dict[tuple[str, str], list[tuple[int, float]]] = {}
    for g in inst.groups:
        on_time()
        if len(g.members) > 1:
            g.z = {c: milp.var(0.0, 1.0, 0.0, integer=True) for c in g.allowed}
            milp.row(((col, 1.0) for col in g.z.values()), 1.0, 1.0)
        else:
            g.z = {}
        for n in g.members:
            w = 0.0 if elastic or problem != Problem.PERFORMANCE else system.node[n].weight
            opts = inst.choices[n]
            grid = _grid(inst, n, modelled) if compact_form else None
            for c in g.allowed:
                if grid is not None:
                    lo, step = grid
                    p = g.z[c] if g.z else milp.var(0.0, 1.0, 0.0, integer=True)
                    m = milp.var(0.0, len(opts) - 1, 0.0, integer=True)
                    y = milp.var(-_INF, _INF, w)
                    milp.row([(m, 1.0), (p, -(len(opts) - 1))], -_INF, 0.0)  # m <= M·p
                    # y <= P_k·p + (P_{k+1} - P_k)·(m - k·p): the concave envelope's pieces
                    for k in range(len(opts) - 1):
                        slope = opts[k + 1].performance - opts[k].performance
                        milp.row([(y, 1.0), (m, -slope), (p, -(opts[k].performance - slope * k))], -_INF, 0.0)
                    compact[(n, c)] = (p, m)
                    placed_terms[(n, c)] = [(p, 1.0)]
                    cpu_terms[(n, c)] = [(p, lo), (m, step)]
                    continue
                cols = []
                for k, ch in enumerate(opts):
                    col = milp.var(0.0, 1.0, w * ch.performance, integer=True)
                    x[(n, k, c)] = col
                    cols.append((col, ch.cpu))
                placed_terms[(n, c)] = [(col, 1.0) for col, _ in cols]
                cpu_terms[(n, c)] = cols
            if g.z:
                for c in g.allowed:
                    if (n, c) not in compact:
                        milp.row(placed_terms[(n, c)] + [(g.z[c], -1.0)], 0.0, 0.0)
            else:
                milp.row((t for c in g.allowed for t in placed_terms[(n, c)]), 1.0, 1.0)

    if system.has_flow:
        _flow_rows(inst, milp, x)

    def placed(node: str, comp: str) -> list[tuple[int, float]]:
        """Terms of the 0/1 expression 'node sits on comp' (empty when it cannot)."""
        g = inst.group_of[node]
        if comp not in g.allowed:
            return []
        if g.z:
            return [(g.z[comp], 1.0)]
        return placed_terms[(node, comp)]

    # CPU per computer (eq 3)
    server_cap: dict[str, int] = {}
    for comp in system.computers:
        on_time()
        terms = [t for g in inst.groups if comp.name in g.allowed
                 for n in g.members for t in cpu_terms[(n, comp.name)]]
        if problem == Problem.SERVER_CAPACITY and comp.kind == "server":
            cost = 0.0 if elastic else 1.0
            server_cap[comp.name] = milp.var(0.0, inst.cap[comp.name], cost)
            terms.append((server_cap[comp.name], -1.0))
            milp.row(terms, -_INF, 0.0)
            continue
        if not terms:
            continue
        if elastic:
            s = milp.var(0.0, _INF, 1.0 / max(inst.cap[comp.name], 1.0))
            slack[f"computer {comp.name}"] = s
            terms.append((s, -1.0))
        milp.row(terms, -_INF, inst.cap[comp.name])

    # computers joined by no path: the two ends of an edge cannot sit there together
    if system.links:
        for e in system.edges:
            on_time()
            gs, gd = inst.group_of[e.src], inst.group_of[e.dst]
            if gs is gd:
                continue
            for a in gs.allowed:
                for b in gd.allowed:
                    if a != b and system.route(a, b) is None:
                        milp.row(placed(e.src, a) + placed(e.dst, b), -_INF, 1.0)

    # bandwidth per link (eq 4) and per shared medium
    if active:
        load_terms: list[list[tuple[int, float]]] = [[] for _ in system.links]
        pair_cols: dict[tuple[int, str, str], int] = {}
        for ei in modelled:
            on_time()
            e = system.edges[ei]
            gs, gd = inst.group_of[e.src], inst.group_of[e.dst]
            bw = [system.edge_bandwidth(e, ch) for ch in inst.choices[e.src]]
            big = max(bw)

            def traffic(comps: Iterable[str], src: str = e.src, allowed: tuple[str, ...] = gs.allowed,
                        bw: list[float] = bw) -> list[tuple[int, float]]:
                """b_e · [src on one of comps]"""
                out: list[tuple[int, float]] = []
                for c in comps:
                    if c not in allowed:
                        continue
                    if (src, c) in compact:  # constant traffic (see _grid)
                        out.append((compact[(src, c)][0], bw[0]))
                    else:
                        out.extend((x[(src, k, c)], bw[k]) for k in range(len(bw)) if bw[k] != 0.0)
                return out

            for li in sorted(active):
                always = _crossing_always(inst, e, li)
                if always is False:
                    continue
                if always:
                    load_terms[li].extend(traffic(gs.allowed))
                    continue
                if li in inst.cut:
                    side = inst.cut[li]
                    t = milp.var(0.0, _INF)
                    for part in (side, frozenset(system.computer) - side):
                        src_in = [c for c in gs.allowed if c in part]
                        if not src_in:
                            continue
                        dst_in = [term for c in gd.allowed if c in part for term in placed(e.dst, c)]
                        # t >= b_e [s in part] - M [d in part]
                        milp.row([(t, 1.0)] + [(j, -a) for j, a in traffic(src_in)]
                                 + [(j, big) for j, _ in dst_in], 0.0, _INF)
                    load_terms[li].append((t, 1.0))
                    continue
                for a, b in inst.pairs[li]:
                    if a not in gs.allowed or b not in gd.allowed:
                        continue
                    key = (ei, a, b)
                    if key not in pair_cols:
                        f = milp.var(0.0, _INF)
                        pair_cols[key] = f
                        # f >= b_e [s on a] - M (1 - [d on b])
                        milp.row([(f, 1.0)] + [(j, -w) for j, w in traffic([a])]
                                 + [(j, -big) for j, _ in placed(e.dst, b)], -big, _INF)
                    load_terms[li].append((pair_cols[key], 1.0))
        load_cols: dict[int, int] = {}
        for li, link in enumerate(system.links):
            if not load_terms[li]:
                continue
            load = milp.var(0.0, _INF)
            load_cols[li] = load
            milp.row(load_terms[li] + [(load, -1.0)], 0.0, 0.0)
            terms = [(load, 1.0)]
            if elastic:
                s = milp.var(0.0, _INF, 1.0 / max(link.bandwidth_kBps, 1e-6))
                slack[_link_name(system, li)] = s
                terms.append((s, -1.0))
            milp.row(terms, -_INF, link.bandwidth_kBps)
        for medium in system.media:
            on_medium = [load_cols[li] for li in system.medium_links[medium.name] if li in load_cols]
            if not on_medium:
                continue
            terms = [(col, 1.0) for col in on_medium]
            if elastic:
                s = milp.var(0.0, _INF, 1.0 / max(medium.bandwidth_kBps, 1e-6))
                slack[f"medium {medium.name}"] = s
                terms.append((s, -1.0))
            milp.row(terms, -_INF, medium.bandwidth_kBps)
    return _Built(milp, x, server_cap, slack, compact)


def _flow_rows(inst: Instance, milp: _Milp, x: dict[tuple[str, int, str], int]) -> None:
    """The data flow, linear: a driven node's choices are its settings at each input rate
    (:meth:`System.flow_choices`), so "its input runs at rate f" is the sum of its x columns
    at f, and "its publisher publishes at f" the sum of the publisher's x columns whose
    choice gives f. One row per driven node and rate sets the two equal: the product of the
    upstream and the downstream choice, linearised exactly (docs/solvers.md)."""
    system = inst.system
    for name in system.flow_order:
        parent = system.flow_parent[name]
        sides: dict[float, list[tuple[int, float]]] = {}
        for k, ch in enumerate(inst.choices[name]):
            assert ch.input_hz is not None
            cols = [x[(name, k, c)] for c in inst.group_of[name].allowed]
            sides.setdefault(ch.input_hz, []).extend((col, 1.0) for col in cols)
        for k, ch in enumerate(inst.choices[parent]):
            f = system.input_hz(name, ch)
            cols = [x[(parent, k, c)] for c in inst.group_of[parent].allowed]
            sides.setdefault(f, []).extend((col, -1.0) for col in cols)
        for terms in sides.values():
            milp.row(terms, 0.0, 0.0)


def start_assignment(inst: Instance, start: Assignment) -> tuple[Assignment, dict[str, int]] | None:
    """A MIP start mapped onto the pruned model (a dominated choice becomes the kept choice
    that dominates it), with each node's kept position; None when it is not feasible
    (placement, CPU, bandwidth), so that HiGHS is not handed a broken start."""
    system = inst.system
    placement: dict[str, str] = {}
    choice: dict[str, Choice] = {}
    position: dict[str, int] = {}
    for g in inst.groups:
        comps = {start.placement.get(n) for n in g.members}
        comp = comps.pop() if len(comps) == 1 else None
        if comp is None or comp not in g.allowed:
            return None
        for n in g.members:
            ch = start.choice.get(n)
            original = next((i for i, o in enumerate(inst.original[n]) if o == ch), None)
            pos = None if original is None else inst.replace[n].get(original)
            if pos is None:
                return None
            placement[n], choice[n], position[n] = comp, inst.choices[n][pos], pos
    load = computer_loads(system, placement, choice)
    if any(load[c] > inst.cap[c] + 1e-9 * max(1.0, inst.cap[c]) for c in load):
        return None
    if system.network_violation(placement, choice) is not None:
        return None
    if system.has_flow and system.flow_violation(choice) is not None:
        return None
    capacities = server_sizes(system, placement, choice) if inst.problem == Problem.SERVER_CAPACITY else {}
    return Assignment(placement, choice, capacities), position


def _start_values(inst: Instance, built: _Built, start: Assignment, position: dict[str, int]) -> dict[int, float]:
    """The integer columns of a (mapped, feasible) MIP start; HiGHS completes the
    continuous ones."""
    values = {col: 0.0 for col in built.x.values()}
    for p, m in built.compact.values():
        values[p] = 0.0
        values[m] = 0.0
    for g in inst.groups:
        comp = start.placement[g.members[0]]
        for n in g.members:
            if (n, comp) in built.compact:
                p, m = built.compact[(n, comp)]
                values[p] = 1.0
                values[m] = float(position[n])
            else:
                values[built.x[(n, position[n], comp)]] = 1.0
        for c, col in g.z.items():
            values[col] = 1.0 if c == comp else 0.0
    return values


def _extract(inst: Instance, built: _Built, values: Sequence[float]) -> Assignment:
    placement: dict[str, str] = {}
    choice: dict[str, Choice] = {}
    for (n, k, c), col in built.x.items():
        if values[col] > 0.5:
            placement[n] = c
            choice[n] = inst.choices[n][k]
    for (n, c), (p, m) in built.compact.items():
        if values[p] > 0.5:
            placement[n] = c
            choice[n] = inst.choices[n][int(round(values[m]))]
    capacities: dict[str, float] = {}
    if inst.problem == Problem.SERVER_CAPACITY:
        capacities = {c: round(size, 9) for c, size in server_sizes(inst.system, placement, choice).items()}
    return Assignment(placement, choice, capacities)


def _diagnose(inst: Instance, time_limit: float | None) -> str:
    """Why the MILP is infeasible: solve an elastic copy where capacities and bandwidths may
    overflow at a cost, and name what overflows in its best placement."""
    import highspy

    built = _build(inst, elastic=True)
    h = built.milp.solve(False, time_limit=time_limit, mip_gap=0.0)
    if h.getModelStatus() not in (highspy.HighsModelStatus.kOptimal,) and h.getInfo().primal_solution_status != 2:
        return ("no placement satisfies residence, coresidence, CPU and bandwidth together "
                "(the diagnosis did not finish)")
    values = h.getSolution().col_value
    over = [(label, values[col]) for label, col in built.slack.items() if values[col] > 1e-6]
    if not over:
        return "no placement satisfies residence, coresidence, CPU and bandwidth together"
    system = inst.system
    parts: list[str] = []
    for label, amount in over:
        if label.startswith("computer "):
            comp = label.split(" ", 1)[1]
            parts.append(f"{comp} would need {inst.cap[comp] + amount:g} CPU but has {inst.cap[comp]:g}")
        elif label.startswith("medium "):
            m = system.medium[label.split(" ", 1)[1]]
            parts.append(f"{label} would carry {m.bandwidth_kBps + amount:g} kB/s but has {m.bandwidth_kBps:g}")
        else:
            li = next(i for i in range(len(system.links)) if _link_name(system, i) == label)
            bw = system.links[li].bandwidth_kBps
            parts.append(f"{label} would carry {bw + amount:g} kB/s but has {bw:g}")
    kinds = sorted({"CPU" if label.startswith("computer ") else "bandwidth" for label, _ in over})
    return (f"{' and '.join(kinds)}: even the placement that overflows least breaks a limit: "
            + "; ".join(parts))


def _lp_rounding(inst: Instance, built: _Built, values: Sequence[float], maximise: bool, mip_gap: float,
                 time_limit: float | None) -> Assignment | None:
    """A start for big models: keep each node group only on the computers where the LP
    relaxation puts some of it (most groups: one), and solve that much smaller MILP."""
    groups = []
    for g in inst.groups:
        mass = {c: sum(values[built.x[(n, k, c)]] for n in g.members for k in range(len(inst.choices[n])))
                for c in g.allowed}
        best = max(mass, key=lambda c: mass[c])
        groups.append(Group(g.members, tuple(c for c in g.allowed if c == best or mass[c] >= 0.05)))
    fixed = Instance(inst.system, inst.problem, inst.original, inst.choices, inst.replace, groups,
                      {n: g for g in groups for n in g.members}, inst.cap, inst.min_cpu, inst.cut, inst.pairs)
    sub = _build(fixed)
    h = sub.milp.solve(maximise, time_limit=time_limit, mip_gap=mip_gap)
    if h.getInfo().primal_solution_status != 2:
        return None
    return _extract(fixed, sub, h.getSolution().col_value)


def trivial_bound(system: System, choices: Mapping[str, list[Choice]]) -> float:
    """Σ w·(best performance): no plan can do better (Problem 1)."""
    return sum(system.node[n].weight * max(c.performance for c in opts) for n, opts in choices.items())


def within_trivial_bound(system: System, problem: Problem, choices: Mapping[str, list[Choice]], plan: Plan) -> Plan:
    """The plan with its bound as the rule wants it (every exact path applies this): never
    looser than the trivial one (Problem 1: Σ w·max P; Problem 2: no server capacity at
    all), never on the wrong side of the objective, and stated whenever there is an
    objective (a solve stopped before proving anything states the trivial one). HiGHS
    reports its dual bound as it stands, which before its root LP is solved can be anything
    (29250.5 beside an objective of 75.6 was seen)."""
    if plan.objective is None:
        return plan
    if problem == Problem.PERFORMANCE:
        ceiling = trivial_bound(system, choices)
        plan.bound = max(min(ceiling if plan.bound is None else plan.bound, ceiling), plan.objective)
    else:
        plan.bound = min(max(0.0 if plan.bound is None else plan.bound, 0.0), plan.objective)
    return plan


def _reserve(time_limit: float) -> float:
    """The seconds of a time limit kept from HiGHS and from building the model: HiGHS stops a
    little after its limit, the plan is built after it, and a big model takes a while to
    free (~0.12 s at 1,000 x 100)."""
    return max(RESERVE_SHARE * time_limit, RESERVE_S)


def greedy_start(inst: Instance, choices: dict[str, list[Choice]]) -> tuple[Assignment, dict[str, int]] | None:
    """The paper's greedy's plan mapped onto the pruned model, None when it finds none."""
    from perfros_bag.solver import start_of
    from perfros_bag.solver.flow import solve_heuristic

    plan = solve_heuristic(inst.system, inst.problem, choices, Method.GREEDY)
    raw = start_of(plan, choices) if plan.status != Status.INFEASIBLE else None
    return start_assignment(inst, raw) if raw is not None else None


def solve_exact(system: System, problem: Problem, choices: dict[str, list[Choice]], *,
                time_limit: float | None = None, mip_gap: float = 0.0,
                start: Assignment | None = None, prepared: Instance | str | None = None) -> Plan:
    """Solve Problem 1 (max Σ w·P) or Problem 2 (min Σ server capacity) exactly with HiGHS.

    ``choices`` are each node's candidates (:func:`perfros_bag.solver.fixed_choices`).
    The plan's status is ``optimal`` when proven (gap below 1e-6 relative), ``feasible``
    with the solver's ``bound`` when ``time_limit`` or a positive ``mip_gap`` stopped it
    first, or ``infeasible`` with a reason naming the constraint. ``start`` (e.g. the
    greedy+ plan) is checked and passed to HiGHS as a MIP start; on hard instances it is
    what lets HiGHS close the gap quickly (docs/solvers.md). ``time_limit`` covers the
    whole call, set-up included: when the set-up uses it up, the start is the answer (with
    the LP bound when there is one). ``prepared``: :func:`prepare_instance`'s answer when
    the caller has it.
    """
    import highspy

    t0 = time.perf_counter()
    if problem not in (1, 2):
        raise InputError(system.source, f"problem must be 1 or 2, got {problem!r}")
    if mip_gap < 0 or not math.isfinite(mip_gap):
        raise InputError(None, f"mip_gap must be >= 0, got {mip_gap!r}")
    if prepared is None:
        prepared = prepare_instance(system, problem, choices)
    if isinstance(prepared, str):
        return Plan.infeasible(problem, Method.EXACT, prepared, solve_s=time.perf_counter() - t0,
                               system=system.source)
    inst = prepared
    mapped = start_assignment(inst, start) if start is not None else None
    maximise = problem == Problem.PERFORMANCE

    def remaining() -> float | None:
        """HiGHS's time limit for its next run: what is left, but a reserve (HiGHS stops a
        little after its limit; the plan is built after it) when there is a start to fall
        back on (else HiGHS is the only way to a plan: it gets all that is left)."""
        if time_limit is None:
            return None
        reserve = _reserve(time_limit) if mapped is not None else 0.0
        return max(time_limit - reserve - (time.perf_counter() - t0), 0.01)

    def out_of_time() -> bool:
        return time_limit is not None and time.perf_counter() - t0 >= time_limit

    def done(assignment: Assignment, bound: float, proven: bool) -> Plan:
        value = plan_objective(system, assignment, problem)
        if not math.isfinite(bound):
            bound = value if proven else (math.inf if maximise else 0.0)
        bound = max(bound, value) if maximise else min(bound, value)
        proven = proven or abs(bound - value) <= 1e-6 * max(1.0, abs(value))
        plan = build_plan(system, assignment, problem=problem, method=Method.EXACT,
                          status=Status.OPTIMAL if proven else Status.FEASIBLE,
                          bound=value if proven else (bound if math.isfinite(bound) else None),
                          solve_s=time.perf_counter() - t0)
        return within_trivial_bound(system, problem, choices, plan)

    if mapped is not None and out_of_time():  # the set-up used the time: the start is the answer
        return done(mapped[0], _INF if maximise else -_INF, False)
    try:  # with a start to fall back on, building the model may stop at the time limit
        built = _build(inst, deadline=None if time_limit is None or mapped is None
                       else t0 + time_limit - _reserve(time_limit))
    except _OutOfTime:  # so did building the model: the start is the answer
        assert mapped is not None
        return done(mapped[0], _INF if maximise else -_INF, False)
    big = len(built.milp.cost) > _BIG_MODEL
    if mapped is not None and out_of_time():
        return done(mapped[0], _INF if maximise else -_INF, False)
    known = _INF if maximise else -_INF  # the best bound proven so far (the LP relaxation's)
    if mapped is not None or big:
        # The LP relaxation is cheap next to HiGHS's MIP presolve on big models, and the
        # x form's LP bound is tight: when it already proves the start within mip_gap,
        # stop there (measured: 200 nodes x 20 computers, greedy+ within 0.3 % of it).
        # A big model without a start gets one by rounding the LP's placement.
        lp_started = time.perf_counter()
        lp = built.milp.solve(maximise, time_limit=remaining(), mip_gap=mip_gap, relax=True)
        lp_seconds = time.perf_counter() - lp_started
        if lp.getModelStatus() == highspy.HighsModelStatus.kOptimal:
            lp_bound = float(lp.getInfo().objective_function_value)
            known = lp_bound
            if mapped is None:
                rounded = _lp_rounding(inst, built, lp.getSolution().col_value, maximise, mip_gap, remaining())
                mapped = start_assignment(inst, rounded) if rounded is not None else None
            if mapped is not None:
                value = plan_objective(system, mapped[0], problem)
                # the MILP starts with this LP: no time left for it, the start is the answer
                too_late = time_limit is not None and time_limit - (time.perf_counter() - t0) < lp_seconds
                if abs(lp_bound - value) <= max(mip_gap * abs(value), 1e-6 * max(1.0, abs(value))) or too_late:
                    return done(mapped[0], lp_bound, False)
        elif mapped is not None and time_limit is not None:  # the LP ran out of time: so would the MILP
            return done(mapped[0], _INF if maximise else -_INF, False)
    start_values = _start_values(inst, built, *mapped) if mapped is not None else None
    h = built.milp.solve(maximise, time_limit=remaining(), mip_gap=mip_gap, start=start_values)
    status = h.getModelStatus()
    info = h.getInfo()
    has_solution = info.primal_solution_status == 2  # kSolutionStatusFeasible
    if status == highspy.HighsModelStatus.kInfeasible or (not has_solution and status in (
            highspy.HighsModelStatus.kUnboundedOrInfeasible,)):
        reason = _diagnose(inst, remaining())
        return Plan.infeasible(problem, Method.EXACT, reason, solve_s=time.perf_counter() - t0,
                               system=system.source)
    if not has_solution and mapped is None and time_limit is not None:
        mapped = greedy_start(inst, choices)  # the limit came first: the best plan at hand
        if mapped is None:  # the greedy got stuck (a binding network): greedy+'s, briefly
            from perfros_bag.solver.local import plus_start

            mapped = plus_start(inst, choices)
    if not has_solution and mapped is not None:  # HiGHS stopped before it found a plan
        return done(mapped[0], known, False)
    if not has_solution:
        limit = "the time limit" if time_limit is not None else "the solver's limits"
        return Plan.infeasible(problem, Method.EXACT,
                               f"no feasible plan found within {limit} (HiGHS: {h.modelStatusToString(status)}); "
                               "infeasibility was not proven: a longer time limit may find one",
                               solve_s=time.perf_counter() - t0, system=system.source)
    assignment = _extract(inst, built, h.getSolution().col_value)
    dual = float(info.mip_dual_bound)  # before its root LP, HiGHS's is no better than the LP's
    return done(assignment, min(dual, known) if maximise else max(dual, known), False)
