"""Latency budgets in the solvers: exact equal to brute force, the heuristics never over a
budget, an impossible budget named with its bound, the independent checker refusing a plan
over budget."""

from __future__ import annotations

import json
import math
import random
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.latency import plan_predictions
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import System


def _instance(seed: int, budget: dict[str, float] | None = None) -> dict[str, object]:
    rng = random.Random(seed)
    per_hz = [round(rng.uniform(0.5, 4.0), 2) for _ in range(2)]
    return {
        "computers": [{"name": "robot", "kind": "robot", "capacity": rng.choice([40, 60, 90])},
                      {"name": "server", "kind": "server", "capacity": rng.choice([60, 120, 200])}],
        "links": [{"between": ["robot", "server"], "bandwidth_kBps": rng.choice([800, 1500, 3000])}],
        "nodes": [
            {"name": "camera", "weight": 0.3, "residence": ["robot"], "parameter": {"name": "rate"},
             "topics": ["/cam"],
             "settings": [{"value": 5, "cpu": 2, "performance": 50, "frequency_hz": 5, "bandwidth_kBps": 500},
                          {"value": 10, "cpu": 4, "performance": 100, "frequency_hz": 10, "bandwidth_kBps": 1000}]},
            {"name": "detector", "weight": 0.3, "input": "/cam", "parameter": {"name": "scale"}, "topics": ["/det"],
             "settings": [{"value": 1, "cpu": 1, "cpu_per_hz": per_hz[0] + 2, "performance": 100,
                           "bytes_per_msg": 20000},
                          {"value": 2, "cpu": 1, "cpu_per_hz": per_hz[0], "performance": 60, "bytes_per_msg": 20000}]},
            {"name": "tracker", "weight": 0.2, "input": "/det", "parameter": {"name": "k"}, "topics": ["/trk"],
             "settings": [{"value": 1, "cpu": 1, "cpu_per_hz": per_hz[1], "performance": 100, "bytes_per_msg": 100},
                          {"value": 2, "cpu": 1, "cpu_per_hz": per_hz[1] / 2, "performance": 70,
                           "bytes_per_msg": 100}]},
            {"name": "logger", "weight": 0.2, "parameter": {"name": "level"}, "topics": ["/log"],
             "settings": [{"value": 1, "cpu": 10, "performance": 50, "frequency_hz": 1},
                          {"value": 2, "cpu": 30, "performance": 100, "frequency_hz": 1}]},
        ],
        "edges": [{"from": "camera", "to": "detector", "topic": "/cam"},
                  {"from": "detector", "to": "tracker", "topic": "/det"}],
        "chains": [{"name": "vision", "topics": ["/cam", "/det", "/trk"],
                    **({"budget_ms": budget} if budget else {})}],
        # odd seeds: the computers are CFS-capped cgroups of a 10 ms period (deploy's), so an
        # idle node's burst ends a period sooner (system/latency.burst_time, check.py's copy)
        # ... and their links shaped by a tc bucket of 10 ms (deploy's tbf): a message below
        # the link's rate crosses 10 ms sooner
        **({"latency": {"cfs_period_ms": 10, "link_burst_ms": 10}} if seed % 2 else {}),
    }


def _predicted(system: System, problem: int, method: str) -> list[float]:
    plan = solve(system, problem, method)
    return [] if plan.status == "infeasible" else [p.p95_ms or math.inf for p in plan_predictions(system, plan)]


@pytest.mark.parametrize("seed", range(12))
def test_exact_with_a_budget_equals_brute_force_and_holds_it(seed: int) -> None:
    free = parse_system(_instance(seed))
    loose = _predicted(free, 1, "exact")
    assert loose, "the instance without a budget is feasible"
    # a budget 10-90 % of the way from the fastest hop-by-hop bound to the unbudgeted optimum's latency
    from perfros_bag.solver import fixed_choices
    from perfros_bag.system.latency import fastest_bound
    from perfros_bag.system.types import Problem

    choices = fixed_choices(free, Problem.PERFORMANCE, None, 1.0)
    lo = fastest_bound(free, free.chains[0], choices)
    assert lo is not None
    share = random.Random(seed).uniform(0.1, 0.9)
    budget = lo[1] + share * max(loose[0] - lo[1], 1.0)
    system = parse_system(_instance(seed, {"p95": round(budget, 3)}))
    exact, brute = solve(system, 1, "exact"), solve(system, 1, "bruteforce")
    assert exact.status == brute.status
    if brute.status == "infeasible":
        assert "vision" in (exact.reason or "")
        return
    assert exact.status == "optimal"
    assert exact.objective == pytest.approx(brute.objective, abs=1e-6)
    assert check_plan(system, exact) == []  # within its budget, by the checker's own copy of the rule
    assert exact.chains[0]["predicted_ms"]["p95"] <= budget * (1 + 1e-9)


