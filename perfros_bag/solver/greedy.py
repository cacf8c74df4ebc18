"""The paper's greedy heuristics (section III): Algorithms 1 and 2 (Problem 1), 3 (Problem 2).

Where the paper's pseudo-code leaves a choice open, this is what we do (deterministic:
ties go to the node / computer listed first in the system):

- Nodes are allocated as coresidence groups (a group moves as one), so coresidence holds
  at every step; bandwidth (eq 4) and residence are checked at every step too.
- Algorithm 1, initial allocation at each node's minimum setting: groups with a residence
  constraint, then coresidence groups, then the rest; each phase by decreasing CPU, each
  group onto the allowed computer with the largest free capacity where it fits.
- Algorithm 2: repeatedly the configurable node with the best weighted performance gain
  per CPU unit of its next step (one CPU unit with a curve, the next setting otherwise)
  is raised one step; a node whose step does not fit (CPU or bandwidth) leaves the set.
- Algorithm 1, lines 9-16: a computer is *full* when it has no free CPU or a node on it
  cannot take its next step for lack of CPU. From each full computer, nodes (first only
  the non-maximal ones, then any) are moved, by decreasing gradient, to the non-full
  computer with the largest free capacity that can hold them; upgrades follow each phase.
- Algorithm 3: groups with a residence constraint first, then the rest, each phase by
  decreasing CPU; a group goes to the allowed computer with the least free capacity that
  still holds it (best fit); when none does, the server needing the least growth grows by
  exactly what is missing (never past ``max_capacity``).
"""

from __future__ import annotations

import heapq
import math

from perfros_bag.solver.state import EPS, State, fmt_units
from perfros_bag.system.plan import Method, Plan
from perfros_bag.system.types import Choice, Problem, System


def solve_greedy(system: System, problem: Problem, choices: dict[str, list[Choice]]) -> Plan:
    return greedy_plan(*run_greedy(system, problem, choices))


def greedy_plan(state: State, reason: str | None) -> Plan:
    """The plan of the greedy's final ``state``, or why it found none (``reason``)."""
    system, problem = state.system, state.problem
    if reason is not None:
        if not state.proven:
            reason += " (this is where the greedy got stuck: greedy+ or exact may still find a plan)"
        return Plan.infeasible(problem, Method.GREEDY, reason, system=system.source)
    return state.plan(Method.GREEDY)


def run_greedy(system: System, problem: Problem, choices: dict[str, list[Choice]]) -> tuple[State, str | None]:
    """The greedy's final state, and why it failed (None when it found a plan)."""
    state = State(system, problem, choices)
    reason = algorithm1(state) if problem == Problem.PERFORMANCE else algorithm3(state)
    return state, reason


# ---- Problem 1 ------------------------------------------------------------------------
def algorithm1(state: State) -> str | None:
    reason = initial_allocation(state)
    if reason is not None:
        return reason
    conf = [n for n in state.nodes if len(state.ladder[n]) > 1]
    upgrade(state, conf)
    for c in [c for c in state.computers if is_full(state, c)]:
        relocate_from(state, c, only_nonmax=True)
    upgrade(state, conf)
    for c in [c for c in state.computers if is_full(state, c)]:
        relocate_from(state, c, only_nonmax=False)
    upgrade(state, conf)
    return None


def _phases(state: State) -> list[list[int]]:
    """Group indices: residence-constrained, then coresidence groups, then the rest."""
    every = set(state.computers)
    res = [gi for gi, _ in enumerate(state.groups) if set(state.group_allowed[gi]) != every]
    cores = [gi for gi, g in enumerate(state.groups) if len(g) > 1 and gi not in res]
    rest = [gi for gi, g in enumerate(state.groups) if len(g) == 1 and gi not in res]
    return [res, cores, rest]


def _by_cpu_desc(state: State, groups: list[int]) -> list[int]:
    return sorted(groups, key=lambda gi: (-state.group_cpu(gi), gi))


def initial_allocation(state: State) -> str | None:
    for phase in _phases(state):
        for gi in _by_cpu_desc(state, phase):
            targets = sorted(state.group_allowed[gi], key=lambda c: (-state.free(c), state.computers.index(c)))
            why: dict[str, str] = {}
            for c in targets:
                r = state.move_group(gi, c)
                if r is None:
                    break
                why[c] = r
            else:
                return explain(state, gi, why)
    return None


