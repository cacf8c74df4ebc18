"""Problem 1 on fleets: column generation over the fleet's structure (Dantzig-Wolfe, i.e.
the Lagrangian dual of the shared CPU capacities), then a MILP over the columns found.

A robot's nodes interact with the rest of a fleet only through the computers they may
share (the servers) and the network. This solver splits the instance that way:

- A robot is *private* when every node group (a coresidence group, or a lone node)
  allowed on it has it as its only allowed robot (the fleet: a robot's stack runs on
  its robot or on a server). Its block is those groups; its own capacity stays inside the
  block's subproblem. Every other computer (the servers, robots shared between blocks)
  is *relaxed*: its capacity becomes a price.
- Each block's subproblem, given prices ``λ`` per relaxed computer, is a multiple-choice
  knapsack on its robot (each group: a setting on the robot, or "offloaded": its best
  relaxed computer and settings at value ``w·P - λ·U``), solved exactly by dynamic
  programming on the CPU grid (``local.combine_tables``, greedy+'s knapsack step). A group
  that belongs to no block (a camera tracker) is its own subproblem. Identical
  subproblems (same nodes' choices, weights, computers, capacity: identical trackers,
  robots of equal capacity) are aggregated into one class with a count.
- The master LP (HiGHS) chooses a convex combination of each class's columns under the
  relaxed capacities; its duals are the next prices; the subproblems price new columns.
  For any prices ``λ >= 0``, ``Σ_class count·max(subproblem) + Σ λ·capacity`` is an upper
  bound on Problem 1 (the Lagrangian bound, at least as tight as the x form's LP bound:
  the robot knapsacks are solved integrally); the best one seen is the plan's ``bound``.
- The columns found, made integer (a count per column), are a small MILP that HiGHS
  solves with the paper's greedy's plan as its start: its answer is the plan.

Links and media that could overflow (``instance.active_links``) are coupling rows too, each
with its price: a block's own edges load them (exactly, per column) and are priced in its
subproblem by a tree over its home/away patterns (:func:`_price_network`, never above a
column's true reduced value, so the bound stays a bound); the traffic between blocks is
reserved on them when the plan is made. The plan is checked against the whole network.
Problem 2 (servers sized to their load, settings fixed) is the same search with a column
worth minus the CPU it puts on the relaxed computers (nothing at home): the plan's servers
are sized to their load, its objective and bound are Σ sizes (the bound: minus the
Lagrangian one, a lower bound on every plan's).

Driven nodes (system.yaml ``input:``): a block carries the data flow on its robot (a
camera whose rate is a knob and the detector it drives, wherever the detector runs). Its
*views* are the consistent assignments of its publishers' rates (:func:`flow_views`): in
each, every member keeps only the choices that agree with it (the detector's at the
camera's rate, so its CPU and the image traffic on the access point follow the rate), and
the choices are independent again. The block's pricing is the best over its views; every
consistent column lies in exactly one, so the pricing is exact and the Lagrangian bound
stays a proof. A flow that leaves its robot's block (a driven node that may only run on a
server, a node driven from two robots) is not decomposed: :func:`decomposable` is False
and ``exact`` solves the whole MILP, whose flow rows tie the choices; so is a block with
more than :data:`MAX_VIEWS` views.

:func:`decomposable` says whether an instance qualifies; otherwise ``solve --method exact``
uses the MILP.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from perfros_bag.solver.instance import (
    Group,
    Instance,
    Progress,
    active_links,
    crossings,
    prepare_instance,
    trivial_bound,
)
from perfros_bag.solver.local import combine_tables, on_grid
from perfros_bag.solver.milp import quiet_highs
from perfros_bag.solver.starts import PLUS_START_MAX_S, greedy_start, plus_start
from perfros_bag.system.plan import Assignment, Method, Plan, Status
from perfros_bag.system.rules import build_plan, computer_loads, server_sizes, weighted_performance
from perfros_bag.system.types import Choice, Edge, Problem, System

__all__ = ["decomposable", "flow_decline", "solve_decomposed"]


GRID_SCALES = (1, 2, 4, 5, 10)  # CPU grid factors tried (CPU x factor must be integers)
MAX_CELLS = 5_000  # CPU cells of one private computer's knapsack table
MAX_GROUP_OPTIONS = 20_000  # setting combinations of one coresidence group
CG_SHARE = 0.5  # share of the time limit column generation may take
PLAN_SHARE = 0.05  # share kept for building the plan (the --time-limit promise is 5 %)
PLAN_MIN_S = 0.15  # ... at least this: HiGHS stops a little after its limit (measured up to ~0.1 s)
NO_LIMIT_S = 120.0  # the MILP's limit when no time limit is given
REL_TOL = 1e-6  # "optimal": bound - objective within this (relative), as exact.py
FIRST_MIP_SHARE = 0.5  # of the time left, for the MILP over the generated columns
NEAR_LIMIT = 20_000  # columns the reduced-cost enumeration may add (else it is not tried)
CG_TOL = 1e-7  # column generation stops when the LP is this close to the bound (relative)
# of the budget, for greedy+'s first plan when the greedy finds none (at most starts.PLUS_START_MAX_S)
GREEDY_PLUS_SHARE = 0.1
MAX_PATTERNS = 1024  # with network rows: home/away patterns of one block's pricing
MAX_VIEWS = 64  # consistent rate assignments of one block's data-flow trees (each priced)


@dataclass
class _Item:
    """One node group: its home options (on its private robot) and its members' choices."""

    members: tuple[str, ...]
    relaxed: np.ndarray  # indices of the relaxed computers it may go to
    home_units: np.ndarray  # per home option: CPU in grid units
    home_values: np.ndarray  # per home option: Σ w·P
    home_levels: list[tuple[int, ...]]  # per home option: each member's kept position
    member_cpu: list[np.ndarray]  # per member: CPU of each kept choice
    member_val: list[np.ndarray]  # per member: w·P of each kept choice


@dataclass
class _Edge:
    """An edge between two items of one block (a class with one instance): it loads the
    network rows when its ends are on different computers."""

    pub: int  # the publisher's item
    member: int  # the publisher's position among its item's members
    sub: int  # the subscriber's item
    bw: np.ndarray  # kB/s at each kept choice of the publisher
    home_bw: np.ndarray  # kB/s at each home option of the publisher's item


@dataclass
class _Outer:
    """An edge from one item of a block to a node outside it (a lone group, another block):
    the links it crosses wherever that node runs, per computer of the item, at its least."""

    item: int
    member: int  # the publisher's position in the item; -1: the item is the subscriber
    bw: np.ndarray  # the block end publishes: kB/s per kept choice; else [the publisher's least]
    home_bw: np.ndarray  # the block end publishes: kB/s per home option of the item
    at_home: tuple[int, ...]  # links (with rows) crossed whatever the other end's computer, item at home
    away: dict[int, tuple[int, ...]]  # the same per relaxed computer of the item


