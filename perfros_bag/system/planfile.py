"""plan.json (format ``perfros-bag/plan@1``, docs/formats.md): the one reader and writer.

:func:`save_plan` / :func:`plan_document` write it, :func:`load_plan` / :func:`parse_plan`
read it back, checking the fields validate, export and report rely on. Writing what was
read gives the same bytes.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from perfros_bag.doccheck import Doc
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fileio import DOCUMENT_KINDS, atomic_write_json, expect_kind, read_json
from perfros_bag.limits import number_problem
from perfros_bag.system.plan import Plan, PlannedComputer, PlannedLink, PlannedNode, PlannedTopic, Status, method_of
from perfros_bag.system.types import Problem, System

PLAN_FORMAT = "perfros-bag/plan@1"
_KNOWN = {"format", "problem", "method", "status", "objective", "bound", "solve_s", "reason", "system",
          "computers", "links", "nodes", "chains"}


def plan_document(plan: Plan) -> dict[str, Any]:
    """The plan as the JSON object of plan.json (plain values, fields in their order)."""
    out: dict[str, Any] = {
        "format": PLAN_FORMAT, "problem": int(plan.problem), "method": str(plan.method),
        "status": str(plan.status), "objective": plan.objective, "bound": plan.bound,
        "solve_s": plan.solve_s,
    }
    if plan.reason is not None:
        out["reason"] = plan.reason
    if plan.system is not None:
        out["system"] = plan.system
    out["computers"] = {
        name: {"kind": c.kind, "capacity": c.capacity, "cpu": c.cpu,
               **({} if c.margin is None else {"margin": c.margin})}
        for name, c in plan.computers.items()
    }
    out["links"] = [
        {"between": list(link.between), "bandwidth_kBps": link.bandwidth_kBps, "load_kBps": link.load_kBps,
         **({"medium": link.medium} if link.medium else {})}
        for link in plan.links
    ]
    out["nodes"] = {
        name: {
            "computer": n.computer, "parameter": n.parameter, "value": n.value, "cpu": n.cpu,
            "performance": n.performance, "weight": n.weight,
            "topics": {t: {"frequency_hz": r.frequency_hz, "bandwidth_kBps": r.bandwidth_kBps}
                       for t, r in n.topics.items()},
            **({"input": n.input, "input_hz": n.input_hz, "bandwidth_kBps": n.bandwidth_kBps}
               if n.input is not None else {}),
            **({} if n.measured is None else {"measured": n.measured}),
            **({} if n.loo_error is None else {"loo_error": n.loo_error}),
            **({"standalone": True} if n.standalone else {}),
        }
        for name, n in plan.nodes.items()
    }
    if plan.chains:
        out["chains"] = plan.chains
    out.update(plan.extra)
    return out


def save_plan(plan: Plan, path: str | Path) -> None:
    """Write plan.json atomically."""
    atomic_write_json(path, plan_document(plan))


def load_plan(path: str | Path) -> Plan:
    """Read a plan.json, checking the fields validate/export rely on."""
    p = Path(path)
    return parse_plan(read_json(p), str(p))


#: a node's CPU may exceed its computer's capacity by this much (relative) and still fit:
#: the solvers' rounding
CAPACITY_SLACK = 1e-6


def _num(d: dict[str, Any], key: str, where: str, path: str, *, optional: bool = True,
         nonneg: bool = False, positive: bool = False) -> float | None:
    """``d[key]``: a finite number within :mod:`perfros_bag.limits` (>= 0 / > 0 when
    asked); None when absent and ``optional``."""
    v = d.get(key)
    if v is None:
        if optional:
            return None
        raise Doc(path).fail(where, f"missing {key!r}")
    problem = number_problem(v, nonneg=nonneg, positive=positive)
    if problem is not None:
        raise Doc(path).fail(where, f"{key!r} {problem}")
    return float(v)


def _text(d: dict[str, Any], key: str, where: str, path: str) -> str | None:
    v = d.get(key)
    if v is not None and not isinstance(v, str):
        raise Doc(path).fail(where, f"{key!r} must be a string, got {type(v).__name__}")
    return v


def _topic(d: dict[str, Any], key: str, where: str, path: str) -> str | None:
    """A topic name field (a driven node's ``input``), checked by ROS's rule like
    system.yaml's."""
    from perfros_bag.system.names import NameKind, name_problem

    v = _text(d, key, where, path)
    problem = None if v is None else name_problem(NameKind.TOPIC, v)
    if problem is not None:
        raise InputError(path, f"{where}: {key!r} {problem}")
    return v


def parse_plan(data: Any, path: str = "plan.json") -> Plan:
    """A plan from its JSON object (``path`` names it in errors)."""
    expect_kind(path, data, DOCUMENT_KINDS[PLAN_FORMAT], {DOCUMENT_KINDS[PLAN_FORMAT]})
    if not isinstance(data, dict):
        raise InputError(path, "not a plan: expected a JSON object")
    fmt = data.get("format")
    if fmt != PLAN_FORMAT:
        raise InputError(path, f"not a perfros-bag plan (format {fmt!r}, expected {PLAN_FORMAT!r})")
    status = data.get("status")
    if status not in tuple(Status):
        raise InputError(path, f"status must be one of {', '.join(Status)}, got {status!r}")
    problem = data.get("problem")
    if isinstance(problem, bool) or problem not in tuple(Problem):
        raise InputError(path, f"problem must be 1 or 2, got {problem!r}")
    method = data.get("method", "")
    if not isinstance(method, str):
        raise InputError(path, f"plan: 'method' must be a string, got {type(method).__name__}")
    plan = Plan(Problem(problem), method_of(method), Status(status),
                _num(data, "objective", "plan", path), _num(data, "bound", "plan", path),
                _num(data, "solve_s", "plan", path, nonneg=True), reason=_text(data, "reason", "plan", path),
                system=_text(data, "system", "plan", path),
                extra={k: v for k, v in data.items() if k not in _KNOWN})
    comps = data.get("computers") or {}
    if not isinstance(comps, dict):
        raise InputError(path, "computers must be an object")
    for name, c in comps.items():
        if not isinstance(c, dict):
            raise InputError(path, f"computer {name!r}: must be an object")
        kind = c.get("kind", "server")
        if kind not in ("robot", "server"):
            raise InputError(path, f"computer {name!r}: 'kind' must be 'robot' or 'server', got {kind!r}")
        plan.computers[name] = PlannedComputer(kind, _num(c, "capacity", f"computer {name!r}", path, nonneg=True),
                                               _num(c, "cpu", f"computer {name!r}", path, nonneg=True) or 0.0,
                                               _num(c, "margin", f"computer {name!r}", path, nonneg=True))
    links = data.get("links") or []
    if not isinstance(links, list):
        raise InputError(path, "links must be a list")
    for i, link in enumerate(links):
        if not isinstance(link, dict) or not isinstance(link.get("between"), list) or len(link["between"]) != 2:
            raise InputError(path, f"links[{i}]: needs between: [a, b]")
        if not all(isinstance(c, str) for c in link["between"]):
            raise InputError(path, f"links[{i}]: between must name two computers")
        plan.links.append(PlannedLink((link["between"][0], link["between"][1]),
                                      _num(link, "bandwidth_kBps", f"links[{i}]", path, optional=False,
                                           nonneg=True) or 0.0,
                                      _num(link, "load_kBps", f"links[{i}]", path, nonneg=True) or 0.0,
                                      _text(link, "medium", f"links[{i}]", path)))
    nodes = data.get("nodes") or {}
    if not isinstance(nodes, dict):
        raise InputError(path, "nodes must be an object")
    if plan.status != Status.INFEASIBLE and not nodes:
        raise InputError(path, "the plan has no nodes")
    if plan.status != Status.INFEASIBLE and not plan.computers:
        raise InputError(path, "the plan has no computers")
    forced = data.get("forced", False)
    if not isinstance(forced, bool):
        raise InputError(path, f"plan: 'forced' must be true or false, got {forced!r}")
    for name, n in nodes.items():
        plan.nodes[name] = _parse_node(n, f"node {name!r}", path)
        _check_placed(plan, name, path, forced=forced)
    plan.chains = _parse_chains(data.get("chains"), path)
    return plan


def _parse_chains(raw: Any, path: str) -> list[dict[str, Any]]:
    """plan.json ``chains``: each a name, its topics, ``predicted_ms`` {p50, p95} (numbers
    >= 0, or null when it cannot be predicted), ``budget_ms`` and ``hops`` (each with its own
    ``predicted_ms``); kept as read."""
    if raw is None:
        return []
    if not isinstance(raw, list):
        raise InputError(path, "chains must be a list")
    for i, c in enumerate(raw):
        where = f"chains[{i}]"
        if not isinstance(c, dict) or not isinstance(c.get("name"), str):
            raise InputError(path, f"{where}: needs a name")
        for label, d in [(where, c), *((f"{where}.hops[{j}]", h) for j, h in enumerate(c.get("hops") or []))]:
            if not isinstance(d, dict):
                raise InputError(path, f"{label}: must be an object")
            for key in ("predicted_ms", "budget_ms"):
                pred = d.get(key)
                if pred is None:
                    continue
                if not isinstance(pred, dict):
                    raise InputError(path, f"{label}: {key!r} must be an object")
                for q in ("p50", "p95"):
                    _num(pred, q, f"{label}.{key}", path, nonneg=True)
    return raw


def is_forced(plan: Plan) -> bool:
    """Whether the plan says ``"forced": true``: built on purpose beyond what its computers
    hold (e.g. to overload one), so its nodes' CPU may exceed their computer's capacity."""
    return plan.extra.get("forced") is True


def _check_placed(plan: Plan, name: str, path: str, *, forced: bool = False) -> None:
    """The node's computer is one of the plan's, and (unless the plan is ``forced``) the
    node's CPU fits its capacity."""
    node = plan.nodes[name]
    computer = plan.computers.get(node.computer)
    if computer is None:
        raise InputError(path, f"node {name!r}: placed on {node.computer!r}, which is not among the plan's computers "
                               f"({', '.join(map(repr, plan.computers)) or 'none'})")
    cap = computer.capacity
    if not forced and cap is not None and node.cpu > cap * (1 + CAPACITY_SLACK) + CAPACITY_SLACK:
        raise InputError(path, f"node {name!r}: 'cpu' {node.cpu:g} exceeds the capacity {cap:g} of its computer "
                               f"{node.computer!r}")


def _parse_node(n: Any, where: str, path: str) -> PlannedNode:
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
        topics[t] = PlannedTopic(_num(r, "frequency_hz", f"{where} topic {t!r}", path, nonneg=True),
                                 _num(r, "bandwidth_kBps", f"{where} topic {t!r}", path, nonneg=True))
    return PlannedNode(
        computer=n["computer"],
        cpu=_num(n, "cpu", where, path, optional=False, nonneg=True) or 0.0,
        performance=_num(n, "performance", where, path, optional=False, nonneg=True) or 0.0,
        weight=_num(n, "weight", where, path, optional=False, positive=True) or 0.0,
        parameter=_text(n, "parameter", where, path), value=_num(n, "value", where, path), topics=topics,
        input=_topic(n, "input", where, path), input_hz=_num(n, "input_hz", where, path, nonneg=True),
        bandwidth_kBps=_num(n, "bandwidth_kBps", where, path, nonneg=True),
        measured=_flag(n, "measured", where, path), loo_error=_errors(n, "loo_error", where, path),
        standalone=bool(_flag(n, "standalone", where, path)),
    )


def _flag(d: dict[str, Any], key: str, where: str, path: str) -> bool | None:
    v = d.get(key)
    if v is not None and not isinstance(v, bool):
        raise Doc(path).fail(where, f"{key!r} must be true or false, got {v!r}")
    return v


def _errors(d: dict[str, Any], key: str, where: str, path: str) -> dict[str, float | None] | None:
    """A mapping of quantity -> a number >= 0 or null (``loo_error``); None when absent."""
    v = d.get(key)
    if v is None:
        return None
    if not isinstance(v, dict):
        raise Doc(path).fail(where, f"{key!r} must be an object")
    return {str(q): _num(v, q, f"{where}.{key}", path, nonneg=True) for q in v}


def check_against_system(plan: Plan, system: System, plan_path: str | Path | None = None) -> None:
    """Every node of the plan must be a node of ``system``, every computer of the plan one
    of its computers, and a driven node's ``input`` the system's (an :class:`InputError`
    naming the system otherwise): a plan for another system cannot be validated or
    deployed with this one. The nodes of one container must share a computer
    (:meth:`System.container_problem`: an error naming the plan)."""
    unknown = [n for n in plan.nodes if n not in system.node]
    if unknown:
        raise InputError(system.source, f"plan node(s) {', '.join(map(repr, unknown))} are not in the system")
    strange = [c for c in plan.computers if c not in system.computer]
    if strange:
        raise InputError(system.source, f"plan computer(s) {', '.join(map(repr, strange))} are not in the system "
                                        f"(its computers: {', '.join(map(repr, system.computer))})")
    for name, pn in plan.nodes.items():  # a driven node follows the same input in both
        wanted = system.node[name].input
        if pn.input != wanted:
            raise InputError(system.source, f"plan node {name!r} follows input {pn.input or 'none'}, the system's "
                                            f"follows {wanted or 'none'}: the plan was made from another system")
    split = system.container_problem({n: p.computer for n, p in plan.nodes.items()}, plan.standalone)
    if split is not None:
        raise InputError(plan_path, split)


def plan_system(plan: Plan, plan_path: str | Path, system_path: str | Path | None = None) -> System | None:
    """The plan's system, checked against the plan (:func:`check_against_system`):
    ``system_path`` when given, else the system the plan was solved from when its path
    still exists (relative paths: beside the plan first, then from the working directory);
    None, with a warning, when it cannot be found or read."""
    from perfros_bag.system.systemfile import load_system

    if system_path is not None:
        system = load_system(system_path)
        check_against_system(plan, system, plan_path)
        return system
    if not plan.system:
        return None
    raw = Path(plan.system)
    for cand in ([raw] if raw.is_absolute() else [Path(plan_path).parent / raw, raw]):
        if cand.is_file():
            try:
                system = load_system(cand)
            except InputError as exc:
                warnings.warn(f"the plan's system could not be read ({exc}); going on without it",
                              PerfrosWarning, stacklevel=2)
                return None
            check_against_system(plan, system, plan_path)
            return system
    warnings.warn(f"the plan's system {plan.system!r} was not found (beside the plan or here): "
                  "links are not checked and CPU traces match nodes by name only",
                  PerfrosWarning, stacklevel=2)
    return None
