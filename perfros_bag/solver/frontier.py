"""The performance / server-capacity frontier: the best Problem 1 value for each total
server capacity, from the Problem 2 minimum up to where performance stops rising.

- At a total capacity ``C`` every server gets ``C`` times its share of the system's
  server capacities (equal shares when a server has none): with one server, ``C`` is its
  capacity.
- The lowest capacity worth asking about is where Problem 2's plan with every node at its
  lowest setting fits those shares (one server: Problem 2's minimum, below which no plan
  exists); the highest is where Problem 2's plan with every node at its highest setting
  fits them (every node can run at its best: Σ w·P cannot rise further). Each point is
  Problem 1 solved by ``method`` (default ``exact``: a proven
  optimum, or a plan with its bound and gap when a time limit stops it).
- Only proven bounds are stated: a heuristic's point (greedy, greedy+) has none (``None``,
  ``null`` in frontier.json), not its own objective.
- A frontier never falls as capacity grows: a plan that fits at ``C`` fits at any larger
  capacity, so a point whose plan is worse than one found at a smaller capacity takes that
  plan's value and says so (``carried_from``: the capacity it was found at). Likewise a
  bound proven at ``C`` holds at every smaller capacity (the smallest such bound is kept).

With one server the exact method gets every point at once (:func:`frontier_values`),
by enumerating where the movable node groups go (``solve --pareto`` on Table II-sized
instances): a plan is, for every node group that may go to more than one computer, a
computer; then each computer's best settings are a knapsack (greedy+'s step,
``local.combine_tables``). So with ``M`` the movable groups, the best Σ w·P at server capacity
``C`` is ``max over S ⊆ M (groups on the server) of R(M \\ S) + T_S(C)`` where ``T_S`` is the
server's knapsack table over its fixed groups and ``S`` (one table gives every capacity)
and ``R`` the best split of the rest over the robots (their knapsack values). That is
``(robots + 1)^|M|`` combinations: Table II instance 6 has 10 movable groups and 2 robots
(59,049). It applies when the network can never overflow and CPU lies on a grid;
otherwise each point is one solve.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.errors import InputError
from perfros_bag.fileio import atomic_write_text, read_json
from perfros_bag.solver.candidates import fixed_choices, lowest_settings
from perfros_bag.solver.decompose import cpu_grid_scale, home_options
from perfros_bag.solver.dispatch import solve
from perfros_bag.solver.instance import active_links, prepare_instance
from perfros_bag.solver.local import combine_tables
from perfros_bag.system.plan import Status
from perfros_bag.system.types import Problem, System

__all__ = ["DEFAULT_POINTS", "FORMAT", "FrontierPoint", "capacity_range", "document_points", "frontier",
           "frontier_document", "frontier_values", "monotone", "parse_range", "read_frontier", "with_server_capacity",
           "write_frontier"]

FORMAT = "perfros-bag frontier 1"

DEFAULT_POINTS = 21

#: the most points a frontier may ask for: each one is a solve (1,000,000 ran past 60 s
#: and 2 GB); refused as the range is read
MAX_POINTS = 1000


def parse_range(text: str) -> tuple[float | None, float | None, int]:
    """``auto``, ``LO:HI`` or ``LO:HI:POINTS`` (an empty end: its default from
    :func:`capacity_range`) -> (low, high, points). An unreadable, empty or inverted range
    is an :class:`InputError`."""
    if text.strip().lower() == "auto":
        return None, None, DEFAULT_POINTS
    parts = [p.strip() for p in text.split(":")]
    if len(parts) not in (2, 3):
        raise InputError(None, f"frontier range {text!r}: expected auto, LO:HI or LO:HI:POINTS")
    try:
        low = float(parts[0]) if parts[0] else None
        high = float(parts[1]) if parts[1] else None
        points = int(parts[2]) if len(parts) == 3 and parts[2] else DEFAULT_POINTS
    except ValueError:
        raise InputError(None, f"frontier range {text!r}: not numbers") from None
    if any(v is not None and (not math.isfinite(v) or v < 0) for v in (low, high)):
        raise InputError(None, f"frontier range {text!r}: capacities must be finite and >= 0")
    if low is not None and high is not None and high <= low:
        raise InputError(None, f"frontier range {text!r} is empty or inverted")
    if points < 2:
        raise InputError(None, f"frontier range {text!r}: at least 2 points")
    if points > MAX_POINTS:
        raise InputError(None, f"frontier range {text!r}: at most {MAX_POINTS:,} points (each one a solve), "
                               f"got {points:,}")
    return low, high, points


@dataclass
class FrontierPoint:
    capacity: float  # total server capacity
    status: Status
    objective: float | None  # Σ w·P of the best plan found
    bound: float | None  # proven: no plan at this capacity does better (None: none proven)
    solve_s: float
    carried_from: float | None = None  # the smaller capacity whose (better) plan this is

    @property
    def gap(self) -> float | None:
        """(bound - objective) / objective; 0 when proven optimal."""
        if self.objective is None or self.bound is None:
            return None
        return max(self.bound - self.objective, 0.0) / max(abs(self.objective), 1e-12)

    def to_json(self) -> dict[str, Any]:
        """The point as frontier.json holds it (docs/formats.md, the one place)."""
        return {"server_capacity": round(self.capacity, 9), "status": str(self.status), "objective": self.objective,
                "bound": self.bound, "gap": self.gap, "solve_s": round(self.solve_s, 6),
                "carried_from": None if self.carried_from is None else round(self.carried_from, 9)}


def _servers(system: System) -> list[str]:
    servers = [c.name for c in system.computers if c.kind == "server"]
    if not servers:
        raise InputError(system.source, "the frontier needs at least one server (its capacity is what varies)")
    return servers


def _shares(system: System) -> dict[str, float]:
    """Each server's share of the total server capacity (equal when one has none)."""
    servers = _servers(system)
    caps = [system.computer[s].capacity for s in servers]
    known = [c for c in caps if c is not None]
    if len(known) == len(caps) and sum(known) > 0:
        return {s: c / sum(known) for s, c in zip(servers, known, strict=True)}
    return {s: 1 / len(servers) for s in servers}


