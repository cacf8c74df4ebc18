"""The model's rules on a placement (System.capacities / link_loads / network_violation and
rules.build_plan), checked against the independent checker (solver/check.py) on random
placements of a system with tight links, a shared medium and an unreachable computer."""

from __future__ import annotations

import copy
import math
import random
from typing import Any

import pytest

from perfros_bag.errors import InputError
from perfros_bag.solver.check import check_plan
from perfros_bag.system.plan import Assignment, Status
from perfros_bag.system.rules import build_plan, computer_loads, server_sizes
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Choice, Problem, System

# r1 - srv - r2 (links of 10 kB/s on a 15 kB/s wifi), r2 - r3 wired; island joined to nothing
SYSTEM: dict[str, Any] = {
    "computers": [
        {"name": "r1", "kind": "robot", "capacity": 50},
        {"name": "r2", "kind": "robot", "capacity": 50},
        {"name": "r3", "kind": "robot", "capacity": 50},
        {"name": "srv", "kind": "server", "capacity": 100, "max_capacity": 120},
        {"name": "island", "kind": "server", "capacity": 100},
    ],
    "links": [
        {"between": ["r1", "srv"], "bandwidth_kBps": 10, "medium": "wifi"},
        {"between": ["r2", "srv"], "bandwidth_kBps": 10, "medium": "wifi"},
        {"between": ["r2", "r3"], "bandwidth_kBps": 6},
    ],
    "media": [{"name": "wifi", "bandwidth_kBps": 15}],
    "nodes": [
        {"name": "a", "weight": 0.25, "settings": [{"cpu": 10, "performance": 100, "bandwidth_kBps": 4}]},
        {"name": "b", "weight": 0.25, "parameter": {"name": "p"},
         "settings": [{"value": 1, "cpu": 20, "performance": 50, "bandwidth_kBps": 2},
                      {"value": 2, "cpu": 40, "performance": 90, "bandwidth_kBps": 8}]},
        {"name": "c", "weight": 0.25, "topics": ["/c/x", "/c/y"],
         "settings": [{"cpu": 30, "performance": 80, "bandwidth_kBps": 3}]},
        {"name": "d", "weight": 0.25, "settings": [{"cpu": 5, "performance": 100, "bandwidth_kBps": 1}]},
    ],
    "edges": [{"from": "a", "to": "b"}, {"from": "b", "to": "c"}, {"from": "c", "to": "d"},
              {"from": "d", "to": "a", "bandwidth_kBps": 2.5}],
}
NETWORK = ("link ", "medium ", "no network path")


def system() -> System:
    return parse_system(copy.deepcopy(SYSTEM), "rules.yaml")


def random_assignment(s: System, rng: random.Random) -> Assignment:
    placement = {n.name: rng.choice([c.name for c in s.computers]) for n in s.nodes}
    choice = {n.name: rng.choice(n.choices()) for n in s.nodes}
    return Assignment(placement, choice)


def test_link_loads_and_network_rule_agree_with_the_independent_checker() -> None:
    s = system()
    rng = random.Random(7)
    seen = {"fits": 0, "overload": 0, "no path": 0}
    for _ in range(400):
        a = random_assignment(s, rng)
        plan = build_plan(s, a, problem=Problem.PERFORMANCE, method="t", status=Status.FEASIBLE)
        problems = check_plan(s, plan)
        # build_plan's link loads are the checker's own sums (else "plan reports load ...")
        assert not [p for p in problems if "plan reports" in p], problems
        # computer loads likewise
        assert {c: pc.cpu for c, pc in plan.computers.items()} == pytest.approx(
            computer_loads(s, a.placement, a.choice))
        violation = s.network_violation(a.placement, a.choice)
        network_problems = [p for p in problems if p.startswith(NETWORK) or "no network path" in p]
        assert (violation is None) == (not network_problems), (violation, problems)
        kind = "fits" if violation is None else "no path" if "no network path" in violation else "overload"
        seen[kind] += 1
    assert all(seen.values()), seen  # every case was exercised


def test_link_loads_leave_out_unplaced_ends() -> None:
    s = system()
    choice: dict[str, Choice] = {n.name: n.choices()[-1] for n in s.nodes}
    whole = {"a": "r1", "b": "srv", "c": "r3", "d": "r3"}
    partial: dict[str, str | None] = {**whole, "c": None}
    full_loads, part_loads = s.link_loads(whole, choice), s.link_loads(partial, choice)
    # only b->c and c->d involve c: b->c crosses srv-r2 and r2-r3; c->d is local to r3
    b_to_c = s.edge_bandwidth(s.edges[1], choice["b"])
    route = s.route("srv", "r3")
    assert route is not None and len(route) == 2
    assert [full - part for full, part in zip(full_loads, part_loads, strict=True)] == pytest.approx(
        [b_to_c if li in route else 0.0 for li in range(len(s.links))])


def test_capacities_per_problem() -> None:
    s = system()
    assert s.capacities(Problem.PERFORMANCE) == {c.name: c.capacity for c in s.computers}
    sized = s.capacities(Problem.SERVER_CAPACITY)
    assert sized["srv"] == 120 and sized["island"] == math.inf  # max_capacity, else unbounded
    assert {c: sized[c] for c in ("r1", "r2", "r3")} == {c: s.computer[c].capacity for c in ("r1", "r2", "r3")}
    data = copy.deepcopy(SYSTEM)
    del data["computers"][3]["capacity"]
    unsized = parse_system(data, "unsized.yaml")
    with pytest.raises(InputError, match=r"^unsized.yaml: computer\(s\) 'srv' have no capacity: Problem 1 needs"):
        unsized.capacities(Problem.PERFORMANCE)
    assert unsized.capacities(Problem.SERVER_CAPACITY)["srv"] == 120


def test_server_sizes_are_their_loads() -> None:
    s = system()
    rng = random.Random(3)
    for _ in range(50):
        a = random_assignment(s, rng)
        sizes = server_sizes(s, a.placement, a.choice)
        for c in s.computers:
            on_it = sum(a.choice[n].cpu for n, comp in a.placement.items() if comp == c.name)
            if c.kind == "server":
                assert sizes[c.name] == pytest.approx(on_it)
            else:
                assert c.name not in sizes


def test_allowed_to_all_is_the_intersection() -> None:
    data = copy.deepcopy(SYSTEM)
    data["nodes"][0]["residence"] = ["r1", "srv", "r2"]
    data["nodes"][1]["residence"] = ["r2", "srv"]
    s = parse_system(data, "res.yaml")
    for group in (["a"], ["a", "b"], ["b", "c"], ["c", "d"]):
        expected = [c.name for c in s.computers if all(c.name in s.allowed(n) for n in group)]
        assert list(s.allowed_to_all(group)) == expected
    assert s.allowed_to_all(["a", "b"]) == ("r2", "srv")  # system order, not residence order
