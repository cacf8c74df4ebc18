"""Load and validate ``system.yaml`` (and the system part of ``model.json``).

Every problem is an :class:`~perfros_bag.errors.InputError` naming the file, the node
(or computer, link, edge) and the field: ``system.yaml: node 'tracker1': settings[1].cpu
must be > 0``. Unknown keys are errors (a typo must not silently drop a constraint).
Weights that do not sum to 1 are normalised with a warning (eq 6).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from perfros_bag.doccheck import Doc
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fileio import SYSTEM_KIND, expect_kind, file_kind, kind_of, read_yaml
from perfros_bag.limits import MAX_COEFFICIENT, MAX_MAGNITUDE, number_problem
from perfros_bag.system.modelpart import read_model_system
from perfros_bag.system.names import (
    NameKind,
    address_problem,
    name_problem,
    ros2_problem,
    text_problem,
)
from perfros_bag.system.types import (
    CURVE_FORMS,
    Aggregate,
    Better,
    Budget,
    Chain,
    Computer,
    Curve,
    Edge,
    LatencyParams,
    Link,
    Medium,
    Metric,
    Node,
    Parameter,
    Setting,
    System,
    TopicRate,
)

TOP_KEYS = {"cpu_unit", "computers", "links", "media", "nodes", "edges", "machines", "chains", "latency",
            "membership"}
#: system.yaml ``membership``: what solvers may do with ``container:``: "keep" every hosted
#: node in its container, or "choose" (a plan may run a hosted node standalone, paying the copy)
MEMBERSHIPS = ("keep", "choose")
CHAIN_KEYS = {"name", "topics", "budget_ms"}
BUDGET_KEYS = {"p50", "p95"}
#: system.yaml ``latency:`` (the latency model's parameters, perfros_bag.system.latency)
#: the kernel's longest CFS bandwidth period, in ms (latency.cfs_period_ms)
MAX_CFS_PERIOD_MS = 1000.0
LATENCY_KEYS = {"units_per_core", "overhead_ms", "queue_factor", "p95_ratio", "queue_size", "link_efficiency",
                "backlog_msgs", "cfs_period_ms", "link_burst_ms", "service_scale", "node_p95_ratio", "source"}
COMPUTER_KEYS = {"name", "kind", "capacity", "max_capacity"}
LINK_KEYS = {"between", "bandwidth_kBps", "medium"}
MEDIUM_KEYS = {"name", "bandwidth_kBps"}
NODE_KEYS = {
    "name", "weight", "residence", "coresidence", "parameter", "topics", "process",
    "settings", "curve", "launch", "relations", "metric", "input", "cpu_error_between", "container", "threads",
    "copy_cpu_per_MBps",
}
METRIC_KEYS = {"topic", "field", "aggregate", "better", "range"}
#: ``cpu_error`` (optional, CPU units >= 0): what the setting may need beyond its ``cpu``
#: (measured headroom, perfros_bag.system.cpuerror; ``fit`` writes it)
#: ``threads`` (optional, >= 1, on a node or a setting): its busy threads, its weight in the
#: CFS share of an overloaded computer (perfros_bag.system.cpushare; ``fit`` writes the node's)
SETTING_KEYS = {"value", "cpu", "performance", "frequency_hz", "bandwidth_kBps", "topics", "cpu_error", "threads"}
#: a driven node's setting (``input:``) also says how it follows its input rate, and its
#: error as a share of its CPU (``cpu_error_share``, >= 0) instead of ``cpu_error``; ``step``
#: (with ``max_frequency_hz``): how the cap acts, :data:`STEPS`
DRIVEN_KEYS = {"cpu_per_hz", "out_per_in", "max_frequency_hz", "bytes_per_msg", "cpu_error_share", "step"}
#: ``step: period``: a period throttle (topic_tools/throttle), its output ``x / ceil(x / cap)``
STEPS = ("period",)
TOPIC_RATE_KEYS = {"frequency_hz", "bandwidth_kBps"}
PARAMETER_KEYS = {"name", "unit", "type"}
CURVE_KEYS = {"form", "coef", "cpu", "domain", "scale"}
EDGE_KEYS = {"from", "to", "topic", "bandwidth_kBps"}
LAUNCH_KEYS = {"package", "type", "param", "name", "namespace"}
RELATION_KEYS = {"parameter->cpu", "parameter->performance", "cpu->performance",
                 "parameter->frequency", "parameter->bandwidth"}
# ... and per topic: "parameter->frequency:<topic>", "parameter->bandwidth:<topic>"
TOPIC_RELATIONS = {"parameter->frequency", "parameter->bandwidth"}
#: the ROS rule each ``launch:`` field follows
LAUNCH_NAME_KINDS = {"package": NameKind.PACKAGE, "type": NameKind.EXECUTABLE, "param": NameKind.PARAMETER,
                     "name": NameKind.NODE, "namespace": NameKind.NAMESPACE}


class _Ctx(Doc):
    """Where we are in the file, for error messages (:class:`~perfros_bag.doccheck.Doc`),
    and system.yaml's own checks."""

    path: str  # the source as the system states it (System.source)

    def label(self, obj: Any, where: str) -> str | None:
        """A free-text label (a unit): text, or a finite number taken as text; None stays None."""
        if obj is None or isinstance(obj, str):
            return obj
        if number_problem(obj, limit=math.inf) is not None:
            raise self.fail(where, f"must be text, got {kind_of(obj)} {obj!r}"[:200])
        return str(obj)

    def name(self, obj: Any, where: str, kind: NameKind) -> str:
        """A name ROS can use (:mod:`perfros_bag.system.names`); one valid for ROS 1 only
        is kept with a warning."""
        name = self.string(obj, where)
        problem = name_problem(kind, name)
        if problem is not None:
            raise self.fail(where, f"{name!r} {problem}")
        ros2 = ros2_problem(kind, name)
        if ros2 is not None:
            warnings.warn(f"{self.path}: {where}: {name!r} is a valid ROS 1 {kind} but not a ROS 2 one ({ros2})",
                          PerfrosWarning, stacklevel=3)
        return name

    def str_list(self, obj: Any, where: str, kind: NameKind | None = None) -> tuple[str, ...]:
        if isinstance(obj, str):
            obj = [obj]
        if not isinstance(obj, list):
            raise self.fail(where, f"must be a list of names, got {kind_of(obj)}")
        if kind is not None:
            return tuple(self.name(x, f"{where}[{i}]", kind) for i, x in enumerate(obj))
        return tuple(self.string(x, f"{where}[{i}]") for i, x in enumerate(obj))

    def seq(self, obj: Any, where: str) -> list[Any]:
        return [] if obj is None else self.items(obj, where)

    def named(self, obj: Any, section: str, what: str, allowed: set[str], required: set[str], *,
              at_least_one: bool = True, kind: NameKind | None = None) -> Iterator[tuple[str, str, Mapping[str, Any]]]:
        """The entries of a list of named mappings as (name, ``what 'name'``, mapping);
        a name given twice is an error, and so is an empty list when ``at_least_one``;
        with ``kind``, each name must follow that kind's ROS rule."""
        items = self.seq(obj, section)
        if at_least_one and not items:
            raise self.fail(section, f"at least one {what} is needed")
        seen: set[str] = set()
        for i, item in enumerate(items):
            m = self.mapping(item, f"{section}[{i}]", allowed, required)
            name = (self.string(m["name"], f"{section}[{i}].name") if kind is None
                    else self.name(m["name"], f"{section}[{i}].name", kind))
            where = f"{what} {name!r}"
            if name in seen:
                raise self.fail(where, "defined twice")
            seen.add(name)
            yield name, where, m



