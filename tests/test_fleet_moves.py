"""greedy+'s relocation moves at fleet scale (solver/fleetmoves.py) and the exact method's
answer on a driven fleet the decomposition declines (issue 32), on fleets small enough for
the brute force, the decomposition's proven bound and the independent checker."""

from __future__ import annotations

import random
import time

import pytest

from perfros_bag.casestudy.instances import wifi_fleet_instance
from perfros_bag.solver import decompose as decompose_mod
from perfros_bag.solver import dispatch, flow, local, solve
from perfros_bag.solver.candidates import fixed_choices
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.decompose import decomposable, flow_decline, solve_decomposed
from perfros_bag.solver.fleetmoves import fleet_moves, refit
from perfros_bag.solver.greedy import run_greedy
from perfros_bag.solver.instance import trivial_bound
from perfros_bag.solver.state import State
from perfros_bag.system.plan import Method, Status
from perfros_bag.system.types import Problem, System
from tests.test_decompose_flow import driven_fleet, system_of


def greedy_at_lowest_rates(system: System) -> State:
    """The paper's greedy on every camera at its lowest rate (greedy+'s fleet start), or
    greedy+'s feasible start where the greedy finds no plan."""
    choices = fixed_choices(system, Problem.PERFORMANCE)
    lowest = flow._restricted(system, choices, {p: o[0] for p, o in flow._class_options(system, choices).items()})
    assert lowest is not None
    state, why = run_greedy(system, Problem.PERFORMANCE, lowest)
    if why is None:
        return state
    found = local.feasible_start(system, Problem.PERFORMANCE, lowest)  # what greedy+ starts from then
    assert found is not None, why
    return found


def consistent(system: System, plan: object) -> bool:
    """Every driven node planned at the rate its publisher gives it."""
    nodes = plan.nodes  # type: ignore[attr-defined]
    return all(nodes[n.name].input_hz == pytest.approx(nodes[system.flow_parent[n.name]].value)
               for n in system.nodes if n.input is not None)


SMALL = range(10)


@pytest.mark.parametrize("seed", SMALL)
def test_relocations_against_brute_force(seed: int) -> None:
    """On the greedy's state: the moves keep a plan the checker passes, each applied move
    raises Σ w·P, and the result is at most the brute force's optimum."""
    system = system_of(driven_fleet(seed, robots=2))
    state = greedy_at_lowest_rates(system)
    before = state.value()
    applied = fleet_moves(state, time.monotonic() + 60)
    plan = state.plan(Method.GREEDY_PLUS)
    best = solve(system, 1, "bruteforce")
    assert check_plan(system, plan) == [] and consistent(system, plan)
    assert plan.objective is not None and best.objective is not None
    assert plan.objective <= best.objective + 1e-9
    assert plan.objective >= before - 1e-12
    if applied:
        assert plan.objective > before + 1e-9


@pytest.mark.parametrize("seed", range(4))
def test_relocations_on_whole_stacks_against_the_decomposition(seed: int) -> None:
    """Three robots with whole stacks (the groups that gain by going home or out): moves are
    applied, each raising Σ w·P, the checker passes and the result is at most the
    decomposition's proven bound."""
    system = system_of(wifi_fleet_instance(3, 1, robots_per_ap=3, trackers=2, ap_kBps=2350.0, seed=seed,
                                           driven=True))
    state = greedy_at_lowest_rates(system)
    before = state.value()
    applied = fleet_moves(state, time.monotonic() + 60)
    plan = state.plan(Method.GREEDY_PLUS)
    assert applied > 0 and plan.objective is not None and plan.objective > before + 1e-9
    assert check_plan(system, plan) == [] and consistent(system, plan)
    proven = solve_decomposed(system, Problem.PERFORMANCE, fixed_choices(system, Problem.PERFORMANCE))
    assert proven is not None and proven.bound is not None
    assert plan.objective <= proven.bound + 1e-9


