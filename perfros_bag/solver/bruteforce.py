"""Brute force over every (choice, computer) per node: the reference optimum for tests.

Exhaustive depth-first enumeration; it prunes only partial assignments that already break
a CPU or coresidence constraint (which cannot become feasible again), so the optimum is
exact. Tiny instances only: more than :data:`LIMIT` combinations is refused.
"""

from __future__ import annotations

import math

from perfros_bag.errors import InputError
from perfros_bag.system.plan import Assignment, Plan, build_plan, infeasible_plan
from perfros_bag.system.types import Choice, System

LIMIT = 1_000_000
EPS = 1e-9


def combinations(system: System, choices: dict[str, list[Choice]]) -> int:
    """How many (choice, computer) combinations an exhaustive search visits at most."""
    return math.prod(len(choices[n.name]) * len(system.allowed(n.name)) for n in system.nodes)


def solve_bruteforce(system: System, problem: int, choices: dict[str, list[Choice]]) -> Plan:
    total = combinations(system, choices)
    if total > LIMIT:
        raise InputError(system.source, f"too large for bruteforce: {total:.3g} combinations (limit {LIMIT:.0e}); "
                                        "use --method exact")
    nodes = [n.name for n in system.nodes]
    comps = system.computer
    # Problem 2 servers are sized to their load (bounded by max_capacity); Problem 1 and robots are fixed.
    cap: dict[str, float] = {}
    for c in system.computers:
        if problem == 2 and c.kind == "server":
            cap[c.name] = c.max_capacity if c.max_capacity is not None else math.inf
        else:
            cap[c.name] = c.capacity if c.capacity is not None else 0.0
    group_of: dict[str, str] = {}
    for g in system.coresidence_groups:
        for n in g:
            group_of[n] = g[0]
    edges = list(system.edges)

    load = {c: 0.0 for c in comps}
    place: dict[str, str] = {}
    pick: dict[str, Choice] = {}
    group_at: dict[str, str] = {}
    best: list[tuple[float, dict[str, str], dict[str, Choice]]] = []

    def network_ok() -> bool:
        link = [0.0] * len(system.links)
        for e in edges:
            a, b = place[e.src], place[e.dst]
            if a == b:
                continue
            route = system.route(a, b)
            if route is None:
                return False
            bw = system.edge_bandwidth(e, pick[e.src])
            for li in route:
                link[li] += bw
        for i, lk in enumerate(system.links):
            if link[i] > lk.bandwidth_kBps + EPS:
                return False
        for m in system.media:
            if sum(link[i] for i, lk in enumerate(system.links) if lk.medium == m.name) > m.bandwidth_kBps + EPS:
                return False
        return True

    def value() -> float:
        if problem == 1:
            return sum(system.node[n].weight * pick[n].performance for n in nodes)
        return -sum(load[c.name] for c in system.computers if c.kind == "server")

    def visit(i: int) -> None:
        if i == len(nodes):
            if not network_ok():
                return
            v = value()
            if not best or v > best[0][0] + EPS:
                best[:] = [(v, dict(place), dict(pick))]
            return
        n = nodes[i]
        g = group_of[n]
        fixed = group_at.get(g)
        for comp in system.allowed(n):
            if fixed is not None and comp != fixed:
                continue
            for ch in choices[n]:
                if load[comp] + ch.cpu > cap[comp] + EPS:
                    continue
                load[comp] += ch.cpu
                place[n], pick[n] = comp, ch
                if fixed is None:
                    group_at[g] = comp
                visit(i + 1)
                if fixed is None:
                    del group_at[g]
                load[comp] -= ch.cpu
                del place[n], pick[n]

    visit(0)
    if not best:
        return infeasible_plan(problem, "bruteforce",
                               f"no assignment satisfies the CPU, bandwidth, residence and coresidence "
                               f"constraints ({total} combinations searched)", system=system.source)
    v, placement, choice = best[0]
    capacities: dict[str, float] = {}
    if problem == 2:
        for c in system.computers:
            if c.kind == "server":
                capacities[c.name] = sum(choice[n].cpu for n in nodes if placement[n] == c.name)
    plan = build_plan(system, Assignment(placement, choice, capacities), problem=problem, method="bruteforce",
                      status="optimal")
    plan.bound = plan.objective
    return plan
