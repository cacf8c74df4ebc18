"""plan.json: what is written reads back into the same plan and writes the same bytes; the
closed sets (problem, method, status) are enums in memory and plain JSON values on disk."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from perfros_bag.errors import InfeasibleError, InputError
from perfros_bag.fileio import atomic_write_json
from perfros_bag.solver import solve
from perfros_bag.system.plan import Method, Plan, Status
from perfros_bag.system.planfile import is_forced, load_plan, parse_plan, save_plan
from perfros_bag.system.systemfile import load_system
from perfros_bag.system.types import Problem

ROOT = Path(__file__).resolve().parent.parent
INSTANCE1 = ROOT / "fixtures" / "casestudy" / "instance1.yaml"

HAND_WRITTEN: dict[str, Any] = {
    "format": "perfros-bag/plan@1", "problem": 2, "method": "by hand", "status": "feasible",
    "objective": 30.0, "bound": None, "solve_s": None, "system": "system.yaml",
    "computers": {"r1": {"kind": "robot", "capacity": 50.0, "cpu": 20.0},
                  "srv": {"kind": "server", "capacity": 30.0, "cpu": 30.0}},
    "links": [{"between": ["r1", "srv"], "bandwidth_kBps": 10.0, "load_kBps": 2.5, "medium": "wifi"}],
    "nodes": {"a": {"computer": "r1", "parameter": "rate", "value": 5.0, "cpu": 20.0, "performance": 80.0,
                    "weight": 0.5, "topics": {"/a": {"frequency_hz": 5.0, "bandwidth_kBps": 2.5}}},
              "b": {"computer": "srv", "parameter": None, "value": None, "cpu": 30.0, "performance": 100.0,
                    "weight": 0.5, "topics": {}}},
    "note": "an extra field a tool added",
}


def rewrite(src: Path, dst: Path) -> Plan:
    plan = load_plan(src)
    save_plan(plan, dst)
    return plan


@pytest.mark.parametrize(("problem", "method"), [(1, "greedy"), (1, "greedy+"), (2, "greedy"), (1, "exact")])
def test_solved_plan_round_trips_byte_for_byte(tmp_path: Path, problem: int, method: str) -> None:
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    save_plan(solve(load_system(INSTANCE1), problem, method), first)
    plan = rewrite(first, second)
    assert second.read_bytes() == first.read_bytes()
    assert plan.problem is Problem(problem) and plan.method is Method(method)
    assert isinstance(plan.status, Status)
    doc = json.loads(first.read_text())  # plain JSON values, not enum names
    assert type(doc["problem"]) is int and doc["problem"] == problem
    assert doc["method"] == method and doc["status"] in ("optimal", "feasible")


def test_hand_written_plan_round_trips_byte_for_byte(tmp_path: Path) -> None:
    """Written by another writer (fields in the documented order, an unknown method label,
    an extra field): reading and writing it again changes no byte."""
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    atomic_write_json(first, HAND_WRITTEN)
    plan = rewrite(first, second)
    assert second.read_bytes() == first.read_bytes()
    assert plan.method == "by hand" and not isinstance(plan.method, Method)
    assert plan.extra == {"note": "an extra field a tool added"}


def test_infeasible_plan_round_trips_and_refuses(tmp_path: Path) -> None:
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    save_plan(Plan.infeasible(Problem.PERFORMANCE, Method.EXACT, "robot1 is too small", system="s.yaml"), first)
    plan = rewrite(first, second)
    assert second.read_bytes() == first.read_bytes()
    assert plan.status is Status.INFEASIBLE and plan.nodes == {}
    with pytest.raises(InfeasibleError) as caught:
        plan.require_feasible(first, "deploy")
    assert str(caught.value) == f"{first}: infeasible: robot1 is too small (nothing to deploy)"
    plan.status = Status.FEASIBLE
    plan.require_feasible(first, "deploy")  # no error


@pytest.mark.parametrize(("field", "value", "message"), [
    ("status", "great", "status must be one of optimal, feasible, infeasible, got 'great'"),
    ("status", ["optimal"], "status must be one of"),
    ("problem", 3, "problem must be 1 or 2, got 3"),
    ("problem", True, "problem must be 1 or 2, got True"),
])
def test_closed_sets_are_checked(field: str, value: Any, message: str) -> None:
    with pytest.raises(InputError, match="^p.json: " + message.replace("[", r"\[")):
        parse_plan({**HAND_WRITTEN, field: value}, "p.json")


def test_plan_coerces_raw_values_to_enums() -> None:
    plan = Plan(2, "exact", "optimal")  # type: ignore[arg-type]
    assert plan.problem is Problem.SERVER_CAPACITY and plan.method is Method.EXACT
    assert plan.status is Status.OPTIMAL
    with pytest.raises(ValueError):
        Plan(1, "exact", "good")  # type: ignore[arg-type]


def _overloaded(**top: Any) -> dict[str, Any]:
    """HAND_WRITTEN with node a needing 60 CPU units on r1 (capacity 50)."""
    doc = json.loads(json.dumps(HAND_WRITTEN))
    doc["nodes"]["a"]["cpu"] = 60.0
    doc["computers"]["r1"]["cpu"] = 60.0
    doc.update(top)
    return doc


def test_a_forced_plan_may_exceed_its_computers_and_says_so(tmp_path: Path) -> None:
    """A node whose cpu exceeds its computer's capacity is refused, unless the plan says
    ``"forced": true`` (built beyond its computers on purpose); the mark round-trips."""
    with pytest.raises(InputError, match="node 'a': 'cpu' 60 exceeds the capacity 50 of its computer 'r1'"):
        parse_plan(_overloaded(), "p.json")
    with pytest.raises(InputError, match="node 'a': 'cpu' 60 exceeds the capacity 50"):
        parse_plan(_overloaded(forced=False), "p.json")
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    atomic_write_json(first, _overloaded(forced=True))
    plan = rewrite(first, second)
    assert second.read_bytes() == first.read_bytes()
    assert is_forced(plan) and plan.nodes["a"].cpu == 60.0 > plan.computers["r1"].capacity  # type: ignore[operator]
    assert not is_forced(parse_plan(HAND_WRITTEN, "p.json"))
    for bad in ("yes", 1, None):
        with pytest.raises(InputError, match="'forced' must be true or false"):
            parse_plan(_overloaded(forced=bad), "p.json")