def explain(state: State, gi: int, why: dict[str, str]) -> str:
    """Why group ``gi`` fits on none of its allowed computers, naming nodes and computers."""
    group = state.groups[gi]
    who = " + ".join(group)
    cpu = state.group_cpu(gi)
    allowed = state.group_allowed[gi]
    lowest = (" at its lowest setting"
              if state.problem == Problem.PERFORMANCE and any(len(state.ladder[n]) > 1 for n in group) else "")
    if len(allowed) == 1:
        c = allowed[0]
        # alone on its only computer it does not fit: no solver can do better
        state.proven = cpu > state.maxcap[c] + EPS * max(1.0, state.maxcap[c])
        constraint = "residence" if allowed != state.computers else "the only computer"
        if why.get(c, "").startswith(f"{c} has"):
            has = fmt_units(state.free(c)) if math.isclose(state.free(c), state.cap[c]) else \
                f"{fmt_units(state.free(c))} free (of {fmt_units(state.cap[c])})"
            return f"{who} needs {fmt_units(cpu)} CPU{lowest} on {c} ({constraint}) but {c} has {has}"
        return f"{who} cannot run on {c} ({constraint}): {why.get(c, 'no room')}"
    parts = "; ".join(f"{c}: {why.get(c, 'not tried')}" for c in allowed)
    scope = "allowed computer" if allowed != state.computers else "computer"
    return f"no {scope} can take {who} ({fmt_units(cpu)} CPU{lowest}): {parts}"


def upgrade(state: State, conf: list[str]) -> None:
    """Algorithm 2: raise the node with the best gain per CPU unit, one step at a time."""
    heap: list[tuple[float, int, str]] = []
    for n in conf:
        if not state.at_max(n) and state.place[n] is not None:
            heap.append((-state.gradient(n), state.order[n], n))
    heapq.heapify(heap)
    while heap:
        _, _, n = heapq.heappop(heap)
        if state.change({n: (state.place[n], state.level[n] + 1)}) is not None:
            continue  # its computer (or a link) is full: n leaves V_aux
        if not state.at_max(n):
            heapq.heappush(heap, (-state.gradient(n), state.order[n], n))


def is_full(state: State, c: str) -> bool:
    """No free CPU on ``c``, or a node on it whose next step does not fit (read straight
    from the ladders: a fleet's relocation asks this of every target, thousands of times)."""
    free = state.free(c)
    if free <= EPS:
        return True
    room = free + EPS
    for n in state.members[c]:
        lad, k = state.ladder[n], state.level[n]
        if k + 1 < len(lad) and lad[k + 1].cpu - lad[k].cpu > room:
            return True
    return False


def relocate_from(state: State, c: str, *, only_nonmax: bool) -> None:
    """Algorithm 1 lines 11 / 15: move groups off full computer ``c``, best gradient first,
    each to the non-full allowed computer with the largest free capacity that holds it."""
    groups = sorted({state.group_of[n] for n in state.on(c)})
    if only_nonmax:
        groups = [gi for gi in groups
                  if any(len(state.ladder[n]) > 1 and not state.at_max(n) for n in state.groups[gi])]
    groups.sort(key=lambda gi: (-max(state.gradient(n) for n in state.groups[gi]), -state.group_cpu(gi), gi))
    for gi in groups:
        targets = [t for t in state.group_allowed[gi] if t != c and not is_full(state, t)]
        targets.sort(key=lambda t: (-state.free(t), state.computers.index(t)))
        for t in targets:
            if state.move_group(gi, t) is None:
                break


# ---- Problem 2 ------------------------------------------------------------------------
def algorithm3(state: State) -> str | None:
    every = set(state.computers)
    res = [gi for gi in range(len(state.groups)) if set(state.group_allowed[gi]) != every]
    rest = [gi for gi in range(len(state.groups)) if gi not in set(res)]
    for phase in (res, rest):
        for gi in _by_cpu_desc(state, phase):
            reason = _place_p2(state, gi)
            if reason is not None:
                return reason
    return None


def _place_p2(state: State, gi: int) -> str | None:
    allowed = state.group_allowed[gi]
    why: dict[str, str] = {}
    # best fit without growing anything
    for c in sorted(allowed, key=lambda c: (state.free(c), state.computers.index(c))):
        need = state.group_cpu(gi)
        if state.free(c) + EPS >= need:
            r = state.move_group(gi, c)
            if r is None:
                return None
            why[c] = r
    # grow the server that needs the least growth
    servers = [c for c in allowed if state.kind[c] == "server"]
    for c in sorted(servers, key=lambda c: (-state.free(c), state.computers.index(c))):
        need = state.group_cpu(gi) - state.free(c)
        if state.cap[c] + need > state.maxcap[c] + EPS * max(1.0, state.maxcap[c]):
            why[c] = f"{c} would need {fmt_units(state.cap[c] + need)} CPU > max_capacity {fmt_units(state.maxcap[c])}"
            continue
        old = state.cap[c]
        state.cap[c] = old + need
        r = state.move_group(gi, c)
        if r is None:
            return None
        state.cap[c] = old
        why[c] = r
    for c in allowed:
        why.setdefault(c, f"{c} has {fmt_units(state.free(c))} CPU free")
    return explain(state, gi, why)