@dataclass
class _Class:
    """Identical subproblems: a private robot and its groups, or one lone group."""

    home: str | None
    cap_units: int
    items: list[_Item]
    instances: list[list[tuple[str, ...]]]  # per instance, the member names of each item
    home_of: list[str | None]  # per instance, its private robot
    edges: list[_Edge] = field(default_factory=list)  # with network rows: the block's own edges
    outer: list[_Outer] = field(default_factory=list)  # ... and its edges to the rest, at their least
    links: frozenset[int] = frozenset()  # the network rows' links those edges may cross
    # a block carrying data-flow trees (a camera and the detector it drives): per consistent
    # assignment of its publishers' rates, the block with each member's choices cut to those
    # that agree with it (masked items; their edges' and outer edges' home traffic to match).
    # Pricing takes the best of them; empty: the block itself, every choice free
    views: list[_Class] = field(default_factory=list)


@dataclass
class _Column:
    cls: int
    value: float  # Σ w·P
    use: dict[int, float]  # relaxed computer -> CPU
    parts: tuple[tuple[int, tuple[int, ...]], ...]  # per item: (relaxed computer or -1: home, levels)


@dataclass
class _Model:
    inst: Instance
    relaxed: list[str]
    cap: np.ndarray  # per coupling row: the relaxed computers' CPU, then the network rows' kB/s
    classes: list[_Class]
    # network rows (after the CPU rows): per link that can overflow, its row and its medium's row
    link_rows: dict[int, list[int]] = field(default_factory=dict)
    reserve: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per row: traffic between blocks, at most
    row_names: list[str] = field(default_factory=list)  # per row: "computer C", "link A-B", "medium M"
    cramped: list[int] = field(default_factory=list)  # rows the traffic between blocks could fill alone
    # Problem 2 (servers sized to their load): a column's value is minus the CPU it puts on
    # the relaxed computers (the servers), nothing at home; maximising it minimises Σ sizes
    sized: bool = False


def cpu_grid_scale(cpus: Sequence[float]) -> int | None:
    for s in GRID_SCALES:
        if on_grid(cpus, s):
            return s
    return None


def home_options(inst: Instance, members: tuple[str, ...], scale: int,
                 allowed: dict[str, frozenset[int]] | None = None) -> tuple[np.ndarray, np.ndarray,
                                                                          list[tuple[int, ...]]] | None:
    """A group's settings on its robot: every combination of its members' choices (only the
    positions ``allowed`` names, for the members it names), keeping for each CPU the best
    value (and nothing dominated)."""
    lists = [inst.choices[n] for n in members]
    positions = [sorted(allowed[n]) if allowed and n in allowed else list(range(len(x)))
                 for n, x in zip(members, lists, strict=True)]
    if math.prod(len(x) for x in positions) > MAX_GROUP_OPTIONS:
        return None
    weight = {n: inst.system.node[n].weight for n in members}
    best: dict[int, tuple[float, tuple[int, ...]]] = {}
    for levels in itertools.product(*positions):
        cpu = sum(lists[i][k].cpu for i, k in enumerate(levels))
        value = sum(weight[n] * lists[i][k].performance for i, (n, k) in enumerate(zip(members, levels, strict=True)))
        units = int(round(cpu * scale))
        if units not in best or value > best[units][0] + 1e-12:
            best[units] = (value, levels)
    units_sorted = sorted(best)
    keep: list[int] = []
    top = -math.inf
    for u in units_sorted:
        if best[u][0] > top + 1e-12:
            keep.append(u)
            top = best[u][0]
    return (np.array(keep, dtype=np.int64), np.array([best[u][0] for u in keep]), [best[u][1] for u in keep])


def flow_views(inst: Instance, nodes: Sequence[str]) -> list[dict[str, frozenset[int]]]:
    """The consistent rate assignments of one data-flow tree (``nodes``: its source, then the
    nodes it drives in flow order): per assignment, each node's kept choices that agree with
    it (a source's choices at one output rate; a driven node's at the input rate its
    publisher then gives and, when it drives others, at one output rate of its own). Every
    consistent choice of the tree's nodes lies in exactly one assignment."""
    return _views(inst.system, inst.choices, nodes)


def flow_decline(system: System, choices: dict[str, list[Choice]]) -> str | None:
    """Why the decomposition cannot take this system's data flow, read from the system and
    its choices alone (no prepared instance: milliseconds on a fleet), or None: a flow tree
    that does not lie in one robot's block (:func:`_model`'s blocks), or a robot whose trees
    have more than :data:`MAX_VIEWS` consistent rate assignments (counted on ``choices``,
    before the instance drops dominated ones)."""
    if not system.has_flow:
        return None
    kind = {c.name: c.kind for c in system.computers}
    robots_of = [[c for c in allowed if kind[c] == "robot"] for allowed in system.group_computers]
    private = {c for c, k in kind.items() if k == "robot"}
    for robots in robots_of:
        if len(robots) != 1:
            private -= set(robots)
    block_of = {n: robots[0] for g, robots in zip(system.coresidence_groups, robots_of, strict=True)
                for n in g if len(robots) == 1 and robots[0] in private}
    trees = _flow_trees(system)
    per_robot: dict[str, int] = {}
    for root, nodes in trees.items():
        homes = {block_of.get(n) for n in nodes}
        if len(homes) != 1 or None in homes:
            return (f"the data flow from {root} spans more than one robot's block (or reaches a node shared "
                    f"between robots): its rates cannot be priced robot by robot")
        home = block_of[root]
        per_robot[home] = per_robot.get(home, 1) * len(_views(system, choices, nodes))
        if per_robot[home] > MAX_VIEWS:
            return (f"robot {home} carries more than {MAX_VIEWS} consistent rate assignments of its data flow "
                    f"to price")
    return None


def _flow_trees(system: System) -> dict[str, list[str]]:
    """Per data-flow source, its tree: the source, then the nodes it drives in flow order."""
    trees: dict[str, list[str]] = {}
    for n in system.flow_order:
        root = n
        while root in system.flow_parent:
            root = system.flow_parent[root]
        trees.setdefault(root, [root]).append(n)
    return trees


def _views(system: System, choices: dict[str, list[Choice]], nodes: Sequence[str]) -> list[dict[str, frozenset[int]]]:
    """:func:`flow_views` on ``choices`` (node -> its choices)."""
    def output(n: str, k: int) -> tuple[float, ...]:
        return tuple(round(system.input_hz(child, choices[n][k]), 9) for child in system.flow_children.get(n, ()))

    out: list[dict[str, frozenset[int]]] = []
    # depth-first over the nodes in flow order: (next node, positions so far, rate each node is given)
    stack: list[tuple[int, dict[str, frozenset[int]], dict[str, float]]] = [(0, {}, {})]
    while stack:
        i, chosen, given = stack.pop()
        if i == len(nodes):
            out.append(chosen)
            continue
        n = nodes[i]
        ks = [k for k, ch in enumerate(choices[n])
              if n not in given or (ch.input_hz is not None and math.isclose(ch.input_hz, given[n], rel_tol=1e-9,
                                                                                abs_tol=1e-9))]
        by_output: dict[tuple[float, ...], list[int]] = {}
        for k in ks:
            by_output.setdefault(output(n, k), []).append(k)
        for rates, group in by_output.items():
            more = dict(given)
            for child, f in zip(system.flow_children.get(n, ()), rates, strict=True):
                more[child] = f
            stack.append((i + 1, {**chosen, n: frozenset(group)}, more))
    return out


