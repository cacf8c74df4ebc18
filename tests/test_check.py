"""The independent plan checker: it accepts a hand-computed feasible plan and catches every
kind of violation in deliberately broken ones."""

from __future__ import annotations

import copy
from typing import Any

import pytest

from perfros_bag.solver.check import check_plan, plan_objective
from perfros_bag.system.plan import Plan
from perfros_bag.system.planfile import parse_plan
from perfros_bag.system.systemfile import parse_system

# r1, r2: robots of 50; srv: a server of 100 (Problem 2: at most 120). Links r1-srv and
# r2-srv carry 10 kB/s each, both on the wifi medium of 15 kB/s.
SYSTEM: dict[str, Any] = {
    "computers": [
        {"name": "r1", "kind": "robot", "capacity": 50},
        {"name": "r2", "kind": "robot", "capacity": 50},
        {"name": "srv", "kind": "server", "capacity": 100, "max_capacity": 120},
    ],
    "links": [
        {"between": ["r1", "srv"], "bandwidth_kBps": 10, "medium": "wifi"},
        {"between": ["r2", "srv"], "bandwidth_kBps": 10, "medium": "wifi"},
    ],
    "media": [{"name": "wifi", "bandwidth_kBps": 15}],
    "nodes": [
        {"name": "a", "weight": 0.25, "residence": ["r1"],
         "settings": [{"cpu": 10, "performance": 100, "bandwidth_kBps": 4}]},
        {"name": "b", "weight": 0.25, "parameter": {"name": "p"},
         "settings": [{"value": 1, "cpu": 20, "performance": 50, "bandwidth_kBps": 2},
                      {"value": 2, "cpu": 40, "performance": 90, "bandwidth_kBps": 8}]},
        {"name": "c", "weight": 0.25, "coresidence": ["d"],
         "settings": [{"cpu": 30, "performance": 80, "bandwidth_kBps": 1}]},
        {"name": "d", "weight": 0.25, "settings": [{"cpu": 5, "performance": 100, "bandwidth_kBps": 1}]},
    ],
    "edges": [{"from": "a", "to": "b"}, {"from": "b", "to": "c"}, {"from": "c", "to": "d"}],
}


def node(computer: str, cpu: float, perf: float) -> dict[str, Any]:
    return {"computer": computer, "cpu": cpu, "performance": perf, "weight": 0.25}


# Hand-computed: a, b (value 2) on r1 = 50 CPU; c, d on srv = 35. Only b->c crosses
# r1-srv, at b's 8 kB/s. Objective 0.25 * (100 + 90 + 80 + 100) = 92.5.
GOOD: dict[str, Any] = {
    "format": "perfros-bag/plan@1", "problem": 1, "method": "hand", "status": "feasible", "objective": 92.5,
    "computers": {"r1": {"kind": "robot", "capacity": 50, "cpu": 50}, "r2": {"kind": "robot", "capacity": 50, "cpu": 0},
                  "srv": {"kind": "server", "capacity": 100, "cpu": 35}},
    "links": [{"between": ["r1", "srv"], "bandwidth_kBps": 10, "load_kBps": 8},
              {"between": ["r2", "srv"], "bandwidth_kBps": 10, "load_kBps": 0}],
    "nodes": {"a": node("r1", 10, 100), "b": node("r1", 40, 90), "c": node("srv", 30, 80), "d": node("srv", 5, 100)},
}


def system(**changes: Any) -> Any:
    data = copy.deepcopy(SYSTEM)
    for key, value in changes.items():
        section, name, field = key.split("__")
        for item in data[section]:
            if item.get("name") == name or "-".join(item.get("between", [])) == name:
                item[field] = value
    return parse_system(data, "check.yaml")


def plan(**node_changes: dict[str, Any]) -> Plan:
    data = copy.deepcopy(GOOD)
    for name, fields in node_changes.items():
        data["nodes"][name].update(fields)
    # keep the reported loads consistent so only the intended violation shows
    data["computers"] = {c: {**v, "cpu": 0} for c, v in data["computers"].items()}
    for n in data["nodes"].values():
        if n["computer"] in data["computers"]:
            data["computers"][n["computer"]]["cpu"] += n["cpu"]
    data["links"] = []
    return parse_plan(data, "plan.json")


