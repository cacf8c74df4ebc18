"""Brute force as the reference on random tiny instances: greedy <= greedy+ <= optimum
(Problem 1; reversed for Problem 2), every plan passes the checker, and what brute force
proves infeasible no heuristic solves."""

from __future__ import annotations

import itertools
import random
import warnings

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.casestudy.instances import random_tiny, table2_instance
from perfros_bag.errors import InputError
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.systemfile import parse_system


def tiny(seed: int):  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(random_tiny(random.Random(seed)), f"tiny-{seed}.yaml")


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), problem=st.sampled_from([1, 2]))
def test_heuristics_bounded_by_brute_force(seed: int, problem: int) -> None:
    s = tiny(seed)
    best = solve(s, problem, "bruteforce")
    g = solve(s, problem, "greedy")
    gp = solve(s, problem, "greedy+")
    for p in (best, g, gp):
        if p.status != "infeasible":
            assert check_plan(s, p) == [], (p.method, check_plan(s, p))
    if best.status == "infeasible":
        assert g.status == gp.status == "infeasible"
        return
    assert best.status == "optimal" and best.objective is not None
    if g.status != "infeasible":
        assert gp.status != "infeasible", "greedy+ starts from the greedy's plan"
    if gp.status == "infeasible":
        return
    assert gp.objective is not None
    sign = 1 if problem == 1 else -1
    assert sign * gp.objective <= sign * best.objective + 1e-9
    if g.objective is not None:
        assert sign * g.objective <= sign * gp.objective + 1e-9


def independent_optimum(s, problem: int) -> float | None:  # type: ignore[no-untyped-def]
    """A second, naive enumeration (itertools.product over every node's choice and
    computer, feasibility from the checker's own rules) to cross-check brute force."""
    from perfros_bag.system.plan import Assignment
    from perfros_bag.system.rules import build_plan

    names = [n.name for n in s.nodes]
    opts = [[(c, ch) for c in s.allowed(n)
             for ch in (s.node[n].choices() if problem == 1 else s.node[n].choices()[-1:])]
            for n in names]
    best: float | None = None
    for combo in itertools.product(*opts):
        placement = {n: c for n, (c, _) in zip(names, combo, strict=True)}
        choice = {n: ch for n, (_, ch) in zip(names, combo, strict=True)}
        caps = {}
        if problem == 2:
            caps = {c.name: sum(choice[n].cpu for n in names if placement[n] == c.name)
                    for c in s.computers if c.kind == "server"}
        plan = build_plan(s, Assignment(placement, choice, caps), problem=problem, method="naive", status="feasible")
        if check_plan(s, plan):
            continue
        v = plan.objective
        assert v is not None
        if best is None or (v > best if problem == 1 else v < best):
            best = v
    return best


@pytest.mark.parametrize("seed", range(12))
def test_brute_force_matches_naive_enumeration(seed: int) -> None:
    s = tiny(1000 + seed)
    for problem in (1, 2):
        want = independent_optimum(s, problem)
        got = solve(s, problem, "bruteforce")
        if want is None:
            assert got.status == "infeasible"
        else:
            assert got.objective == pytest.approx(want)


def test_brute_force_refuses_large_instances() -> None:
    s = parse_system(table2_instance(6), "instance6.yaml")
    with pytest.raises(InputError, match="too large for bruteforce"):
        solve(s, 1, "bruteforce")


def test_brute_force_has_no_recursion_limit() -> None:
    """3,000 nodes with one setting each on one computer: one combination, searched without
    a call per node (Python's default recursion limit is 1,000)."""
    import sys

    nodes = [{"name": f"n{i}", "weight": 1, "settings": [{"cpu": 1, "performance": 1 + i % 3}]} for i in range(3000)]
    s = parse_system({"computers": [{"name": "robot", "kind": "robot", "capacity": 3000}], "nodes": nodes}, "big.yaml")
    assert len(s.nodes) > 2 * sys.getrecursionlimit()
    plan = solve(s, 1, "bruteforce")
    assert plan.status == "optimal" and check_plan(s, plan) == []
    assert plan.objective == pytest.approx(sum(1 + i % 3 for i in range(3000)) / 3000)