def _model(system: System, inst: Instance, active: set[int] | None = None) -> _Model | str:
    """The blocks and classes of a prepared instance, or why it does not decompose.
    ``active``: the links that can overflow (``instance.active_links``): each, and each medium
    of one, becomes a network row beside the relaxed computers' CPU rows."""
    active = active or set()
    sized = inst.problem == Problem.SERVER_CAPACITY
    kind = {c.name: c.kind for c in system.computers}
    robots_of = {g.members: [c for c in g.allowed if kind[c] == "robot"] for g in inst.groups}
    private = {c.name for c in system.computers if c.kind == "robot"}
    for g in inst.groups:
        if len(robots_of[g.members]) != 1:
            private -= set(robots_of[g.members])
    relaxed = [c.name for c in system.computers if c.name not in private]
    rindex = {c: i for i, c in enumerate(relaxed)}
    blocks: dict[str, list[Group]] = {c: [] for c in private}
    lone: list[Group] = []
    for g in inst.groups:
        home = robots_of[g.members][0] if len(robots_of[g.members]) == 1 else None
        (blocks[home] if home in private else lone).append(g)
    cpus = [ch.cpu for g in inst.groups for n in g.members for ch in inst.choices[n]]
    scale = cpu_grid_scale(cpus)
    if scale is None:
        return "CPU levels are not on a grid of at most 1/10 unit"
    if any(inst.cap[c] * scale > MAX_CELLS for c in private):
        return f"a robot's capacity exceeds {MAX_CELLS} grid cells"

    # the data flow: each tree (a source and the nodes it drives) must lie in one robot's block
    block_of = {n: home for home, gs in blocks.items() for g in gs for n in g.members}
    trees = _flow_trees(system)
    block_trees: dict[str, list[list[str]]] = {}
    for root, nodes in trees.items():
        homes = {block_of.get(n) for n in nodes}
        if len(homes) != 1 or None in homes:
            return (f"the data flow from {root} spans more than one robot's block (or reaches a node shared "
                    f"between robots): its rates cannot be priced robot by robot")
        block_trees.setdefault(block_of[root], []).append(nodes)

    def item(g: Group, home: str | None, allowed: dict[str, frozenset[int]] | None = None) -> _Item | None:
        relaxed_ok = np.array([rindex[c] for c in g.allowed if c in rindex], dtype=np.int64)
        mc = [np.array([ch.cpu for ch in inst.choices[n]]) for n in g.members]
        mv = [-c if sized else np.array([system.node[n].weight * ch.performance for ch in inst.choices[n]])
              for n, c in zip(g.members, mc, strict=True)]
        if allowed:  # a view: a choice that disagrees with the view's rates is worth -inf
            mv = [v if n not in allowed else np.where(np.isin(np.arange(len(v)), sorted(allowed[n])), v, -np.inf)
                  for n, v in zip(g.members, mv, strict=True)]
        if home is None:
            return _Item(g.members, relaxed_ok, np.zeros(0, dtype=np.int64), np.zeros(0), [], mc, mv)
        opts = home_options(inst, g.members, scale, allowed)
        if opts is None:
            return None
        if sized:  # at home a group costs nothing: its cheapest option alone
            opts = (opts[0][:1], np.zeros(1), opts[2][:1])
        return _Item(g.members, relaxed_ok, opts[0], opts[1], opts[2], mc, mv)

    def signature(g: Group) -> tuple[Any, ...]:
        return tuple((system.node[n].weight, tuple((ch.cpu, ch.performance) for ch in inst.choices[n]))
                     for n in g.members) + (tuple(c for c in g.allowed if c in rindex),)

    classes: list[_Class] = []
    by_sig: dict[tuple[Any, ...], int] = {}
    for home in [c.name for c in system.computers if c.name in private]:
        gs = blocks[home]
        if not gs:
            continue
        cap_units = int(math.floor(inst.cap[home] * scale + 1e-6))
        flow = block_trees.get(home, [])
        sig: tuple[Any, ...] = (cap_units, tuple(sorted((signature(g) for g in gs), key=repr)),
                                home if active or flow else None)  # network rows, a data flow: its own class
        gs = sorted(gs, key=lambda g: repr(signature(g)))
        if sig in by_sig:
            cl = classes[by_sig[sig]]
            cl.instances.append([g.members for g in gs])
            cl.home_of.append(home)
            continue
        items = [item(g, home) for g in gs]
        if any(it is None for it in items):
            return "a coresidence group has too many setting combinations"
        by_sig[sig] = len(classes)
        classes.append(_Class(home, cap_units, [it for it in items if it is not None], [[g.members for g in gs]],
                              [home]))
        if flow:
            masks = [dict(itertools.chain.from_iterable(m.items() for m in combo))
                     for combo in itertools.product(*(flow_views(inst, nodes) for nodes in flow))]
            if not masks:
                return f"robot {home}'s data flow has no choices that agree with their inputs' rates"
            if len(masks) > MAX_VIEWS:
                return (f"robot {home} carries {len(masks)} consistent rate assignments of its data flow: "
                        f"more than {MAX_VIEWS} to price")
            for mask in masks:
                view_items = [item(g, home, mask) for g in gs]
                if any(it is None for it in view_items):
                    return "a coresidence group has too many setting combinations"
                classes[-1].views.append(_Class(home, cap_units, [it for it in view_items if it is not None],
                                                classes[-1].instances, [home]))
    for g in lone:
        sig = ("lone", signature(g))
        if sig in by_sig:
            classes[by_sig[sig]].instances.append([g.members])
            classes[by_sig[sig]].home_of.append(None)
            continue
        it = item(g, None)
        assert it is not None
        by_sig[sig] = len(classes)
        classes.append(_Class(None, 0, [it], [[g.members]], [None]))
    # a Problem 2 server without max_capacity: no plan puts more than every node's CPU on it
    room = sum(max(ch.cpu for ch in opts) for opts in inst.choices.values()) + 1.0
    cap = np.array([min(inst.cap[c], room) for c in relaxed], dtype=float)
    model = _Model(inst, relaxed, cap, classes, row_names=[f"computer {c}" for c in relaxed], sized=sized)
    if active:
        why = _network_rows(model, active)
        if why is not None:
            return why
    return model


def _home_bw(it: _Item, member: int, bw: np.ndarray) -> np.ndarray:
    """kB/s at each home option of ``it`` of its ``member``'s edge (``bw`` per kept choice)."""
    return np.array([bw[levels[member]] for levels in it.home_levels]) if it.home_levels else np.zeros(0)


def _add_outer(model: _Model, e: Edge, end: tuple[int, int, int], bw: np.ndarray, publishes: bool) -> None:
    """Record edge ``e`` between a block item (``end``: class, item, member) and the rest:
    the links with rows that it crosses wherever its other end runs, for each computer of
    the item (a lower bound on its load, priced in the block and counted in its columns;
    the reserve covers it at its most all the same)."""
    inst, system = model.inst, model.inst.system
    cl = model.classes[end[0]]
    it = cl.items[end[1]]
    other = inst.group_of[e.dst if publishes else e.src].allowed
    home = cl.home_of[0]
    assert home is not None

    def always(x: str) -> tuple[int, ...]:
        if x in other:
            return ()
        common: set[int] | None = None
        for o in other:
            route = system.route(x, o) if publishes else system.route(o, x)
            links = {li for li in route or () if li in model.link_rows}
            common = links if common is None else common & links
        return tuple(sorted(common or ()))

    at_home = always(home)
    away = {int(r): always(model.relaxed[r]) for r in it.relaxed}
    if not at_home and not any(away.values()):
        return
    if publishes:
        cl.outer.append(_Outer(end[1], end[2], bw, _home_bw(it, end[2], bw), at_home, away))
    else:
        least = float(bw.min())
        cl.outer.append(_Outer(end[1], -1, np.array([least]), np.full(len(it.home_levels), least), at_home, away))
    cl.links = cl.links | frozenset(at_home) | frozenset(li for links in away.values() for li in links)


