"""The exact (MILP) solver against independent computations: the brute force on tiny
instances, the independent checker, the greedy solvers' bounds and hand-computed optima."""

from __future__ import annotations

import random
import warnings
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.casestudy.instances import random_tiny, table2_instance
from perfros_bag.solver import fixed_choices
from perfros_bag.solver.bruteforce import solve_bruteforce
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.exact import solve_exact
from perfros_bag.solver.greedy import solve_greedy
from perfros_bag.solver.local import solve_greedy_plus
from perfros_bag.solver.starts import start_of
from perfros_bag.system.plan import Assignment, Plan
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import System


def system_of(data: dict[str, Any]) -> System:
    for node in data["nodes"]:  # several settings need a parameter to set
        if len(node.get("settings", [])) > 1:
            node.setdefault("parameter", {"name": "p"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # weight normalisation warnings
        return parse_system(data, "test.yaml")


def exact(system: System, problem: int, **kw: Any) -> Plan:
    plan = solve_exact(system, problem, fixed_choices(system, problem), **kw)
    if plan.status != "infeasible":
        assert check_plan(system, plan) == [], plan
        if problem == 1:
            assert plan.bound is not None and plan.bound >= plan.objective - 1e-9
        else:
            assert plan.bound is not None and plan.bound <= plan.objective + 1e-9
    return plan


def setting(cpu: float, perf: float, bw: float = 0.0) -> dict[str, float]:
    return {"cpu": cpu, "performance": perf, "bandwidth_kBps": bw}


# ---------------------------------------------------------------------------------------------
# exact == brute force on random tiny instances (trees, and networks with a cycle)


def with_cycle(data: dict[str, Any]) -> dict[str, Any]:
    """Close a 3-computer chain into a triangle: routes then tie-break and no link is a cut,
    so the solver must use its pair form."""
    names = [c["name"] for c in data["computers"]]
    links = data.get("links", [])
    if len(names) == 3 and len(links) == 2:
        joined = {frozenset(link["between"]) for link in links}
        for a, b in ((names[0], names[1]), (names[1], names[2]), (names[0], names[2])):
            if frozenset((a, b)) not in joined:
                links.append({"between": [a, b], "bandwidth_kBps": 3, **({"medium": "air"} if "media" in data else {})})
                break
    return data


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), cycle=st.booleans())
def test_exact_matches_bruteforce(seed: int, cycle: bool) -> None:
    data = random_tiny(random.Random(seed))
    if cycle:
        data = with_cycle(data)
    system = system_of(data)
    for problem in (1, 2):
        choices = fixed_choices(system, problem)
        ours = exact(system, problem)
        ref = solve_bruteforce(system, problem, choices)
        assert (ours.status == "infeasible") == (ref.status == "infeasible"), (ours.reason, ref.reason)
        if ref.status == "infeasible":
            assert ours.reason
            continue
        assert ours.status == "optimal"
        assert ours.objective == pytest.approx(ref.objective, abs=1e-6)


def test_pair_form_is_used_and_exact_on_a_cycle() -> None:
    """A triangle whose direct link a-c is too thin: traffic a->c must not take it, and the
    route table says it would, so the node moves to b (found by brute force too)."""
    data = {
        "computers": [{"name": n, "kind": "server", "capacity": 10} for n in ("a", "b", "c")],
        "links": [{"between": ["a", "b"], "bandwidth_kBps": 10}, {"between": ["b", "c"], "bandwidth_kBps": 10},
                  {"between": ["a", "c"], "bandwidth_kBps": 1}],
        "nodes": [
            {"name": "src", "weight": 0.5, "residence": ["a"], "settings": [setting(1, 100, 5)]},
            {"name": "dst", "weight": 0.5, "residence": ["b", "c"], "settings": [setting(1, 50), setting(9, 100)]},
            {"name": "hog", "weight": 0.1, "residence": ["b"], "settings": [setting(5, 100)]},
        ],
        "edges": [{"from": "src", "to": "dst"}],
    }
    system = system_of(data)
    plan = exact(system, 1)
    ref = solve_bruteforce(system, 1, fixed_choices(system, 1))
    assert plan.objective == pytest.approx(ref.objective)
    # dst at 9 CPU only fits on c (b holds hog), but a->c carries 5 > 1: dst sits on b at 1 CPU
    assert plan.nodes["dst"].computer == "b" and plan.nodes["dst"].cpu == 1


# ---------------------------------------------------------------------------------------------
# hand-checked cases: each constraint binds


