"""``solve --headroom H``: every computer keeps H of its capacity free. Checked against the
same instance written with its capacities cut by hand, and by the independent checker."""

from __future__ import annotations

import copy
import subprocess
import sys
from typing import Any

import pytest
import yaml

from perfros_bag.errors import InputError
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.planfile import load_plan
from perfros_bag.system.systemfile import parse_system
from tests.test_flow import EXAMPLE

pytestmark = pytest.mark.filterwarnings("ignore:.*weights sum to")


def cut(data: dict[str, Any], keep: float) -> dict[str, Any]:
    out = copy.deepcopy(data)
    for c in out["computers"]:
        for key in ("capacity", "max_capacity"):
            if key in c:
                c[key] = c[key] * keep
    return out


@pytest.mark.parametrize("method", ["exact", "greedy+", "bruteforce"])
@pytest.mark.parametrize("headroom", [0.1, 0.35])
def test_problem_1_equals_the_instance_with_capacities_cut_by_hand(method: str, headroom: float) -> None:
    system = parse_system(copy.deepcopy(EXAMPLE), "flow.yaml")
    plan = solve(system, 1, method, headroom=headroom)
    by_hand = solve(parse_system(cut(EXAMPLE, 1 - headroom), "cut.yaml"), 1, method)
    assert plan.status == by_hand.status
    assert plan.objective == pytest.approx(by_hand.objective)
    assert check_plan(system, plan) == []
    for c in EXAMPLE["computers"]:
        pc = plan.computers[c["name"]]
        assert pc.capacity == c["capacity"]
        assert pc.margin == pytest.approx(headroom * c["capacity"])
        assert pc.cpu <= (1 - headroom) * c["capacity"] + 1e-9


def test_problem_2_sizes_servers_with_the_margin() -> None:
    data = copy.deepcopy(EXAMPLE)
    system = parse_system(data, "flow.yaml")
    plain = solve(system, 2, "exact")
    kept = solve(system, 2, "exact", headroom=0.25)
    assert check_plan(system, kept) == []
    server = kept.computers["server"]
    assert server.capacity == pytest.approx(server.cpu / 0.75)
    assert server.margin == pytest.approx(0.25 * server.capacity)
    assert kept.objective == pytest.approx(server.capacity)
    assert kept.objective >= plain.objective - 1e-9


def test_checker_refuses_a_plan_that_eats_its_margin() -> None:
    system = parse_system(copy.deepcopy(EXAMPLE), "flow.yaml")
    plan = solve(system, 1, "exact")
    busiest = max(plan.computers.values(), key=lambda pc: pc.cpu / (pc.capacity or 1))
    busiest.margin = (busiest.capacity or 0) - busiest.cpu + 1.0
    assert any("margin" in why for why in check_plan(system, plan))


@pytest.mark.parametrize("bad", [-0.1, 1.0, 2.0, float("nan")])
def test_headroom_outside_0_1_is_refused(bad: float) -> None:
    system = parse_system(copy.deepcopy(EXAMPLE), "flow.yaml")
    with pytest.raises(InputError, match="headroom must be in"):
        solve(system, 1, "exact", headroom=bad)


def test_cli_headroom(tmp_path: Any) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(EXAMPLE))
    bad = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(path), "--headroom", "1"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert [line for line in bad.stderr.splitlines() if line.strip()] == ["error: --headroom must be in [0, 1), got 1.0"]
    good = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(path), "--method", "exact",
                           "--headroom", "0.2", "--out", str(tmp_path / "plan.json")], capture_output=True, text=True)
    assert good.returncode == 0, good.stderr
    plan = load_plan(tmp_path / "plan.json")
    assert plan.extra["headroom"] == 0.2
    assert {n: pc.margin for n, pc in plan.computers.items()} == pytest.approx({"robot": 6.0, "server": 10.0})