@pytest.mark.parametrize("seed", (0, 1))
def test_greedy_plus_fleet_path_against_the_decomposition(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Six robots with whole stacks, greedy+ forced onto its fleet path (relocations by
    fleetmoves, no passes of greedy runs): the checker passes, each detector at its camera's
    rate, at least the greedy's plan at the rates it starts from and at most the
    decomposition's proven bound."""
    data = wifi_fleet_instance(6, 1, robots_per_ap=3, trackers=2, ap_kBps=2350.0, seed=seed, driven=True)
    system = system_of(data)
    monkeypatch.setattr(local, "MOVES_LIMIT", 0)
    monkeypatch.setattr(flow, "PLUS_PASS_MAX_S", -1.0)
    calls: list[int] = []
    moves = local.fleet_moves
    monkeypatch.setattr(local, "fleet_moves", lambda *a: calls.append(moves(*a)) or calls[-1])
    plan = solve(system, 1, "greedy+")
    assert calls and calls[0] > 0  # the relocation moves ran and applied some
    assert plan.status != Status.INFEASIBLE and check_plan(system, plan) == [] and consistent(system, plan)
    start = greedy_at_lowest_rates(system).value()
    choices = fixed_choices(system, Problem.PERFORMANCE)
    proven = solve_decomposed(system, Problem.PERFORMANCE, choices)
    assert proven is not None and proven.bound is not None and plan.objective is not None
    assert start - 1e-9 <= plan.objective <= proven.bound + 1e-9


@pytest.mark.parametrize("seed", range(20))
def test_refit_fits_and_follows_algorithm_2(seed: int) -> None:
    """refit from random levels: the levels fit the capacity (summed here), None exactly
    when the lowest levels do not fit; from the lowest levels, the same levels as greedy+'s
    own Algorithm 2 rule on one computer (``local._marginal``)."""
    system = system_of(wifi_fleet_instance(3, 1, robots_per_ap=3, trackers=2, seed=seed, driven=True))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    state = State(system, Problem.PERFORMANCE, choices)
    rng = random.Random(seed)
    nodes = rng.sample(state.nodes, 6)
    state.cap["server1"] = cap = float(rng.randint(10, 400))
    start = {n: rng.randrange(len(state.ladder[n])) for n in nodes}
    got = refit(state, "server1", start)
    lowest = sum(state.ladder[n][0].cpu for n in nodes)
    if lowest > cap + 1e-9:
        assert got is None
        return
    assert got is not None and set(got) == set(nodes)
    assert sum(state.ladder[n][k].cpu for n, k in got.items()) <= cap + 1e-6
    ordered = sorted(nodes, key=state.order.__getitem__)
    assert refit(state, "server1", dict.fromkeys(nodes, 0)) == local._marginal(state, cap, ordered)[1]


# ---- a driven fleet the decomposition declines ------------------------------------------
def test_flow_decline_agrees_with_the_decomposition(monkeypatch: pytest.MonkeyPatch) -> None:
    """flow_decline (from the system alone) names a reason exactly where the prepared
    decomposition does not qualify: none on plain driven fleets, the flow across robots,
    the views limit."""
    for seed in range(4):
        system = system_of(driven_fleet(seed))
        choices = fixed_choices(system, Problem.PERFORMANCE)
        assert flow_decline(system, choices) is None and decomposable(system, Problem.PERFORMANCE, choices)
        across = system_of(driven_fleet(seed, detectors_on_servers_only=True))
        across_choices = fixed_choices(across, Problem.PERFORMANCE)
        why = flow_decline(across, across_choices)
        assert why is not None and "spans more than one robot" in why
        assert not decomposable(across, Problem.PERFORMANCE, across_choices)
    monkeypatch.setattr(decompose_mod, "MAX_VIEWS", 2)  # each robot's camera has 3 rates
    system = system_of(driven_fleet(0))
    choices = fixed_choices(system, Problem.PERFORMANCE)
    why = flow_decline(system, choices)
    assert why is not None and "more than 2" in why and not decomposable(system, Problem.PERFORMANCE, choices)


@pytest.mark.parametrize("seed", (0, 2))
def test_declined_fleet_too_big_for_the_milp_gets_greedy_plus_and_the_trivial_bound(
        seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Above the whole MILP's size limit a declined fleet gets greedy+'s plan, the trivial
    bound (Σ w·max P, a proof) and a note saying both; the plan is at most the brute
    force's optimum, the bound at least it."""
    system = system_of(driven_fleet(seed, detectors_on_servers_only=True))
    monkeypatch.setattr(dispatch, "DECOMPOSE_COLUMNS", 0)
    monkeypatch.setattr(dispatch, "DECLINED_MILP_COLUMNS", 0)
    plan = solve(system, 1, "exact", time_limit=30)
    best = solve(system, 1, "bruteforce")
    assert plan.status == Status.FEASIBLE and check_plan(system, plan) == [] and consistent(system, plan)
    assert plan.objective is not None and best.objective is not None and plan.bound is not None
    assert plan.objective <= best.objective + 1e-9 <= plan.bound + 2e-9
    assert plan.bound == pytest.approx(trivial_bound(system, fixed_choices(system, Problem.PERFORMANCE)))
    assert plan.reason is not None and "declines" in plan.reason and "greedy+" in plan.reason
    assert "trivial" in plan.reason and "\n" not in plan.reason


def test_declined_fleet_small_enough_gets_the_whole_milp_and_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """Below that limit: the whole MILP's optimum (the brute force's), and the note."""
    system = system_of(driven_fleet(1, detectors_on_servers_only=True))
    monkeypatch.setattr(dispatch, "DECOMPOSE_COLUMNS", 0)
    plan = solve(system, 1, "exact", time_limit=30)
    best = solve(system, 1, "bruteforce")
    assert plan.status == Status.OPTIMAL and check_plan(system, plan) == []
    assert plan.objective == pytest.approx(best.objective, rel=1e-7)
    assert plan.reason is not None and "declines" in plan.reason and "whole MILP" in plan.reason
