"""``solve``: a system, a problem and a method -> a :class:`Plan` (the dispatch described
in :mod:`perfros_bag.solver`): the candidate choices, the headroom kept free (a share of
every computer, or each node's measured CPU error), the method, and for ``exact`` the
choice between the fleet decomposition and the MILP with or without a greedy+ start.

The exact methods (numpy, HiGHS) are imported when they run: greedy, greedy+ and brute
force need neither, and a missing HiGHS is an :class:`InputError` of ``exact`` alone.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping

from perfros_bag.errors import InputError
from perfros_bag.solver.bruteforce import solve_bruteforce
from perfros_bag.solver.budgets import (
    budgeted,
    impossible_budget,
    restate_chains,
    solve_with_cuts,
    within_budgets,
)
from perfros_bag.solver.candidates import fixed_choices
from perfros_bag.solver.flow import solve_heuristic
from perfros_bag.solver.instance import (
    Progress,
    active_links,
    prepare_instance,
    trivial_bound,
    within_trivial_bound,
)
from perfros_bag.system.cpuerror import FAIR_SHARE, choice_error, states_errors
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.types import Choice, Problem, System

__all__ = ["AUTO", "DECOMPOSE_COLUMNS", "METHODS", "START_COLUMNS", "START_SHARE", "check_headroom",
           "exact_columns", "inflate_choices", "solve", "with_headroom"]

#: the solvers' names (``Method`` values), in the order the docs list them
METHODS: tuple[str, ...] = tuple(Method)

#: ``headroom`` that keeps each node's measured CPU error free (:mod:`perfros_bag.system.cpuerror`)
AUTO = "auto"


def check_headroom(headroom: object) -> float | str:
    """``headroom`` when it is :data:`AUTO` or a number in [0, 1); else an
    :class:`~perfros_bag.errors.InputError`."""
    if headroom == AUTO:
        return AUTO
    if isinstance(headroom, bool) or not isinstance(headroom, int | float) or not 0.0 <= headroom < 1.0:
        raise InputError(None, f"headroom must be in [0, 1), got {headroom!r} "
                               f"(or {AUTO!r}: the model's measured errors)")
    return float(headroom)


def solve(system: System, problem: int, method: str, *, resolution: float = 1.0,
          settings: Mapping[str, float] | None = None, time_limit: float | None = None,
          progress: Progress | None = None, headroom: float | str = 0.0) -> Plan:
    """Solve Problem ``problem`` (1 or 2) with ``method`` (a :class:`Method`); the
    returned plan carries ``solve_s``.

    ``headroom`` (in [0, 1)): the share of every computer's capacity the plan keeps free
    (:func:`with_headroom`); each computer's ``margin`` in the plan says how much.
    ``headroom="auto"`` (:data:`AUTO`): every node's choice needs its CPU plus its measured
    error (:func:`inflate_choices`) for the solve; the plan states the model's CPU and each
    computer's ``margin``, the sum of its nodes' errors.

    An infeasible instance gives a plan with status ``infeasible`` and a ``reason`` (not an
    exception: :meth:`Plan.require_feasible` turns it into one); bad input (unknown method,
    a Problem 1 server without capacity) raises :class:`~perfros_bag.errors.InputError`.
    """
    if isinstance(problem, bool) or problem not in tuple(Problem):
        raise InputError(system.source, f"problem must be 1 or 2, got {problem!r}")
    if method not in METHODS:
        raise InputError(None, f"unknown method {method!r} (one of {', '.join(METHODS)})")
    the_problem, the_method = Problem(problem), Method(method)
    system.capacities(the_problem)  # every capacity the problem needs is there
    headroom = check_headroom(headroom)
    if not isinstance(headroom, str) and headroom > 0:
        plan = solve(with_headroom(system, headroom), problem, method, resolution=resolution, settings=settings,
                     time_limit=time_limit, progress=progress)
        return _give_back(system, plan, headroom)
    if system.membership == "choose":  # each freed variant solved as it is, the best kept
        from perfros_bag.solver.membership import solve_membership

        def one(variant: System, seconds: float | None) -> Plan:
            return solve(variant, problem, method, resolution=resolution, settings=settings, time_limit=seconds,
                         progress=progress, headroom=headroom)

        plan = solve_membership(system, the_problem, one, time_limit)
        plan.method = the_method
        return plan
    start = time.perf_counter()  # --time-limit counts from here: the choices, the set-up and the solve
    deadline = None if time_limit is None else start + time_limit
    choices = fixed_choices(system, the_problem, settings, resolution)
    real: dict[str, list[Choice]] = {}
    if headroom == AUTO:  # every choice raised by its measured error; the plan stated on the model after
        choices, real = inflate_choices(system, choices)
    plan = _dispatch(system, the_problem, the_method, choices, deadline, progress)
    plan.solve_s = time.perf_counter() - start
    plan.method = the_method
    if plan.system is None:
        plan.system = system.source
    if headroom == AUTO:
        _give_back_errors(system, plan, choices, real)
    return plan


def inflate_choices(system: System, choices: Mapping[str, list[Choice]]
                    ) -> tuple[dict[str, list[Choice]], dict[str, list[Choice]]]:
    """Each choice with its CPU raised by its measured error
    (:func:`perfros_bag.system.cpuerror.choice_error`), sorted by that CPU and re-indexed;
    and, position by position, the choice it was made from."""
    inflated: dict[str, list[Choice]] = {}
    real: dict[str, list[Choice]] = {}
    for name, options in choices.items():
        node = system.node[name]
        pairs = sorted(((dataclasses.replace(c, cpu=c.cpu + choice_error(node, c)), c) for c in options),
                       key=lambda pair: pair[0].cpu)
        inflated[name] = [dataclasses.replace(up, index=i) for i, (up, _) in enumerate(pairs)]
        real[name] = [c for _, c in pairs]
    return inflated, real


def _give_back_errors(system: System, plan: Plan, inflated: Mapping[str, list[Choice]],
                      real: Mapping[str, list[Choice]]) -> None:
    """A plan solved on :func:`inflate_choices`' choices, stated on the model: each node's
    ``cpu`` its real choice's; each computer's ``cpu`` the sum of those and its ``margin`` the
    sum of its nodes' errors (a Problem 2 server sized to load + margin). An infeasible plan's
    reason says the errors were kept free; a model without any error keeps the floor only."""
    plan.extra["headroom"] = AUTO
    if plan.status == Status.INFEASIBLE:
        plan.reason = f"{plan.reason} (with each node's measured CPU error kept free: headroom auto)"
        return
    if not states_errors(system):
        plan.reason = (f"headroom auto: the model states no cpu_error, so each node keeps only the floor, "
                       f"{100 * FAIR_SHARE:g} % of its CPU, free")
    load = {c.name: 0.0 for c in system.computers}
    margin = {c.name: 0.0 for c in system.computers}
    for node in system.nodes:
        pn = plan.nodes[node.name]
        k = next((i for i, c in enumerate(inflated[node.name])
                  if math.isclose(c.cpu, pn.cpu, rel_tol=1e-9, abs_tol=1e-9)
                  and math.isclose(c.performance, pn.performance, rel_tol=1e-9, abs_tol=1e-9)
                  and _same_number(c.value, pn.value)
                  and (node.input is None or _same_number(c.input_hz, pn.input_hz))), None)
        if k is None:  # pragma: no cover - every solver plans one of the choices it was given
            raise AssertionError(f"node {node.name!r}: the plan's CPU {pn.cpu:g} is none of its inflated choices")
        up, own = inflated[node.name][k], real[node.name][k]
        pn.cpu = own.cpu
        load[pn.computer] += own.cpu
        margin[pn.computer] += up.cpu - own.cpu
    sized = plan.problem == Problem.SERVER_CAPACITY
    for name, pc in plan.computers.items():
        pc.cpu = round(load[name], 9)
        pc.margin = round(margin[name], 9)
        if sized and system.computer[name].kind == "server":
            pc.capacity = pc.cpu + pc.margin
    restate_chains(system, plan)


def _same_number(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


def with_headroom(system: System, headroom: float) -> System:
    """The system with every computer's capacity (and a server's ``max_capacity``) cut to
    ``1 - headroom`` of it: what a plan may fill when it keeps ``headroom`` free."""
    keep = 1.0 - headroom
    computers = tuple(dataclasses.replace(
        c, capacity=None if c.capacity is None else c.capacity * keep,
        max_capacity=None if c.max_capacity is None else c.max_capacity * keep) for c in system.computers)
    return dataclasses.replace(system, computers=computers)


def _give_back(system: System, plan: Plan, headroom: float) -> Plan:
    """A plan solved on :func:`with_headroom`'s system, stated on ``system``: each computer
    its own capacity (a Problem 2 server: its load over ``1 - headroom``) and its
    ``margin``, the CPU units kept free; Problem 2's objective and bound the sized capacity."""
    plan.extra["headroom"] = headroom
    if plan.status == Status.INFEASIBLE:
        plan.reason = f"{plan.reason} (with {100 * headroom:g} % of every computer kept free)"
        return plan
    keep = 1.0 - headroom
    sized = plan.problem == Problem.SERVER_CAPACITY
    for name, pc in plan.computers.items():
        c = system.computer[name]
        pc.capacity = (pc.capacity or 0.0) / keep if sized and c.kind == "server" else c.capacity
        pc.margin = None if pc.capacity is None else pc.capacity * headroom
    if sized:
        plan.objective = None if plan.objective is None else plan.objective / keep
        plan.bound = None if plan.bound is None else plan.bound / keep
    restate_chains(system, plan)
    return plan