def link_case(link_bw: float) -> System:
    return system_of({
        "computers": [{"name": "r", "kind": "robot", "capacity": 15}, {"name": "s", "kind": "server", "capacity": 100}],
        "links": [{"between": ["r", "s"], "bandwidth_kBps": link_bw}],
        "nodes": [
            {"name": "sensor", "weight": 0.5, "residence": ["r"], "settings": [setting(5, 100, 4)]},
            {"name": "proc", "weight": 0.5, "settings": [setting(8, 50), setting(20, 100)]},
        ],
        "edges": [{"from": "sensor", "to": "proc"}],
    })


def test_binding_link() -> None:
    # 4 kB/s cannot cross a 3 kB/s link: proc stays on the robot, where only 8 CPU fit
    plan = exact(link_case(3), 1)
    assert plan.status == "optimal"
    assert plan.objective == pytest.approx(0.5 * 100 + 0.5 * 50)
    assert plan.nodes["proc"].computer == "r" and plan.links[0].load_kBps == 0
    # a 5 kB/s link lets proc move to the server at its best setting
    plan = exact(link_case(5), 1)
    assert plan.objective == pytest.approx(100)
    assert plan.nodes["proc"].computer == "s" and plan.links[0].load_kBps == pytest.approx(4)


def test_bandwidth_follows_the_publishers_setting() -> None:
    def case(link_bw: float) -> System:
        return system_of({
            "computers": [{"name": "r", "kind": "robot", "capacity": 10},
                          {"name": "s", "kind": "server", "capacity": 10}],
            "links": [{"between": ["r", "s"], "bandwidth_kBps": link_bw}],
            "nodes": [
                {"name": "cam", "weight": 0.5, "residence": ["r"], "settings": [setting(1, 40, 2), setting(2, 100, 6)]},
                {"name": "det", "weight": 0.5, "residence": ["s"], "settings": [setting(1, 100)]},
            ],
            "edges": [{"from": "cam", "to": "det"}],
        })

    plan = exact(case(5), 1)
    assert plan.nodes["cam"].cpu == 1 and plan.objective == pytest.approx(70)
    assert plan.links[0].load_kBps == pytest.approx(2)
    plan = exact(case(6), 1)
    assert plan.nodes["cam"].cpu == 2 and plan.objective == pytest.approx(100)


def medium_case(medium_bw: float) -> System:
    robot_nodes = []
    for i in (1, 2):
        robot_nodes += [
            {"name": f"a{i}", "weight": 0.1, "residence": [f"r{i}"], "settings": [setting(1, 100, 4)]},
            {"name": f"b{i}", "weight": 0.4, "residence": [f"r{i}", "s"],
             "settings": [setting(1, 10), setting(30, 100)]},
        ]
    return system_of({
        "computers": [{"name": "r1", "kind": "robot", "capacity": 20}, {"name": "r2", "kind": "robot", "capacity": 20},
                      {"name": "s", "kind": "server", "capacity": 100}],
        "links": [{"between": ["r1", "s"], "bandwidth_kBps": 10, "medium": "air"},
                  {"between": ["r2", "s"], "bandwidth_kBps": 10, "medium": "air"}],
        "media": [{"name": "air", "bandwidth_kBps": medium_bw}],
        "nodes": robot_nodes,
        "edges": [{"from": "a1", "to": "b1"}, {"from": "a2", "to": "b2"}],
    })


def test_binding_shared_medium() -> None:
    # each link could carry 4 kB/s, the shared channel only 6: one b moves to the server
    plan = exact(medium_case(6), 1)
    assert plan.objective == pytest.approx(0.1 * 100 * 2 + 0.4 * 100 + 0.4 * 10)
    on_server = [n for n in ("b1", "b2") if plan.nodes[n].computer == "s"]
    assert len(on_server) == 1
    assert sum(link.load_kBps for link in plan.links) == pytest.approx(4)
    plan = exact(medium_case(8), 1)
    assert plan.objective == pytest.approx(100)
    assert sum(link.load_kBps for link in plan.links) == pytest.approx(8)


def test_binding_residence() -> None:
    def case(residence: list[str] | None) -> System:
        node: dict[str, Any] = {"name": "x", "weight": 1, "settings": [setting(5, 50), setting(50, 100)]}
        if residence:
            node["residence"] = residence
        return system_of({"computers": [{"name": "big", "kind": "server", "capacity": 100},
                                        {"name": "small", "kind": "robot", "capacity": 10}],
                          "nodes": [node]})

    plan = exact(case(["small"]), 1)
    assert plan.nodes["x"].computer == "small" and plan.objective == pytest.approx(50)
    plan = exact(case(None), 1)
    assert plan.nodes["x"].computer == "big" and plan.objective == pytest.approx(100)


