"""The heuristics on a system with driven nodes (system.yaml ``input``).

The paper's greedy and greedy+ treat every node's choices as independent. Along the data
flow they are not: a driven node's choice must be made for the rate its input's publisher
gives (:meth:`~perfros_bag.system.types.System.flow_choices`). Fix, for every node that
drives others (a *publisher*), the rates it publishes (its *rate class*), and what is left
is the paper's problem: each publisher keeps its choices in that class, each driven node
its choices at that input rate, and every combination of them is consistent. A publisher
that is itself driven is fixed by its own setting instead (its rates then follow its input).
So:

- one inner run of the heuristic per assignment of rate classes (:func:`_restricted`);
- every assignment when there are at most :data:`ENUMERATE` of them (a camera with three
  rates and a throttle with four: 12), else a coordinate search valued by the paper's
  greedy (fast): start with every publisher at its lowest class, then, publisher by
  publisher, keep the class that gives the best plan, until a pass changes nothing or
  :data:`PASSES` passes have run (when every tree has as many options, a fleet of alike
  robots, the search starts from the best of "every tree at its k-th option"); greedy+
  then runs on the best assignment it found.

The exact solver needs none of this: its rows tie the choices together
(:mod:`perfros_bag.solver.exact`, its flow rows).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

from perfros_bag.solver.greedy import greedy_plan, run_greedy, solve_greedy
from perfros_bag.solver.state import State
from perfros_bag.system.plan import Method, Plan, better_plan
from perfros_bag.system.types import Choice, Problem, System

if TYPE_CHECKING:
    from perfros_bag.solver.local import Improver

#: at most this many rate-class assignments are all tried; above, a coordinate search
ENUMERATE = 64
#: coordinate-search passes over the publishers
PASSES = 3
#: the whole search's time (seconds) when the caller sets none: past it, the best plan found
#: so far (at least the first assignment's, every publisher at its cheapest) is the answer
SEARCH_BUDGET_S = 60.0
#: greedy+'s own budget (seconds) on the assignment the search found (its local search can
#: take minutes on a few hundred nodes)
FINAL_BUDGET_S = 10.0

#: greedy+ along a data flow with many rate assignments (Problem 1), on a fleet: when one
#: pass of the greedy's tree-by-tree search (a greedy run per tree option) would take longer
#: than this (seconds), no passes: greedy+ on every publisher at its cheapest, then rate moves
PLUS_PASS_MAX_S = 20.0
#: ... greedy+'s whole time there (seconds), or the caller's deadline
PLUS_RATES_S = 4.0
#: of that time, greedy+'s own search on the start's rates (its relocation moves; the rest:
#: the rate moves)
PLUS_SHARE = 0.8
#: a rate move may send a following group to this many servers (those with the most free CPU)
MOVE_SERVERS = 2

#: per publisher: the rates it publishes (one per node it drives), or a driven publisher's own setting
Pick = tuple[float, ...] | int
Classes = dict[str, Pick]


def solve_heuristic(system: System, problem: Problem, choices: dict[str, list[Choice]], method: Method, *,
                    time_budget: float | None = None) -> Plan:
    """``method`` (greedy or greedy+) on ``choices``; along the data flow when the system has one."""
    if not system.has_flow:
        return _inner(system, problem, choices, method, time_budget)
    deadline = time.monotonic() + (SEARCH_BUDGET_S if time_budget is None else time_budget)
    options = _class_options(system, choices)
    publishers = sorted(options, key=lambda p: system.flow_order.index(p) if p in system.flow_order else -1)
    tried: dict[tuple[Method, tuple[Pick, ...]], Plan | None] = {}
    combos = 1
    for p in publishers:
        combos *= len(options[p])

    def run(classes: Classes, how: Method) -> Plan | None:
        key = (how, tuple(classes[p] for p in publishers))
        if key not in tried:
            restricted = _restricted(system, choices, classes)
            left = max(deadline - time.monotonic(), 0.0)
            if how == Method.GREEDY_PLUS and combos > ENUMERATE:
                left = min(left, FINAL_BUDGET_S)
            tried[key] = None if restricted is None else _inner(system, problem, restricted, how, left)
        return tried[key]

    def late() -> bool:
        return time.monotonic() > deadline

    if combos <= ENUMERATE:  # few: every assignment with the method itself
        for pick in itertools.product(*(options[p] for p in publishers)):
            if late() and tried:
                break
            run(dict(zip(publishers, pick, strict=True)), method)
        return _best(tried.values(), problem, method, system)
    # many: a coordinate search valued by the (fast) greedy, then greedy+ on its best;
    # a move sets every publisher of one source's tree at once (a camera's rate together
    # with its detector's setting), one publisher at a time where a tree has too many
    current: Classes = {p: options[p][0] for p in publishers}
    t_run = time.monotonic()
    start: State | None = None  # greedy+ (Problem 1): the greedy's state, greedy+'s start on a fleet
    restricted = _restricted(system, choices, current)
    if restricted is not None and method == Method.GREEDY_PLUS and problem == Problem.PERFORMANCE:
        start, why = run_greedy(system, problem, restricted)
        tried[(Method.GREEDY, tuple(current[p] for p in publishers))] = greedy_plan(start, why)
        start = start if why is None else None
    best = run(current, Method.GREEDY)
    first = dict(current)
    t_run = time.monotonic() - t_run  # one greedy run: what a try of the passes costs
    moves: list[list[Classes]] = []
    for members in _trees(system, publishers):
        joint = [dict(zip(members, pick, strict=True)) for pick in itertools.product(*(options[p] for p in members))]
        if len(joint) <= ENUMERATE:
            moves.append(joint)
        else:
            moves.extend([{p: cls} for cls in options[p]] for p in members)
    # greedy+ (Problem 1) where a pass of whole greedy runs would cost more than
    # PLUS_PASS_MAX_S (a fleet): no passes; greedy+ from every publisher at its cheapest, its
    # relocation moves (:mod:`perfros_bag.solver.fleetmoves`) and its rate moves (valued on
    # the computers they touch)
    rates = (method == Method.GREEDY_PLUS and problem == Problem.PERFORMANCE
             and t_run * sum(len(m) for m in moves) > PLUS_PASS_MAX_S)
    # a fleet of alike robots: first every tree at its k-th option together (one run each),
    # the best of them the start of the tree-by-tree moves
    if not rates and len(moves) > 1 and len({len(m) for m in moves}) == 1:
        for k in range(len(moves[0])):
            if late():
                break
            trial = {**current}
            for move in moves:
                trial.update(move[k])
            plan = run(trial, Method.GREEDY)
            if better_plan(plan, best, problem):
                best, current = plan, trial
    passes_until = time.monotonic() if rates else deadline
    for _ in range(PASSES):
        changed = False
        for move in moves:
            for change in move:
                if time.monotonic() > passes_until:
                    break
                trial = {**current, **change}
                plan = run(trial, Method.GREEDY)
                if better_plan(plan, best, problem):
                    best, current, changed = plan, trial, True
        if not changed:
            break
    if method == Method.GREEDY:
        return _best(tried.values(), problem, method, system)
    if rates:
        plus = _greedy_plus_rates(system, choices, current, moves, min(deadline, time.monotonic() + PLUS_RATES_S),
                                  start if current == first else None)
        if plus is not None:  # greedy+ from the greedy's plan on ``current``: never below it
            return _best([plus], problem, method, system)
    run(current, method)  # greedy+ on the best assignment the search found
    return _best([plan for (how, _), plan in tried.items() if how == method] or list(tried.values()),
                 problem, method, system)


def _greedy_plus_rates(system: System, choices: dict[str, list[Choice]], current: Classes,
                       moves: list[list[Classes]], deadline: float, start: State | None = None) -> Plan | None:
    """greedy+ on the rate classes ``current``, then rate moves until none improves or the
    deadline: a move sets one tree's publishers (``moves``' options) and places the nodes
    whose choices follow (their groups anywhere allowed, when at most :data:`ENUMERATE`
    placements), valued by the knapsack optimum of the computers it touches. None when
    greedy+ finds no plan on ``current``. ``start``: the greedy's state on ``current``, when
    the caller has it (changed in place)."""
    from perfros_bag.solver.local import run_greedy_plus  # deferred: numpy, for greedy+ only

    restricted = _restricted(system, choices, current)
    if restricted is None:
        return None
    improver = run_greedy_plus(system, Problem.PERFORMANCE, restricted,
                               time_budget=PLUS_SHARE * max(deadline - time.monotonic(), 0.0), start=start)
    if isinstance(improver, str):
        return None
    _rate_moves(improver, system, choices, dict(current), moves, deadline)
    improver.run()
    return improver.s.plan(Method.GREEDY_PLUS)


def _following(system: System, publishers: Iterable[str]) -> list[str]:
    """The publishers and every node their rates drive, in node order."""
    out = set(publishers)
    for name in system.flow_order:
        if system.flow_parent[name] in out:
            out.add(name)
    return [n.name for n in system.nodes if n.name in out]


def _rate_moves(improver: Improver, system: System, choices: dict[str, list[Choice]], current: Classes,
                moves: list[list[Classes]], deadline: float) -> None:
    """Best-improvement rate moves on ``improver``'s state (see :func:`_greedy_plus_rates`),
    sweeping the trees until a sweep changes nothing or the deadline. A following group may
    stay, go to a robot it may use, or to one of the :data:`MOVE_SERVERS` allowed servers
    with the most free CPU."""
    from perfros_bag.solver.state import ladder

    s = improver.s
    changed = True
    while changed and time.monotonic() < deadline:
        changed = False
        for move, nodes in [(move, _following(system, move[0])) for move in moves]:
            if time.monotonic() > deadline:
                return
            gis = sorted({s.group_of[n] for n in nodes})
            here = {c for n in nodes if (c := s.place[n]) is not None}
            targets = []
            for gi in gis:
                servers = sorted((c for c in s.group_allowed[gi] if s.kind[c] == "server"), key=lambda c: -s.free(c))
                keep = {s.place[s.groups[gi][0]], *servers[:MOVE_SERVERS]}
                targets.append([c for c in s.group_allowed[gi] if c in keep or s.kind[c] != "server"])
            placements = list(itertools.product(*targets))
            if len(placements) > ENUMERATE:
                placements = [tuple(s.place[s.groups[gi][0]] or "" for gi in gis)]
            best: tuple[float, Classes, dict[str, str], dict[str, list[Choice]] | None] | None = None
            now = tuple(s.place[s.groups[gi][0]] for gi in gis)
            for change in move:
                same = all(current[p] == cls for p, cls in change.items())  # then a move of place alone
                restricted = _restricted(system, choices, {**current, **change}) if change else None
                if change and restricted is None:
                    continue
                lads = {n: ladder(restricted[n]) if restricted else s.ladder[n] for n in nodes}
                for combo in placements:
                    if same and combo == now:
                        continue
                    where = {n: combo[gis.index(s.group_of[n])] for n in nodes}
                    gain = 0.0
                    for c in here | set(combo):
                        base = [m for m in s.members[c] if m not in where]
                        gain += improver.trial_value(c, base, {n: lads[n] for n in nodes if where[n] == c})
                        gain -= improver.current(s.members[c])
                    if gain > 1e-9 and (best is None or gain > best[0] + 1e-12):
                        best = (gain, change, where, restricted)
            if best is not None and _apply_rates(improver, best[2], best[3]):
                current.update(best[1])
                changed = True


def _apply_rates(improver: Improver, where: dict[str, str], restricted: dict[str, list[Choice]] | None) -> bool:
    """Move the following nodes ``where`` with their choices from ``restricted`` (None: their
    own), every computer touched at its best settings, in one checked change; undone when
    it fails."""
    s = improver.s
    nodes = list(where)
    comps = {s.place[n] for n in nodes} | set(where.values())
    snap, old = s.snapshot(), {n: list(s.ladder[n]) for n in nodes}
    if s.change({n: (None, 0) for n in nodes}) is not None:
        return False
    for n in nodes:
        if restricted is not None:
            s.set_ladder(n, restricted[n])
    changes: dict[str, tuple[str | None, int]] = {}
    for c in comps:
        assert c is not None
        held = sorted(s.members[c] | {n for n in nodes if where[n] == c}, key=s.order.__getitem__)
        for m, k in improver.levels(c, held).items():
            changes[m] = (c, k)
    if any(n not in changes for n in nodes) or s.change(changes) is not None:
        for n in nodes:
            s.place[n] = None
            s.set_ladder(n, old[n])
        s.restore(snap)
        return False
    if restricted is not None:
        improver.relevel(nodes)
    return True


def _trees(system: System, publishers: list[str]) -> list[list[str]]:
    """The publishers grouped by the source their data comes from, in ``publishers`` order."""
    groups: dict[str, list[str]] = {}
    for p in publishers:
        root = p
        while root in system.flow_parent:
            root = system.flow_parent[root]
        groups.setdefault(root, []).append(p)
    return list(groups.values())


def _inner(system: System, problem: Problem, choices: dict[str, list[Choice]], method: Method,
           time_budget: float | None) -> Plan:
    if method == Method.GREEDY_PLUS:
        from perfros_bag.solver.local import solve_greedy_plus  # deferred: numpy, for greedy+ only

        return solve_greedy_plus(system, problem, choices, time_budget=time_budget)
    return solve_greedy(system, problem, choices)


def _output(system: System, publisher: str, choice: Choice) -> tuple[float, ...]:
    """The rates a publisher's choice gives the nodes it drives, in their order."""
    return tuple(system.input_hz(child, choice) for child in system.flow_children[publisher])


