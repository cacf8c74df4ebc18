"""Solvers for the paper's two problems (section II), one entry point: :func:`solve`.

- Problem 1 (eq 1): choose a setting and a computer for every node to maximise
  Σ w·P under eq 3-9.
- Problem 2 (eq 2): settings are fixed (``settings``, default each node's maximum-CPU
  choice); choose a computer per node to minimise the total server capacity (robots keep
  their capacity; a server's size is its load, bounded by ``max_capacity`` when set).

Every solver receives the same candidates from :func:`fixed_choices` and has the
signature ``(system, problem, choices) -> Plan`` (the exact solver also takes
``time_limit``):

- ``greedy``      :func:`perfros_bag.solver.greedy.solve_greedy` (the paper's Algorithms 1-3)
- ``greedy+``     :func:`perfros_bag.solver.local.solve_greedy_plus` (greedy + local search)
  (with driven nodes both run per rate class of each publisher:
  :func:`perfros_bag.solver.flow.solve_heuristic`)
- ``exact``       ``perfros_bag.solver.exact.solve_exact(system, problem, choices, *, time_limit=None)``;
  on Problem 1 above :data:`DECOMPOSE_COLUMNS` columns :func:`solve` uses
  :func:`perfros_bag.solver.decompose.solve_decomposed` (column generation over the
  fleet's structure, a plan and a proven bound) when the instance qualifies (CPU on a
  grid; links and media that can overflow carried as coupling rows; no driven nodes:
  :func:`perfros_bag.solver.decompose.decomposable`); otherwise, above
  :data:`START_COLUMNS`, it first runs greedy+ (along the data flow when there is one,
  :mod:`perfros_bag.solver.flow`) for :data:`START_SHARE` of ``time_limit`` and passes
  its plan as the MIP start
- ``bruteforce``  :func:`perfros_bag.solver.bruteforce.solve_bruteforce` (tiny instances)

``settings`` (Problem 2) maps node -> **CPU level** (units of the system's CPU scale).
:func:`settings_from_values` converts node -> parameter value to CPU levels, and
:func:`settings_from_plan` takes them from a plan.json.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.types import Choice, Node, Problem, System

#: ``progress(incumbent or None, bound, elapsed seconds)``: the exact method's fleet solver
#: (:mod:`perfros_bag.solver.decompose`) calls it as its plan or its bound improves
Progress = Callable[[float | None, float, float], None]

#: the solvers' names (``Method`` values), in the order the docs list them
METHODS: tuple[str, ...] = tuple(Method)

__all__ = ["DECOMPOSE_COLUMNS", "DrivenLevel", "MAX_CHOICES", "METHODS", "Progress", "START_COLUMNS", "START_SHARE",
           "check_resolution", "choice_count", "exact_columns", "fixed_choices", "lowest_settings", "settings_from_plan",
           "with_headroom", "AUTO", "check_headroom", "inflate_choices",
           "settings_from_values", "solve", "start_of"]


class DrivenLevel(float):
    """A driven node's Problem 2 CPU level that also names its own setting (an index into
    ``Node.settings``): two settings may need the same CPU at one input rate and still
    publish at different rates, so the level alone would not say which."""

    setting: int

    def __new__(cls, cpu: float, setting: int) -> DrivenLevel:
        level = super().__new__(cls, cpu)
        level.setting = setting
        return level


def _where(system: System) -> str | None:
    return system.source


def _match_cpu(system: System, node: Node, cpu: float, resolution: float) -> Choice:
    """The node's choice at CPU level ``cpu`` (a curve node off the grid gets a choice at
    exactly that level)."""
    choices = node.choices(resolution)
    for ch in choices:
        if math.isclose(ch.cpu, cpu, rel_tol=1e-9, abs_tol=1e-6):
            return ch
    if node.curve is not None:
        lo, hi = node.curve.domain
        if lo - 1e-6 <= cpu <= hi + 1e-6:
            return node.choice_at(0, min(max(cpu, lo), hi))
        raise InputError(_where(system), f"node {node.name!r}: setting CPU {cpu:g} is outside its curve's range [{lo:g}, {hi:g}]")
    have = ", ".join(f"{c.cpu:g}" for c in choices)
    raise InputError(_where(system), f"node {node.name!r}: no setting with CPU {cpu:g} (its settings' CPU: {have})")


#: the most candidate choices (summed over the nodes) a solve may create. A curve node has
#: one choice per ``resolution`` CPU units of its domain; each choice costs the solvers time
#: and memory (measured, docs/formats.md: 23,500 choices solve exactly in ~17 s).
MAX_CHOICES = 100_000


def choice_count(system: System, resolution: float) -> int:
    """How many candidate choices the nodes have at ``resolution`` (computed, not built)."""
    total = 0
    for node in system.nodes:
        if node.curve is None:
            total += len(node.settings)
        else:
            lo, hi = node.curve.domain
            total += math.floor((hi - lo) / resolution + 1e-9) + 2
    return total


def check_resolution(system: System, resolution: float) -> None:
    """Raise an :class:`InputError` when ``resolution`` is not a finite number > 0 or would
    create more than :data:`MAX_CHOICES` choices."""
    if isinstance(resolution, bool) or not isinstance(resolution, int | float) or not math.isfinite(resolution) \
            or resolution <= 0:
        raise InputError(_where(system), f"resolution must be > 0, got {resolution!r}")
    count = choice_count(system, resolution)
    if count > MAX_CHOICES:
        widest = max((n for n in system.nodes if n.curve is not None),
                     key=lambda n: n.curve.domain[1] - n.curve.domain[0] if n.curve else 0.0)
        assert widest.curve is not None
        lo, hi = widest.curve.domain
        raise InputError(_where(system), f"resolution {resolution:g} gives {count:.3g} choices over the curves' CPU "
                                         f"ranges (node {widest.name!r}: [{lo:g}, {hi:g}]), more than the "
                                         f"{MAX_CHOICES:,} the solvers take: use a coarser resolution")


def fixed_choices(system: System, problem: Problem, settings: Mapping[str, float] | None = None,
                  resolution: float = 1.0, *, own: Mapping[str, int] | None = None) -> dict[str, list[Choice]]:
    """Each node's candidate choices, sorted by CPU: all of them for Problem 1; for Problem 2
    the single fixed one (``settings[node]`` as a CPU level, default the maximum-CPU choice).

    A driven node's choices are its settings at each input rate its input can take
    (:meth:`System.flow_choices`); for Problem 2 its CPU level is the one at its input's
    fixed rate, or ``own[node]`` names its setting (an index into ``Node.settings``)."""
    check_resolution(system, resolution)
    if settings:
        unknown = sorted(set(settings) - set(system.node))
        if unknown:
            raise InputError(_where(system), f"settings: unknown node(s) {', '.join(map(repr, unknown))}")
    out: dict[str, list[Choice]] = {}
    for node in system.nodes:
        if problem == Problem.PERFORMANCE or node.driven:  # a driven node's CPU follows its input: below
            out[node.name] = node.choices(resolution)
        elif settings and node.name in settings:
            out[node.name] = [_match_cpu(system, node, float(settings[node.name]), resolution)]
        else:
            out[node.name] = [node.choices(resolution)[-1]]
    if not system.has_flow:
        return out

    def fixed(name: str, options: list[Choice]) -> list[Choice]:
        """Problem 2: the driven node's one choice at its input's (fixed) rate: the one at
        ``settings[name]``'s CPU level, else its maximum-CPU one."""
        if own and name in own:
            return [c for c in options if c.setting == own[name]][:1]
        if settings and name in settings:
            given = settings[name]
            if isinstance(given, DrivenLevel):
                options = [c for c in options if c.setting == given.setting]
            level = float(given)
            match = [c for c in options if math.isclose(c.cpu, level, rel_tol=1e-9, abs_tol=1e-6)]
            if not match:
                have = ", ".join(f"{c.cpu:g}" for c in options)
                raise InputError(_where(system), f"node {name!r}: no setting with CPU {level:g} at its input's rate "
                                                 f"(its settings' CPU there: {have})")
            return match[:1]
        return [max(options, key=lambda c: (c.cpu, c.performance))]

    out = system.flow_choices(out, fixed if problem == Problem.SERVER_CAPACITY else None)
    total = sum(len(v) for v in out.values())
    if total > MAX_CHOICES:
        raise InputError(_where(system), f"the driven nodes' settings at every input rate their inputs can take give "
                                         f"{total:,} choices, more than the {MAX_CHOICES:,} the solvers take: use a "
                                         "coarser resolution or fewer settings upstream")
    return out


