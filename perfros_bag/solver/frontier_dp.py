"""Every point of a one-server frontier at once, exactly, by enumerating where the movable
node groups go (``solve --pareto`` on Table II-sized instances).

With one server, a plan is: for every node group that may go to more than one computer,
a computer; then each computer's best settings are a knapsack (greedy+'s step,
``local.combine_tables``). So with ``M`` the movable groups, the best Σ w·P at server capacity
``C`` is ``max over S ⊆ M (groups on the server) of R(M \\ S) + T_S(C)`` where ``T_S`` is the
server's knapsack table over its fixed groups and ``S`` (one table gives every capacity)
and ``R`` the best split of the rest over the robots (their knapsack values). That is
``(robots + 1)^|M|`` combinations: Table II instance 6 has 10 movable groups and 2 robots
(59,049). It applies when the network can never overflow and CPU lies on a grid; the
caller falls back to one solve per point otherwise.
"""

from __future__ import annotations

import math

import numpy as np

from perfros_bag.solver import exact as exact_mod
from perfros_bag.solver.decompose import cpu_grid_scale, home_options
from perfros_bag.solver.local import combine_tables
from perfros_bag.system.types import Problem, System

MAX_COMBINATIONS = 300_000  # (robots + 1) ** movable groups
MAX_CELLS = 20_000  # server capacity in grid cells


def frontier_values(system: System, high: float, resolution: float = 1.0) -> tuple[np.ndarray, int] | None:
    """Per server capacity ``k / scale`` (k = 0 .. high·scale), the best Σ w·P (-inf: no
    plan), and ``scale``; None when the method does not apply. ``system`` has one server;
    its capacity is replaced by ``high`` for the pruning."""
    if system.has_flow:  # a driven node's CPU follows its publisher's choice: no per-computer knapsack
        return None
    from perfros_bag.solver import fixed_choices
    from perfros_bag.solver.frontier import with_server_capacity

    servers = [c.name for c in system.computers if c.kind == "server"]
    if len(servers) != 1:
        return None
    top = with_server_capacity(system, high)
    inst = exact_mod.prepare_instance(top, Problem.PERFORMANCE, fixed_choices(top, Problem.PERFORMANCE, resolution=resolution))
    if isinstance(inst, str) or exact_mod.active_links(inst):
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