def test_binding_coresidence() -> None:
    def case(together: bool) -> System:
        p: dict[str, Any] = {"name": "p", "weight": 0.5, "settings": [setting(10, 50), setting(20, 100)]}
        q: dict[str, Any] = {"name": "q", "weight": 0.5, "settings": [setting(10, 50), setting(20, 100)]}
        if together:
            p["coresidence"] = ["q"]
        return system_of({"computers": [{"name": "a", "kind": "server", "capacity": 30},
                                        {"name": "b", "kind": "server", "capacity": 30}], "nodes": [p, q]})

    plan = exact(case(True), 1)
    assert plan.nodes["p"].computer == plan.nodes["q"].computer
    assert plan.objective == pytest.approx(75)
    plan = exact(case(False), 1)
    assert plan.nodes["p"].computer != plan.nodes["q"].computer
    assert plan.objective == pytest.approx(100)


def test_problem2_sizes_servers_and_respects_max_capacity() -> None:
    def case(max_cap: float | None) -> System:
        servers = [{"name": f"s{i}", "kind": "server", **({"max_capacity": max_cap} if max_cap else {})}
                   for i in (1, 2)]
        return system_of({
            "computers": [{"name": "r", "kind": "robot", "capacity": 20}, *servers],
            "nodes": [{"name": f"n{i}", "weight": 1, "settings": [setting(c, 100)]}
                      for i, c in enumerate((15, 15, 30))],
        })

    plan = exact(case(None), 2)
    # the robot takes one 15; the servers carry 15 + 30
    assert plan.status == "optimal" and plan.objective == pytest.approx(45)
    plan = exact(case(25), 2)  # the 30 fits on no server any more
    assert plan.status == "infeasible"
    assert plan.reason == "n2 needs 30 CPU at its minimum setting but the largest computer allowed for it, s1, has 25"
    plan = exact(case(30), 2)
    assert plan.objective == pytest.approx(45)
    assert max(c.capacity or 0 for name, c in plan.computers.items() if name != "r") <= 30


# ---------------------------------------------------------------------------------------------
# infeasible instances: a reason naming the constraint


def test_infeasible_residence_names_node_and_computer() -> None:
    data = table2_instance(1, continuous=False)
    data["computers"][0]["capacity"] = 10  # robot1
    plan = exact(system_of(data), 1)
    assert plan.status == "infeasible" and plan.objective is None
    assert plan.reason == "youbot_core1 needs 16 CPU on robot1 (residence) but robot1 has 10"


def test_infeasible_coresidence_and_packing() -> None:
    nodes = [{"name": f"n{i}", "weight": 1, "settings": [setting(8, 1)]} for i in range(3)]
    comps = [{"name": "a", "kind": "server", "capacity": 12}, {"name": "b", "kind": "server", "capacity": 12}]
    # 24 CPU on 24 capacity, but three 8s do not pack into two 12s: the elastic diagnosis
    plan = exact(system_of({"computers": comps, "nodes": nodes}), 1)
    assert plan.status == "infeasible"
    assert plan.reason is not None and plan.reason.startswith("CPU:") and "would need 16 CPU but has 12" in plan.reason
    nodes[0]["coresidence"] = ["n1"]
    plan = exact(system_of({"computers": comps, "nodes": nodes}), 1)
    assert plan.reason == ("coresidence: nodes n0, n1 need 16 CPU together at their minimum settings "
                           "but the largest computer allowed for them, a, has 12")


def test_infeasible_bandwidth() -> None:
    def case(dst_residence: list[str] | None) -> System:
        dst: dict[str, Any] = {"name": "n2", "weight": 1, "settings": [setting(8, 1)]}
        if dst_residence:
            dst["residence"] = dst_residence
        return system_of({
            "computers": [{"name": "a", "kind": "server", "capacity": 10},
                          {"name": "b", "kind": "server", "capacity": 10}],
            "links": [{"between": ["a", "b"], "bandwidth_kBps": 1}],
            "nodes": [{"name": "n1", "weight": 1, "residence": ["a"], "settings": [setting(8, 1, 5)]}, dst],
            "edges": [{"from": "n1", "to": "n2"}],
        })

    plan = exact(case(["b"]), 1)
    assert plan.reason == "bandwidth: link a-b carries at least 5 kB/s (edges n1->n2 must cross it) but has 1"
    # n2 may sit on a, but then a overflows: the diagnosis names the cheaper violation
    plan = exact(case(None), 1)
    assert plan.status == "infeasible" and plan.reason is not None
    assert "a would need 16 CPU but has 10" in plan.reason


# ---------------------------------------------------------------------------------------------
# the case study: discrete Table I against brute force; greedy and greedy+ as bounds