@pytest.mark.parametrize("method", ["greedy", "greedy+"])
@pytest.mark.parametrize("seed", range(12))
def test_the_heuristics_never_return_a_plan_over_a_budget(seed: int, method: str) -> None:
    free = parse_system(_instance(seed))
    loose = _predicted(free, 1, "exact")
    system = parse_system(_instance(seed, {"p95": round(0.8 * loose[0], 3)}))
    plan = solve(system, 1, method)
    if plan.status == "infeasible":
        assert "vision" in (plan.reason or "") or "budget" in (plan.reason or "")
        return
    assert check_plan(system, plan) == []


def test_the_checker_refuses_a_plan_over_a_budget() -> None:
    free = parse_system(_instance(3))
    plan = solve(free, 1, "exact")
    p95 = plan.chains[0]["predicted_ms"]["p95"]
    tight = parse_system(_instance(3, {"p95": round(p95 / 2, 3)}))
    plan.chains[0]["budget_ms"] = {"p95": round(p95 / 2, 3)}
    problems = check_plan(tight, plan)
    assert any(p.startswith("chain vision: predicted p95 ") and f"> budget {round(p95 / 2, 3):g} ms" in p
               for p in problems), problems
    assert check_plan(free, plan) == []  # the same plan without the budget: its stated latency agrees


def test_the_checker_refuses_a_plan_that_misstates_its_latency() -> None:
    system = parse_system(_instance(5))
    plan = solve(system, 1, "exact")
    plan.chains[0]["predicted_ms"] = {"p50": 1.0, "p95": 2.0}
    assert any("chain vision: plan states p50 1.0 ms" in p for p in check_plan(system, plan))


def test_an_impossible_budget_is_one_line_naming_the_chain_and_its_bound(tmp_path: Path) -> None:
    data = _instance(7, {"p95": 0.5})
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "plan.json"
    res = CliRunner().invoke(app, ["solve", str(path), "--problem", "1", "--method", "exact", "--out", str(out)])
    assert res.exit_code == 2
    [line] = [ln for ln in res.stderr.splitlines() if ln.strip()]
    # the bound, by hand: each hop at its fastest choice, alone on the largest computer (at most
    # one core, 100 units), beside its input; overhead 1 ms, service w / v, 1.3 x service and the
    # wait of a periodic input: none below utilisation 1, above it the oldest of the full queue
    # (1) and socket backlog (2): 2.95 input periods, at most 3 services. Seed 7's computers
    # are CFS-capped (10 ms): below utilisation 1 a capped node ends one period sooner, never
    # sooner than at one core
    speed = min(100, max(c["capacity"] for c in data["computers"]))  # type: ignore[index]
    period = data["latency"]["cfs_period_ms"] / 1000  # type: ignore[index]
    hops = []
    for settings in (data["nodes"][1]["settings"], data["nodes"][2]["settings"]):  # type: ignore[index]
        best = math.inf
        for s in settings:
            for lam in (5, 10):  # the camera's rates; each hop passes every message on
                w = (s["cpu"] + s["cpu_per_hz"] * lam) / lam
                svc = w / speed
                rho = lam * svc
                if rho <= 1:
                    svc = max(svc - period, w / 100)
                wait = 0.0 if rho < 1 else min(2.95 / lam, 3 * svc)
                best = min(best, 1 + 1000 * (1.3 * svc + wait))
        hops.append(best)
    assert f"chain 'vision': no plan keeps its predicted p95 within its budget of 0.5 ms: in every plan it is at " \
           f"least {sum(hops):.4g} ms" in line
    assert json.loads(out.read_text())["status"] == "infeasible"


@pytest.mark.parametrize("seed", range(8))
def test_problem_2_with_a_budget_equals_brute_force(seed: int) -> None:
    data = _instance(seed)
    for c in data["computers"]:  # type: ignore[union-attr]
        if c["kind"] == "server":
            c.pop("capacity")
            c["max_capacity"] = 400
        else:
            c["capacity"] = 90  # every node fits at its highest setting
    free = parse_system(data)
    plan = solve(free, 2, "exact")
    assert plan.status == "optimal"
    p95 = plan.chains[0]["predicted_ms"]["p95"]
    data["chains"][0]["budget_ms"] = {"p95": round(p95 * random.Random(seed).uniform(0.5, 1.0), 3)}  # type: ignore[index]
    system = parse_system(data)
    exact, brute = solve(system, 2, "exact"), solve(system, 2, "bruteforce")
    assert exact.status == brute.status
    if brute.status != "infeasible":
        assert exact.objective == pytest.approx(brute.objective, abs=1e-6)
        assert check_plan(system, exact) == []


@pytest.mark.parametrize("headroom", [0.2, "auto"])
def test_a_plan_with_headroom_keeps_its_budget_as_restated(headroom: float | str) -> None:
    free = parse_system(_instance(4))
    loose = solve(free, 1, "exact").chains[0]["predicted_ms"]["p95"]
    system = parse_system(_instance(4, {"p95": round(0.6 * loose, 3)}))
    for method in ("exact", "greedy+"):
        plan = solve(system, 1, method, headroom=headroom)
        if plan.status == "infeasible":
            continue
        assert plan.chains[0]["predicted_ms"]["p95"] <= 0.6 * loose + 1e-6
        assert check_plan(system, plan) == []  # the restated plan's latency, as the checker predicts it