#: how far (CPU units) a setting's CPU may lie outside its curve's range without a warning:
#: ``perfros-bag fit`` rounds the range's ends inwards to whole units.
ROUNDING_UNITS = 1.0


def settings_from_values(system: System, values: Mapping[str, float], resolution: float = 1.0) -> dict[str, float]:
    """node -> parameter value  ==>  node -> CPU level: the choice or the setting with that
    value; else a curve node's fitted ``parameter->cpu`` relation evaluated at it.

    A curve node's level is clamped to its curve's CPU range, so that
    :func:`fixed_choices` always accepts it: a setting's measured CPU (or the fit's value)
    may lie just outside that range, which a fitted model narrows (whole CPU units, and
    where the performance fit leaves [0, max], see docs/formats.md). Beyond
    :data:`ROUNDING_UNITS` the clamp is reported with a :class:`PerfrosWarning`."""
    check_resolution(system, resolution)
    out: dict[str, float] = {}
    own: dict[str, int] = {}  # driven nodes: the setting with the value
    for name, v in values.items():
        node = system.node.get(name)
        if node is None:
            raise InputError(_where(system), f"settings: unknown node {name!r}")
        if not math.isfinite(v):
            raise InputError(_where(system), f"settings: node {name!r}: value {v!r} is not a finite number")
        if node.driven:
            own[name] = _setting_with_value(system, node, v)
            continue
        rel = node.relations.get("parameter->cpu")
        # a setting first (its own, measured CPU: on a fitted curve several CPU levels may
        # map back to the same end value), then the fitted relation, then a choice
        match = [s.cpu for s in node.settings if s.value is not None and math.isclose(s.value, v, rel_tol=1e-9, abs_tol=1e-9)]
        if not (match or (rel is not None and node.curve is not None)):
            match = [c.cpu for c in node.choices(resolution)
                     if c.value is not None and math.isclose(c.value, v, rel_tol=1e-9, abs_tol=1e-9)]
        if match:
            cpu = match[0]
        elif rel is not None and node.curve is not None:
            plo, phi = rel.domain
            if not plo - 1e-9 <= v <= phi + 1e-9:
                raise InputError(_where(system), f"settings: node {name!r}: value {v:g} is outside its parameter's "
                                                 f"range [{plo:g}, {phi:g}]")
            cpu = rel(v)
        else:
            have = sorted({c.value for c in node.choices(resolution) if c.value is not None}
                          | {s.value for s in node.settings if s.value is not None})
            hint = f"its values: {', '.join(f'{x:g}' for x in have)}" if have else "it has no parameter values, only CPU levels"
            raise InputError(_where(system), f"settings: node {name!r} has no setting with value {v:g} ({hint})")
        if not math.isfinite(cpu):
            raise InputError(_where(system), f"settings: node {name!r}: value {v:g} gives no finite CPU level "
                                             f"(its parameter->cpu relation gives {cpu!r})")
        out[name] = _clamp(system, node, v, cpu)
    if own:  # a driven node's CPU level is its setting's at the rate its input then has
        fixed = fixed_choices(system, Problem.SERVER_CAPACITY, out, resolution, own=own)
        out.update({name: DrivenLevel(fixed[name][0].cpu, own[name]) for name in own})
    return out


