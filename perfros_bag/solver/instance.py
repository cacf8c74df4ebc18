"""The instance the exact methods share (:mod:`~perfros_bag.solver.exact`, the fleet
decomposition :mod:`~perfros_bag.solver.decompose`, the frontier's enumeration): a
system's candidate choices pruned once, its coresidence groups with the computers that can
hold them, each link's form (cut or pairs), the edges' crossings, the face-value
infeasibility checks, the mapping of a plan onto the pruned model (a MIP start) and the
trivial bound. No solver runs here: it imports nothing but the system model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from perfros_bag.errors import InputError
from perfros_bag.system.plan import Assignment, Plan
from perfros_bag.system.rules import computer_loads, server_sizes
from perfros_bag.system.types import Choice, Edge, Problem, System

__all__ = ["EPS", "Group", "Instance", "Progress", "active_links", "crossing_always", "crossings", "link_name",
           "load_bounds", "prepare_instance", "start_assignment", "trivial_bound", "within_trivial_bound"]

#: the tolerance on CPU and bandwidth sums (pruning, face-value checks, active links)
EPS = 1e-9
_INF = math.inf

#: ``progress(incumbent or None, bound, elapsed seconds)``: the exact method's fleet solver
#: (:mod:`perfros_bag.solver.decompose`) calls it as its plan or its bound improves
Progress = Callable[[float | None, float, float], None]


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
    # edge (src, dst) -> links it always crosses, links it may cross (see crossings)
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


def crossings(inst: Instance, edge: Edge) -> tuple[frozenset[int], frozenset[int]]:
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


def crossing_always(inst: Instance, edge: Edge, li: int) -> bool | None:
    """True when the edge crosses link ``li`` wherever its ends go, False when it never
    can, None otherwise."""
    always, maybe = crossings(inst, edge)
    return True if li in always else (None if li in maybe else False)


def link_name(system: System, li: int) -> str:
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
    forced_load, forced_edges = load_bounds(inst, forced=True)
    for li, link in enumerate(system.links):
        if forced_load[li] > link.bandwidth_kBps + EPS:
            return (f"bandwidth: {link_name(system, li)} carries at least {forced_load[li]:g} kB/s "
                    f"(edges {', '.join(forced_edges[li])} must cross it) but has {link.bandwidth_kBps:g}")
    for m in system.media:
        load = system.medium_load(forced_load, m.name)
        if load > m.bandwidth_kBps + EPS:
            return (f"bandwidth: medium {m.name} carries at least {load:g} kB/s on its links "
                    f"(edges that must cross them) but has {m.bandwidth_kBps:g}")
    return None


def load_bounds(inst: Instance, *, forced: bool) -> tuple[list[float], list[list[str]]]:
    """Per link, a bound on its load and the edges (``src->dst``) in it: with ``forced``,
    the least load (the edges that cross it wherever their ends go, at their publishers'
    least traffic); otherwise the most (every edge that may cross it, at the most traffic)."""
    system = inst.system
    bound = [0.0] * len(system.links)
    edges: list[list[str]] = [[] for _ in system.links]
    for e in system.edges:
        always, maybe = crossings(inst, e)
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



def active_links(inst: Instance) -> set[int]:
    """Links (by index) whose bandwidth, or whose medium's, could ever be exceeded: the
    others need no rows at all. Computed once per instance."""
    if inst.active is not None:
        return inst.active
    system = inst.system
    potential, _ = load_bounds(inst, forced=False)
    active = {li for li, link in enumerate(system.links) if potential[li] > link.bandwidth_kBps + EPS}
    for m in system.media:
        if system.medium_load(potential, m.name) > m.bandwidth_kBps + EPS:
            active.update(system.medium_links[m.name])
    inst.active = active
    return active



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