def _class_options(system: System, choices: Mapping[str, list[Choice]]) -> dict[str, list[Pick]]:
    """Per publisher, what fixes its rates: a source's rate classes, the lowest total rate
    first; a driven publisher's own settings, the least CPU per input message first."""
    out: dict[str, list[Pick]] = {}
    for p in system.flow_children:
        if p in system.flow_parent:
            node = system.node[p]
            own = sorted({ch.setting for ch in choices[p] if ch.setting is not None},
                         key=lambda j: (node.settings[j].cpu_per_hz or 0.0, node.settings[j].cpu, j))
            out[p] = list(own)
        else:
            rates: list[tuple[float, ...]] = sorted({_output(system, p, ch) for ch in choices[p]},
                                                    key=lambda c: (sum(c), c))
            out[p] = list(rates)
    return out


def _restricted(system: System, choices: Mapping[str, list[Choice]],
                classes: Classes) -> dict[str, list[Choice]] | None:
    """The choices consistent with ``classes``: a source publisher's in its rate class, a
    driven node's at the rate its publisher then gives it (and a driven publisher's at its
    own setting); None when a node has none left."""
    out: dict[str, list[Choice]] = {}
    given: dict[str, tuple[float, ...]] = {}  # publisher -> the rates it gives its children
    for name, options in choices.items():  # the sources first: driven nodes below, in flow order
        if name in system.flow_parent:
            continue
        kept = options
        cls = classes.get(name)
        if isinstance(cls, tuple):
            kept = [ch for ch in kept if _output(system, name, ch) == cls]
            given[name] = cls
        if not kept:
            return None
        out[name] = kept
    for name in system.flow_order:
        parent = system.flow_parent[name]
        rate = given[parent][system.flow_children[parent].index(name)]
        kept = [ch for ch in choices[name] if ch.input_hz == rate]
        if name in classes:
            kept = [ch for ch in kept if ch.setting == classes[name]]
            if kept:
                given[name] = _output(system, name, kept[0])
        if not kept:
            return None
        out[name] = kept
    return {name: out[name] for name in choices}


def _best(plans: Iterable[Plan | None], problem: Problem, method: Method, system: System) -> Plan:
    found = list(plans)
    best: Plan | None = None
    for plan in found:
        if better_plan(plan, best, problem):
            best = plan
    if best is not None:
        best.method = method
        return best
    reasons = [p.reason for p in found if p is not None and p.reason]
    why = reasons[0] if reasons else "no setting of the driven nodes fits any rate their inputs can take"
    return Plan.infeasible(problem, method, f"{why} (at every input rate tried)", system=system.source)