def _network_rows(model: _Model, active: set[int]) -> str | None:
    """Add the network's coupling rows to ``model``: one per link that can overflow and one
    per medium of such a link; each block's own edges (both ends in the block) become
    :class:`_Edge` s priced in its subproblem; the traffic of every other edge (between
    blocks, to a lone group), at its most, is reserved on the rows it may cross when the
    plan is made (the bound does not need it: leaving traffic out only relaxes). Returns why
    the instance does not decompose, or None."""
    inst, system = model.inst, model.inst.system
    n_cpu = len(model.relaxed)
    caps: list[float] = []
    for li in sorted(active):
        model.link_rows[li] = [n_cpu + len(caps)]
        caps.append(system.links[li].bandwidth_kBps)
        model.row_names.append(f"link {system.links[li].between[0]}-{system.links[li].between[1]}")
    for m in system.media:
        links = [li for li in system.medium_links[m.name] if li in active]
        if links:
            row = n_cpu + len(caps)
            caps.append(m.bandwidth_kBps)
            model.row_names.append(f"medium {m.name}")
            for li in system.medium_links[m.name]:
                model.link_rows.setdefault(li, []).append(row)
    reserve = np.zeros(n_cpu + len(caps))
    where: dict[str, tuple[int, int, int]] = {}  # node -> (class, item, member) inside a block
    for ci, cl in enumerate(model.classes):
        if cl.home is not None:
            for i, members in enumerate(cl.instances[0]):
                for j, n in enumerate(members):
                    where[n] = (ci, i, j)
    for e in system.edges:
        bw = np.array([system.edge_bandwidth(e, ch) for ch in inst.choices[e.src]])
        if len(bw) == 0 or bw.max() <= 0:
            continue
        _, maybe = crossings(inst, e)
        rows = [row for li in maybe for row in model.link_rows.get(li, ())]
        if not rows:
            continue
        a, b = where.get(e.src), where.get(e.dst)
        if a is not None and b is not None and a[0] == b[0]:
            if a[1] != b[1]:
                cl = model.classes[a[0]]
                cl.edges.append(_Edge(a[1], a[2], b[1], bw, _home_bw(cl.items[a[1]], a[2], bw)))
                cl.links = cl.links | frozenset(li for li in maybe if li in model.link_rows)
            continue
        for row in rows:
            reserve[row] += bw.max()
        end = a if a is not None else b  # the block end (the publisher's, when both are in blocks)
        if end is not None:
            _add_outer(model, e, end, bw, a is not None)
    for cl in model.classes:
        free = sum(1 for it in cl.items if len(it.relaxed) and len(it.home_units))
        if (cl.edges or cl.outer) and 2 ** free > MAX_PATTERNS:
            return f"a block has {free} node groups that may go either way: more than {MAX_PATTERNS} patterns to price"
    for cl in model.classes:  # each view: the same edges, their home traffic at its own home options
        for view in cl.views:
            view.links = cl.links
            view.edges = [_Edge(e.pub, e.member, e.sub, e.bw, _home_bw(view.items[e.pub], e.member, e.bw))
                          for e in cl.edges]
            view.outer = [_Outer(o.item, o.member, o.bw,
                                 _home_bw(view.items[o.item], o.member, o.bw) if o.member >= 0
                                 else np.full(len(view.items[o.item].home_levels), float(o.bw[0])),
                                 o.at_home, o.away) for o in cl.outer]
    model.cap = np.concatenate([model.cap, np.array(caps)])
    model.reserve = reserve
    # rows the traffic between blocks could fill on its own: the MILP over the columns cannot
    # use them (the instance is the whole MILP's), but they may prove the instance infeasible
    model.cramped = [int(j) for j in np.nonzero(reserve >= model.cap)[0] if j >= n_cpu]
    return None


def _qualified(system: System, problem: Problem, choices: dict[str, list[Choice]],
               prepared: Instance | str | None) -> _Model | None:
    """The decomposition's model when the instance qualifies (:func:`decomposable`), else
    None. ``prepared``: ``instance.prepare_instance``'s answer when the caller has it."""
    if problem not in (Problem.PERFORMANCE, Problem.SERVER_CAPACITY):
        return None
    inst = prepare_instance(system, problem, choices) if prepared is None else prepared
    if isinstance(inst, str):
        return None
    model = _model(system, inst, active_links(inst))
    return None if isinstance(model, str) else model


def decomposable(system: System, problem: Problem, choices: dict[str, list[Choice]]) -> bool:
    """Whether :func:`solve_decomposed` applies: Problem 1 or 2, CPU levels on a grid, each
    data-flow tree inside one robot's block (at most :data:`MAX_VIEWS` views), and links
    or media that can overflow carried as coupling rows (at most :data:`MAX_PATTERNS`
    home/away patterns per block, traffic between blocks that cannot fill a row on its
    own); an instance infeasible on its face is left to the exact solver (which names the
    constraint)."""
    model = _qualified(system, problem, choices, None)
    return model is not None and not model.cramped


# ---- pricing ----------------------------------------------------------------------------
def _offload(it: _Item, lam: np.ndarray) -> tuple[float, int, tuple[int, ...]]:
    """The item's best relaxed computer at prices ``lam``: reduced value, computer, levels."""
    if len(it.relaxed) == 0:
        return -math.inf, -1, ()
    prices = lam[it.relaxed]
    total = np.zeros(len(it.relaxed))
    picks = []
    for cpu, val in zip(it.member_cpu, it.member_val, strict=True):
        red = val[None, :] - prices[:, None] * cpu[None, :]
        arg = np.argmax(red, axis=1)
        total += red[np.arange(len(prices)), arg]
        picks.append(arg)
    r = int(np.argmax(total))
    return float(total[r]), int(it.relaxed[r]), tuple(int(p[r]) for p in picks)


def _price(model: _Model, ci: int, lam: np.ndarray) -> tuple[float, _Column]:
    """The class's best column at prices ``lam`` and its reduced value (before the
    convexity dual): a block with a data flow, the best over its views (each consistent
    assignment of its rates; every consistent column lies in one, so the best is exact)."""
    cl = model.classes[ci]
    if cl.views:
        return max((_price_view(model, ci, view, lam) for view in cl.views), key=lambda t: t[0])
    return _price_view(model, ci, cl, lam)


