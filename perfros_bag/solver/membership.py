"""``membership: choose``: a plan may run a container's hosted nodes standalone.

A hosted node (system.yaml ``container:``, a nodelet in its manager) either stays in its
container, so on its computer, or runs in a process of its own (ROS 1 ``nodelet
standalone``) anywhere its residence allows, paying the copy of its input it then receives
(:meth:`~perfros_bag.system.types.System.copy_charge`). Which nodes leave is a decision
on a handful of nodes, so it is taken by enumeration: every subset of the nodes that may
leave gives one system (:meth:`~perfros_bag.system.types.System.freed`), each is solved as
it is by the method asked, and the best plan wins.

This is exact whenever the method is: a plan of the true model runs each hosted node either
in its container (the subset without it covers that plan) or standalone (the subset with it,
at the same CPU). A freed node that a plan still puts on its container's computer is loaded
into the container after all: its copy is taken off its CPU and its computer's
(:func:`restate`), which keeps every constraint (less CPU) and never changes Σ w·P.
"""

from __future__ import annotations

import itertools
import time
import warnings
from collections.abc import Callable

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.system.plan import Plan, Status, better_plan
from perfros_bag.system.types import Problem, System

__all__ = ["MAX_FREEABLE", "freeable", "restate", "solve_membership"]

#: at most this many hosted nodes may leave their containers (2^6 = 64 solves)
MAX_FREEABLE = 6


def freeable(system: System) -> tuple[str, ...]:
    """The hosted nodes a plan may run standalone: those of a container with a measured copy
    price. The others stay in their container, with a warning naming them."""
    out = list(system.may_leave)
    kept = [n.name for n in system.nodes if n.container is not None and n.name not in out]
    if kept:
        warnings.warn(PerfrosWarning(
            f"{system.source}: membership: choose: node(s) {', '.join(kept)} stay in their container: a node runs "
            "standalone only when its container has a measured copy_cpu_per_MBps"),
            stacklevel=3)
    if len(out) > MAX_FREEABLE:
        raise InputError(system.source, f"membership: choose: {len(out)} hosted nodes may leave their containers "
                                        f"({', '.join(out)}): 2^{len(out)} plans to solve, at most "
                                        f"{MAX_FREEABLE} nodes (fix the others with membership: keep)")
    return tuple(out)


def restate(system: System, variant: System, plan: Plan) -> Plan:
    """``variant``'s plan (``variant``: ``system.freed(...)``) stated on ``system``: each freed
    node away from its container's computer marked ``standalone``; one on that computer loaded
    into the container after all, its copy (the charge ``freed`` put on it) taken off its CPU
    and its computer's."""
    plan.system = system.source
    if plan.status == Status.INFEASIBLE:
        return plan
    for name, (per_hz, fixed) in variant.charged.items():
        pn = plan.nodes.get(name)
        host = system.node[name].container
        if pn is None or host is None or host not in plan.nodes:
            continue
        if pn.computer != plan.nodes[host].computer:
            pn.standalone = True
            continue
        taken = per_hz * (pn.input_hz or 0.0) + fixed
        pn.cpu -= taken
        pc = plan.computers.get(pn.computer)
        if pc is not None:
            pc.cpu -= taken
    return plan


def solve_membership(system: System, problem: Problem, solve_one: Callable[[System, float | None], Plan],
                     time_limit: float | None = None) -> Plan:
    """The best of ``solve_one(variant, seconds)`` over every subset of :func:`freeable`
    nodes, the subsets ordered from none freed (the kept membership first); each solve
    gets an equal share of what is left of ``time_limit``. The plan is ``optimal`` when
    every variant's is (or is infeasible), its bound the best of the variants' bounds."""
    names = freeable(system)
    subsets = [c for k in range(len(names) + 1) for c in itertools.combinations(names, k)]
    start = time.perf_counter()
    best: Plan | None = None
    first: Plan | None = None
    proven, bounds = True, []  # bounds: None once a feasible variant has none (a heuristic's)
    bounds_known = True
    for i, subset in enumerate(subsets):
        left = None if time_limit is None else max(time_limit - (time.perf_counter() - start), 0.0) / (len(subsets) - i)
        variant = system.freed(subset)
        plan = restate(system, variant, solve_one(variant, left))
        first = first or plan
        if plan.status == Status.INFEASIBLE:
            continue
        proven = proven and plan.status == Status.OPTIMAL
        if plan.bound is None:
            bounds_known = False
        else:
            bounds.append(plan.bound)
        if better_plan(plan, best, problem):
            best = plan
    if best is None:
        assert first is not None
        return first
    best.status = Status.OPTIMAL if proven else Status.FEASIBLE
    if not bounds_known:
        best.bound = None
    elif bounds:
        best.bound = max(bounds) if problem == Problem.PERFORMANCE else min(bounds)
    best.extra["membership"] = {"freeable": list(names), "plans_solved": len(subsets),
                                "standalone": sorted(best.standalone)}
    return best
