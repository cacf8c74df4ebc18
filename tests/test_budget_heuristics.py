"""greedy+ under latency budgets against brute force and the exact MILP, on instances whose
budgets bind (tests/budget_gen.py): a plan wherever brute force has one, accepted by the
independent checker (budgets included), never better than the optimum, and at it on most
instances; and the rule at utilisation 1 (a Problem 2 server sized to its load) agreed on by
the model and the checker."""

from __future__ import annotations

import dataclasses
import random
import warnings

import pytest
from budget_gen import flow_instance, random_plan, vision_instance

from perfros_bag.solver import solve
from perfros_bag.solver.budgets import capacities_of
from perfros_bag.solver.check import check_plan
from perfros_bag.system.latency import predict_chain
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem, System


def _instances(family: str, problem: int, seeds: int) -> list[tuple[int, System]]:
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in range(seeds):
            s = flow_instance(seed, problem) if family == "flow" else vision_instance(seed, problem)
            if s is not None:
                out.append((seed, s))
    return out


def _worse_or_equal(problem: int, got: float, best: float) -> bool:
    return got <= best + 1e-6 if problem == 1 else got >= best - 1e-6


@pytest.mark.parametrize(("family", "problem", "reference", "seeds", "at_optimum"), [
    ("flow", 1, "bruteforce", 30, 0.95),
    ("flow", 2, "bruteforce", 30, 0.95),
    ("vision", 2, "bruteforce", 30, 0.95),
    ("vision", 1, "exact", 8, 0.5),
])
def test_greedy_plus_has_a_plan_wherever_the_optimum_does(family: str, problem: int, reference: str, seeds: int,
                                                          at_optimum: float) -> None:
    instances = _instances(family, problem, seeds)
    assert len(instances) >= 0.8 * seeds
    optimal = binding = 0
    for seed, system in instances:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            best = solve(system, problem, reference)
            plus = solve(system, problem, "greedy+")
            free = solve(dataclasses.replace(system, chains=tuple(
                dataclasses.replace(c, budget_ms=None) for c in system.chains)), problem, reference)
        # the generator budgets a plan that fits: the optimum within the budgets exists
        assert best.status != "infeasible", (family, seed)
        assert best.objective is not None and free.objective is not None
        binding += abs(best.objective - free.objective) > 1e-6
        assert plus.status != "infeasible", (family, problem, seed, plus.reason)
        assert check_plan(system, plus) == [], (family, problem, seed)
        assert plus.objective is not None and _worse_or_equal(problem, plus.objective, best.objective)
        optimal += abs(plus.objective - best.objective) <= 1e-6
    assert binding >= 1  # some budget changes the optimum
    assert optimal >= at_optimum * len(instances), (optimal, len(instances))


def test_greedy_plus_beats_main_s_repair_where_the_chain_needs_room() -> None:
    """Problem 2, one robot: the chain's two hops fit the robot beside a plain node, but are
    only fast enough without it (moving the plain node to the server: capacity 3), which the
    old repair, moving only the chain's own nodes, could not find."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        system = flow_instance(1, 2)
    assert system is not None
    brute, plus = solve(system, 2, "bruteforce"), solve(system, 2, "greedy+")
    assert brute.status == "optimal" and plus.status != "infeasible"
    assert plus.objective == pytest.approx(brute.objective)
    assert check_plan(system, plus) == []


@pytest.mark.parametrize("seed", range(25))
def test_a_server_sized_to_its_load_waits_nothing_in_the_model_and_the_checker(seed: int) -> None:
    """On a Problem 2 server sized to its load, beside a node that needs less (CFS meets it
    first), the detector gets exactly its planned CPU, so its utilisation is 1 (rounding puts
    it on either side): a message finds it just freed, no wait, the same in the model and the
    checker's copy."""
    rng = random.Random(seed)
    per_hz = round(rng.uniform(0.5, 9.0), 3)
    rate = rng.choice([2, 3, 5, 7, 10])
    data = {
        "computers": [{"name": "robot", "kind": "robot", "capacity": 50}, {"name": "server", "kind": "server"}],
        "links": [{"between": ["robot", "server"], "bandwidth_kBps": 100000}],
        "nodes": [
            {"name": "camera", "weight": 0.4, "residence": ["robot"], "topics": ["/cam"],
             "settings": [{"value": rate, "cpu": 1, "performance": 1, "frequency_hz": rate, "bandwidth_kBps": 10}]},
            {"name": "detector", "weight": 0.4, "input": "/cam", "residence": ["server"], "topics": ["/det"],
             "settings": [{"value": 1, "cpu": round(rng.uniform(0, 2), 3), "cpu_per_hz": per_hz, "performance": 1,
                           "bytes_per_msg": 100}]},
            {"name": "other", "weight": 0.2, "residence": ["server"], "topics": ["/o"],
             "settings": [{"value": 1, "cpu": round(rng.uniform(0.05, 0.9), 3), "performance": 1, "frequency_hz": 1,
                           "bandwidth_kBps": 1}]},
        ],
        "edges": [{"from": "camera", "to": "detector"}],
        "chains": [{"name": "vision", "topics": ["/cam", "/det"]}],
    }
    system = parse_system(data)
    plan = solve(system, 2, "exact")
    [hop] = plan.chains[0]["hops"]
    assert hop["utilisation"] == pytest.approx(1.0, abs=1e-9)
    assert hop["wait_ms"] == 0 and hop["wait_p95_ms"] == 0
    assert hop["service_ms"] == pytest.approx(1000 / rate, rel=1e-6)  # it runs at exactly its CPU: a period
    assert check_plan(system, plan) == []


def test_random_plan_fits_and_its_latency_is_within_the_budgets_it_made() -> None:
    """The generator's premise: the random plan it budgets keeps every budget."""
    for seed in range(10):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            system = flow_instance(seed, 1)
        if system is None:
            continue
        plan = random_plan(system, 1, random.Random(seed))
        assert plan is not None
        # a different random plan need not keep them; the one the generator drew did, so the
        # exact optimum within the budgets exists (checked by the test above); here only: the
        # rule predicts every budgeted chain of a random plan
        caps = capacities_of(system, Problem.PERFORMANCE, plan)
        for chain in system.chains:
            assert predict_chain(system, chain, plan.placement, plan.choice, caps).p95_ms is not None