def read_system_data(path: str | Path) -> Any:
    """The parsed, unchecked content of a ``system.yaml``, or the ``system`` part of a
    ``model.json`` (a ``.json`` file without one is a system written as JSON)."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        return read_model_system(p)
    data = read_yaml(p)
    kind = file_kind(p) if not isinstance(data, Mapping) else None  # a CSV table reads as one string
    if kind is not None:
        raise InputError(p, f"this is {kind}, expected a system.yaml or model.json")
    return data


def load_system(path: str | Path) -> System:
    """Read and validate a ``system.yaml`` (or a ``model.json``, whose ``system`` part has
    the same shape)."""
    return parse_system(read_system_data(path), str(Path(path)))


def parse_system(data: Any, source: str = "system.yaml") -> System:
    ctx = _Ctx(source)
    if data is None:
        raise ctx.fail("", "the file is empty")
    expect_kind(source, data, "a system.yaml or model.json", {SYSTEM_KIND})
    top = ctx.mapping(data, "", TOP_KEYS, {"computers", "nodes"})

    computers = _computers(ctx, top["computers"])
    names = {c.name for c in computers}
    media = _media(ctx, top.get("media"))
    links = _links(ctx, top.get("links"), names, {m.name for m in media})
    nodes = _nodes(ctx, top["nodes"], names)
    node_names = {n.name for n in nodes}
    edges = _edges(ctx, top.get("edges"), node_names)
    machines = _machines(ctx, top.get("machines"), names)
    cpu_unit = ctx.label(top.get("cpu_unit"), "cpu_unit")
    membership = _membership(ctx, top.get("membership"))

    for n in nodes:
        for m in n.coresidence:
            if m not in node_names:
                raise ctx.fail(f"node {n.name!r}: coresidence", f"unknown node {m!r}")
            if m == n.name:
                raise ctx.fail(f"node {n.name!r}: coresidence", "a node cannot list itself")
    _check_containers(ctx, nodes)

    total = sum(n.weight for n in nodes)
    if abs(total - 1.0) > 1e-6:
        warnings.warn(f"{source}: node weights sum to {total:g}, not 1; normalised (eq 6)",
                      PerfrosWarning, stacklevel=2)
        nodes = [_reweight(n, n.weight / total) for n in nodes]

    chains = _chains(ctx, top.get("chains"), nodes, edges)
    latency = _latency(ctx, top.get("latency"), node_names)
    system = System(tuple(computers), tuple(nodes), tuple(links), tuple(media), tuple(edges),
                    cpu_unit, machines, source, chains, latency, membership)
    _check_groups(ctx, system)
    _check_flow(ctx, system)
    _check_budgets(ctx, system)
    return system


def _membership(ctx: _Ctx, raw: Any) -> str:
    """``membership``: "keep" (the default): every node stays in its ``container:``;
    "choose": a plan may run a hosted node standalone (:meth:`System.freed`)."""
    if raw is None:
        return "keep"
    if raw not in MEMBERSHIPS:
        raise ctx.fail("membership", f"must be one of {', '.join(MEMBERSHIPS)}, got {raw!r}")
    return str(raw)


def _check_budgets(ctx: _Ctx, system: System) -> None:
    """A chain with a budget must be one the latency model can follow, hop by hop."""
    from perfros_bag.system.latency import chain_hops

    for chain in system.chains:
        if chain.budget_ms is None:
            continue
        hops = chain_hops(system, chain)
        if isinstance(hops, str):
            raise ctx.fail(f"chain {chain.name!r}: budget_ms", f"its latency cannot be predicted: {hops}")


def _latency(ctx: _Ctx, raw: Any, nodes: set[str]) -> LatencyParams:
    """``latency: {units_per_core, overhead_ms, queue_factor, p95_ratio, queue_size,
    link_efficiency, backlog_msgs, cfs_period_ms, link_burst_ms, service_scale: {node: x},
    node_p95_ratio: {node: x}, source}``, every field optional (the defaults of :class:`LatencyParams`)."""
    if raw is None:
        return LatencyParams()
    m = ctx.mapping(raw, "latency", LATENCY_KEYS)
    base = LatencyParams()
    kw: dict[str, Any] = {}
    for key in ("units_per_core", "p95_ratio", "link_efficiency"):
        if m.get(key) is not None:
            kw[key] = ctx.number(m[key], f"latency.{key}", positive=True)
    for key in ("overhead_ms", "queue_factor", "backlog_msgs", "cfs_period_ms", "link_burst_ms"):
        if m.get(key) is not None:
            kw[key] = ctx.number(m[key], f"latency.{key}", nonneg=True)
    if kw.get("p95_ratio", base.p95_ratio) < 1:
        raise ctx.fail("latency.p95_ratio", f"must be at least 1, got {kw['p95_ratio']:g}")
    if kw.get("cfs_period_ms", base.cfs_period_ms) > MAX_CFS_PERIOD_MS:
        raise ctx.fail("latency.cfs_period_ms", f"must be at most {MAX_CFS_PERIOD_MS:g} (the kernel's longest CFS "
                                                f"period), got {kw['cfs_period_ms']:g}")
    if kw.get("link_efficiency", base.link_efficiency) > 1:
        raise ctx.fail("latency.link_efficiency", f"must be at most 1, got {kw['link_efficiency']:g}")
    if m.get("queue_size") is not None:
        q = ctx.number(m["queue_size"], "latency.queue_size", positive=True)
        if q != int(q):
            raise ctx.fail("latency.queue_size", f"must be a whole number of messages, got {q:g}")
        kw["queue_size"] = int(q)
    for key in ("service_scale", "node_p95_ratio"):
        per = ctx.mapping(m.get(key) or {}, f"latency.{key}", nodes)
        kw[key] = {str(n): ctx.number(v, f"latency.{key}.{n}", positive=True) for n, v in per.items()}
        low = [n for n, v in kw[key].items() if key == "node_p95_ratio" and v < 1]
        if low:
            raise ctx.fail(f"latency.{key}.{low[0]}", "must be at least 1")
    if m.get("source") is not None:
        kw["source"] = ctx.string(m["source"], "latency.source")
    return LatencyParams(**kw)


def _check_flow(ctx: _Ctx, system: System) -> None:
    """Every ``input`` names a topic exactly one node publishes, and inputs form no cycle."""
    for n in system.nodes:
        if n.input is None:
            continue
        publishers = system.publishers.get(n.input, ())
        if not publishers:
            raise ctx.fail(f"node {n.name!r}: input", f"no node of the system publishes {n.input} "
                                                      "(list it under that node's topics)")
        if len(publishers) > 1:
            raise ctx.fail(f"node {n.name!r}: input", f"{n.input} is published by several nodes "
                                                      f"({', '.join(map(repr, publishers))}): a driven node "
                                                      "follows exactly one publisher")
    cycle = system.flow_cycle()
    if cycle is not None:
        path = " <- ".join([*cycle, cycle[0]])
        raise ctx.fail(f"node {cycle[0]!r}: input", f"the inputs form a cycle: {path} (each node driven by the next)")


def _reweight(n: Node, weight: float) -> Node:
    from dataclasses import replace

    return replace(n, weight=weight)


def _computers(ctx: _Ctx, raw: Any) -> list[Computer]:
    out: list[Computer] = []
    for name, where, m in ctx.named(raw, "computers", "computer", COMPUTER_KEYS, {"name", "kind"},
                                      kind=NameKind.COMPUTER):
        kind = m["kind"]
        if kind not in ("robot", "server"):
            raise ctx.fail(f"{where}: kind", f"must be 'robot' or 'server', got {kind!r}")
        capacity = ctx.opt_number(m.get("capacity"), f"{where}: capacity", nonneg=True)
        if capacity is None and kind == "robot":
            raise ctx.fail(f"{where}: capacity", "a robot needs a capacity (only servers are sized by Problem 2)")
        max_cap = ctx.opt_number(m.get("max_capacity"), f"{where}: max_capacity", nonneg=True)
        out.append(Computer(name, kind, capacity, max_cap))
    return out


def _media(ctx: _Ctx, raw: Any) -> list[Medium]:
    out: list[Medium] = []
    for name, where, m in ctx.named(raw, "media", "medium", MEDIUM_KEYS, {"name", "bandwidth_kBps"},
                                    at_least_one=False):
        out.append(Medium(name, ctx.number(m["bandwidth_kBps"], f"{where}: bandwidth_kBps", nonneg=True)))
    return out


def _links(ctx: _Ctx, raw: Any, computers: set[str], media: set[str]) -> list[Link]:
    out: list[Link] = []
    pairs: set[frozenset[str]] = set()
    for i, item in enumerate(ctx.seq(raw, "links")):
        where = f"links[{i}]"
        m = ctx.mapping(item, where, LINK_KEYS, {"between", "bandwidth_kBps"})
        between = ctx.str_list(m["between"], f"{where}.between")
        if len(between) != 2 or between[0] == between[1]:
            raise ctx.fail(f"{where}.between", f"must name two different computers, got {list(between)}")
        for c in between:
            if c not in computers:
                raise ctx.fail(f"{where}.between", f"unknown computer {c!r}")
        key = frozenset(between)
        if key in pairs:
            raise ctx.fail(where, f"a second link between {between[0]!r} and {between[1]!r}")
        pairs.add(key)
        medium = None if m.get("medium") is None else ctx.string(m["medium"], f"{where}.medium")
        if medium is not None and medium not in media:
            raise ctx.fail(f"{where}.medium", f"unknown medium {medium!r} (declare it under media:)")
        bw = ctx.number(m["bandwidth_kBps"], f"{where}.bandwidth_kBps", nonneg=True)
        out.append(Link((between[0], between[1]), bw, medium))
    return out


def parse_curve(ctx_path: str, raw: Any, where: str, *, default_scale: float = 1.0) -> Curve:
    ctx = _Ctx(ctx_path)
    m = ctx.mapping(raw, where, CURVE_KEYS, {"form", "coef"})
    form = m["form"]
    if form not in CURVE_FORMS:
        raise ctx.fail(f"{where}.form", f"unknown form {form!r} (one of {', '.join(CURVE_FORMS)})")
    coef_raw = m["coef"]
    if not isinstance(coef_raw, list):
        raise ctx.fail(f"{where}.coef", "must be a list of numbers")
    coef = tuple(ctx.number(c, f"{where}.coef[{i}]", limit=MAX_COEFFICIENT) for i, c in enumerate(coef_raw))
    dom_raw = m.get("domain", m.get("cpu"))
    if dom_raw is None:
        raise ctx.fail(where, "needs its domain: cpu: [min, max]")
    if not isinstance(dom_raw, list) or len(dom_raw) != 2:
        raise ctx.fail(f"{where}.cpu", "must be [min, max]")
    lo = ctx.number(dom_raw[0], f"{where}.cpu[0]")
    hi = ctx.number(dom_raw[1], f"{where}.cpu[1]")
    scale = ctx.number(m.get("scale", default_scale), f"{where}.scale", positive=True)
    try:
        curve = Curve(form, coef, (lo, hi), scale)
    except ValueError as exc:
        raise ctx.fail(where, str(exc)) from None
    _check_outputs(ctx, curve, where)
    return curve


def curve_output_problem(curve: Curve) -> str | None:
    """Why ``curve`` cannot be used over its domain (an output that is not a finite number
    within :data:`~perfros_bag.limits.MAX_MAGNITUDE` at the domain's ends or, for a
    quadratic, at its vertex), or None."""
    lo, hi = curve.domain
    xs = [lo, hi]
    a, b = (curve.coef[0], curve.coef[1]) if curve.form == "quadratic" else (0.0, 0.0)
    if a != 0 and lo < -b / (2 * a) * curve.scale < hi:
        xs.append(-b / (2 * a) * curve.scale)
    for x in xs:
        try:
            y: Any = curve(x)
        except (OverflowError, ValueError, ZeroDivisionError):
            y = math.inf
        if isinstance(y, complex) or number_problem(y) is not None:
            return (f"gives {y!r} at {x:g}: a curve's values over its domain must be finite numbers "
                    f"at most {MAX_MAGNITUDE:g} in magnitude")
    return None


def _check_outputs(ctx: _Ctx, curve: Curve, where: str) -> None:
    problem = curve_output_problem(curve)
    if problem is not None:
        raise ctx.fail(where, problem)


def _check_containers(ctx: _Ctx, nodes: list[Node]) -> None:
    """``container`` names another node of the system, one that is not hosted itself."""
    by_name = {n.name: n for n in nodes}
    for n in nodes:
        if n.container is None:
            continue
        host = by_name.get(n.container)
        if host is None:
            raise ctx.fail(f"node {n.name!r}: container", f"unknown node {n.container!r} (the container is a node "
                                                          "of the system: the process that hosts it)")
        if host.name == n.name:
            raise ctx.fail(f"node {n.name!r}: container", "a node cannot host itself")
        if host.container is not None:
            raise ctx.fail(f"node {n.name!r}: container", f"{host.name!r} is itself hosted by {host.container!r}: "
                                                          "a container runs in a process of its own")
    hosts = {n.container for n in nodes}
    for n in nodes:
        if n.copy_cpu_per_MBps is not None and n.name not in hosts:
            raise ctx.fail(f"node {n.name!r}: copy_cpu_per_MBps", "only a container (a node others name as their "
                                                                  "container:) has a copy price")


def _nodes(ctx: _Ctx, raw: Any, computers: set[str]) -> list[Node]:
    out: list[Node] = []
    for name, where, m in ctx.named(raw, "nodes", "node", NODE_KEYS, {"name", "weight"}, kind=NameKind.NODE):
        weight = ctx.number(m["weight"], f"{where}: weight", positive=True)

        residence: tuple[str, ...] | None = None
        if m.get("residence") is not None:
            residence = ctx.str_list(m["residence"], f"{where}: residence")
            if not residence:
                raise ctx.fail(f"{where}: residence", "is empty: the node could sit on no computer")
            for c in residence:
                if c not in computers:
                    raise ctx.fail(f"{where}: residence", f"unknown computer {c!r}")
        coresidence = ctx.str_list(m["coresidence"], f"{where}: coresidence") if m.get("coresidence") else ()

        parameter = None
        if m.get("parameter") is not None:
            pm = ctx.mapping(m["parameter"], f"{where}: parameter", PARAMETER_KEYS, {"name"})
            ptype = pm.get("type")
            if ptype is not None and ptype not in ("int", "float"):
                raise ctx.fail(f"{where}: parameter.type", f"must be 'int' or 'float', got {ptype!r}")
            unit = pm.get("unit")
            parameter = Parameter(ctx.name(pm["name"], f"{where}: parameter.name", NameKind.PARAMETER),
                                  ctx.label(unit, f"{where}: parameter.unit"), ptype)

        topics = ctx.str_list(m["topics"], f"{where}: topics", NameKind.TOPIC) if m.get("topics") else ()
        process = m.get("process")
        if process is not None:
            process = ctx.string(process, f"{where}: process")
            import re

            try:
                re.compile(process)
            except re.error as exc:
                raise ctx.fail(f"{where}: process", f"not a valid regular expression: {exc}") from None

        driven_by = None if m.get("input") is None else ctx.name(m["input"], f"{where}: input", NameKind.TOPIC)
        settings = tuple(_setting(ctx, s, f"{where}: settings[{j}]", driven=driven_by is not None)
                         for j, s in enumerate(ctx.seq(m.get("settings"), f"{where}: settings")))
        if driven_by is not None and m.get("curve") is not None:
            raise ctx.fail(f"{where}: curve", "a driven node (input:) takes discrete settings, not a CPU curve: "
                                              "its CPU follows its input's rate")
        curve = None
        if m.get("curve") is not None:
            curve = parse_curve(ctx.path, m["curve"], f"{where}: curve", default_scale=100.0)
            if curve.domain[0] <= 0:
                raise ctx.fail(f"{where}: curve.cpu", "the CPU range must be above 0")
        if not settings and curve is None:
            raise ctx.fail(where, "needs settings (at least one) or a curve")
        if parameter is None and len(settings) > 1:
            raise ctx.fail(where, "has several settings but no parameter: name the parameter they set")

        relations: dict[str, Curve] = {}
        if m.get("relations") is not None:
            per_topic = {k for k in m["relations"] if isinstance(k, str) and k.partition(":")[0] in TOPIC_RELATIONS
                         and k.partition(":")[2]} if isinstance(m["relations"], Mapping) else set()
            rm = ctx.mapping(m["relations"], f"{where}: relations", RELATION_KEYS | per_topic)
            for key, rv in rm.items():
                if key in per_topic:
                    ctx.name(key.partition(":")[2], f"{where}: relations.{key}", NameKind.TOPIC)
                relations[key] = parse_curve(ctx.path, rv, f"{where}: relations.{key}")

        launch: dict[str, str] = {}
        if m.get("launch") is not None:
            lm = ctx.mapping(m["launch"], f"{where}: launch", LAUNCH_KEYS)
            hosted = m.get("container") is not None
            kind = lm.get("type")
            if not hosted and isinstance(kind, str) and name_problem(NameKind.PLUGIN, kind) is None:
                raise ctx.fail(f"{where}: launch.type", f"{kind!r} names a plugin class, which only a node with a "
                               "container (a nodelet's manager, a component container) loads: add container: or "
                               "give an executable")
            launch = {k: ctx.name(v, f"{where}: launch.{k}", _launch_kind(k, v, hosted)) for k, v in lm.items()}

        metric = _metric(ctx, m["metric"], f"{where}: metric") if m.get("metric") is not None else None
        between = ctx.opt_number(m.get("cpu_error_between"), f"{where}: cpu_error_between", nonneg=True)
        if between is not None and curve is None:
            raise ctx.fail(f"{where}: cpu_error_between",
                           "only a node with a curve has CPU levels between its settings")
        container = None if m.get("container") is None else ctx.name(m["container"], f"{where}: container",
                                                                       NameKind.NODE)
        threads = _threads(ctx, m.get("threads"), f"{where}: threads")
        copy = ctx.opt_number(m.get("copy_cpu_per_MBps"), f"{where}: copy_cpu_per_MBps", nonneg=True)
        out.append(Node(name, weight, settings, curve, residence, coresidence, parameter,
                        topics, process, launch, relations, metric, driven_by, between, container, threads, copy))
    return out


def _launch_kind(key: str, value: Any, hosted: bool) -> NameKind:
    """The rule ``launch.KEY`` follows: a hosted node's (``container:``) ``type`` may name its
    plugin class (``pkg::Class`` or ``pkg/name``) instead of an executable."""
    if key == "type" and isinstance(value, str) and ("::" in value or "/" in value):
        return NameKind.PLUGIN if hosted else NameKind.EXECUTABLE
    return LAUNCH_NAME_KINDS[key]


def _threads(ctx: _Ctx, raw: Any, where: str) -> float | None:
    """An optional busy-thread count: a number >= 1."""
    value = ctx.opt_number(raw, where, positive=True)
    if value is not None and value < 1:
        raise ctx.fail(where, f"must be >= 1 (busy threads), got {raw!r}")
    return value


def _metric(ctx: _Ctx, raw: Any, where: str) -> Metric:
    m = ctx.mapping(raw, where, METRIC_KEYS, {"topic"})
    topic = ctx.string(m["topic"], f"{where}.topic")
    aggregate = m.get("aggregate", "mean")
    if aggregate not in {a.value for a in Aggregate}:
        raise ctx.fail(f"{where}.aggregate",
                       f"must be one of {', '.join(a.value for a in Aggregate)}, got {aggregate!r}")
    better = m.get("better", "higher")
    if better not in {b.value for b in Better}:
        raise ctx.fail(f"{where}.better", f"must be 'higher' or 'lower', got {better!r}")
    if m.get("field") is None and aggregate != Aggregate.RATE:
        raise ctx.fail(where, "needs a 'field' (only aggregate 'rate' does without)")
    field = "" if m.get("field") is None else ctx.string(m["field"], f"{where}.field")
    bounds = None
    if m.get("range") is not None:
        rr = m["range"]
        if not isinstance(rr, list) or len(rr) != 2:
            raise ctx.fail(f"{where}.range", f"must be [low, high], got {rr!r}")
        lo, hi = (ctx.number(x, f"{where}.range") for x in rr)
        if not hi > lo:
            raise ctx.fail(f"{where}.range", f"high must be above low, got {rr!r}")
        bounds = (lo, hi)
    return Metric(topic, field, Aggregate(aggregate), Better(better), bounds)


def _setting(ctx: _Ctx, raw: Any, where: str, *, driven: bool = False) -> Setting:
    m = ctx.mapping(raw, where, SETTING_KEYS | DRIVEN_KEYS,
                    {"cpu", "performance"} | ({"cpu_per_hz"} if driven else set()))
    if not driven:
        extra = sorted(k for k in DRIVEN_KEYS if k in m)
        if extra:
            raise ctx.fail(where, f"{', '.join(extra)}: only a driven node (one with input:) follows an input rate")
    elif "cpu_error" in m:
        raise ctx.fail(f"{where}.cpu_error", "a driven node (input:) states its error relative to its CPU: "
                                             "cpu_error_share")
    step = m.get("step")
    if step is not None:
        if step not in STEPS:
            raise ctx.fail(f"{where}.step", f"must be one of {', '.join(STEPS)}, got {step!r}"[:200])
        if m.get("max_frequency_hz") is None:
            raise ctx.fail(f"{where}.step", "a step says how max_frequency_hz caps the output: give max_frequency_hz")
    topics: dict[str, TopicRate] = {}
    if m.get("topics") is not None:
        tm = ctx.mapping(m["topics"], f"{where}.topics",
                         set(m["topics"]) if isinstance(m["topics"], Mapping) else set())
        for topic, rate in tm.items():
            ctx.name(topic, f"{where}.topics", NameKind.TOPIC)
            rm = ctx.mapping(rate, f"{where}.topics.{topic}", TOPIC_RATE_KEYS)
            topics[str(topic)] = TopicRate(
                ctx.opt_number(rm.get("frequency_hz"), f"{where}.topics.{topic}.frequency_hz", nonneg=True),
                ctx.opt_number(rm.get("bandwidth_kBps"), f"{where}.topics.{topic}.bandwidth_kBps", nonneg=True),
            )
    return Setting(
        # a driven node's cpu is the part that does not follow its input: it may be 0
        cpu=ctx.number(m["cpu"], f"{where}.cpu", positive=not driven, nonneg=driven),
        performance=ctx.number(m["performance"], f"{where}.performance", nonneg=True),
        value=ctx.opt_number(m.get("value"), f"{where}.value"),
        frequency_hz=ctx.opt_number(m.get("frequency_hz"), f"{where}.frequency_hz", nonneg=True),
        bandwidth_kBps=ctx.opt_number(m.get("bandwidth_kBps"), f"{where}.bandwidth_kBps", nonneg=True),
        topics=topics,
        # a driven setting's CPU per input Hz is required: null is no number (not 0)
        cpu_per_hz=(ctx.number if driven else ctx.opt_number)(m.get("cpu_per_hz"), f"{where}.cpu_per_hz",
                                                               nonneg=True),
        out_per_in=ctx.opt_number(m.get("out_per_in"), f"{where}.out_per_in", nonneg=True),
        max_frequency_hz=ctx.opt_number(m.get("max_frequency_hz"), f"{where}.max_frequency_hz", nonneg=True),
        bytes_per_msg=ctx.opt_number(m.get("bytes_per_msg"), f"{where}.bytes_per_msg", nonneg=True),
        step="period" if step == "period" else None,
        cpu_error=ctx.opt_number(m.get("cpu_error"), f"{where}.cpu_error", nonneg=True),
        cpu_error_share=ctx.opt_number(m.get("cpu_error_share"), f"{where}.cpu_error_share", nonneg=True),
        threads=_threads(ctx, m.get("threads"), f"{where}.threads"),
    )


def _edges(ctx: _Ctx, raw: Any, nodes: set[str]) -> list[Edge]:
    out: list[Edge] = []
    for i, item in enumerate(ctx.seq(raw, "edges")):
        where = f"edges[{i}]"
        m = ctx.mapping(item, where, EDGE_KEYS, {"from", "to"})
        src = ctx.string(m["from"], f"{where}.from")
        dst = ctx.string(m["to"], f"{where}.to")
        for end in (src, dst):
            if end not in nodes:
                raise ctx.fail(where, f"unknown node {end!r}")
        topic = m.get("topic")
        out.append(Edge(src, dst, None if topic is None else ctx.name(topic, f"{where}.topic", NameKind.TOPIC),
                        ctx.opt_number(m.get("bandwidth_kBps"), f"{where}.bandwidth_kBps", nonneg=True)))
    return out


def _chains(ctx: _Ctx, raw: Any, nodes: list[Node], edges: list[Edge]) -> tuple[Chain, ...]:
    """``chains: [{name, topics: [first, ..., last]}]``: at least two distinct topics, each
    one a node's or an edge's."""
    known = {t for n in nodes for t in n.topics} | {e.topic for e in edges if e.topic is not None}
    out: list[Chain] = []
    for name, where, m in ctx.named(raw, "chains", "chain", CHAIN_KEYS, {"name", "topics"}, at_least_one=False):
        topics = ctx.str_list(m["topics"], f"{where}: topics", NameKind.TOPIC)
        if len(topics) < 2:
            raise ctx.fail(f"{where}: topics", f"a chain needs at least 2 topics, got {len(topics)}")
        if len(set(topics)) != len(topics):
            raise ctx.fail(f"{where}: topics", "a topic is listed twice")
        for i, t in enumerate(topics):
            if t not in known:
                raise ctx.fail(f"{where}: topics[{i}]", f"{t!r} is not a topic of any node or edge of the system")
        out.append(Chain(name, topics, _budget(ctx, m.get("budget_ms"), f"{where}: budget_ms")))
    return tuple(out)


def _budget(ctx: _Ctx, raw: Any, where: str) -> Budget | None:
    """``budget_ms: {p50: X, p95: Y}`` (either or both): positive, finite milliseconds."""
    if raw is None:
        return None
    m = ctx.mapping(raw, where, BUDGET_KEYS)
    bounds = {k: ctx.number(m[k], f"{where}.{k}", positive=True) for k in ("p50", "p95") if m.get(k) is not None}
    if not bounds:
        raise ctx.fail(where, "give p50, p95 or both (milliseconds)")
    if "p50" in bounds and "p95" in bounds and bounds["p95"] < bounds["p50"]:
        raise ctx.fail(where, f"p95 {bounds['p95']:g} ms is below p50 {bounds['p50']:g} ms")
    return Budget(bounds.get("p50"), bounds.get("p95"))


def _machines(ctx: _Ctx, raw: Any, computers: set[str]) -> dict[str, dict[str, str]]:
    if raw is None:
        return {}
    m = ctx.mapping(raw, "machines", computers)
    out: dict[str, dict[str, str]] = {}
    for name, attrs in m.items():
        am = ctx.mapping(attrs, f"machines.{name}",
                         {"address", "user", "env_loader", "ssh_port", "password", "default"})
        out[str(name)] = {str(k): _machine_attr(ctx, f"machines.{name}.{k}", str(k), v) for k, v in am.items()}
    return out


def _machine_attr(ctx: _Ctx, where: str, key: str, raw: Any) -> str:
    """A ``machines:`` attribute as the text roslaunch gets: a scalar, no control
    characters; ``address`` a host name, IP address or substitution."""
    if isinstance(raw, Mapping | list) or raw is None:
        raise ctx.fail(where, f"must be a single value, got {kind_of(raw)}")
    text = raw if isinstance(raw, str) else ctx.label(raw, where) or ""
    problem = text_problem(text) or (address_problem(text) if key == "address" else None)
    if problem is not None:
        raise ctx.fail(where, f"{text!r} {problem}")
    return text


def _check_groups(ctx: _Ctx, system: System) -> None:
    """Every coresidence group must have a computer allowed for all its members; under
    ``membership: choose``, once every node that may leave its container has left (a plan
    that keeps such a node in then needs a computer for the whole container, which the
    solvers find or not)."""
    if system.membership == "choose" and system.may_leave:
        system = system.freed(system.may_leave)
    for group in system.coresidence_groups:
        if not system.allowed_to_all(group):
            who = ", ".join(repr(n) for n in group)
            host = next((n for n in group if n in system.containers), None)
            pair = next(((a, b) for i, a in enumerate(group) for b in group[i + 1:]
                         if not system.allowed_to_all((a, b))), None)
            if host is not None and pair is not None:  # name the two nodes the membership ties
                a, b = pair
                raise ctx.fail(f"container {host!r}: residence",
                               f"nodes {a!r} (allowed on {', '.join(system.allowed(a))}) and {b!r} (allowed on "
                               f"{', '.join(system.allowed(b))}) share the process of container {host!r}, so its "
                               f"computer, and no computer is allowed for both (coresident nodes: {who})")
            raise ctx.fail(f"node {group[0]!r}: residence",
                           f"coresident nodes {who} have no computer allowed for all of them")
