"""Fleets whose network binds (issue 22): the 1,180-node wifi fleet and large random
variants of it, planned by every heuristic without a recursion limit, each plan checked by
the independent checker (solver/check.py)."""

from __future__ import annotations

import random
import warnings
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.casestudy.instances import wifi_fleet_instance
from perfros_bag.solver import fixed_choices
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.greedy import solve_greedy
from perfros_bag.solver.local import solve_greedy_plus
from perfros_bag.system.plan import Plan, Status
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem, System


def system_of(data: dict[str, Any], name: str = "wifi-fleet.yaml") -> System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(data, name)


def test_wifi_fleet_shape() -> None:
    data = wifi_fleet_instance()
    system = system_of(data)
    assert len(system.nodes) == 1180 and len(system.computers) == 100
    assert sorted(m.name for m in system.media) == sorted(f"ap{j}" for j in range(1, 11))
    assert all(m.bandwidth_kBps == 9000.0 for m in system.media)
    servers = {c.name for c in system.computers if c.kind == "server"}
    for r in (1, 45, 90):
        assert system.allowed(f"camera{r}") == (f"robot{r}",)
        assert set(system.allowed(f"detector{r}")) == {f"robot{r}", *servers}
        link = next(lk for lk in system.links if f"robot{r}" in lk.between)
        assert link.medium == f"ap{(r - 1) // 9 + 1}"
    assert abs(sum(n.weight for n in system.nodes) - 1) < 1e-9
    assert wifi_fleet_instance() == data  # seeded


def binding_fleet(seed: int, robots_per_ap: int, streams: float, cut: float) -> dict[str, Any]:
    """A wifi fleet of >= 1,000 nodes whose access points carry ``streams`` camera streams
    and whose robot links are cut at random to between ``cut`` and 4 streams: both the links
    and the media bind."""
    data = wifi_fleet_instance(90 if seed % 2 else 81, 10 if seed % 2 else 9, robots_per_ap=robots_per_ap,
                               ap_kBps=2300.0 * streams, seed=seed)
    rng = random.Random(seed)
    for link in data["links"]:
        if link.get("medium") and rng.random() < 0.3:
            link["bandwidth_kBps"] = round(2300.0 * rng.uniform(cut, 4.0), 1)
    return data


def assert_checked(system: System, plan: Plan) -> None:
    """A feasible plan passes the checker; an infeasible one says why, in one line."""
    if plan.status == Status.INFEASIBLE:
        assert plan.reason and "\n" not in plan.reason
    else:
        assert check_plan(system, plan) == [], plan.reason


@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(seed=st.integers(0, 10_000), robots_per_ap=st.integers(3, 12), streams=st.floats(0.5, 4.0),
       cut=st.floats(0.3, 1.5), problem=st.sampled_from([Problem.PERFORMANCE, Problem.SERVER_CAPACITY]))
def test_heuristics_plan_large_binding_fleets(seed: int, robots_per_ap: int, streams: float, cut: float,
                                              problem: Problem) -> None:
    """greedy and greedy+ (a small time budget) on >= 1,000 nodes with binding links and media:
    no RecursionError whatever the size, every plan passes check_plan."""
    system = system_of(binding_fleet(seed, robots_per_ap, streams, cut))
    assert len(system.nodes) >= 1000
    choices = fixed_choices(system, problem)
    assert_checked(system, solve_greedy(system, problem, choices))
    assert_checked(system, solve_greedy_plus(system, problem, choices, time_budget=1.0))
