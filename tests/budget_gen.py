"""Instances whose latency budgets bind, for the heuristics against the exact MILP and brute
force (tests/test_budget_heuristics.py, tests/bench/bench_budget_heuristics.py).

Two families:

- **flow**: :func:`test_flow.random_flow` (robots around a server, a camera per robot
  feeding a chain or tree of driven nodes, a plain node), with one chain per leaf of the
  data flow (camera -> ... -> leaf), and a p95 budget on about half of them (at least one)
  at 100-115 % of that chain's latency in a random plan that fits: some plan keeps every
  budget, and the unbudgeted optimum often does not;
- **vision**: bench_budgets' vision fleets (camera -> people detector per robot, a
  smoother coresident with the camera, a shared wifi), Problem 2 at fixed settings with the
  robots' capacities drawn so that a detector fits on some robots and not on others.

Problem 2 has no server capacity (the servers are sized).
"""

from __future__ import annotations

import copy
import math
import random
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent / "bench"))

from bench_budgets import fleet  # noqa: E402
from test_flow import random_flow  # noqa: E402

from perfros_bag.solver import fixed_choices  # noqa: E402
from perfros_bag.solver.budgets import capacities_of, fits_model, with_flow  # noqa: E402
from perfros_bag.system.latency import predict_chain  # noqa: E402
from perfros_bag.system.plan import Assignment  # noqa: E402
from perfros_bag.system.rules import server_sizes  # noqa: E402
from perfros_bag.system.systemfile import parse_system  # noqa: E402
from perfros_bag.system.types import Problem, System  # noqa: E402


def with_chains(data: dict[str, Any], budgets: dict[str, float] | None = None) -> dict[str, Any]:
    """``data`` with a chain per leaf of its data flow (``c_<leaf>``: the topics from the
    source to the leaf's output), with ``budgets[name]`` as its p95 budget when given."""
    out = copy.deepcopy(data)
    by_name = {n["name"]: n for n in out["nodes"]}
    publisher = {t: n["name"] for n in out["nodes"] for t in n["topics"]}
    driven = [n for n in out["nodes"] if "input" in n]
    inputs = {n["input"] for n in driven}
    chains = []
    for n in driven:
        if n["topics"][0] in inputs:
            continue
        path, at = [n["topics"][0]], n
        while "input" in at:
            path.insert(0, at["input"])
            at = by_name[publisher[at["input"]]]
        chain: dict[str, Any] = {"name": f"c_{n['name']}", "topics": path}
        if budgets and chain["name"] in budgets:
            chain["budget_ms"] = {"p95": budgets[chain["name"]]}
        chains.append(chain)
    out["chains"] = chains
    return out


def _sized(data: dict[str, Any]) -> dict[str, Any]:
    for c in data["computers"]:
        if c["kind"] == "server":
            c.pop("capacity", None)
    return data


def random_plan(system: System, problem: int, rng: random.Random, tries: int = 2000) -> Assignment | None:
    """A random assignment that fits (CPU, residence, coresidence, network; no budget): each
    node a random choice (driven nodes at their input's rate), each coresidence group a random
    computer it may use; None when ``tries`` draws found none."""
    the_problem = Problem(problem)
    choices = fixed_choices(system, the_problem, None, 1.0)
    fits = fits_model(system, the_problem, system.capacities(the_problem))
    for _ in range(tries):
        choice = with_flow(system, {n: rng.choice(c) for n, c in choices.items()}, choices)
        if choice is None:
            continue
        placement = {n: comp for g, comps in zip(system.coresidence_groups, system.group_computers, strict=True)
                     for comp in [rng.choice(comps)] for n in g}
        caps = server_sizes(system, placement, choice) if the_problem == Problem.SERVER_CAPACITY else {}
        assignment = Assignment(placement, choice, caps)
        if fits(assignment):
            return assignment
    return None


def _budgeted(data: dict[str, Any], problem: int, rng: random.Random, name: str) -> System | None:
    """``data`` with a p95 budget on about half its chains (at least one): 100-115 % of that
    chain's latency in a random plan that fits (:func:`random_plan`), so some plan keeps every
    budget and the optimum without budgets often does not; None when no such plan was drawn."""
    system = parse_system(copy.deepcopy(data), name)
    plan = random_plan(system, problem, rng)
    if plan is None:
        return None
    caps = capacities_of(system, Problem(problem), plan)
    loads = system.link_loads(plan.placement, plan.choice)
    chosen = [c for c in system.chains if rng.random() < 0.5] or list(system.chains[:1])
    for chain in chosen:
        got = predict_chain(system, chain, plan.placement, plan.choice, caps, loads)
        if got.p95_ms is not None and math.isfinite(got.p95_ms):
            entry = next(c for c in data["chains"] if c["name"] == chain.name)
            entry["budget_ms"] = {"p95": round(got.p95_ms * rng.uniform(1.0, 1.15) + 1e-3, 3)}
    return parse_system(data, name)


def flow_instance(seed: int, problem: int) -> System | None:
    """The flow family's instance ``seed`` for ``problem`` (None: no plan even unbudgeted)."""
    rng = random.Random(seed)
    data = with_chains(random_flow(rng))
    if problem == 2:
        _sized(data)
    return _budgeted(data, problem, rng, f"flow-{seed}.yaml")


def vision_instance(seed: int, problem: int = 2) -> System | None:
    """The vision family's instance ``seed`` (2-3 robots of 15-35 units). Problem 2: every
    node's setting fixed (the camera at 2 or 5 Hz, so every frame stream fits the wifi; the
    detector's and the smoother's drawn per robot); Problem 1: all their settings."""
    rng = random.Random(seed)
    robots = rng.randint(2, 3)
    data = fleet(robots)
    data["media"][0]["bandwidth_kBps"] = 4000 * robots
    for c in data["computers"]:
        if c["kind"] == "robot":
            c["capacity"] = rng.choice([15, 20, 25, 35])
    if problem == 2:
        _sized(data)
        for n in data["nodes"]:
            keep = rng.randrange(2 if n["name"].endswith("_camera") else len(n["settings"]))
            n["settings"] = [n["settings"][keep]]
            n.pop("parameter", None)
    return _budgeted(data, problem, rng, f"vision-{seed}.yaml")
