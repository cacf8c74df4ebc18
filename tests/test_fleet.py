"""Fleet instances and the decomposition solver (solver/decompose.py) against the exact
MILP on the whole model and the independent checker."""

from __future__ import annotations

import copy
import functools
import random
import warnings
from typing import Any

import pytest

from perfros_bag.casestudy.instances import fleet_instance, random_instance, wifi_fleet_instance
from perfros_bag.solver import (
    DECOMPOSE_COLUMNS,
    exact_columns,
    fixed_choices,
    solve,
)
from perfros_bag.solver import exact as exact_mod
from perfros_bag.solver import instance as instance_mod
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.decompose import decomposable, solve_decomposed
from perfros_bag.solver.exact import solve_exact
from perfros_bag.solver.instance import trivial_bound, within_trivial_bound
from perfros_bag.system.plan import Method, Plan, Status
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem, System


def system_of(data: dict[str, Any], name: str = "fleet.yaml") -> System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(data, name)


def test_fleet_instance_shape() -> None:
    data = fleet_instance(200, 20, seed=3)
    system = system_of(data)
    assert len(system.nodes) == 200 and len(system.computers) == 20
    servers = [c.name for c in system.computers if c.kind == "server"]
    robots = [c.name for c in system.computers if c.kind == "robot"]
    assert len(servers) == 2 and len(robots) == 18
    assert abs(sum(n.weight for n in system.nodes) - 1) < 1e-9
    # one stack per robot: its nodes run on that robot or a server, youbot_core on the robot
    for r, robot in enumerate(robots, start=1):
        assert system.allowed(f"youbot_core{r}") == (robot,)
        assert set(system.allowed(f"amcl{r}")) == {robot, *servers}
    trackers = [n for n in system.nodes if n.name.startswith("tracker")]
    assert len(trackers) == 200 - 1 - 6 * 18 and all(set(system.allowed(n.name)) == set(servers) for n in trackers)
    assert {lk.medium for lk in system.links if robots[0] in lk.between} == {"wifi"}
    assert fleet_instance(200, 20, seed=3) == data  # seeded
    anywhere = system_of(fleet_instance(60, 6, offload_only=False))
    assert len(anywhere.allowed("amcl1")) == 6


def assert_bounds(system: System, plan: Plan, optimum: float) -> None:
    """bound >= the exact optimum >= the plan's objective, and the plan passes the checker."""
    assert check_plan(system, plan) == [], plan
    assert plan.objective is not None and plan.bound is not None
    assert plan.bound >= optimum - 1e-7 * optimum
    assert optimum >= plan.objective - 1e-7 * optimum
    assert plan.bound <= trivial_bound(system, fixed_choices(system, Problem.PERFORMANCE)) + 1e-9
    if plan.status == Status.OPTIMAL:
        assert plan.objective == pytest.approx(optimum, rel=1e-6)
        assert plan.bound == plan.objective


CASES = ([(f"fleet-{seed}-{'curves' if c else 'settings'}", fleet_instance(40, 5, seed=seed, continuous=c))
          for seed in (1, 2) for c in (False, True)]
         + [("fleet-anywhere", fleet_instance(27, 4, seed=3, offload_only=False, continuous=False))]
         + [(f"random-{seed}", random_instance(random.Random(seed))) for seed in (1, 2, 3, 5)])


@pytest.mark.parametrize(("name", "data"), CASES, ids=[c[0] for c in CASES])
def test_decomposition_against_the_exact_milp(name: str, data: dict[str, Any]) -> None:
    plan = decomposition_against_the_milp(system_of(data, name))
    # with no time limit, the reduced-cost enumeration closes these small instances
    assert plan.status == Status.OPTIMAL


def decomposition_against_the_milp(system: System) -> Plan:
    """The decomposition's plan, checked against the exact MILP's optimum (assert_bounds)."""
    choices = fixed_choices(system, Problem.PERFORMANCE)
    assert decomposable(system, Problem.PERFORMANCE, choices)
    exact = solve_exact(system, Problem.PERFORMANCE, choices, time_limit=60)
    assert exact.status == Status.OPTIMAL and exact.objective is not None
    plan = solve_decomposed(system, Problem.PERFORMANCE, choices)
    assert plan is not None and plan.method == Method.EXACT
    assert_bounds(system, plan, exact.objective)
    return plan


def test_progress_reports_incumbent_and_bound() -> None:
    system = system_of(fleet_instance(40, 5, seed=1))
    seen: list[tuple[float | None, float, float]] = []
    plan = solve_decomposed(system, Problem.PERFORMANCE, fixed_choices(system, Problem.PERFORMANCE),
                            progress=lambda inc, bound, t: seen.append((inc, bound, t)))
    assert plan is not None and seen
    bounds = [b for _, b, _ in seen]
    assert all(b >= plan.objective - 1e-9 for b in bounds)  # type: ignore[operator]
    assert seen[-1][0] == pytest.approx(plan.objective) and seen[-1][1] == pytest.approx(plan.bound)