@pytest.mark.parametrize("problem", [1, 2])
def test_table2_instance1_discrete_matches_bruteforce(problem: int) -> None:
    system = system_of(table2_instance(1, continuous=False))
    plan = exact(system, problem)
    ref = solve_bruteforce(system, problem, fixed_choices(system, problem))
    assert plan.status == "optimal"
    assert plan.objective == pytest.approx(ref.objective, abs=1e-9)


@pytest.mark.parametrize("instance", [1, 2, 3, 4])
def test_exact_bounds_the_greedy_solvers(instance: int) -> None:
    system = system_of(table2_instance(instance))
    for problem in (1, 2):
        choices = fixed_choices(system, problem)
        best = exact(system, problem)
        assert best.status == "optimal"
        for heuristic in (solve_greedy(system, problem, choices), solve_greedy_plus(system, problem, choices)):
            assert heuristic.objective is not None
            if problem == 1:
                assert best.objective >= heuristic.objective - 1e-9
            else:
                assert best.objective <= heuristic.objective + 1e-9


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_exact_bounds_greedy_on_tiny(seed: int) -> None:
    system = system_of(random_tiny(random.Random(seed)))
    for problem in (1, 2):
        choices = fixed_choices(system, problem)
        best = exact(system, problem)
        greedy = solve_greedy(system, problem, choices)
        if greedy.status == "infeasible" or best.status == "infeasible":
            assert not (best.status == "infeasible" and greedy.status != "infeasible")
            continue
        assert ((best.objective >= greedy.objective - 1e-9) if problem == 1
                else (best.objective <= greedy.objective + 1e-9))


def test_mip_start_and_gap() -> None:
    system = system_of(table2_instance(4))
    choices = fixed_choices(system, 1)
    best = exact(system, 1)
    greedy = solve_greedy_plus(system, 1, choices)
    start = start_of(greedy, choices)
    assert start is not None
    warm = exact(system, 1, start=start)
    assert warm.status == "optimal" and warm.objective == pytest.approx(best.objective, abs=1e-7)
    # a loose gap: a feasible plan no worse than the gap allows, and an honest bound
    loose = exact(system, 1, mip_gap=0.05, start=start)
    assert loose.status in ("optimal", "feasible")
    assert loose.objective >= (1 - 0.05) * best.objective - 1e-9
    assert loose.bound is not None and loose.bound >= best.objective - 1e-6


def test_time_limit_returns_best_plan_with_bound() -> None:
    system = system_of(table2_instance(6))
    plan = exact(system, 1, time_limit=0.05)
    # a tiny limit: either a plan (optimal or feasible with its bound) or an honest "not found"
    if plan.status == "infeasible":
        assert plan.reason is not None and "time" in plan.reason
    else:
        assert plan.bound is not None and plan.bound >= plan.objective - 1e-9


def test_start_is_checked_and_the_lp_bound_can_prove_it() -> None:
    system = system_of(table2_instance(5))
    choices = fixed_choices(system, 1)
    best = exact(system, 1)
    greedy = solve_greedy(system, 1, choices)
    as_start = start_of(greedy, choices)
    assert as_start is not None
    # within a 50 % gap of the LP bound: the start comes back as it is, with that bound
    loose = exact(system, 1, mip_gap=0.5, start=as_start)
    assert loose.objective == pytest.approx(greedy.objective)
    assert loose.status == "feasible" and loose.bound is not None
    assert best.objective <= loose.bound <= 1.5 * loose.objective
    # an infeasible start (every node on the server at its top setting) is ignored
    top = {n: choices[n][-1] for n in choices}
    broken = Assignment({n: "server" for n in choices}, top)
    plan = exact(system, 1, start=broken)
    assert plan.status == "optimal" and plan.objective == pytest.approx(best.objective, abs=1e-7)


def test_big_model_path_lp_rounding_start(monkeypatch: pytest.MonkeyPatch) -> None:
    """Models above milp.BIG_MODEL columns solve the LP first and round its placement into a
    start (and run without MIP presolve): same optimum, checked plan."""
    import perfros_bag.solver.exact as exact_mod
    import perfros_bag.solver.milp as milp_mod

    system = system_of(table2_instance(4))
    best = exact(system, 1)
    calls: list[int] = []
    real = exact_mod._lp_rounding

    def spy(*args: Any, **kw: Any) -> Any:
        calls.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(milp_mod, "BIG_MODEL", 0)
    monkeypatch.setattr(exact_mod, "_lp_rounding", spy)
    plan = exact(system, 1)
    assert calls, "the LP rounding start was not tried"
    assert plan.status == "optimal" and plan.objective == pytest.approx(best.objective, abs=1e-7)
    loose = exact(system, 1, mip_gap=0.05)
    assert loose.objective >= 0.95 * best.objective - 1e-9