def _price_view(model: _Model, ci: int, cl: _Class, lam: np.ndarray) -> tuple[float, _Column]:
    """:func:`_price` on one view ``cl`` of class ``ci`` (the class itself when it has none)."""
    if (cl.edges or cl.outer) and any(lam[row] > 0 for li in cl.links for row in model.link_rows[li]):
        return _price_network(model, ci, cl, lam)
    offs = [_offload(it, lam) for it in cl.items]
    if cl.home is None:
        red, r, levels = offs[0]
        return red, _column(model, ci, ((r, levels),))
    table = np.zeros(cl.cap_units + 1)
    steps = []
    for it, (off, _, _) in zip(cl.items, offs, strict=True):
        if len(it.home_units):
            units = np.concatenate([[0], it.home_units])
            values = np.concatenate([[off], it.home_values])
            table, arg = combine_tables(table, units, values)
        else:
            table, arg = table + off, np.zeros(len(table), dtype=np.int64)
        steps.append((it, arg))
    parts: list[tuple[int, tuple[int, ...]]] = []
    x = cl.cap_units
    for (it, arg), (_, r, levels) in zip(reversed(steps), reversed(offs), strict=True):
        k = int(arg[x])
        if k == 0:
            parts.append((r, levels))
        else:
            parts.append((-1, it.home_levels[k - 1]))
            x -= int(it.home_units[k - 1])
    parts.reverse()
    return float(table[-1]), _column(model, ci, tuple(parts))


def _price_network(model: _Model, ci: int, cl: _Class, lam: np.ndarray) -> tuple[float, _Column]:
    """A block's best column when its own edges' traffic is priced (``lam`` on the network
    rows): every home/away pattern of its items, in a tree (each item decided in turn, the
    items that must stay home first; a home item adds its settings to the robot's knapsack
    table, an away item its best relaxed computer and settings). Each edge's price is taken
    when the later of its two items is decided: exactly when that one is the publisher away
    (its computer and setting known) or the publisher home (its setting, in the table);
    otherwise at its least (the publisher's least traffic, the cheapest route). An edge with
    both ends home or both away is free. So the returned value is at least the best column's
    true reduced value (the Lagrangian bound stays a bound), and the column is a real one
    (its load is computed exactly by :func:`_column`). ``cl``: the class ``ci`` or one of its views."""
    home = cl.home_of[0]
    assert home is not None
    system = model.inst.system
    price = {li: float(sum(lam[row] for row in rows)) for li, rows in model.link_rows.items()}

    def route_price(a: str, b: str) -> float:
        return sum(price.get(li, 0.0) for li in system.route(a, b) or ())

    n = len(cl.items)
    order = sorted(range(n), key=lambda i: (len(cl.items[i].relaxed) > 0 and len(cl.items[i].home_units) > 0, i))
    pos = {i: p for p, i in enumerate(order)}
    later: list[list[_Edge]] = [[] for _ in range(n)]
    for e in cl.edges:
        later[e.pub if pos[e.pub] > pos[e.sub] else e.sub].append(e)
    out_price: list[np.ndarray] = []  # per item: route price home -> each relaxed computer
    in_price: list[np.ndarray] = []  # per item: route price each relaxed computer -> home
    for it in cl.items:
        out_price.append(np.array([route_price(home, model.relaxed[r]) for r in it.relaxed]))
        in_price.append(np.array([route_price(model.relaxed[r], home) for r in it.relaxed]))

    outer_home = [np.zeros(len(it.home_units)) for it in cl.items]  # per item: the outer edges' price, home
    outer_away: list[list[np.ndarray]] = [[np.zeros((len(it.relaxed), len(c))) for c in it.member_cpu]
                                          for it in cl.items]  # per item, member: [relaxed, level]
    for o in cl.outer:
        it = cl.items[o.item]
        at_home = sum(price.get(li, 0.0) for li in o.at_home)
        outer_home[o.item] = outer_home[o.item] + o.home_bw * at_home
        per_r = np.array([sum(price.get(li, 0.0) for li in o.away[int(r)]) for r in it.relaxed])
        m = o.member if o.member >= 0 else 0
        bws = o.bw if o.member >= 0 else np.full(len(it.member_cpu[0]), o.bw[0])
        outer_away[o.item][m] = outer_away[o.item][m] + per_r[:, None] * bws[None, :]

    def home_values(i: int, away: dict[int, bool]) -> np.ndarray:
        it = cl.items[i]
        vals = it.home_values - outer_home[i]
        for e in later[i]:
            other = e.sub if e.pub == i else e.pub
            if not away[other]:
                continue
            if e.pub == i:  # home publisher -> away subscriber: its setting's traffic, the cheapest route
                vals = vals - e.home_bw * float(out_price[other].min())
            else:  # away publisher (decided before) -> home: its least traffic, the cheapest route
                vals = vals - float(e.bw.min()) * float(in_price[other].min())
        return vals

    def away_value(i: int, away: dict[int, bool]) -> tuple[float, int, tuple[int, ...]]:
        it = cl.items[i]
        prices = lam[it.relaxed]
        total = np.zeros(len(it.relaxed))
        reds = [val[None, :] - prices[:, None] * cpu[None, :] - out for cpu, val, out
                in zip(it.member_cpu, it.member_val, outer_away[i], strict=True)]
        for e in later[i]:
            other = e.sub if e.pub == i else e.pub
            if away[other]:
                continue
            if e.pub == i:  # away publisher -> home subscriber: exact
                reds[e.member] = reds[e.member] - in_price[i][:, None] * e.bw[None, :]
            else:  # home publisher (in the table) -> away subscriber: its least traffic
                total -= float(e.bw.min()) * out_price[i]
        picks = []
        for red in reds:
            arg = np.argmax(red, axis=1)
            total += red[np.arange(len(prices)), arg]
            picks.append(arg)
        r = int(np.argmax(total))
        return float(total[r]), int(it.relaxed[r]), tuple(int(p[r]) for p in picks)

    best = -math.inf
    best_path: tuple[tuple[int, bool, Any], ...] = ()
    # depth-first over the patterns, an explicit stack: (depth, table, constant, decisions)
    stack: list[tuple[int, np.ndarray, float, tuple[tuple[int, bool, Any], ...]]] = [
        (0, np.zeros(cl.cap_units + 1), 0.0, ())]
    while stack:
        depth, table, const, path = stack.pop()
        if depth == n:
            if float(table[-1]) + const > best:
                best, best_path = float(table[-1]) + const, path
            continue
        i = order[depth]
        it = cl.items[i]
        away = {j: a for j, a, _ in path}
        if len(it.home_units):
            t, arg = combine_tables(table, it.home_units, home_values(i, away))
            if np.isfinite(t[-1]):
                stack.append((depth + 1, t, const, (*path, (i, False, arg))))
        if len(it.relaxed):
            v, r, levels = away_value(i, away)
            stack.append((depth + 1, table, const + v, (*path, (i, True, (r, levels)))))
    parts: list[tuple[int, tuple[int, ...]]] = [(-1, ())] * n
    x = cl.cap_units
    for i, is_away, data in reversed(best_path):
        if is_away:
            parts[i] = data
        else:
            k = int(data[x])
            parts[i] = (-1, cl.items[i].home_levels[k])
            x -= int(cl.items[i].home_units[k])
    return best, _column(model, ci, tuple(parts))


