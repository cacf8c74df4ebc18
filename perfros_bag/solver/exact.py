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

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from perfros_bag.errors import InputError
from perfros_bag.solver import milp as mip
from perfros_bag.solver.budgets import Row
from perfros_bag.solver.instance import (
    EPS,
    Group,
    Instance,
    active_links,
    crossing_always,
    link_name,
    prepare_instance,
    start_assignment,
    within_trivial_bound,
)
from perfros_bag.solver.starts import greedy_start, plus_start
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.rules import build_plan, server_sizes
from perfros_bag.system.rules import objective as plan_objective
from perfros_bag.system.types import Choice, Problem, System

__all__ = ["solve_exact"]

_INF = math.inf
#: the share of a time limit (at least RESERVE_S) not handed to HiGHS nor to building the
#: model: measured, a MILP run at 200 x 20 (80,000 columns) stops up to ~0.1 s after its
#: limit, and freeing a half-built 1,000 x 100 model takes ~0.12 s; the plan is built after
#: them (--time-limit is honoured within 5 %)
RESERVE_SHARE = 0.05
RESERVE_S = 0.2


# ---------------------------------------------------------------------------------------------
# The MILP


@dataclass
class _Built:
    milp: mip.Milp
    x: dict[tuple[str, int, str], int]  # (node, kept position, computer) -> column
    server_cap: dict[str, int]  # Problem 2: server -> capacity column
    slack: dict[str, int]  # elastic copy: constraint label -> overflow column
    # compact nodes: (node, computer) -> (placed column, level column); level m is the
    # kept position (CPU = lo + r·m)
    compact: dict[tuple[str, str], tuple[int, int]] = field(default_factory=dict)



def _modelled_edges(inst: Instance, active: set[int]) -> list[int]:
    system = inst.system
    out = []
    for ei, e in enumerate(system.edges):
        if inst.group_of[e.src] is inst.group_of[e.dst]:
            continue
        if max(system.edge_bandwidth(e, ch) for ch in inst.choices[e.src]) <= 0:
            continue
        if any(crossing_always(inst, e, li) is not False for li in active):
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
           deadline: float | None = None, cuts: Sequence[Row] = ()) -> _Built:
    """The MILP of the instance. Past ``deadline`` (``time.perf_counter()``), raises
    :class:`_OutOfTime` (checked per node group, computer and edge: at 1,000 x 100 the whole
    build takes over a second)."""
    system, problem = inst.system, inst.problem

    def on_time() -> None:
        if deadline is not None and time.perf_counter() > deadline:
            raise _OutOfTime
    milp = mip.Milp()
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
                always = crossing_always(inst, e, li)
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
                slack[link_name(system, li)] = s
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
    for row_terms, upper in cuts:  # latency budgets: floors and no-good cuts (perfros_bag.solver.budgets)
        cut_row: list[tuple[int, float]] = []
        for term in row_terms:
            if term.choice is None:
                cut_row += [(col, term.coef * a) for col, a in placed(term.node, term.computer)]
                continue
            pos = next((i for i, ch in enumerate(inst.choices[term.node]) if ch == term.choice), None)
            column = None if pos is None else x.get((term.node, pos, term.computer))
            if column is not None:  # a pruned choice or a computer its group cannot use has no column
                cut_row.append((column, term.coef))
        milp.row(cut_row, -_INF, upper)
    return _Built(milp, x, server_cap, slack, compact)


def _flow_rows(inst: Instance, milp: mip.Milp, x: dict[tuple[str, int, str], int]) -> None:
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
    import highspy  # lazy, as in milp.py: a missing HiGHS fails the exact method only

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
            li = next(i for i in range(len(system.links)) if link_name(system, i) == label)
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



def _reserve(time_limit: float) -> float:
    """The seconds of a time limit kept from HiGHS and from building the model: HiGHS stops a
    little after its limit, the plan is built after it, and a big model takes a while to
    free (~0.12 s at 1,000 x 100)."""
    return max(RESERVE_SHARE * time_limit, RESERVE_S)



def solve_exact(system: System, problem: Problem, choices: dict[str, list[Choice]], *,
                time_limit: float | None = None, mip_gap: float = 0.0,
                start: Assignment | None = None, prepared: Instance | str | None = None,
                cuts: Sequence[Row] = ()) -> Plan:
    """Solve Problem 1 (max Σ w·P) or Problem 2 (min Σ server capacity) exactly with HiGHS.

    ``choices`` are each node's candidates (:func:`perfros_bag.solver.fixed_choices`).
    The plan's status is ``optimal`` when proven (gap below 1e-6 relative), ``feasible``
    with the solver's ``bound`` when ``time_limit`` or a positive ``mip_gap`` stopped it
    first, or ``infeasible`` with a reason naming the constraint. ``start`` (e.g. the
    greedy+ plan) is checked and passed to HiGHS as a MIP start; on hard instances it is
    what lets HiGHS close the gap quickly (docs/solvers.md). ``time_limit`` covers the
    whole call, set-up included: when the set-up uses it up, the start is the answer (with
    the LP bound when there is one). ``prepared``: :func:`prepare_instance`'s answer when
    the caller has it. ``cuts``: rows over the placement columns (latency budgets:
    :func:`perfros_bag.solver.budgets.floor_rows` and the no-good cuts of ``cut_of``).
    """
    import highspy  # lazy, as in milp.py: a missing HiGHS fails the exact method only

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
        built = _build(inst, cuts=cuts, deadline=None if time_limit is None or mapped is None
                       else t0 + time_limit - _reserve(time_limit))
    except _OutOfTime:  # so did building the model: the start is the answer
        assert mapped is not None
        return done(mapped[0], _INF if maximise else -_INF, False)
    big = len(built.milp.cost) > mip.BIG_MODEL
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