def with_server_capacity(system: System, total: float) -> System:
    """The system with its servers' capacities summing to ``total``, in proportion to their
    capacities (equal shares when one has none)."""
    share = _shares(system)
    computers = tuple(dataclasses.replace(c, capacity=total * share[c.name]) if c.name in share else c
                      for c in system.computers)
    return dataclasses.replace(system, computers=computers)


def capacity_range(system: System, *, resolution: float = 1.0, time_limit: float | None = None,
                   headroom: float | str = 0.0) -> tuple[float, float]:
    """The total server capacities at which Problem 2's plan fits the servers' shares, with
    every node at its lowest setting and with every node at its highest (exact solver),
    keeping ``headroom`` free (:func:`~perfros_bag.solver.dispatch.solve`'s). With one
    server: Problem 2's minimum in both cases."""
    share = _shares(system)
    lowest = lowest_settings(system, resolution)
    ends = []
    for settings in (lowest, None):
        plan = solve(system, Problem.SERVER_CAPACITY, "exact", resolution=resolution, settings=settings,
                     time_limit=time_limit, headroom=headroom)
        if plan.status == Status.INFEASIBLE or plan.objective is None:
            which = "lowest" if settings is not None else "highest"
            raise InputError(system.source, f"frontier: Problem 2 at every node's {which} setting has no plan: "
                                            f"{plan.reason}")
        sizes = {s: plan.computers[s].capacity or 0.0 for s in share}
        ends.append(max(sizes[s] / share[s] for s in share))
    return ends[0], ends[1]