def _column(model: _Model, ci: int, parts: tuple[tuple[int, tuple[int, ...]], ...]) -> _Column:
    cl = model.classes[ci]
    value = 0.0
    use: dict[int, float] = {}
    for it, (r, levels) in zip(cl.items, parts, strict=True):
        for cpu, val, k in zip(it.member_cpu, it.member_val, levels, strict=True):
            if r >= 0 or not model.sized:
                value += float(val[k])
            if r >= 0:
                use[r] = use.get(r, 0.0) + float(cpu[k])
    if cl.edges:  # the block's own traffic on the network rows, exactly
        route = model.inst.system.route
        where = [cl.home_of[0] if r < 0 else model.relaxed[r] for r, _ in parts]
        for e in cl.edges:
            a, b = where[e.pub], where[e.sub]
            if a != b:
                bw = float(e.bw[parts[e.pub][1][e.member]])
                for li in route(a, b) or ():  # type: ignore[arg-type]
                    for row in model.link_rows.get(li, ()):
                        use[row] = use.get(row, 0.0) + bw
    for o in cl.outer:  # its traffic with the rest: at its least
        r, levels = parts[o.item]
        bw = float(o.bw[levels[o.member]] if o.member >= 0 else o.bw[0])
        for li in o.at_home if r < 0 else o.away[r]:
            for row in model.link_rows[li]:
                use[row] = use.get(row, 0.0) + bw
    return _Column(ci, value, use, parts)


def _column_of(model: _Model, assignment: Assignment, position: dict[str, int]) -> list[_Column]:
    """The columns of a feasible plan (one per class instance)."""
    rindex = {c: i for i, c in enumerate(model.relaxed)}
    out = []
    for ci, cl in enumerate(model.classes):
        for inst_members, home in zip(cl.instances, cl.home_of, strict=True):
            parts = []
            for members in inst_members:
                comp = assignment.placement[members[0]]
                r = -1 if comp == home else rindex[comp]
                parts.append((r, tuple(position[n] for n in members)))
            out.append(_column(model, ci, tuple(parts)))
    return out


def _offload_options(it: _Item, lam: np.ndarray, floor: float) -> list[tuple[float, int, tuple[int, ...]]]:
    """Every (reduced value, relaxed computer, member levels) of an offloaded item whose
    reduced value at ``lam`` is at least ``floor``."""
    out: list[tuple[float, int, tuple[int, ...]]] = []
    prices = lam[it.relaxed]
    reds = [val[None, :] - prices[:, None] * cpu[None, :] for cpu, val in zip(it.member_cpu, it.member_val,
                                                                              strict=True)]
    for ri, r in enumerate(it.relaxed):
        rows = [red[ri] for red in reds]
        rest = np.concatenate([np.cumsum([row.max() for row in rows][::-1])[::-1][1:], [0.0]])
        stack: list[tuple[int, float, tuple[int, ...]]] = [(0, 0.0, ())]
        while stack:
            m, acc, levels = stack.pop()
            if m == len(rows):
                out.append((acc, int(r), levels))
                continue
            for k in np.nonzero(acc + rows[m] + rest[m] >= floor)[0]:
                stack.append((m + 1, acc + float(rows[m][k]), (*levels, int(k))))
    return out


def _near_columns(model: _Model, lam: np.ndarray, priced: Sequence[tuple[float, _Column]], slack: float,
                  limit: int) -> tuple[list[_Column], bool]:
    """Every column whose reduced value at ``lam`` is within ``slack`` of its class's best.
    With ``slack`` = the Lagrangian bound at ``lam`` minus the incumbent, these are the only
    columns a better plan can use (a plan's value is the bound minus Σ over its columns of
    (best - reduced value)). A private robot's are enumerated through its knapsack tables.
    Returns the columns and whether the list is complete (at most ``limit`` of them)."""
    out: list[_Column] = []
    for ci, cl in enumerate(model.classes):
        floor = priced[ci][0] - slack - 1e-9 * max(1.0, abs(priced[ci][0]))
        if cl.home is None:
            for _, r, levels in _offload_options(cl.items[0], lam, floor):
                out.append(_column(model, ci, ((r, levels),)))
            if len(out) > limit:
                return out[:limit], False
            continue
        for view in cl.views or [cl]:  # a data flow: each view's columns (every consistent one is in one)
            tables = [np.zeros(view.cap_units + 1)]
            options: list[list[tuple[int, float, tuple[int, tuple[int, ...]]]]] = []
            for it in view.items:
                best_off = _offload(it, lam)[0]
                offs = _offload_options(it, lam, best_off - slack - 1e-9) if len(it.relaxed) else []
                opts = [(0, red, (r, levels)) for red, r, levels in offs]
                opts += [(int(u), float(v), (-1, lv)) for u, v, lv in zip(it.home_units, it.home_values, it.home_levels,
                                                                          strict=True)]
                options.append(opts)
                units = np.concatenate([[0], it.home_units]).astype(np.int64)
                values = np.concatenate([[best_off], it.home_values])
                tables.append(combine_tables(tables[-1], units, values)[0])
            stack: list[tuple[int, int, float, tuple[tuple[int, tuple[int, ...]], ...]]] = [
                (len(view.items) - 1, view.cap_units, 0.0, ())]
            while stack:
                q, x, acc, parts = stack.pop()
                if q < 0:
                    out.append(_column(model, ci, parts))
                    if len(out) > limit:
                        return out[:limit], False
                    continue
                for u, v, part in options[q]:
                    if u <= x and acc + v + tables[q][x - u] >= floor:
                        stack.append((q - 1, x - u, acc + v, (part, *parts)))
    return out, True


