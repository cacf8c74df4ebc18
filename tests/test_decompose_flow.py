"""The fleet decomposition on driven fleets (issue 32): a robot's block carries its data
flow (a camera's rate and the detector it drives), checked against the tool's brute force
and the whole MILP on fleets small enough for them."""

from __future__ import annotations

import random
import warnings
from typing import Any

import pytest

from perfros_bag.casestudy.instances import wifi_fleet_instance
from perfros_bag.solver import decompose as decompose_mod
from perfros_bag.solver import dispatch, solve
from perfros_bag.solver.candidates import fixed_choices
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.decompose import decomposable, flow_views, solve_decomposed
from perfros_bag.solver.exact import solve_exact
from perfros_bag.solver.instance import prepare_instance, trivial_bound
from perfros_bag.system.plan import Status
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem, System


def driven_fleet(seed: int, robots: int = 2, *, detectors_on_servers_only: bool = False) -> dict[str, Any]:
    """A small driven wifi fleet: per robot its core, a camera whose rate is a knob, the
    detector it drives (on the robot or the server) and the environment node; capacities
    drawn so that rates, settings and offloading trade off, an access point that holds
    one 20 Hz stream."""
    keep = ("camera", "detector", "environment", "youbot_core")
    data = wifi_fleet_instance(robots, 1, trackers=1, driven=True, seed=seed, robots_per_ap=2, ap_kBps=1600.0)
    names = {n["name"] for n in data["nodes"] if n["name"].rstrip("0123456789") in keep}
    data["nodes"] = [n for n in data["nodes"] if n["name"] in names]
    data["edges"] = [e for e in data["edges"] if e["from"] in names and e["to"] in names]
    rng = random.Random(seed)
    for c in data["computers"]:
        c["capacity"] = rng.choice([30, 40, 50, 60, 80]) if c["kind"] == "robot" else rng.choice([40, 60, 90])
    if detectors_on_servers_only:  # the flow then spans a robot and the server: not one block
        servers = [c["name"] for c in data["computers"] if c["kind"] == "server"]
        for n in data["nodes"]:
            if n["name"].startswith("detector"):
                n["residence"] = servers
    return data


def system_of(data: dict[str, Any]) -> System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(data, "driven.yaml")


@pytest.mark.parametrize("seed", range(8))
def test_decomposed_driven_fleet_against_brute_force(seed: int) -> None:
    """The decomposition's plan is feasible (checker), its objective at most the brute
    force's optimum, its bound at least it (a proof), and equal to it when it says optimal."""
    system = system_of(driven_fleet(seed))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    assert decomposable(system, Problem.PERFORMANCE, choices)
    best = solve(system, 1, "bruteforce")
    assert best.status == Status.OPTIMAL and best.objective is not None
    plan = solve_decomposed(system, Problem.PERFORMANCE, choices)
    assert plan is not None and check_plan(system, plan) == []
    assert plan.objective is not None and plan.bound is not None
    assert plan.objective <= best.objective + 1e-7
    assert plan.bound >= best.objective - 1e-7
    assert plan.bound <= trivial_bound(system, choices) + 1e-9
    if plan.status == Status.OPTIMAL:
        assert plan.objective == pytest.approx(best.objective, rel=1e-7)
    for node in system.nodes:  # each detector planned at the rate its camera publishes
        if node.input is not None:
            parent = system.flow_parent[node.name]
            assert plan.nodes[node.name].input_hz == pytest.approx(plan.nodes[parent].value)


@pytest.mark.parametrize("seed", (0, 1))
def test_decomposed_bigger_driven_fleet_against_the_whole_milp(seed: int) -> None:
    """Six robots, their whole stacks and trackers: the whole MILP proves its optimum; the
    decomposition's bound is at least it and its plan at most it."""
    data = wifi_fleet_instance(6, 1, robots_per_ap=3, trackers=2, ap_kBps=2350.0, seed=seed, driven=True)
    system = system_of(data)
    choices = fixed_choices(system, Problem.PERFORMANCE)
    assert decomposable(system, Problem.PERFORMANCE, choices)
    exact = solve_exact(system, Problem.PERFORMANCE, choices, time_limit=120)
    assert exact.status == Status.OPTIMAL and exact.objective is not None
    plan = solve_decomposed(system, Problem.PERFORMANCE, choices)
    assert plan is not None and check_plan(system, plan) == []
    assert plan.objective is not None and plan.bound is not None
    assert plan.objective <= exact.objective + 1e-7 <= plan.bound + 2e-7


def test_flow_views_partition_the_consistent_choices() -> None:
    """Every consistent (camera, detector) pair lies in exactly one view, and no
    inconsistent pair in any (against the system's own flow rule)."""
    system = system_of(driven_fleet(0))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    inst = prepare_instance(system, Problem.PERFORMANCE, choices)
    assert not isinstance(inst, str)
    views = flow_views(inst, ["camera1", "detector1"])
    cams, dets = inst.choices["camera1"], inst.choices["detector1"]
    for i, cam in enumerate(cams):
        for j, det in enumerate(dets):
            consistent = system.flow_violation({"camera1": cam, "detector1": det}) is None
            holding = [v for v in views if i in v["camera1"] and j in v["detector1"]]
            assert len(holding) == (1 if consistent else 0)