def lowest_settings(system: System, resolution: float = 1.0) -> dict[str, float]:
    """node -> CPU level with every node at its least-CPU setting (a driven node's at the rate
    its input then has): Problem 2's ``settings`` for "everything at its lowest"."""
    base = {n.name: n.choices(resolution)[0].cpu for n in system.nodes if not n.driven}
    own = {n.name: _least_setting(n) for n in system.nodes if n.driven}
    fixed = fixed_choices(system, Problem.SERVER_CAPACITY, base, resolution, own=own)
    return {name: options[0].cpu for name, options in fixed.items()}


def _least_setting(node: Node) -> int:
    """A driven node's setting with the least CPU per input message (then base CPU)."""
    return min(range(len(node.settings)), key=lambda j: (node.settings[j].cpu_per_hz or 0.0, node.settings[j].cpu))


def _setting_with_value(system: System, node: Node, value: float) -> int:
    """The index of the driven node's setting with ``value``."""
    j = node.setting_index(value)
    if j is not None:
        return j
    have = ", ".join(f"{s.value:g}" for s in node.settings if s.value is not None) or "none"
    raise InputError(_where(system), f"settings: node {node.name!r} has no setting with value {value:g} "
                                     f"(its values: {have})")


def _clamp(system: System, node: Node, value: float, cpu: float) -> float:
    """``cpu`` clamped to the node's curve range (discrete nodes: unchanged)."""
    if node.curve is None:
        return cpu
    lo, hi = node.curve.domain
    clamped = min(max(cpu, lo), hi)
    if abs(clamped - cpu) > ROUNDING_UNITS + 1e-6:
        where = f"{_where(system)}: " if _where(system) else ""
        warnings.warn(f"{where}settings: node {node.name!r}: value {value:g} needs {cpu:.4g} CPU, outside its "
                      f"curve's range [{lo:g}, {hi:g}]: using {clamped:g}", PerfrosWarning, stacklevel=3)
    return clamped