# ---- the master ---------------------------------------------------------------------------
class _Master:
    """The restricted master LP/MILP on HiGHS, grown column by column."""

    def __init__(self, model: _Model, penalty: float) -> None:
        import highspy  # lazy, as in milp.py: a missing HiGHS fails the exact method only

        self.hs = highspy
        self.h = quiet_highs()
        self.h.setOptionValue("output_flag", False)
        self.h.setOptionValue("random_seed", 0)
        self.h.changeObjectiveSense(highspy.ObjSense.kMaximize)
        self.model = model
        inf = highspy.kHighsInf
        n_cls, n_rel = len(model.classes), len(model.cap)  # the relaxed computers' rows, then the network's
        counts = np.array([len(cl.instances) for cl in model.classes], dtype=float)
        lower = np.concatenate([counts, np.full(n_rel, -inf)])
        upper = np.concatenate([counts, model.cap])
        self.h.addRows(n_cls + n_rel, lower, upper, 0, np.zeros(n_cls + n_rel, dtype=np.int32),
                       np.zeros(0, dtype=np.int32), np.zeros(0))
        self.n_cls = n_cls
        # overflow of each relaxed capacity at a penalty: keeps the LP feasible from the start
        self.h.addCols(n_rel, np.full(n_rel, -penalty), np.zeros(n_rel), np.full(n_rel, inf), n_rel,
                       np.arange(n_rel, dtype=np.int32), (n_cls + np.arange(n_rel)).astype(np.int32), -np.ones(n_rel))
        self.n_over = n_rel
        self.columns: list[_Column] = []
        self.keys: set[tuple[int, tuple[tuple[int, tuple[int, ...]], ...]]] = set()
        self.subscribed = False

    def add(self, cols: Sequence[_Column]) -> int:
        fresh = []
        for c in cols:
            key = (c.cls, c.parts)
            if key not in self.keys:
                self.keys.add(key)
                fresh.append(c)
        if not fresh:
            return 0
        starts: list[int] = []
        index: list[int] = []
        value: list[float] = []
        for c in fresh:
            starts.append(len(index))
            index.append(c.cls)
            value.append(1.0)
            for r, u in sorted(c.use.items()):
                if u:
                    index.append(self.n_cls + r)
                    value.append(u)
        counts = [float(len(self.model.classes[c.cls].instances)) for c in fresh]
        self.h.addCols(len(fresh), np.array([c.value for c in fresh]), np.zeros(len(fresh)), np.array(counts),
                       len(index), np.array(starts, dtype=np.int32), np.array(index, dtype=np.int32),
                       np.array(value))
        self.columns.extend(fresh)
        return len(fresh)

    def overflowing(self) -> list[int]:
        """The rows the last LP overflows (its overflow columns at a positive value), most first."""
        over = np.asarray(self.h.getSolution().col_value)[:self.n_over]
        return [int(j) for j in np.argsort(-over) if over[j] > 1e-9]

    def solve_lp(self, time_limit: float) -> tuple[float, np.ndarray, np.ndarray] | None:
        self.h.setOptionValue("time_limit", max(time_limit, 0.01))
        self.h.run()
        if self.h.getModelStatus() != self.hs.HighsModelStatus.kOptimal:
            return None
        sol = self.h.getSolution()
        duals = np.asarray(sol.row_dual)
        return float(self.h.getInfo().objective_function_value), duals[:self.n_cls], np.maximum(duals[self.n_cls:], 0.0)

    def solve_mip(self, time_limit: float, start: dict[int, float] | None,
                  improved: Callable[[float], None] | None = None) -> tuple[list[float], bool] | None:
        """The columns made integer (overflow off): the count of each column and whether HiGHS
        proved it the best over these columns, or None when it found none. ``improved(objective)``
        is called on every better plan HiGHS finds."""
        n = self.n_over + len(self.columns)
        self.h.changeColsIntegrality(len(self.columns), np.arange(self.n_over, n, dtype=np.int32),
                                     np.full(len(self.columns), self.hs.HighsVarType.kInteger))
        self.h.changeColsBounds(self.n_over, np.arange(self.n_over, dtype=np.int32), np.zeros(self.n_over),
                                np.zeros(self.n_over))
        reserve = self.model.reserve
        if reserve.any():  # the plan leaves room for the traffic between blocks (at its most)
            rows = np.nonzero(reserve)[0]
            self.h.changeRowsBounds(len(rows), (self.n_cls + rows).astype(np.int32),
                                    np.full(len(rows), -self.hs.kHighsInf),
                                    self.model.cap[rows] - reserve[rows])
        self.h.setOptionValue("time_limit", max(time_limit, 0.01))
        self.h.setOptionValue("mip_rel_gap", 0.0)
        self.h.setOptionValue("mip_abs_gap", 1e-7)
        if start:
            full = {j: 0.0 for j in range(n)}
            full.update({self.n_over + j: v for j, v in start.items()})
            self.h.setSolution(n, np.array(list(full), dtype=np.int32), np.array(list(full.values())))
        if improved is not None and not self.subscribed:
            self.h.cbMipImprovingSolution.subscribe(
                lambda event: improved(float(event.data_out.objective_function_value)))
            self.subscribed = True
        self.h.run()
        if self.h.getInfo().primal_solution_status != 2:
            return None
        proven = self.h.getModelStatus() == self.hs.HighsModelStatus.kOptimal
        return list(self.h.getSolution().col_value)[self.n_over:], proven


def _lagrangian(model: _Model, lam: np.ndarray) -> tuple[float, list[tuple[float, _Column]]]:
    """The Lagrangian bound at ``lam`` and each class's best column (reduced value, column)."""
    priced = [_price(model, ci, lam) for ci in range(len(model.classes))]
    total = sum(len(cl.instances) * red for cl, (red, _) in zip(model.classes, priced, strict=True))
    return float(total + float(lam @ model.cap)), priced


def _assignment(model: _Model, counts: Sequence[float], columns: Sequence[_Column]) -> Assignment:
    inst = model.inst
    placement: dict[str, str] = {}
    choice: dict[str, Choice] = {}
    per_class: dict[int, list[tuple[_Column, int]]] = {}
    for col, v in zip(columns, counts, strict=True):
        k = int(round(v))
        if k > 0:
            per_class.setdefault(col.cls, []).append((col, k))
    for ci, cl in enumerate(model.classes):
        queue = [c for c, k in per_class.get(ci, []) for _ in range(k)]
        for (members_list, home), col in zip(zip(cl.instances, cl.home_of, strict=True), queue, strict=True):
            for members, (r, levels) in zip(members_list, col.parts, strict=True):
                comp = home if r < 0 else model.relaxed[r]
                assert comp is not None
                for n, k in zip(members, levels, strict=True):
                    placement[n], choice[n] = comp, inst.choices[n][k]
    return Assignment(placement, choice, {})


def _start(master: _Master, model: _Model, inst: Instance, incumbent: Assignment) -> dict[int, float]:
    """The incumbent as counts of the master's columns (its columns added when missing)."""
    cols = _column_of(model, incumbent, _positions(inst, incumbent))
    master.add(cols)
    index = {(c.cls, c.parts): j for j, c in enumerate(master.columns)}
    start: dict[int, float] = {}
    for c in cols:
        j = index[(c.cls, c.parts)]
        start[j] = start.get(j, 0.0) + 1.0
    return start


def _positions(inst: Instance, assignment: Assignment) -> dict[str, int]:
    """Each node's position among its kept choices (the assignment uses kept choices)."""
    return {n: next(i for i, c in enumerate(inst.choices[n]) if c is ch) for n, ch in assignment.choice.items()}


def _proven_infeasible(model: _Model, rows: Sequence[int], ceiling: float, *, deadline: float) -> str | None:
    """Why no plan exists, when the Lagrangian bound with a steep price on one of ``rows``
    alone falls below the least Σ w·P any plan has (every node at its worst setting): for
    any prices the bound is at least every plan's value, so no plan exists, and that row's
    computer, link or medium is what cannot hold (the least its blocks must put on it,
    wherever they run, exceeds it). None when no row proves it (or past ``deadline``)."""
    floor = _floor(model)
    for j in rows:
        if time.perf_counter() > deadline:
            return None
        steep = 1e6 * (ceiling - floor + 1.0) / max(float(model.cap[j]), 1.0)
        lam = np.zeros(len(model.cap))
        lam[j] = steep
        value, _ = _lagrangian(model, lam)
        if value < floor - 1e-9 * steep * max(float(model.cap[j]), 1.0) - 1e-6:
            unit = "CPU" if j < len(model.relaxed) else "kB/s"
            return (f"{model.row_names[j]} cannot hold what must use it wherever the nodes run: at their least CPU "
                    f"and traffic they need more than its {float(model.cap[j]):.6g} {unit} (proven: the "
                    f"decomposition's Lagrangian bound, priced on it alone, is below every plan's value)")
    return None


def _ceiling(model: _Model) -> float:
    """No plan's value is above this: Σ w·max P (Problem 1); 0, nothing on a server (Problem 2)."""
    return 0.0 if model.sized else trivial_bound(model.inst.system, model.inst.choices)


def _floor(model: _Model) -> float:
    """Every plan's value is at least this: every node at its worst setting (Problem 1);
    every node on a server at its most CPU (Problem 2)."""
    if model.sized:
        return -sum(max(ch.cpu for ch in opts) for opts in model.inst.choices.values())
    system = model.inst.system
    return sum(system.node[n].weight * min(ch.performance for ch in opts) for n, opts in model.inst.choices.items())