def frontier(system: System, *, low: float | None = None, high: float | None = None, points: int = 21,
             resolution: float = 1.0, method: str = "exact",
             time_limit: float | None = None, headroom: float | str = 0.0) -> list[FrontierPoint]:
    """Problem 1 at ``points`` total server capacities evenly spaced from ``low`` to
    ``high`` (default :func:`capacity_range`); ``time_limit`` is per point; every point
    keeps ``headroom`` free (``solve --headroom``: a share in [0, 1) or ``"auto"``)."""
    if points < 2:
        raise InputError(None, f"a frontier needs at least 2 points, got {points}")
    if points > MAX_POINTS:
        raise InputError(None, f"a frontier takes at most {MAX_POINTS:,} points (each one a solve), got {points:,}")
    if low is None or high is None:
        lo, hi = capacity_range(system, resolution=resolution, time_limit=time_limit, headroom=headroom)
        low = lo if low is None else low
        high = hi if high is None else high
    if not (math.isfinite(low) and math.isfinite(high)) or low < 0 or high <= low:
        raise InputError(system.source, f"frontier: the capacity range {low:g} to {high:g} is empty or inverted")
    out: list[FrontierPoint] = []
    if method == "exact" and headroom == 0:  # the table knows no headroom: else a solve per point
        t0 = time.perf_counter()
        table = frontier_values(system, high, resolution)
        if table is not None:
            values, scale = table
            each = (time.perf_counter() - t0) / points
            for i in range(points):
                capacity = low + (high - low) * i / (points - 1)
                v = float(values[min(int(math.floor(capacity * scale + 1e-6)), len(values) - 1)])
                found = math.isfinite(v)
                out.append(FrontierPoint(capacity, Status.OPTIMAL if found else Status.INFEASIBLE,
                                         v if found else None, v if found else None, each))
            return out
    for i in range(points):
        capacity = low + (high - low) * i / (points - 1)
        t0 = time.perf_counter()
        plan = solve(with_server_capacity(system, capacity), Problem.PERFORMANCE, method, resolution=resolution,
                     time_limit=time_limit, headroom=headroom)
        # a heuristic's plan carries no bound: its own objective is not one
        out.append(FrontierPoint(capacity, plan.status, plan.objective, plan.bound, time.perf_counter() - t0))
    return monotone(out)


def monotone(points: list[FrontierPoint], rel_tol: float = 1e-6) -> list[FrontierPoint]:
    """``points`` (by increasing capacity) made consistent with what capacity means: each
    objective is at least the best found at a smaller capacity (that plan fits here too:
    its value is carried forward, ``carried_from`` its capacity, status ``feasible`` unless
    the bound here proves it), and each bound is at most any bound proven at a larger
    capacity (the optimum cannot fall as capacity grows). Points without a plan at every
    smaller capacity are left as they are."""
    out = sorted(points, key=lambda p: p.capacity)
    best: FrontierPoint | None = None  # the best plan at a smaller capacity
    for p in out:
        if best is None or best.objective is None or (p.objective is not None and p.objective >= best.objective):
            best = p if p.objective is not None and (best is None or best.objective is None
                                                    or p.objective > best.objective) else best
            continue
        p.objective, p.status = best.objective, Status.FEASIBLE
        p.carried_from = best.carried_from if best.carried_from is not None else best.capacity
    lowest: float | None = None
    for p in reversed(out):
        if p.bound is not None:
            lowest = p.bound if lowest is None else min(lowest, p.bound)
        if p.objective is not None and lowest is not None:
            p.bound = max(lowest, p.objective)  # a proven bound is never below a plan that fits
            if p.bound - p.objective <= rel_tol * max(1.0, abs(p.objective)):
                p.status = Status.OPTIMAL
    return out


# ---- one server: every point at once ------------------------------------------------
MAX_COMBINATIONS = 300_000  # (robots + 1) ** movable groups
MAX_CELLS = 20_000  # server capacity in grid cells