def test_a_flow_across_robots_is_left_to_the_whole_milp(monkeypatch: pytest.MonkeyPatch) -> None:
    """Detectors that may only run on the server: each flow spans a robot's block and a
    node shared between robots, so the decomposition declines and ``exact`` (sent towards
    it by a zero threshold) answers with the whole MILP: the brute force's optimum."""
    system = system_of(driven_fleet(2, detectors_on_servers_only=True))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    assert not decomposable(system, Problem.PERFORMANCE, choices)
    assert solve_decomposed(system, Problem.PERFORMANCE, choices) is None
    monkeypatch.setattr(dispatch, "DECOMPOSE_COLUMNS", 0)
    plan = solve(system, 1, "exact", time_limit=30)
    best = solve(system, 1, "bruteforce")
    assert plan.status == Status.OPTIMAL and check_plan(system, plan) == []
    assert plan.objective == pytest.approx(best.objective, rel=1e-7)


def test_a_block_with_too_many_rate_assignments_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """Above the views limit the decomposition declines (it does not try); ``exact`` still
    answers, with the whole MILP's optimum."""
    system = system_of(driven_fleet(3))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    monkeypatch.setattr(decompose_mod, "MAX_VIEWS", 2)  # each robot's camera has 3 rates
    assert not decomposable(system, Problem.PERFORMANCE, choices)
    monkeypatch.setattr(dispatch, "DECOMPOSE_COLUMNS", 0)
    plan = solve(system, 1, "exact", time_limit=30)
    best = solve(system, 1, "bruteforce")
    assert check_plan(system, plan) == [] and plan.objective == pytest.approx(best.objective, rel=1e-7)


@pytest.mark.parametrize("seed", (0, 1))
def test_greedy_plus_rate_moves_keep_a_consistent_feasible_plan(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """greedy+'s fleet path (forced: passes of greedy runs "too dear"): after its rate moves
    (a camera's rate with its detector's choices and place, in place on greedy+'s state)
    the plan passes the checker, every detector runs at its camera's rate, it is no better
    than the whole MILP's optimum and no worse than the greedy's plan at the rates it
    starts from (every camera at its lowest)."""
    from perfros_bag.solver import flow
    from perfros_bag.solver.greedy import solve_greedy

    system = system_of(driven_fleet(seed, robots=4))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    calls: list[bool] = []
    apply = flow._apply_rates
    monkeypatch.setattr(flow, "PLUS_PASS_MAX_S", -1.0)
    monkeypatch.setattr(flow, "_apply_rates", lambda *a: calls.append(apply(*a)) or calls[-1])
    plan = solve(system, 1, "greedy+")
    assert any(calls)  # a rate move was made
    assert plan.status != Status.INFEASIBLE and check_plan(system, plan) == []
    for node in system.nodes:
        if node.input is not None:
            assert plan.nodes[node.name].input_hz == pytest.approx(plan.nodes[system.flow_parent[node.name]].value)
    optimum = solve_exact(system, Problem.PERFORMANCE, choices, time_limit=60)
    assert optimum.status == Status.OPTIMAL and optimum.objective is not None
    lowest = flow._restricted(system, choices, {p: opts[0] for p, opts in flow._class_options(system, choices).items()})
    assert lowest is not None
    start = solve_greedy(system, Problem.PERFORMANCE, lowest)
    assert plan.objective is not None and start.objective is not None
    assert start.objective - 1e-9 <= plan.objective <= optimum.objective + 1e-9


P2_CASES = [(f"driven-{seed}", driven_fleet(seed)) for seed in (1, 2)] + [
    (f"wifi6-{seed}-{'driven' if driven else 'plain'}",
     wifi_fleet_instance(6, 1, robots_per_ap=3, trackers=2, ap_kBps=2350.0, seed=seed, driven=driven))
    for seed in (0, 1) for driven in (False, True)]


@pytest.mark.parametrize(("name", "data"), P2_CASES, ids=[c[0] for c in P2_CASES])
def test_problem2_decomposed_against_the_whole_milp(name: str, data: dict[str, Any]) -> None:
    """Problem 2 (servers sized to their load) at Problem 1's settings: the decomposition's
    plan passes the checker, its objective (Σ server sizes, recomputed from its placement)
    is at least the whole MILP's optimum and its bound at most it."""
    from perfros_bag.solver.candidates import settings_from_plan
    from perfros_bag.system.rules import computer_loads

    system = system_of(data)
    settings = settings_from_plan(solve(system, 1, "exact"), system)
    choices = fixed_choices(system, Problem.SERVER_CAPACITY, settings)
    exact = solve_exact(system, Problem.SERVER_CAPACITY, choices, time_limit=60)
    assert exact.status == Status.OPTIMAL and exact.objective is not None
    plan = solve_decomposed(system, Problem.SERVER_CAPACITY, choices)
    assert plan is not None and check_plan(system, plan) == []
    assert plan.objective is not None and plan.bound is not None
    load = computer_loads(system, {n: pn.computer for n, pn in plan.nodes.items()},
                          {n: next(ch for ch in choices[n] if ch.cpu == pn.cpu) for n, pn in plan.nodes.items()})
    assert plan.objective == pytest.approx(sum(load[c.name] for c in system.computers if c.kind == "server"))
    assert plan.bound - 1e-6 <= exact.objective <= plan.objective + 1e-6
    if plan.status == Status.OPTIMAL:
        assert plan.objective == pytest.approx(exact.objective, abs=1e-6)