def _value(model: _Model, assignment: Assignment) -> float:
    """A plan's value in the master's sense (bigger is better): Σ w·P, or minus Σ server sizes."""
    system = model.inst.system
    if model.sized:
        return -sum(server_sizes(system, assignment.placement, assignment.choice).values())
    return weighted_performance(system, assignment.choice)


def _fits(model: _Model, assignment: Assignment) -> bool:
    system = model.inst.system
    load = computer_loads(system, assignment.placement, assignment.choice)
    if any(load[c] > model.inst.cap[c] + 1e-9 * max(1.0, model.inst.cap[c]) for c in load):
        return False
    if system.has_flow and system.flow_violation(assignment.choice) is not None:
        return False
    return system.network_violation(assignment.placement, assignment.choice) is None


def solve_decomposed(system: System, problem: Problem, choices: dict[str, list[Choice]], *,
                     time_limit: float | None = None, progress: Progress | None = None,
                     prepared: Instance | str | None = None) -> Plan | None:
    """Problem 1 or 2 by column generation and a MILP over the columns (module docstring).

    Returns the best plan found with ``bound`` the best Lagrangian bound (never above
    Σ w·max P); ``status`` is ``optimal`` only when they agree within 1e-6 (relative),
    else ``feasible``. ``time_limit`` covers the whole call, set-up included: column
    generation gets at most half of what the set-up left, the MILP over the columns what
    is left but 5 % (at least 0.15 s); when the set-up alone uses the budget, the paper's
    greedy's plan is returned with the bound at hand (at worst Σ w·max P). ``prepared``:
    the instance as ``instance.prepare_instance`` gave it, when the caller has it (else it is
    prepared here). Returns None when the instance does not qualify (:func:`decomposable`: the
    caller then uses the MILP on the whole model) or when no plan was found."""
    t0 = time.perf_counter()

    def elapsed() -> float:
        return time.perf_counter() - t0

    model = _qualified(system, problem, choices, prepared)
    if model is None:
        return None
    if model.sized and progress is not None:  # the master maximises minus Σ sizes: reported as Σ sizes
        told = progress

        def progress(incumbent: float | None, bound: float, seconds: float) -> None:
            told(None if incumbent is None else -incumbent, -bound, seconds)
    inst = model.inst
    ceiling = _ceiling(model)
    spread = ceiling - _floor(model)  # the most two plans' values differ by
    if model.cramped:  # not for this solver (decomposable() is False), unless such a row proves there is no plan
        deadline = math.inf if time_limit is None else t0 + time_limit / 2
        why = _proven_infeasible(model, model.cramped, ceiling, deadline=deadline)
        return None if why is None else Plan.infeasible(problem, Method.EXACT, why, solve_s=elapsed(),
                                                         system=system.source)
    budget = NO_LIMIT_S if time_limit is None else time_limit - max(PLAN_SHARE * time_limit, PLAN_MIN_S)
    master = _Master(model, penalty=spread + 1.0)

    # the paper's greedy: the first columns, and the MILP's start
    # (along a data flow the greedy searches the rates, each try a whole greedy run: bounded)
    mapped = greedy_start(inst, choices, min(GREEDY_PLUS_SHARE * budget, PLUS_START_MAX_S) if system.has_flow else None)
    if mapped is None and len(model.cap) > len(model.relaxed):  # a binding network: the greedy gets stuck
        mapped = plus_start(inst, choices, min(GREEDY_PLUS_SHARE * budget, PLUS_START_MAX_S))
    incumbent: Assignment | None = None
    if mapped is not None:
        incumbent = mapped[0]
        master.add(_column_of(model, *mapped))
    best_value = _value(model, incumbent) if incumbent is not None else None
    bound = ceiling
    lam = np.zeros(len(model.cap))
    lp_value: float | None = None
    cg_until = elapsed() + CG_SHARE * max(budget - elapsed(), 0.0)  # what the set-up left, shared
    # column generation: the Lagrangian bound and new columns at the master's prices
    while True:
        value, priced = _lagrangian(model, lam)
        bound = min(bound, value)
        if progress is not None:
            progress(best_value, bound, elapsed())
        if lp_value is not None and bound - lp_value <= CG_TOL * max(1.0, abs(lp_value)):
            break  # the LP is the Lagrangian dual: no column can improve it
        if elapsed() > cg_until or (master.add([col for _, col in priced]) == 0 and lp_value is not None):
            break
        lp = master.solve_lp(budget - elapsed())
        if lp is None:
            break
        lp_value, _, lam = lp
    if progress is not None:
        progress(best_value, bound, elapsed())
    if incumbent is None and lp_value is not None:  # no plan yet, and the LP overflows a row: a proof?
        why = _proven_infeasible(model, master.overflowing(), ceiling, deadline=t0 + budget)
        if why is not None:
            return Plan.infeasible(problem, Method.EXACT, why, solve_s=elapsed(), system=system.source)
    # the columns, made integer; then, while a gap is left, every lone group's column that a
    # better plan could use (reduced-cost argument), and the MILP again
    def improved(objective: float) -> None:
        if progress is not None:
            progress(objective if best_value is None else max(objective, best_value), bound, elapsed())

    proven = complete = False
    for attempt in range(2):
        if attempt == 0 and incumbent is not None and elapsed() >= budget:
            break  # the set-up and the bound used the time: the greedy's plan is the answer
        if attempt == 1:
            if incumbent is None or best_value is None or elapsed() > budget * 0.9:
                break
            lam_value, priced = _lagrangian(model, lam)
            slack = lam_value - best_value
            if slack <= REL_TOL * max(1.0, abs(best_value)):
                break
            near, complete = _near_columns(model, lam, priced, slack, NEAR_LIMIT)
            if complete:  # else too many to prove anything with, and HiGHS slows down (measured)
                master.add(near)
        start = _start(master, model, inst, incumbent) if incumbent is not None else None
        share = FIRST_MIP_SHARE if attempt == 0 else 1.0
        result = master.solve_mip(share * (budget - elapsed()), start, improved if progress is not None else None)
        if result is not None:
            counts, optimal_here = result
            found = _assignment(model, counts, master.columns)
            value = _value(model, found)
            fits = _fits(model, found)
            if fits and (best_value is None or value > best_value + 1e-12):
                incumbent, best_value = found, value
            # all columns a better plan could use were there, and HiGHS proved none better
            # (a reserve for the traffic between blocks may have excluded a better plan: no proof then)
            proven = (attempt == 1 and complete and optimal_here and fits and value == best_value
                      and not model.reserve.any())
    if incumbent is None:
        return None
    assert best_value is not None
    bound = max(min(bound, ceiling), best_value)
    if proven:
        bound = best_value
    proven = bound - best_value <= REL_TOL * max(1.0, abs(best_value))
    if progress is not None:
        progress(best_value, bound, elapsed())
    if model.sized:  # Problem 2: the servers sized to their load; objective and bound Σ sizes
        incumbent = Assignment(incumbent.placement, incumbent.choice,
                               server_sizes(system, incumbent.placement, incumbent.choice))
        best_value, bound = -best_value, -bound
    return build_plan(system, incumbent, problem=problem, method=Method.EXACT,
                      status=Status.OPTIMAL if proven else Status.FEASIBLE,
                      bound=best_value if proven else bound, solve_s=elapsed())