def frontier_values(system: System, high: float, resolution: float = 1.0) -> tuple[np.ndarray, int] | None:
    """Per server capacity ``k / scale`` (k = 0 .. high·scale), the best Σ w·P (-inf: no
    plan), and ``scale``; None when the method does not apply. ``system`` has one server;
    its capacity is replaced by ``high`` for the pruning."""
    if system.has_flow:  # a driven node's CPU follows its publisher's choice: no per-computer knapsack
        return None
    servers = [c.name for c in system.computers if c.kind == "server"]
    if len(servers) != 1:
        return None
    top = with_server_capacity(system, high)
    inst = prepare_instance(top, Problem.PERFORMANCE, fixed_choices(top, Problem.PERFORMANCE, resolution=resolution))
    if isinstance(inst, str) or active_links(inst):
        return None
    server = servers[0]
    robots = [c.name for c in system.computers if c.name != server]
    scale = cpu_grid_scale([ch.cpu for opts in inst.choices.values() for ch in opts])
    if scale is None or high * scale > MAX_CELLS:
        return None
    movable = [g for g in inst.groups if len(g.allowed) > 1]
    if (len(robots) + 1) ** len(movable) > MAX_COMBINATIONS:
        return None
    items = {}
    for g in inst.groups:
        opts = home_options(inst, g.members, scale)
        if opts is None:
            return None
        items[g.members] = (opts[0], opts[1])

    def fixed_table(comp: str, size: int) -> np.ndarray:
        table = np.zeros(size)
        for g in inst.groups:
            if g.allowed == (comp,):
                table = combine_tables(table, *items[g.members])[0]
        return table

    def subset_tables(comp: str, size: int) -> dict[int, np.ndarray]:
        """Knapsack table of comp's fixed groups plus each subset (bitmask over ``movable``)
        of the movable groups allowed on it."""
        tables = {0: fixed_table(comp, size)}
        for mask in range(1, 1 << len(movable)):
            low = (mask & -mask).bit_length() - 1
            rest = mask & (mask - 1)
            if comp not in movable[low].allowed or rest not in tables:
                continue
            tables[mask] = combine_tables(tables[rest], *items[movable[low].members])[0]
        return tables

    robot_values = []
    for r in robots:
        size = int(math.floor(inst.cap[r] * scale + 1e-6)) + 1
        robot_values.append({mask: float(t[-1]) for mask, t in subset_tables(r, size).items()})
    full = (1 << len(movable)) - 1

    # split[mask]: the best Σ of the robots' values with exactly the groups of ``mask`` on
    # the robots, built robot by robot from the last (a table, not a recursion)
    split: dict[int, float] = {0: 0.0}
    if robots:
        split = {m: v for m, v in robot_values[-1].items() if v > -math.inf}
    for values_i in reversed(robot_values[:-1]):
        nxt: dict[int, float] = {}
        for mask in range(full + 1):
            best = -math.inf
            sub = mask
            while True:  # every subset of mask on this robot, the rest on the later ones
                v = values_i.get(sub)
                if v is not None and v > -math.inf:
                    rest = split.get(mask & ~sub)
                    if rest is not None:
                        best = max(best, v + rest)
                if sub == 0:
                    break
                sub = (sub - 1) & mask
            if best > -math.inf:
                nxt[mask] = best
        split = nxt

    cells = int(math.floor(high * scale + 1e-6)) + 1
    values = np.full(cells, -np.inf)
    for mask, table in subset_tables(server, cells).items():
        rest = split.get(full & ~mask, -math.inf)
        if rest > -math.inf:
            np.maximum(values, table + rest, out=values)
    return values, scale


def frontier_document(system: System, points: list[FrontierPoint], method: str,
                      headroom: float | str = 0.0) -> dict[str, Any]:
    """The frontier as JSON-ready data (docs/formats.md, frontier.json)."""
    return {
        "format": FORMAT,
        "system": system.source,
        "method": method,
        "headroom": headroom,
        "servers": _servers(system),
        "points": [p.to_json() for p in points],
    }


def write_frontier(path: str | Path, doc: dict[str, Any]) -> None:
    """frontier.json, written atomically (the one writer)."""
    atomic_write_text(path, json.dumps(doc, indent=2) + "\n")


def document_points(path: str | Path, fmt: str, what: str) -> tuple[dict[str, Any], list[tuple[str, dict[str, Any]]]]:
    """A frontier-like document (``format`` ``fmt``, a non-empty list of ``points``, each an
    object) and its points, each with its place for messages (``<what>: points[i]``); an
    :class:`InputError` otherwise. Each reader checks its points' own fields."""
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise InputError(path, f"not a {what} (expected a JSON object with format {fmt!r})")
    points = doc.get("points")
    if not isinstance(points, list) or not points:
        raise InputError(path, f"{what}: 'points' must be a non-empty list")
    out = []
    for i, p in enumerate(points):
        where = f"{what}: points[{i}]"
        if not isinstance(p, dict):
            raise InputError(path, f"{where}: not an object")
        out.append((where, p))
    return doc, out


def read_frontier(path: str | Path) -> dict[str, Any]:
    """frontier.json, checked field by field (the one reader): an :class:`InputError` naming
    the broken place otherwise."""
    doc, points = document_points(path, FORMAT, "frontier")
    for where, p in points:
        cap = p.get("server_capacity")
        if isinstance(cap, bool) or not isinstance(cap, int | float) or not math.isfinite(cap):
            raise InputError(path, f"{where}.server_capacity: not a finite number")
        if p.get("status") not in tuple(Status):
            raise InputError(path, f"{where}.status: one of {', '.join(Status)}")
        for key in ("objective", "bound", "gap", "solve_s", "carried_from"):
            v = p.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)):
                raise InputError(path, f"{where}.{key}: not a finite number or null")
    return doc
