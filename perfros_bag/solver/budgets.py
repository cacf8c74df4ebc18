"""Latency budgets in the solvers (system.yaml ``budget_ms``, docs/solvers.md "Latency budgets").

Every method returns only plans whose predicted latency (:mod:`perfros_bag.system.latency`,
the one rule) keeps every budgeted chain within its budget:

- **exact**: lazy no-good cuts. The MILP is solved; when its optimum breaks a budget, a cut
  removes every assignment that holds what made that prediction (:func:`cut_of`), and it is
  solved again. The latency rule is monotone in the load it sees: more CPU planned beside a
  hop node, or more traffic on a link or medium of a hop's route, never makes the hop faster.
  So every assignment that contains the violating one's hop nodes, their inputs' publishers,
  the nodes sharing their computers and the edges loading their routes (same choices, same
  computers) breaks the budget too, and the cut removes only plans that break it. The last
  solve is proven optimal over the plans that keep the budget (tests: equal to brute force).
- **greedy, greedy+**: their plan, or, when it breaks a budget, the best re-placement of the
  broken chains' hop nodes at the same settings (every computer they may use, at most
  :data:`REPAIR_LIMIT` placements); none: no plan (infeasible, the reason names the chain).
- **bruteforce**: every assignment is checked.

A budget no plan can meet is one line naming the chain and a lower bound on its latency
(:func:`impossible_budget`).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass

from perfros_bag.system.latency import (
    budget_violation,
    chain_hops,
    fastest_bound,
    hop_floor,
    plan_predictions,
    predict_chain,
)
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.rules import build_plan, computer_loads, server_sizes
from perfros_bag.system.types import Chain, Choice, Problem, System

#: greedy / greedy+'s repair tries at most this many placements of a chain's hop nodes
REPAIR_LIMIT = 20_000
#: the exact solver adds at most this many cuts
MAX_CUTS = 2_000


def budgeted(system: System) -> list[Chain]:
    """The chains with a budget."""
    return [c for c in system.chains if c.budget_ms is not None]


def capacities_of(system: System, problem: Problem, assignment: Assignment) -> dict[str, float]:
    """Each computer's CPU for the latency rule: its capacity, a Problem 2 server's sized one
    (the assignment's, else its load)."""
    out: dict[str, float] = {}
    sized = server_sizes(system, assignment.placement, assignment.choice) if problem == Problem.SERVER_CAPACITY else {}
    for c in system.computers:
        if problem == Problem.SERVER_CAPACITY and c.kind == "server":
            out[c.name] = assignment.capacities.get(c.name, sized.get(c.name, 0.0))
        else:
            out[c.name] = c.capacity if c.capacity is not None else math.inf
    return out


def violation(system: System, problem: Problem, assignment: Assignment) -> str | None:
    """Why an assignment breaks a budget, or None."""
    if not budgeted(system):
        return None
    return budget_violation(system, assignment.placement, assignment.choice, capacities_of(system, problem, assignment))


def broken_chains(system: System, problem: Problem, assignment: Assignment) -> list[Chain]:
    caps = capacities_of(system, problem, assignment)
    loads = system.link_loads(assignment.placement, assignment.choice)
    return [c for c in budgeted(system)
            if predict_chain(system, c, assignment.placement, assignment.choice, caps, loads).over_budget()]


@dataclass(frozen=True)
class CutTerm:
    """``node`` at choice ``choice`` (None: any choice) on ``computer``; ``negate``: the term
    counts ``1 -`` that (the node is *not* there); ``coef``: its coefficient in a bound row."""

    node: str
    choice: Choice | None
    computer: str
    negate: bool = False
    coef: float = 1.0


#: a linear row over the exact solver's placement columns: sum(coef x term) <= bound
Row = tuple[list[CutTerm], float]


def cut_row(terms: list[CutTerm]) -> Row:
    """A no-good cut as a row: ``sum(terms) <= len(terms) - 1``, each negated term
    ``1 - [n on c]`` with its constant moved to the bound."""
    negated = sum(1 for t in terms if t.negate)
    return [CutTerm(t.node, t.choice, t.computer, coef=-1.0 if t.negate else 1.0) for t in terms], \
        len(terms) - 1 - negated


def floor_rows(system: System, problem: Problem, choices: Mapping[str, Sequence[Choice]]) -> list[Row]:
    """Per budgeted chain and bound, a valid row the MILP holds from the start: the sum over
    its hops of each (choice, computer)'s :func:`hop_floor` is within the budget. The floor
    never exceeds the prediction, so no plan within the budget is lost; choices that are too
    slow on a small computer are gone before the first solve instead of one cut at a time."""
    caps = system.capacities(problem)
    rows: list[Row] = []
    for chain in budgeted(system):
        hops = chain_hops(system, chain)
        assert not isinstance(hops, str) and chain.budget_ms is not None
        for quantile, limit in chain.budget_ms.items():
            q = 0 if quantile == "p50" else 1
            terms: list[CutTerm] = []
            for hop in hops:
                for ch in choices.get(hop.node, ()):
                    for comp in system.allowed(hop.node):
                        cap = caps[comp] if math.isfinite(caps[comp]) else system.latency.units_per_core
                        floor = hop_floor(system, hop.node, ch, cap)
                        if floor is not None and floor[q] > 0:
                            terms.append(CutTerm(hop.node, ch, comp, coef=floor[q]))
            rows.append((terms, limit))
    return rows


def cut_of(system: System, problem: Problem, assignment: Assignment, chain: Chain) -> list[CutTerm]:
    """The terms of a no-good cut ``sum(terms) <= len(terms) - 1`` removing ``assignment`` and
    every assignment whose ``chain`` is at least as late by the rule's monotonicity (module
    doc). Problem 2 sizes servers to their load, which is not monotone: there the hop
    computers' exact membership is fixed in the cut."""
    place, choice = assignment.placement, assignment.choice
    hops = chain_hops(system, chain)
    assert not isinstance(hops, str)
    terms: dict[tuple[str, str, bool], CutTerm] = {}

    def add(node: str, with_choice: bool = True) -> None:
        terms[(node, place[node], False)] = CutTerm(node, choice[node] if with_choice else None, place[node])

    comps: set[str] = set()
    links: set[int] = set()
    for hop in hops:
        parent = system.publishers[hop.src][0]
        add(hop.node)
        add(parent)
        comps.add(place[hop.node])
        route = system.route(place[parent], place[hop.node]) or ()
        links.update(route)
    for n, c in place.items():
        if c in comps:
            add(n)
    if problem == Problem.SERVER_CAPACITY:
        for n in system.node:
            for c in comps:
                if place[n] != c and c in system.allowed(n):
                    terms[(n, c, True)] = CutTerm(n, None, c, negate=True)
    media = {system.links[li].medium for li in links if system.links[li].medium is not None}
    links |= {li for m in media for li in system.medium_links[m or ""]}
    for _, edge, crossed in system.edge_routes(place):
        if crossed and links.intersection(crossed):
            add(edge.src)
            if (edge.dst, place[edge.dst], False) not in terms:
                add(edge.dst, with_choice=False)
    return list(terms.values())


def impossible_budget(system: System, choices: Mapping[str, Sequence[Choice]],
                      chain: Chain | None = None) -> str | None:
    """A chain whose budget is below a lower bound of its latency over every plan (each hop at
    its fastest choice, alone on the largest computer it may use, beside its input), named
    with that bound; None when every budget may be met. ``chain``: only that one."""
    for c in [chain] if chain is not None else budgeted(system):
        if c is None or c.budget_ms is None:
            continue
        bound = fastest_bound(system, c, choices)
        if bound is None:
            continue
        got = {"p50": bound[0], "p95": bound[1]}
        for q, b in c.budget_ms.items():
            if got[q] > b:
                return (f"chain {c.name!r}: no plan keeps its predicted {q} within its budget of {b:g} ms: "
                        f"in every plan it is at least {got[q]:.4g} ms")
    return None


def no_plan_within(system: System, choices: Mapping[str, Sequence[Choice]], what: str) -> str:
    """The reason of a solve that found no plan within the budgets: the first budgeted chain
    with its lower bound."""
    parts = []
    for c in budgeted(system):
        bound = fastest_bound(system, c, choices)
        if bound is not None:
            assert c.budget_ms is not None
            parts.append(f"chain {c.name!r} (budget {', '.join(f'{q} {b:g} ms' for q, b in c.budget_ms.items())}; "
                         f"no plan goes below p50 {bound[0]:.4g} / p95 {bound[1]:.4g} ms)")
    return f"{what} keeps the latency budgets of " + "; ".join(parts)


def repair(system: System, problem: Problem, assignment: Assignment, fits: object) -> Assignment | None:
    """The best re-placement (same choices) of the broken chains' hop nodes that keeps every
    budget and every constraint ``fits(assignment) -> bool`` checks; None when there is none
    within :data:`REPAIR_LIMIT` placements."""
    assert callable(fits)
    broken = broken_chains(system, problem, assignment)
    movers: list[str] = []
    for c in broken:
        hops = chain_hops(system, c)
        assert not isinstance(hops, str)
        for h in hops:
            for n in (system.publishers[h.src][0], h.node):
                if n not in movers:
                    movers.append(n)
    options = [system.allowed(n) for n in movers]
    if math.prod(len(o) for o in options) > REPAIR_LIMIT:
        return None
    best: tuple[float, Assignment] | None = None
    for combo in itertools.product(*options):
        placement = {**assignment.placement, **dict(zip(movers, combo, strict=True))}
        caps = (server_sizes(system, placement, assignment.choice) if problem == Problem.SERVER_CAPACITY else {})
        cand = Assignment(placement, dict(assignment.choice), caps)
        if not fits(cand) or violation(system, problem, cand) is not None:
            continue
        cost = sum(caps.values()) if problem == Problem.SERVER_CAPACITY else 0.0
        if best is None or cost < best[0] - 1e-9:
            best = (cost, cand)
    return None if best is None else best[1]


def fits_model(system: System, problem: Problem, capacities: Mapping[str, float]) -> Callable[[Assignment], bool]:
    """``fits(assignment)``: CPU (eq 3), residence, coresidence and network (eq 4) hold."""
    def fits(a: Assignment) -> bool:
        load = computer_loads(system, a.placement, a.choice)
        for c in system.computers:
            cap = capacities.get(c.name, math.inf)
            if load[c.name] > cap + 1e-9 * max(1.0, cap):
                return False
        for n in system.nodes:
            if a.placement[n.name] not in system.allowed(n.name):
                return False
            if any(a.placement[m] != a.placement[n.name] for m in n.coresidence):
                return False
        return system.network_violation(a.placement, a.choice) is None
    return fits


def assignment_of(plan: Plan, choices: Mapping[str, Sequence[Choice]]) -> Assignment | None:
    """A solver's plan of these ``choices`` as the :class:`Assignment` it came from (each
    node's choice matched on CPU, performance, value and input rate); None when one is not."""
    placement: dict[str, str] = {}
    chosen: dict[str, Choice] = {}
    for name, pn in plan.nodes.items():
        ch = next((c for c in choices.get(name, ())
                   if _same(c.cpu, pn.cpu) and _same(c.performance, pn.performance) and _same(c.value, pn.value)
                   and (pn.input is None or _same(c.input_hz, pn.input_hz))), None)
        if ch is None:
            return None
        placement[name], chosen[name] = pn.computer, ch
    capacities = {n: c.capacity for n, c in plan.computers.items()
                  if plan.problem == Problem.SERVER_CAPACITY and c.kind == "server" and c.capacity is not None}
    return Assignment(placement, chosen, capacities)


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


def within_budgets(system: System, problem: Problem, choices: Mapping[str, Sequence[Choice]],
                   plan: Plan, method: str) -> Plan:
    """A heuristic's plan when it keeps every budget; else, for greedy, the best
    re-placement of the broken chains' nodes (:func:`repair`), else a descent over their
    settings and computers (:func:`descend`); for greedy+, :func:`search` (both of those
    widened to every node the broken chains' latency depends on, then improved); rebuilt as a
    plan; else an infeasible plan naming the chain."""
    if plan.status == Status.INFEASIBLE or not budgeted(system):
        return plan
    assignment = assignment_of(plan, choices)
    if assignment is None:  # pragma: no cover - every solver plans one of the choices it was given
        raise AssertionError("the plan's choices are not the solver's")
    fits = fits_model(system, problem, system.capacities(problem))
    if violation(system, problem, assignment) is None:
        if method != Method.GREEDY_PLUS:
            return plan
        deadline = time.monotonic() + SEARCH_S
        better = _kicks(system, problem, _improve(system, problem, assignment, choices, fits, deadline), choices,
                        fits, deadline)
        if _objective(system, problem, better) <= _objective(system, problem, assignment) + 1e-9:
            return plan
        return build_plan(system, better, problem=problem, method=method, status=Status.FEASIBLE)
    if method == Method.GREEDY_PLUS:
        fixed = search(system, problem, assignment, choices, fits)
    else:
        fixed = repair(system, problem, assignment, fits) or descend(system, problem, assignment, choices, fits)
    if fixed is None:
        why = violation(system, problem, assignment)
        tried = "the chain's nodes" if method != Method.GREEDY_PLUS else "the nodes its latency depends on"
        return Plan.infeasible(problem, method, f"{method}'s plan breaks a latency budget ({why}) and no change of "
                               f"{tried} it tried keeps it: --method exact searches every plan",
                               system=system.source)
    return build_plan(system, fixed, problem=problem, method=method, status=Status.FEASIBLE)


def excess(system: System, problem: Problem, assignment: Assignment) -> float:
    """How far (ms, summed over the budgeted chains and their bounds) the predictions exceed
    their budgets; ``inf`` for a chain that cannot be predicted."""
    caps = capacities_of(system, problem, assignment)
    loads = system.link_loads(assignment.placement, assignment.choice)
    total = 0.0
    for c in budgeted(system):
        for _, got, limit in predict_chain(system, c, assignment.placement, assignment.choice, caps,
                                           loads).over_budget():
            total += got - limit
    return total


def with_flow(system: System, choice: Mapping[str, Choice], choices: Mapping[str, Sequence[Choice]]
              ) -> dict[str, Choice] | None:
    """``choice`` with every driven node at its own setting and the input rate its
    publisher now gives (None when that choice does not exist)."""
    out = dict(choice)
    for name in system.flow_order:
        want = system.input_hz(name, out[system.flow_parent[name]])
        have = out[name]
        if have.input_hz is not None and math.isclose(have.input_hz, want, rel_tol=1e-9, abs_tol=1e-9):
            continue
        match = next((c for c in choices[name] if c.setting == have.setting and c.input_hz is not None
                      and math.isclose(c.input_hz, want, rel_tol=1e-9, abs_tol=1e-9)), None)
        if match is None:
            return None
        out[name] = match
    return out


def _objective(system: System, problem: Problem, a: Assignment) -> float:
    if problem == Problem.PERFORMANCE:
        return sum(system.node[n].weight * ch.performance for n, ch in a.choice.items())
    return -sum(a.capacities.values())


#: the descent changes one node at a time, at most this many times
DESCENT_STEPS = 50


def descend(system: System, problem: Problem, assignment: Assignment, choices: Mapping[str, Sequence[Choice]],
            fits: object) -> Assignment | None:
    """Greedy descent on the budgets' excess: each step moves one node of the broken chains
    (a hop node or its input's publisher) to the (choice, computer) that fits and leaves the
    least excess (ties: the best objective), driven nodes following their input's new rate;
    None when a step cannot lower the excess."""
    assert callable(fits)
    current = assignment
    now = excess(system, problem, current)
    for _ in range(DESCENT_STEPS):
        if now <= 0:
            return current
        movers: list[str] = []
        for c in broken_chains(system, problem, current):
            hops = chain_hops(system, c)
            assert not isinstance(hops, str)
            for h in hops:
                movers += [n for n in (system.publishers[h.src][0], h.node) if n not in movers]
        best: tuple[float, float, Assignment] | None = None
        for n in movers:
            for ch in choices[n]:
                if system.node[n].driven and ch.input_hz != current.choice[n].input_hz:
                    continue  # its rate follows its input
                chosen = with_flow(system, {**current.choice, n: ch}, choices)
                if chosen is None:
                    continue
                for comp in system.allowed(n):
                    placement = {**current.placement, n: comp}
                    caps = server_sizes(system, placement, chosen) if problem == Problem.SERVER_CAPACITY else {}
                    cand = Assignment(placement, chosen, caps)
                    if not fits(cand):
                        continue
                    left = excess(system, problem, cand)
                    key = (left, -_objective(system, problem, cand))
                    if left < now - 1e-9 and (best is None or key < best[:2]):
                        best = (key[0], key[1], cand)
        if best is None:
            return None
        now, current = best[0], best[2]
    return current if now <= 0 else None


def solve_with_cuts(system: System, problem: Problem, choices: Mapping[str, Sequence[Choice]],
                    solve_once: Callable[[list[Row]], Plan], out_of_time: Callable[[], bool]) -> Plan:
    """The exact solver under budgets: solve, cut away an optimum that breaks a budget
    (:func:`cut_of`), solve again, until an optimum keeps them all (it is optimal among the
    plans that do) or none is left (infeasible, naming the chains and their bounds)."""
    floors = floor_rows(system, problem, choices)
    cuts: list[Row] = []
    while True:
        plan = solve_once(floors + cuts)
        if plan.status == Status.INFEASIBLE:
            if cuts or floors:
                plan.reason = no_plan_within(system, choices, "no plan that fits the other constraints")
            return plan
        assignment = assignment_of(plan, choices)
        if assignment is None:  # pragma: no cover - the MILP plans one of its choices
            raise AssertionError("the exact plan's choices are not the solver's")
        broken = broken_chains(system, problem, assignment)
        if not broken:
            return plan
        if out_of_time() or len(cuts) >= MAX_CUTS:
            limit = "the time limit" if out_of_time() else f"{MAX_CUTS} cuts"
            return Plan.infeasible(problem, Method.EXACT, no_plan_within(
                system, choices, f"no plan found within {limit} (not proven: a longer time limit may find one)"),
                system=system.source)
        cuts.append(cut_row(cut_of(system, problem, assignment, broken[0])))


def restate_chains(system: System, plan: Plan) -> None:
    """A plan restated after the solve (headroom given back: its real CPU, its computers'
    whole capacity) predicted again as it will run. Each term of the rule only falls when a
    node needs less or a computer holds more, so a plan that kept its budgets keeps them."""
    if system.chains and plan.status != Status.INFEASIBLE:
        plan.chains = [p.to_dict() for p in plan_predictions(system, plan, warn=False)]


#: greedy+'s budget search (:func:`search`): seconds it may take in all
SEARCH_S = 5.0
#: ... pairs of moves it tries in one step when no single move lowers the excess
PAIR_LIMIT = 20_000
#: ... improving moves it makes once every budget holds
IMPROVE_STEPS = 200


def influencers(system: System, problem: Problem, assignment: Assignment, chains: Sequence[Chain]) -> list[str]:
    """The nodes whose choice or computer the ``chains``' predicted latency depends on in
    ``assignment``: the nodes of their no-good cuts (:func:`cut_of`: the hop nodes, their
    inputs' publishers, every node on a hop computer, the ends of every edge crossing a hop's
    route; in Problem 2 also every node that may join a hop's server, which, sized to its
    new load, can speed the hop up), in node order."""
    named = {t.node for c in chains for t in cut_of(system, problem, assignment, c)}
    return [n.name for n in system.nodes if n.name in named]


def _group_of(system: System) -> dict[str, tuple[tuple[str, ...], tuple[str, ...]]]:
    """node -> (its coresidence group, the computers all of it may use)."""
    return {n: (g, comps) for g, comps in zip(system.coresidence_groups, system.group_computers, strict=True)
            for n in g}


def _neighbours(system: System, problem: Problem, current: Assignment, nodes: Sequence[str],
                choices: Mapping[str, Sequence[Choice]], fits: Callable[[Assignment], bool]) -> Iterator[Assignment]:
    """Every assignment one move away that fits: one of ``nodes`` at another (choice,
    computer), its coresidence group moving with it, the nodes it drives following its new
    rate (:func:`_with_children`)."""
    groups = _group_of(system)
    for n in nodes:
        group, comps = groups[n]
        for ch in choices[n]:
            if system.node[n].driven and ch.input_hz != current.choice[n].input_hz:
                continue  # its rate follows its input
            for chosen in _with_children(system, current.choice, n, ch, choices):
                for comp in comps:
                    if comp == current.placement[n] and chosen == current.choice:
                        continue
                    placement = {**current.placement, **dict.fromkeys(group, comp)}
                    caps = server_sizes(system, placement, chosen) if problem == Problem.SERVER_CAPACITY else {}
                    cand = Assignment(placement, chosen, caps)
                    if fits(cand):
                        yield cand


#: a move of a publisher's choice re-picks the settings of the nodes it drives, at most this many combinations
CHILD_COMBOS = 64


def _with_children(system: System, choice: Mapping[str, Choice], node: str, ch: Choice,
                   choices: Mapping[str, Sequence[Choice]]) -> list[dict[str, Choice]]:
    """``choice`` with ``node`` at ``ch`` and the rates downstream following it: the nodes it
    drives at their own settings, and, when its rate changes, also at each other combination
    of their settings (at most :data:`CHILD_COMBOS`: a faster camera fits only with a
    cheaper detector)."""
    if ch == choice[node]:
        return [dict(choice)]
    base = with_flow(system, {**choice, node: ch}, choices)
    out = [] if base is None else [base]
    children = [m for m in system.flow_order if system.flow_parent.get(m) == node]
    if not children or base is None or all(base[m] == choice[m] for m in children):
        return out
    own = [sorted({c.setting for c in choices[m] if c.setting is not None}) for m in children]
    if math.prod(len(o) for o in own) > CHILD_COMBOS:
        return out
    for combo in itertools.product(*own):
        if all(base[m].setting == k for m, k in zip(children, combo, strict=True)):
            continue
        start = dict(base)
        for m, k in zip(children, combo, strict=True):
            start[m] = next(c for c in choices[m] if c.setting == k)
        got = with_flow(system, start, choices)
        if got is not None:
            out.append(got)
    return out


def search(system: System, problem: Problem, assignment: Assignment, choices: Mapping[str, Sequence[Choice]],
           fits: object, time_s: float = SEARCH_S) -> Assignment | None:
    """greedy+ under budgets: a plan within every budget near ``assignment``, or None.

    1. Start points: ``assignment`` and :func:`repair`'s re-placement of the broken chains'
       nodes (when it finds one).
    2. Descent on the budgets' excess: each step takes the move (:func:`_neighbours`) of a
       node the broken chains depend on (:func:`influencers`: not only their hop nodes but
       the nodes beside them, whose CPU slows them, and the traffic on their routes) that
       leaves the least excess (ties: the best objective); when no single move lowers it,
       the best pair of such moves (at most :data:`PAIR_LIMIT`).
    3. Improvement: moves of any node that keep every constraint and budget and better the
       objective, best first, up to :data:`IMPROVE_STEPS` (a repair gives up objective that
       another node can win back: a setting raised, a server emptied).
    4. Kicks (:func:`_kicks`): each move of any node, then 2 and 3 again, kept when it
       ends better.

    The best plan found within ``time_s`` seconds."""
    assert callable(fits)
    deadline = time.monotonic() + time_s
    starts = [assignment]
    fixed = repair(system, problem, assignment, fits)
    if fixed is not None:
        starts.insert(0, fixed)
    best: Assignment | None = None
    for start in starts:
        found = _descend_wide(system, problem, start, choices, fits, deadline)
        if found is None:
            continue
        found = _improve(system, problem, found, choices, fits, deadline)
        if best is None or _objective(system, problem, found) > _objective(system, problem, best) + 1e-9:
            best = found
    return best if best is None else _kicks(system, problem, best, choices, fits, deadline)


def _kicks(system: System, problem: Problem, best: Assignment, choices: Mapping[str, Sequence[Choice]],
           fits: Callable[[Assignment], bool], deadline: float) -> Assignment:
    """Iterated local search: from ``best``, each move of any node, whether it keeps the
    budgets or not (a detector sent to the server, or another robot's brought home to make
    room there), followed by the descent and the improvement; the first that ends better is
    kept and its kicks tried in turn, until none does or the deadline. (Kicks of only the
    nodes the budgeted chains depend on: 25 of 40 vision Problem 1 instances optimal, mean
    ratio 0.979; of every node: 28, 0.989, 1.1 s instead of 0.7 s on average.)"""
    value = _objective(system, problem, best)
    improved = True
    while improved and time.monotonic() < deadline:
        improved = False
        movers = [n.name for n in system.nodes]
        for kick in _neighbours(system, problem, best, movers, choices, fits):
            if time.monotonic() > deadline:
                break
            found = _descend_wide(system, problem, kick, choices, fits, deadline)
            if found is None:
                continue
            found = _improve(system, problem, found, choices, fits, deadline)
            got = _objective(system, problem, found)
            if got > value + 1e-9 and violation(system, problem, found) is None:
                best, value, improved = found, got, True
                break
    return best


def _descend_wide(system: System, problem: Problem, current: Assignment, choices: Mapping[str, Sequence[Choice]],
                  fits: Callable[[Assignment], bool], deadline: float) -> Assignment | None:
    now = excess(system, problem, current)
    while now > 0:
        if time.monotonic() > deadline:
            return None
        movers = influencers(system, problem, current, broken_chains(system, problem, current))
        best: tuple[float, float, Assignment] | None = None
        for cand in _neighbours(system, problem, current, movers, choices, fits):
            key = (excess(system, problem, cand), -_objective(system, problem, cand))
            if key[0] < now - 1e-9 and (best is None or key < best[:2]):
                best = (key[0], key[1], cand)
            if time.monotonic() > deadline:
                return None
        if best is None:
            best = _best_pair(system, problem, current, movers, choices, fits, now, deadline)
        if best is None:
            return None
        now, current = best[0], best[2]
    return current


def _best_pair(system: System, problem: Problem, current: Assignment, movers: Sequence[str],
               choices: Mapping[str, Sequence[Choice]], fits: Callable[[Assignment], bool], now: float,
               deadline: float) -> tuple[float, float, Assignment] | None:
    """The best two moves, the first of ``movers``, the second of any node, that lower the
    excess below ``now`` together (the first may not, nor fit alone: it is half of a swap, or
    the second makes room for it), at most :data:`PAIR_LIMIT` pairs."""
    best: tuple[float, float, Assignment] | None = None
    tried = 0
    everyone = [n.name for n in system.nodes]
    for first in _neighbours(system, problem, current, movers, choices, lambda _: True):
        for cand in _neighbours(system, problem, first, everyone, choices, fits):
            tried += 1
            key = (excess(system, problem, cand), -_objective(system, problem, cand))
            if key[0] < now - 1e-9 and (best is None or key < best[:2]):
                best = (key[0], key[1], cand)
            if tried >= PAIR_LIMIT or time.monotonic() > deadline:
                return best
    return best


def _improve(system: System, problem: Problem, current: Assignment, choices: Mapping[str, Sequence[Choice]],
             fits: Callable[[Assignment], bool], deadline: float) -> Assignment:
    value = _objective(system, problem, current)
    nodes = [n.name for n in system.nodes]
    for _ in range(IMPROVE_STEPS):
        best: tuple[float, Assignment] | None = None
        for cand in _neighbours(system, problem, current, nodes, choices, fits):
            got = _objective(system, problem, cand)
            if got > (value if best is None else best[0]) + 1e-9 and violation(system, problem, cand) is None:
                best = (got, cand)
            if time.monotonic() > deadline:
                break
        if best is None:
            return current
        value, current = best
        if time.monotonic() > deadline:
            break
    return current