def _dispatch(system: System, problem: Problem, method: Method, choices: dict[str, list[Choice]],
              deadline: float | None, progress: Progress | None) -> Plan:
    budgets = bool(budgeted(system))
    if budgets and (impossible := impossible_budget(system, choices)) is not None:
        return Plan.infeasible(problem, method, impossible, system=system.source)
    if method in (Method.GREEDY, Method.GREEDY_PLUS):
        return within_budgets(system, problem, choices, solve_heuristic(system, problem, choices, method), method)
    if method == Method.BRUTEFORCE:
        return solve_bruteforce(system, problem, choices)
    try:  # deferred: numpy and HiGHS, for the exact method only
        from perfros_bag.solver import exact
    except ImportError as exc:
        raise InputError(None, f"the exact solver is not available ({exc})") from None

    def left() -> float | None:
        """Seconds to the deadline (0 when past it), None without a time limit."""
        return None if deadline is None else max(deadline - time.perf_counter(), 0.0)

    columns = exact_columns(system, choices)
    declined = None  # why the decomposition cannot take the data flow, decided before any preparation
    if system.has_flow and columns > DECOMPOSE_COLUMNS and problem == Problem.PERFORMANCE:
        from perfros_bag.solver.decompose import flow_decline  # deferred: numpy, HiGHS

        declined = flow_decline(system, choices)
    if declined is not None and not budgets:
        if columns > DECLINED_MILP_COLUMNS:  # the whole MILP would overrun any limit: greedy+, stated as such
            budget = None if left() is None else 0.8 * (left() or 0.0)
            plan = solve_heuristic(system, problem, choices, Method.GREEDY_PLUS, time_budget=budget)
            if plan.status == Status.INFEASIBLE:
                return plan
            plan.method, plan.bound = Method.EXACT, None
            return _declined(within_trivial_bound(system, problem, choices, plan), declined, "greedy+'s plan",
                             trivial_bound(system, choices))
        plan = exact.solve_exact(system, problem, choices, time_limit=left(),
                                 start=_exact_start(system, problem, choices, left(), columns))
        return _declined(within_trivial_bound(system, problem, choices, plan), declined, "the whole MILP's plan",
                         trivial_bound(system, choices))
    prepared = prepare_instance(system, problem, choices)  # once, for whichever solver runs
    # the decomposition prices robots one by one, each with the data flow it carries; a flow
    # across robots is the MILP's (its rows): solve_decomposed then declines (None). Latency
    # budgets are the MILP's (its lazy cuts). Problem 2 (one choice a node: its size is nodes x
    # computers) only where the network can bind: there the whole MILP stalls (the wifi fleet:
    # 2.2 % at 30 s; decomposed 0.04 % in 12 s)
    big = columns > DECOMPOSE_COLUMNS if problem == Problem.PERFORMANCE else (
        len(system.nodes) * len(system.computers) > DECOMPOSE_COLUMNS
        and not isinstance(prepared, str) and bool(active_links(prepared)))
    if big and not isinstance(prepared, str) and not budgets:
        from perfros_bag.solver.decompose import solve_decomposed  # deferred: numpy, HiGHS

        decomposed = solve_decomposed(system, problem, choices, time_limit=left(), progress=progress,
                                      prepared=prepared)
        if decomposed is not None:
            return within_trivial_bound(system, problem, choices, decomposed)
    if budgets and not isinstance(prepared, str):  # lazy cuts; a start would be cut and offered again
        return solve_with_cuts(system, problem, choices,
                               lambda cuts: exact.solve_exact(system, problem, choices, time_limit=left(),
                                                              prepared=prepared, cuts=cuts),
                               lambda: deadline is not None and time.perf_counter() >= deadline)
    start = None if isinstance(prepared, str) else _exact_start(system, problem, choices, left(), columns)
    return exact.solve_exact(system, problem, choices, time_limit=left(), start=start, prepared=prepared)