def settings_from_plan(plan: Plan, system: System | None = None, resolution: float = 1.0) -> dict[str, float]:
    """node -> CPU level from a plan (e.g. Problem 1's answer fed to Problem 2): the plan's
    own CPU levels when ``system`` is the one the plan was solved from (or not given); for
    another model of the same nodes (e.g. one fitted with ``fit --cpu p95``), each node's
    parameter value in ``system`` (:func:`settings_from_values`), and a node without a value
    at its one choice there."""
    if system is None or _same_source(plan.system, system.source):
        levels: dict[str, float] = {name: n.cpu for name, n in plan.nodes.items()}
        if system is not None:  # a driven node: its own setting too (by its value)
            for name, n in plan.nodes.items():
                node = system.node.get(name)
                if node is not None and node.driven and n.value is not None:
                    levels[name] = DrivenLevel(n.cpu, _setting_with_value(system, node, n.value))
        return levels
    out = settings_from_values(system, {name: n.value for name, n in plan.nodes.items()
                                        if n.value is not None and name in system.node}, resolution)
    for name, n in plan.nodes.items():
        if name not in out and name in system.node:
            choices = system.node[name].choices(resolution)
            out[name] = choices[0].cpu if len(choices) == 1 else n.cpu
    return out


def _same_source(a: str | None, b: str | None) -> bool:
    """Do two recorded source paths name the same file (best effort)?"""
    from pathlib import Path

    if a is None or b is None:
        return a == b
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return a == b


#: ``headroom`` that keeps each node's measured CPU error free (:mod:`perfros_bag.system.cpuerror`)
AUTO = "auto"


def check_headroom(headroom: object) -> float | str:
    """``headroom`` when it is :data:`AUTO` or a number in [0, 1); else an
    :class:`~perfros_bag.errors.InputError`."""
    if headroom == AUTO:
        return AUTO
    if isinstance(headroom, bool) or not isinstance(headroom, int | float) or not 0.0 <= headroom < 1.0:
        raise InputError(None, f"headroom must be in [0, 1), got {headroom!r} (or {AUTO!r}: the model's measured errors)")
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
        raise InputError(_where(system), f"problem must be 1 or 2, got {problem!r}")
    if method not in METHODS:
        raise InputError(None, f"unknown method {method!r} (one of {', '.join(METHODS)})")
    the_problem, the_method = Problem(problem), Method(method)
    system.capacities(the_problem)  # every capacity the problem needs is there
    headroom = check_headroom(headroom)
    if not isinstance(headroom, str) and headroom > 0:
        plan = solve(with_headroom(system, headroom), problem, method, resolution=resolution, settings=settings,
                     time_limit=time_limit, progress=progress)
        return _give_back(system, plan, headroom)
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
    import dataclasses

    from perfros_bag.system.cpuerror import choice_error

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
    from perfros_bag.system.cpuerror import FAIR_SHARE, states_errors

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


def _same_number(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


def with_headroom(system: System, headroom: float) -> System:
    """The system with every computer's capacity (and a server's ``max_capacity``) cut to
    ``1 - headroom`` of it: what a plan may fill when it keeps ``headroom`` free."""
    import dataclasses

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
    return plan


def _dispatch(system: System, problem: Problem, method: Method, choices: dict[str, list[Choice]],
              deadline: float | None, progress: Progress | None) -> Plan:
    if method in (Method.GREEDY, Method.GREEDY_PLUS):
        from perfros_bag.solver.flow import solve_heuristic

        return solve_heuristic(system, problem, choices, method)
    if method == Method.BRUTEFORCE:
        from perfros_bag.solver.bruteforce import solve_bruteforce

        return solve_bruteforce(system, problem, choices)
    try:
        from perfros_bag.solver import exact
    except ImportError as exc:
        raise InputError(None, f"the exact solver is not available ({exc})") from None

    def left() -> float | None:
        """Seconds to the deadline (0 when past it), None without a time limit."""
        return None if deadline is None else max(deadline - time.perf_counter(), 0.0)

    prepared = exact.prepare_instance(system, problem, choices)  # once, for whichever solver runs
    columns = exact_columns(system, choices)
    # the decomposition prices robots one by one: a data flow across them is the MILP's (its rows)
    if problem == Problem.PERFORMANCE and columns > DECOMPOSE_COLUMNS and not isinstance(prepared, str) \
            and not system.has_flow:
        from perfros_bag.solver.decompose import solve_decomposed

        decomposed = solve_decomposed(system, problem, choices, time_limit=left(), progress=progress,
                                      prepared=prepared)
        if decomposed is not None:
            return exact.within_trivial_bound(system, problem, choices, decomposed)
    start = None if isinstance(prepared, str) else _exact_start(system, problem, choices, left(), columns)
    return exact.solve_exact(system, problem, choices, time_limit=left(), start=start, prepared=prepared)


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
    from perfros_bag.solver.flow import solve_heuristic

    budget = None if time_limit is None else START_SHARE * time_limit
    plan = solve_heuristic(system, problem, choices, Method.GREEDY_PLUS, time_budget=budget)
    if plan.status == Status.INFEASIBLE:
        return None
    return start_of(plan, choices)


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