def test_not_decomposable_when_traffic_between_blocks_could_fill_the_network() -> None:
    """A case-study instance whose robot nodes may run on any computer has no private
    robot: every edge is between blocks, its traffic cannot be priced in a block and could
    fill the tight wifi, so the instance is the MILP's."""
    system = system_of(random_instance(random.Random(4), tight_network=True))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    assert not decomposable(system, Problem.PERFORMANCE, choices)
    assert solve_decomposed(system, Problem.PERFORMANCE, choices) is None
    assert not decomposable(system, Problem.SERVER_CAPACITY, fixed_choices(system, Problem.SERVER_CAPACITY))


def test_solve_exact_uses_the_decomposition_on_a_fleet() -> None:
    system = system_of(fleet_instance(200, 20, seed=0))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    assert exact_columns(system, choices) > DECOMPOSE_COLUMNS
    seen: list[float] = []
    plan = solve(system, 1, "exact", time_limit=60, progress=lambda inc, bound, t: seen.append(bound))
    assert seen  # the decomposition ran (the MILP reports no progress)
    assert plan.method == Method.EXACT and plan.status != Status.INFEASIBLE
    assert check_plan(system, plan) == []
    assert plan.bound is not None and plan.objective is not None
    assert plan.objective - 1e-9 <= plan.bound <= trivial_bound(system, choices) + 1e-9
    # the LP relaxation of the whole model is a bound too; the Lagrangian one is at least as tight
    inst = instance_mod.prepare_instance(system, Problem.PERFORMANCE, choices)
    assert not isinstance(inst, str)
    lp = exact_mod._build(inst).milp.solve(True, time_limit=None, mip_gap=0.0, relax=True)
    assert plan.bound <= lp.getInfo().objective_function_value + 1e-6


def test_a_bound_is_never_looser_than_the_trivial_one() -> None:
    system = system_of(fleet_instance(40, 5, seed=1))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    plan = solve_exact(system, Problem.PERFORMANCE, choices)
    plan.bound, plan.status = 29250.5, Status.FEASIBLE  # what HiGHS reported before its root LP
    fixed = within_trivial_bound(system, Problem.PERFORMANCE, choices, plan)
    assert fixed.bound == pytest.approx(trivial_bound(system, choices))
    plan2 = solve_exact(system, Problem.SERVER_CAPACITY, fixed_choices(system, Problem.SERVER_CAPACITY))
    plan2.bound = -5.0
    assert within_trivial_bound(system, Problem.SERVER_CAPACITY, {}, plan2).bound == 0.0


def binding_network(data: dict[str, Any]) -> dict[str, Any]:
    """The fleet with its wifi cut to half of what its links could ever carry: the network
    can bind (the decomposition carries it as coupling rows, issue 22)."""
    system = system_of(data)
    inst = instance_mod.prepare_instance(system, Problem.PERFORMANCE, fixed_choices(system, Problem.PERFORMANCE))
    assert not isinstance(inst, str)
    potential, _ = instance_mod.load_bounds(inst, forced=False)
    out = copy.deepcopy(data)
    out["media"][0]["bandwidth_kBps"] = system.medium_load(potential, out["media"][0]["name"]) / 2
    assert instance_mod.active_links(instance_mod.prepare_instance(system_of(out), Problem.PERFORMANCE,  # type: ignore[arg-type]
                                                             fixed_choices(system, Problem.PERFORMANCE)))
    return out


FLEET = fleet_instance(200, 20, seed=0)
LIMITED = [("decomposed", FLEET, 1), ("binding", binding_network(FLEET), 1), ("problem2", FLEET, 2),
           ("small", fleet_instance(40, 5, seed=1), 1)]


@functools.cache
def other_objectives(name: str, problem: int) -> tuple[float, ...]:
    """The objectives of other plans of the instance (exact with a longer limit, greedy)
    that pass the checker: no proven bound may be on the wrong side of one."""
    data = next(d for n, d, _ in LIMITED if n == name)
    system = system_of(data, name)
    plans = [solve(system, problem, "exact", time_limit=3), solve(system, problem, "greedy")]
    found = tuple(p.objective for p in plans if p.objective is not None and check_plan(system, p) == [])
    assert found
    return found