def _declined(plan: Plan, why: str, whose: str, ceiling: float) -> Plan:
    """``plan`` on a fleet the decomposition declined, saying so in one line with what its
    bound is: HiGHS's on the whole MILP, or the trivial Σ w·max P (never one that was not
    proven)."""
    if plan.status != Status.INFEASIBLE and not plan.reason and plan.bound is not None:
        trivial = plan.bound >= ceiling - 1e-9
        stated = "the trivial one, Σ w·max P" if trivial else "HiGHS's on the whole MILP"
        plan.reason = f"the fleet decomposition declines ({why}): {whose}; bound {plan.bound:.6g}: {stated}"
    return plan


#: a fleet the decomposition declines (:func:`perfros_bag.solver.decompose.flow_decline`) goes
#: to the whole MILP up to this many columns; above (the 1,180-node driven wifi fleet has
#: ~600,000: the MILP's build alone overran a 20 s limit by 77 s), greedy+ answers with the
#: trivial bound
DECLINED_MILP_COLUMNS = 100_000


#: above this many (node, choice, computer) columns the exact solver gets a MIP start from
#: greedy+ (measured, docs/solvers.md: 200 nodes x 20 computers, ~80,000 columns, HiGHS alone
#: ends 2.9 % from its bound in 30 s, with greedy+'s plan as start 0.3 %). Table II
#: instances (< 5,000 columns) prove optimal in < 1 s without one.
START_COLUMNS = 20_000
#: the share of what is left of ``time_limit`` greedy+ may spend on that start.
START_SHARE = 0.25
#: above this many columns, Problem 1 goes to the decomposition
#: (:mod:`perfros_bag.solver.decompose`) when the instance qualifies. Measured
#: (docs/solvers.md): it proves the 200 x 20 fleet optimal in 0.4 s where the whole MILP
#: takes 24 s; below this size the MILP proves Table II in < 1 s and the decomposition's
#: plans on small instances can be up to a few % off its bound.
DECOMPOSE_COLUMNS = 20_000


def exact_columns(system: System, choices: Mapping[str, list[Choice]]) -> int:
    """The size of the exact model before pruning: Σ over nodes of choices x allowed computers."""
    return sum(len(choices[n.name]) * len(system.allowed(n.name)) for n in system.nodes)


def _exact_start(system: System, problem: Problem, choices: dict[str, list[Choice]],
                 time_limit: float | None, columns: int) -> Assignment | None:
    """greedy+'s plan (within :data:`START_SHARE` of the time left) as the exact solver's MIP
    start on big instances (``columns`` > :data:`START_COLUMNS`); None on small ones, or
    when greedy+ finds nothing."""
    if problem != Problem.PERFORMANCE or columns <= START_COLUMNS:
        return None
    # deferred: starts imports greedy+ (numpy), needed on big instances only
    from perfros_bag.solver.starts import start_of

    budget = None if time_limit is None else START_SHARE * time_limit
    plan = solve_heuristic(system, problem, choices, Method.GREEDY_PLUS, time_budget=budget)
    if plan.status == Status.INFEASIBLE:
        return None
    return start_of(plan, choices)
