"""A plan: one setting and one computer per node, with the loads it is expected to cause.

The types only: solvers produce an :class:`Assignment`,
:func:`perfros_bag.system.rules.build_plan` turns it into a :class:`Plan`, and
:mod:`perfros_bag.system.planfile` reads and writes plan.json.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from perfros_bag.errors import InfeasibleError
from perfros_bag.system.types import Choice, Problem


class Method(StrEnum):
    """The solvers (``--method``)."""

    GREEDY = "greedy"
    GREEDY_PLUS = "greedy+"
    EXACT = "exact"
    BRUTEFORCE = "bruteforce"


class Status(StrEnum):
    """How good a plan is: proven optimal, feasible only, or none exists (then a reason)."""

    OPTIMAL = "optimal"
    FEASIBLE = "feasible"
    INFEASIBLE = "infeasible"


@dataclass
class Assignment:
    """A solver's raw answer: where each node runs and at which choice."""

    placement: dict[str, str]  # node -> computer
    choice: dict[str, Choice]  # node -> chosen setting / CPU level
    capacities: dict[str, float] = field(default_factory=dict)  # Problem 2: sized servers


@dataclass
class PlannedTopic:
    frequency_hz: float | None
    bandwidth_kBps: float | None


@dataclass
class PlannedNode:
    computer: str
    cpu: float
    performance: float
    weight: float
    parameter: str | None = None
    value: float | None = None
    topics: dict[str, PlannedTopic] = field(default_factory=dict)
    # a driven node (system.yaml ``input``): the topic that drives it and its planned rate,
    # and the bandwidth of all its topics at the rate that follows (None: not driven)
    input: str | None = None
    input_hz: float | None = None
    bandwidth_kBps: float | None = None
    #: was its value one a recording ran (``solve`` from a model.json); None: not said
    measured: bool | None = None
    #: a value never measured: per quantity (cpu, frequency_hz, bandwidth_kBps) the fit's
    #: leave-one-out error at it, in its units (None inside: the fit has none)
    loo_error: dict[str, float | None] | None = None
    #: a node hosted by a container (system.yaml ``container``) that the plan runs in a process
    #: of its own (``membership: choose``): ROS 1 ``nodelet standalone``; its ``cpu`` includes
    #: the copy of its input it then receives (:meth:`perfros_bag.system.types.System.copy_charge`)
    standalone: bool = False


@dataclass
class PlannedComputer:
    kind: str
    capacity: float | None
    cpu: float
    margin: float | None = None  # CPU units the plan keeps free (``solve --headroom``); None: none asked


@dataclass
class PlannedLink:
    between: tuple[str, str]
    bandwidth_kBps: float
    load_kBps: float
    medium: str | None = None


@dataclass
class Plan:
    """plan.json as data. ``problem`` and ``status`` are coerced to their enums (a bad
    value raises ``ValueError``); ``method`` is a :class:`Method` when it names one of
    ours, else the label a hand-written plan or another tool gave it."""

    problem: Problem
    method: Method | str
    status: Status
    objective: float | None = None
    bound: float | None = None
    solve_s: float | None = None
    computers: dict[str, PlannedComputer] = field(default_factory=dict)
    links: list[PlannedLink] = field(default_factory=list)
    nodes: dict[str, PlannedNode] = field(default_factory=dict)
    reason: str | None = None
    system: str | None = None  # path of the system/model it was solved from
    #: the system's chains with their predicted latency (perfros_bag.system.latency), as
    #: plan.json's ``chains`` holds them: name, topics, predicted_ms {p50, p95} (None when it
    #: cannot be predicted), budget_ms, hops
    chains: list[dict[str, Any]] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)  # optional fields we do not interpret

    def __post_init__(self) -> None:
        self.problem = Problem(self.problem)
        self.status = Status(self.status)
        self.method = method_of(self.method)

    @classmethod
    def infeasible(cls, problem: Problem, method: Method | str, reason: str, *, solve_s: float | None = None,
                   system: str | None = None) -> Plan:
        """The plan of an instance with no solution: no nodes, and why."""
        return cls(problem, method, Status.INFEASIBLE, None, None, solve_s, reason=reason, system=system)

    @property
    def predicted_performance(self) -> float:
        """Σ w·P over the plan's nodes at their planned values (what eq 10 expects of a run
        of it; Problem 1's objective)."""
        return sum(pn.weight * pn.performance for pn in self.nodes.values())

    @property
    def standalone(self) -> set[str]:
        """The nodes the plan runs in a process of their own (plan.json ``standalone: true``)."""
        return {name for name, pn in self.nodes.items() if pn.standalone}

    def require_feasible(self, path: str | Path | None, purpose: str | None = None) -> None:
        """Raise :class:`~perfros_bag.errors.InfeasibleError` (naming ``path``, the reason
        and, e.g. "nothing to validate", ``purpose``) when the plan is infeasible."""
        if self.status == Status.INFEASIBLE:
            raise InfeasibleError(self.reason or "no reason given", path,
                                  None if purpose is None else f"nothing to {purpose}")


def method_of(label: str) -> Method | str:
    """``label`` as a :class:`Method` when it is one, else unchanged."""
    try:
        return Method(label)
    except ValueError:
        return label


def better_plan(plan: Plan | None, than: Plan | None, problem: Problem) -> bool:
    """Is ``plan`` better than ``than`` for ``problem`` (a higher Σ w·P for Problem 1, a lower
    server capacity for Problem 2; an infeasible plan or None is never better, and anything
    feasible beats it)?"""
    if plan is None or plan.status == Status.INFEASIBLE or plan.objective is None:
        return False
    if than is None or than.status == Status.INFEASIBLE or than.objective is None:
        return True
    if problem == Problem.PERFORMANCE:
        return plan.objective > than.objective + 1e-9
    return plan.objective < than.objective - 1e-9