@pytest.mark.parametrize("limit", [1e-4, 0.05, 0.4])
@pytest.mark.parametrize(("name", "data", "problem"), LIMITED, ids=[c[0] for c in LIMITED])
def test_a_time_limited_plan_passes_the_checker_and_states_a_proven_bound(
        name: str, data: dict[str, Any], problem: int, limit: float) -> None:
    """Whatever path the time limit cuts short (the set-up, the bound, the MILP), the plan
    is feasible by the independent checker and its bound obeys the rule: between the
    objective and the trivial bound (Problem 1: Σ w·max P; Problem 2: 0), and on the right
    side of every plan found without a limit (or by greedy+): a bound is proven, not guessed."""
    system = system_of(data, name)
    the_problem = Problem(problem)
    choices = fixed_choices(system, the_problem)
    plan = solve(system, problem, "exact", time_limit=limit)
    assert plan.status in (Status.FEASIBLE, Status.OPTIMAL), plan.reason
    assert check_plan(system, plan) == []
    assert plan.objective is not None and plan.bound is not None
    found = other_objectives(name, problem)
    tol = 1e-7 * max(1.0, abs(plan.objective))
    if the_problem == Problem.PERFORMANCE:
        assert plan.objective - tol <= plan.bound <= trivial_bound(system, choices) + tol
        assert all(plan.bound >= value - tol for value in found)
    else:
        assert 0.0 <= plan.bound <= plan.objective + tol
        assert all(plan.bound <= value + tol for value in found)
    if plan.status == Status.OPTIMAL:
        assert plan.bound == pytest.approx(plan.objective, rel=1e-6)
    else:
        assert plan.bound != pytest.approx(plan.objective, rel=1e-9, abs=0.0)


def roomy_server(data: dict[str, Any]) -> dict[str, Any]:
    """The fleet with server capacity to spare and robots too small for a detector at its
    best beside their stack: the access points, not the server, limit offloading."""
    for c in data["computers"]:
        c["capacity"] = c["capacity"] * 4 if c["kind"] == "server" else min(c["capacity"], 90)
    return data


WIFI = [(f"wifi-{seed}-{'curves' if c else 'settings'}-{per_ap}",
         roomy_server(wifi_fleet_instance(6, 1, robots_per_ap=per_ap, trackers=2, ap_kBps=2350.0, seed=seed,
                                          continuous=c)))
        for seed, c, per_ap in ((1, False, 3), (2, False, 2), (3, True, 3))]


@pytest.mark.parametrize(("name", "data"), WIFI, ids=[c[0] for c in WIFI])
def test_binding_networks_decompose_with_a_proven_bound(name: str, data: dict[str, Any]) -> None:
    """Issue 22: links and media that can overflow are coupling rows of the decomposition.
    On small fleets whose access points bind (one detector per access point may be
    offloaded), the decomposition's bound is at least the exact MILP's optimum, which is at
    least its plan's objective, and the plan passes the checker."""
    system = system_of(data, name)
    choices = fixed_choices(system, Problem.PERFORMANCE)
    inst = instance_mod.prepare_instance(system, Problem.PERFORMANCE, choices)
    assert not isinstance(inst, str) and instance_mod.active_links(inst)  # the network can bind
    plan = decomposition_against_the_milp(system)
    assert plan.objective is not None
    # the network binds at the optimum: more offloading would pay without it
    unbound = copy.deepcopy(data)
    for m in unbound["media"]:
        m["bandwidth_kBps"] = 1e9
    for link in unbound["links"]:
        link["bandwidth_kBps"] = 1e9
    free = system_of(unbound, name)
    unbound_best = solve_exact(free, Problem.PERFORMANCE, fixed_choices(free, Problem.PERFORMANCE)).objective
    assert unbound_best is not None and unbound_best > (plan.bound or 0.0) + 1e-6


def test_a_link_too_thin_for_what_must_cross_it_is_named() -> None:
    """Robot 1's link carries less than its stack must exchange with the servers wherever its
    nodes run (no single edge is forced across it, so the cheap checks pass): the
    decomposition proves there is no plan and names the link; the exact MILP agrees."""
    data = roomy_server(wifi_fleet_instance(6, 1, robots_per_ap=3, trackers=2, ap_kBps=2350.0, seed=1,
                                            continuous=False))
    for link in data["links"]:
        if "robot1" in link["between"]:
            link["bandwidth_kBps"] = 0.05
    system = system_of(data, "thin.yaml")
    choices = fixed_choices(system, Problem.PERFORMANCE)
    plan = solve_decomposed(system, Problem.PERFORMANCE, choices)
    assert plan is not None and plan.status == Status.INFEASIBLE
    assert plan.reason is not None and plan.reason.startswith("link robot1-server1 cannot hold")
    assert not decomposable(system, Problem.PERFORMANCE, choices)
    exact = solve_exact(system, Problem.PERFORMANCE, choices, time_limit=60)
    assert exact.status == Status.INFEASIBLE and "infeasibility was not proven" not in (exact.reason or "")