def test_hand_computed_plan_is_feasible() -> None:
    s = system()
    p = parse_plan(copy.deepcopy(GOOD))
    assert check_plan(s, p) == []
    assert plan_objective(s, p, 1) == pytest.approx(92.5)


def one(violations: list[str], needle: str) -> None:
    assert violations, "the checker accepted a broken plan"
    assert any(needle in v for v in violations), violations


def test_cpu_over_capacity() -> None:
    one(check_plan(system(computers__r1__capacity=45), parse_plan(copy.deepcopy(GOOD))),
        "computer r1: cpu 50 > capacity 45")


def test_link_over_bandwidth() -> None:
    # b (8 kB/s) on r2: a->b loads r1-srv and r2-srv with 4, b->c loads r2-srv with 8
    v = check_plan(system(), plan(b={"computer": "r2"}))
    one(v, "link r2-srv: load 12 > bandwidth 10")
    one(v, "medium wifi: load 16 > bandwidth 15")


def test_shared_medium_alone() -> None:
    # b at value 1 (2 kB/s) on r2: links carry 4 and 6, the medium 10 > 9
    v = check_plan(system(media__wifi__bandwidth_kBps=9), plan(b={"computer": "r2", "cpu": 20, "performance": 50}))
    assert [x for x in v if not x.startswith("objective")] == ["medium wifi: load 10 > bandwidth 9 kB/s"]


def test_residence() -> None:
    one(check_plan(system(), plan(a={"computer": "srv"})), "node a: residence: on srv, allowed r1")


def test_coresidence() -> None:
    one(check_plan(system(), plan(d={"computer": "r2"})), "coresidence: c on srv but d on r2")


def test_setting_that_does_not_exist() -> None:
    one(check_plan(system(), plan(b={"cpu": 30, "performance": 70})),
        "node b: cpu 30 / performance 70 is none of its settings")


def test_wrong_objective() -> None:
    data = copy.deepcopy(GOOD)
    data["objective"] = 93.5
    one(check_plan(system(), parse_plan(data)), "objective: plan says 93.5, eq 1 gives 92.5")


def test_unplaced_and_unknown_computer() -> None:
    data = copy.deepcopy(GOOD)
    del data["nodes"]["d"]
    one(check_plan(system(), parse_plan(data)), "node d: not placed")
    # plan.json's reader refuses a node on a computer the plan does not list (issue 16), so
    # the checker's own guard is exercised on a Plan built in memory
    p = plan()
    p.nodes["c"].computer = p.nodes["d"].computer = "mars"
    one(check_plan(system(), p), "node c: on unknown computer mars")


def test_reported_loads_must_match() -> None:
    data = copy.deepcopy(GOOD)
    data["computers"]["srv"]["cpu"] = 1
    one(check_plan(system(), parse_plan(data)), "computer srv: plan reports cpu 1, its nodes sum to 35")
    data = copy.deepcopy(GOOD)
    data["links"][0]["load_kBps"] = 2
    one(check_plan(system(), parse_plan(data)), "link r1-srv: plan reports load 2, edges sum to 8")


def test_disconnected_computers() -> None:
    data = copy.deepcopy(SYSTEM)
    data["links"] = data["links"][:1]
    one(check_plan(parse_system(data, "x.yaml"), plan(b={"computer": "r2"})), "no network path between r1 and r2")


def test_problem2_server_capacity() -> None:
    s = system()
    data = copy.deepcopy(GOOD)
    data["problem"] = 2
    data["computers"]["srv"]["capacity"] = 35
    data["objective"] = 35
    assert check_plan(s, parse_plan(copy.deepcopy(data))) == []
    data["computers"]["srv"]["capacity"] = 30
    data["objective"] = 30
    one(check_plan(s, parse_plan(copy.deepcopy(data))), "computer srv: cpu 35 > capacity 30")
    data["computers"]["srv"]["capacity"] = 130
    data["objective"] = 130
    one(check_plan(s, parse_plan(copy.deepcopy(data))), "computer srv: sized 130 > max_capacity 120")
    data["computers"]["srv"]["capacity"] = 35
    data["objective"] = 100
    one(check_plan(s, parse_plan(data)), "objective: plan says 100.0, eq 2 gives 35")


def test_infeasible_plan_is_reported() -> None:
    p = Plan(1, "greedy", "infeasible", reason="x needs 5 CPU")
    assert check_plan(system(), p) == ["plan is infeasible: x needs 5 CPU"]
