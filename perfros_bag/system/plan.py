"""``plan.json``: one setting and one computer per node, with expected loads.

Solvers produce an :class:`Assignment` (node -> computer and :class:`~perfros_bag.system.types.Choice`,
plus server capacities for Problem 2); :func:`build_plan` turns it into a :class:`Plan`
with computer loads, link loads and per-topic expectations. The JSON shape is the
contract of ``design.md`` (format ``perfros-bag/plan@1``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import atomic_write_json, read_json
from perfros_bag.system.types import Choice, System

PLAN_FORMAT = "perfros-bag/plan@1"
STATUSES = ("optimal", "feasible", "infeasible")


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


@dataclass
class PlannedComputer:
    kind: str
    capacity: float | None
    cpu: float


@dataclass
class PlannedLink:
    between: tuple[str, str]
    bandwidth_kBps: float
    load_kBps: float
    medium: str | None = None


@dataclass
class Plan:
    problem: int
    method: str
    status: str
    objective: float | None = None
    bound: float | None = None
    solve_s: float | None = None
    computers: dict[str, PlannedComputer] = field(default_factory=dict)
    links: list[PlannedLink] = field(default_factory=list)
    nodes: dict[str, PlannedNode] = field(default_factory=dict)
    reason: str | None = None
    system: str | None = None  # path of the system/model it was solved from
    extra: dict[str, Any] = field(default_factory=dict)  # optional fields we do not interpret

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "format": PLAN_FORMAT, "problem": self.problem, "method": self.method,
            "status": self.status, "objective": self.objective, "bound": self.bound,
            "solve_s": self.solve_s,
        }
        if self.reason is not None:
            out["reason"] = self.reason
        if self.system is not None:
            out["system"] = self.system
        out["computers"] = {
            name: {"kind": c.kind, "capacity": c.capacity, "cpu": c.cpu} for name, c in self.computers.items()
        }
        out["links"] = [
            {"between": list(link.between), "bandwidth_kBps": link.bandwidth_kBps, "load_kBps": link.load_kBps,
             **({"medium": link.medium} if link.medium else {})}
            for link in self.links
        ]
        out["nodes"] = {
            name: {
                "computer": n.computer, "parameter": n.parameter, "value": n.value, "cpu": n.cpu,
                "performance": n.performance, "weight": n.weight,
                "topics": {t: {"frequency_hz": r.frequency_hz, "bandwidth_kBps": r.bandwidth_kBps}
                           for t, r in n.topics.items()},
            }
            for name, n in self.nodes.items()
        }
        out.update(self.extra)
        return out

    def save(self, path: str | Path) -> None:
        atomic_write_json(path, self.to_dict())


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


def link_loads(system: System, placement: dict[str, str], choice: dict[str, Choice]) -> list[float]:
    """kB/s on every link (system.links order) for a placement: each edge whose ends sit
    on different computers loads every link of the route between them."""
    loads = [0.0] * len(system.links)
    for edge in system.edges:
        a, b = placement[edge.src], placement[edge.dst]
        if a == b:
            continue
        route = system.route(a, b)
        if route is None:
            continue  # disconnected: reported by the checker
        bw = system.edge_bandwidth(edge, choice[edge.src])
        for li in route:
            loads[li] += bw
    return loads


def objective(system: System, assignment: Assignment, problem: int) -> float:
    """Eq 1 (Problem 1: sum of w*P) or eq 2 (Problem 2: total server capacity)."""
    if problem == 1:
        return sum(system.node[n].weight * c.performance for n, c in assignment.choice.items())
    return sum(assignment.capacities.get(c.name, c.capacity or 0.0) for c in system.computers if c.kind == "server")


def build_plan(system: System, assignment: Assignment, *, problem: int, method: str, status: str,
               bound: float | None = None, solve_s: float | None = None, objective_value: float | None = None) -> Plan:
    cpu = {c.name: 0.0 for c in system.computers}
    for n, comp in assignment.placement.items():
        cpu[comp] += assignment.choice[n].cpu
    computers = {
        c.name: PlannedComputer(c.kind, assignment.capacities.get(c.name, c.capacity), round(cpu[c.name], 9))
        for c in system.computers
    }
    loads = link_loads(system, assignment.placement, assignment.choice)
    links = [PlannedLink(link.between, link.bandwidth_kBps, round(load, 9), link.medium)
             for link, load in zip(system.links, loads, strict=True)]
    nodes: dict[str, PlannedNode] = {}
    for node in system.nodes:
        ch = assignment.choice[node.name]
        nodes[node.name] = PlannedNode(
            computer=assignment.placement[node.name], cpu=ch.cpu, performance=ch.performance,
            weight=node.weight, parameter=node.parameter.name if node.parameter else None,
            value=ch.value, topics=expected_topics(system, node.name, ch),
        )
    obj = objective_value if objective_value is not None else objective(system, assignment, problem)
    return Plan(problem, method, status, obj, bound, solve_s, computers, links, nodes,
                system=system.source)


def infeasible_plan(problem: int, method: str, reason: str, *, solve_s: float | None = None,
                    system: str | None = None) -> Plan:
    return Plan(problem, method, "infeasible", None, None, solve_s, reason=reason, system=system)


def load_plan(path: str | Path) -> Plan:
    """Read a plan.json, checking the fields validate/export rely on."""
    p = Path(path)
    data = read_json(p)
    return parse_plan(data, str(p))


def _num(d: dict[str, Any], key: str, where: str, path: str, *, optional: bool = True) -> float | None:
    v = d.get(key)
    if v is None:
        if optional:
            return None
        raise InputError(path, f"{where}: missing {key!r}")
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise InputError(path, f"{where}: {key!r} must be a number, got {v!r}")
    return float(v)


def parse_plan(data: Any, path: str = "plan.json") -> Plan:
    if not isinstance(data, dict):
        raise InputError(path, "not a plan: expected a JSON object")
    fmt = data.get("format")
    if fmt != PLAN_FORMAT:
        raise InputError(path, f"not a perfros-bag plan (format {fmt!r}, expected {PLAN_FORMAT!r})")
    status = data.get("status")
    if status not in STATUSES:
        raise InputError(path, f"status must be one of {', '.join(STATUSES)}, got {status!r}")
    problem = data.get("problem")
    if problem not in (1, 2):
        raise InputError(path, f"problem must be 1 or 2, got {problem!r}")
    known = {"format", "problem", "method", "status", "objective", "bound", "solve_s", "reason",
             "system", "computers", "links", "nodes"}
    plan = Plan(problem, str(data.get("method", "")), status,
                _num(data, "objective", "plan", path), _num(data, "bound", "plan", path),
                _num(data, "solve_s", "plan", path), reason=data.get("reason"), system=data.get("system"),
                extra={k: v for k, v in data.items() if k not in known})
    comps = data.get("computers") or {}
    if not isinstance(comps, dict):
        raise InputError(path, "computers must be an object")
    for name, c in comps.items():
        if not isinstance(c, dict):
            raise InputError(path, f"computer {name!r}: must be an object")
        plan.computers[name] = PlannedComputer(str(c.get("kind", "server")),
                                               _num(c, "capacity", f"computer {name!r}", path),
                                               _num(c, "cpu", f"computer {name!r}", path) or 0.0)
    links = data.get("links") or []
    if not isinstance(links, list):
        raise InputError(path, "links must be a list")
    for i, link in enumerate(links):
        if not isinstance(link, dict) or not isinstance(link.get("between"), list) or len(link["between"]) != 2:
            raise InputError(path, f"links[{i}]: needs between: [a, b]")
        plan.links.append(PlannedLink((str(link["between"][0]), str(link["between"][1])),
                                      _num(link, "bandwidth_kBps", f"links[{i}]", path, optional=False) or 0.0,
                                      _num(link, "load_kBps", f"links[{i}]", path) or 0.0, link.get("medium")))
    nodes = data.get("nodes") or {}
    if not isinstance(nodes, dict):
        raise InputError(path, "nodes must be an object")
    if status != "infeasible" and not nodes:
        raise InputError(path, "the plan has no nodes")
    for name, n in nodes.items():
        where = f"node {name!r}"
        if not isinstance(n, dict):
            raise InputError(path, f"{where}: must be an object")
        if not isinstance(n.get("computer"), str):
            raise InputError(path, f"{where}: missing 'computer'")
        topics: dict[str, PlannedTopic] = {}
        raw_topics = n.get("topics") or {}
        if not isinstance(raw_topics, dict):
            raise InputError(path, f"{where}: topics must be an object")
        for t, r in raw_topics.items():
            if not isinstance(r, dict):
                raise InputError(path, f"{where}: topic {t!r} must be an object")
            topics[t] = PlannedTopic(_num(r, "frequency_hz", f"{where} topic {t!r}", path),
                                     _num(r, "bandwidth_kBps", f"{where} topic {t!r}", path))
        plan.nodes[name] = PlannedNode(
            computer=n["computer"],
            cpu=_num(n, "cpu", where, path, optional=False) or 0.0,
            performance=_num(n, "performance", where, path, optional=False) or 0.0,
            weight=_num(n, "weight", where, path, optional=False) or 0.0,
            parameter=n.get("parameter"), value=_num(n, "value", where, path), topics=topics,
        )
    return plan
