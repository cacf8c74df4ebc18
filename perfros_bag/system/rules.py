"""A solver's answer (an :class:`~perfros_bag.system.plan.Assignment`) made into a plan.

:func:`build_plan` adds what follows from the model: computer loads, link loads
(:meth:`~perfros_bag.system.types.System.link_loads`), the objective (eq 1 or 2) and
per-topic expectations. The network and capacity rules themselves are methods of
:class:`~perfros_bag.system.types.System`.
"""

from __future__ import annotations

from collections.abc import Mapping

from perfros_bag.system.latency import plan_predictions
from perfros_bag.system.plan import (
    Assignment,
    Method,
    Plan,
    PlannedComputer,
    PlannedLink,
    PlannedNode,
    PlannedTopic,
    Status,
)
from perfros_bag.system.types import Choice, Problem, System


def expected_topics(system: System, node: str, choice: Choice) -> dict[str, PlannedTopic]:
    """Per-topic expectations of a node at a choice: per-topic rates when the setting has
    them, else the node's frequency on every topic and its bandwidth split evenly."""
    topics = system.node[node].topics
    out: dict[str, PlannedTopic] = {}
    for t in topics:
        if t in choice.topics:
            r = choice.topics[t]
            out[t] = PlannedTopic(r.frequency_hz, r.bandwidth_kBps)
        else:
            bw = None if choice.bandwidth_kBps is None else choice.bandwidth_kBps / len(topics)
            out[t] = PlannedTopic(choice.frequency_hz, bw)
    return out


def computer_loads(system: System, placement: Mapping[str, str], choice: Mapping[str, Choice]) -> dict[str, float]:
    """CPU on every computer (eq 3's left side): the sum of its nodes' choices, in node order."""
    load = {c.name: 0.0 for c in system.computers}
    for node in system.nodes:
        comp = placement.get(node.name)
        if comp is not None:
            load[comp] += choice[node.name].cpu
    return load


def server_sizes(system: System, placement: Mapping[str, str], choice: Mapping[str, Choice]) -> dict[str, float]:
    """Problem 2: every server sized to its load."""
    load = computer_loads(system, placement, choice)
    return {c.name: load[c.name] for c in system.computers if c.kind == "server"}


def weighted_performance(system: System, choice: Mapping[str, Choice]) -> float:
    """Eq 1: the sum of w*P over the chosen nodes."""
    return sum(system.node[n].weight * c.performance for n, c in choice.items())


def objective(system: System, assignment: Assignment, problem: Problem) -> float:
    """Eq 1 (Problem 1: sum of w*P) or eq 2 (Problem 2: total server capacity)."""
    if problem == Problem.PERFORMANCE:
        return weighted_performance(system, assignment.choice)
    return sum(assignment.capacities.get(c.name, c.capacity or 0.0) for c in system.computers if c.kind == "server")


def build_plan(system: System, assignment: Assignment, *, problem: Problem, method: Method | str, status: Status,
               bound: float | None = None, solve_s: float | None = None, objective_value: float | None = None) -> Plan:
    """The plan of an assignment: each node's computer, choice and topic expectations, the
    computers' and links' loads and the objective (``objective_value`` when given)."""
    cpu = computer_loads(system, assignment.placement, assignment.choice)
    computers = {
        c.name: PlannedComputer(c.kind, assignment.capacities.get(c.name, c.capacity), round(cpu[c.name], 9))
        for c in system.computers
    }
    loads = system.link_loads(assignment.placement, assignment.choice)
    links = [PlannedLink(link.between, link.bandwidth_kBps, round(load, 9), link.medium)
             for link, load in zip(system.links, loads, strict=True)]
    nodes: dict[str, PlannedNode] = {}
    for node in system.nodes:
        ch = assignment.choice[node.name]
        nodes[node.name] = PlannedNode(
            computer=assignment.placement[node.name], cpu=ch.cpu, performance=ch.performance,
            weight=node.weight, parameter=node.parameter.name if node.parameter else None,
            value=ch.value, topics=expected_topics(system, node.name, ch), input=node.input,
            input_hz=ch.input_hz if node.input is not None else None,
            bandwidth_kBps=ch.bandwidth_kBps if node.input is not None else None,
        )
    obj = objective_value if objective_value is not None else objective(system, assignment, problem)
    plan = Plan(problem, method, status, obj, bound, solve_s, computers, links, nodes, system=system.source)
    plan.chains = [p.to_dict() for p in plan_predictions(system, plan)]
    return plan
