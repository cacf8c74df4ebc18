"""MIP starts for the exact methods: a heuristic's plan as an :class:`Assignment`
(:func:`start_of`), and mapped onto the pruned model of an :class:`Instance`
(:func:`greedy_start`, :func:`plus_start`, through ``instance.start_assignment``)."""

from __future__ import annotations

import math
from collections.abc import Mapping

from perfros_bag.solver.flow import solve_heuristic
from perfros_bag.solver.instance import Instance, start_assignment
from perfros_bag.solver.local import solve_greedy_plus
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.types import Choice

__all__ = ["PLUS_START_MAX_S", "greedy_start", "plus_start", "start_of"]

#: greedy+ as the exact solvers' last resort for a plan: its local search at most this long
PLUS_START_MAX_S = 2.0


def start_of(plan: Plan, choices: Mapping[str, list[Choice]]) -> Assignment | None:
    """A plan of these ``choices`` as an :class:`Assignment` (a MIP start); None when a node's
    CPU level is not one of its choices."""
    placement: dict[str, str] = {}
    chosen: dict[str, Choice] = {}
    for name, pn in plan.nodes.items():
        options = choices.get(name, [])
        ch = next((c for c in options if math.isclose(c.cpu, pn.cpu, rel_tol=1e-9, abs_tol=1e-6)), None)
        if ch is None:
            return None
        placement[name], chosen[name] = pn.computer, ch
    return Assignment(placement, chosen, {})


def greedy_start(inst: Instance, choices: dict[str, list[Choice]],
                 budget: float | None = None) -> tuple[Assignment, dict[str, int]] | None:
    """The paper's greedy's plan mapped onto the pruned model, None when it finds none.
    ``budget``: seconds for its search of the rates along a data flow (None: its own default)."""
    plan = solve_heuristic(inst.system, inst.problem, choices, Method.GREEDY, time_budget=budget)
    raw = start_of(plan, choices) if plan.status != Status.INFEASIBLE else None
    return start_assignment(inst, raw) if raw is not None else None


def plus_start(inst: Instance, choices: dict[str, list[Choice]],
               budget: float = PLUS_START_MAX_S) -> tuple[Assignment, dict[str, int]] | None:
    """greedy+'s plan (its local search within ``budget`` seconds) mapped onto the exact
    solvers' pruned model (``instance.start_assignment``), None when it finds none: a plan
    where the paper's greedy gets stuck (a binding network), for the decomposition's first
    incumbent and the MILP's answer when its time limit comes first."""
    plan = solve_greedy_plus(inst.system, inst.problem, choices, time_budget=max(budget, 0.0))
    raw = start_of(plan, choices) if plan.status != Status.INFEASIBLE else None
    return start_assignment(inst, raw) if raw is not None else None
