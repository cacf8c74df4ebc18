"""Brute force over every (choice, computer) per node: the reference optimum for tests.

Exhaustive depth-first enumeration; it prunes only partial assignments that already break
a CPU or coresidence constraint (which cannot become feasible again), so the optimum is
exact. Tiny instances only: more than :data:`LIMIT` combinations is refused.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

from perfros_bag.errors import InputError
from perfros_bag.solver.budgets import budgeted, no_plan_within, violation
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.rules import build_plan, server_sizes, weighted_performance
from perfros_bag.system.types import Choice, Problem, System

LIMIT = 1_000_000
EPS = 1e-9


def combinations(system: System, choices: dict[str, list[Choice]]) -> int:
    """How many (choice, computer) combinations an exhaustive search visits at most (a
    driven node's input rate follows its publisher: only its own settings multiply)."""
    return math.prod(_own_count(choices[n.name]) * len(system.allowed(n.name)) for n in system.nodes)


def _own_count(options: list[Choice]) -> int:
    driven = {ch.setting for ch in options if ch.input_hz is not None}
    return len(driven) if driven else len(options)


def solve_bruteforce(system: System, problem: Problem, choices: dict[str, list[Choice]]) -> Plan:
    total = combinations(system, choices)
    if total > LIMIT:
        raise InputError(system.source, f"too large for bruteforce: {total:.3g} combinations (limit {LIMIT:.0e}); "
                                        "the exact solver takes any size")
    nodes = [n.name for n in system.nodes]
    comps = system.computer
    # Problem 2 servers are sized to their load (bounded by max_capacity); Problem 1 and robots are fixed.
    cap = system.capacities(problem)
    group_of: dict[str, str] = {}
    for g in system.coresidence_groups:
        for n in g:
            group_of[n] = g[0]

    budgets = bool(budgeted(system))
    load = {c: 0.0 for c in comps}
    place: dict[str, str] = {}
    pick: dict[str, Choice] = {}
    group_at: dict[str, str] = {}
    best: list[tuple[float, dict[str, str], dict[str, Choice]]] = []

    def value() -> float:
        if problem == Problem.PERFORMANCE:
            return weighted_performance(system, pick)
        return -sum(load[c.name] for c in system.computers if c.kind == "server")

    def options(i: int) -> Iterator[tuple[str, Choice]]:
        """Node ``i``'s (computer, choice) pairs that keep CPU, coresidence and the data
        flow with the nodes before it."""
        n = nodes[i]
        fixed = group_at.get(group_of[n])
        for comp in system.allowed(n):
            if fixed is not None and comp != fixed:
                continue
            for ch in choices[n]:
                if load[comp] + ch.cpu > cap[comp] + EPS:
                    continue
                if system.has_flow and system.flow_violation({**pick, n: ch}) is not None:
                    continue
                yield comp, ch

    def undo(i: int) -> None:
        n = nodes[i]
        load[place[n]] -= pick[n].cpu
        if opened[i]:
            del group_at[group_of[n]]
        del place[n], pick[n]

    # depth-first with an explicit stack (one iterator per placed node): no recursion limit
    opened = [False] * len(nodes)  # did node i's placement fix its coresidence group's computer?
    stack = [options(0)] if nodes else []
    if not nodes:
        best[:] = [(value(), {}, {})]
    while stack:
        i = len(stack) - 1
        if nodes[i] in place:
            undo(i)
        step = next(stack[-1], None)
        if step is None:
            stack.pop()
            continue
        n = nodes[i]
        comp, ch = step
        load[comp] += ch.cpu
        place[n], pick[n] = comp, ch
        opened[i] = group_of[n] not in group_at
        group_at.setdefault(group_of[n], comp)
        if i + 1 < len(nodes):
            stack.append(options(i + 1))
            continue
        if system.network_violation(place, pick, EPS) is None and (
                not budgets or violation(system, problem, Assignment(place, pick, {})) is None):
            v = value()
            if not best or v > best[0][0] + EPS:
                best[:] = [(v, dict(place), dict(pick))]
    if not best:
        constraints = f"the CPU, bandwidth, residence and coresidence constraints ({total} combinations searched)"
        reason = (no_plan_within(system, choices, f"no assignment that satisfies {constraints}") if budgets
                  else f"no assignment satisfies {constraints}")
        return Plan.infeasible(problem, Method.BRUTEFORCE, reason, system=system.source)
    v, placement, choice = best[0]
    capacities = server_sizes(system, placement, choice) if problem == Problem.SERVER_CAPACITY else {}
    plan = build_plan(system, Assignment(placement, choice, capacities), problem=problem, method=Method.BRUTEFORCE,
                      status=Status.OPTIMAL)
    plan.bound = plan.objective
    return plan
