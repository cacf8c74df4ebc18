"""Benchmark: greedy and greedy+ against the exact MILP where latency budgets bind.

The instances are tests/budget_gen.py's (flow: random data flows, Problems 1 and 2; vision:
the case study's fleets, Problems 1 and 2, the latter at fixed settings), with a p95 budget on about half the
chains at 100-115 % of their latency in a random plan that fits. Per family and problem, over the instances where the
exact MILP finds a plan: how many each heuristic finds a plan for, its ratio to the MILP
optimum (Problem 1: its Σ w·P / the optimum's; Problem 2: the optimum's server capacity / its
own; 1 = optimal; an instance without a plan counts 0), how often it is optimal, and the
mean and worst solve time. Every plan goes through solver/check.py (budgets included).

    .venv/bin/python tests/bench/bench_budget_heuristics.py [--seeds 200]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from budget_gen import flow_instance, vision_instance  # noqa: E402

from perfros_bag.solver import solve  # noqa: E402
from perfros_bag.solver.check import check_plan  # noqa: E402
from perfros_bag.system.types import System  # noqa: E402

METHODS = ("exact", "greedy", "greedy+")


def unbudgeted(system: System) -> System:
    return dataclasses.replace(system, chains=tuple(dataclasses.replace(c, budget_ms=None) for c in system.chains))


def ratio(problem: int, got: float | None, best: float) -> float:
    if got is None:
        return 0.0
    if problem == 1:
        return got / best if best > 0 else 1.0
    return best / got if got > 1e-9 else 1.0


def run(name: str, problem: int, make: Callable[[int], System | None], seeds: int) -> None:
    rows: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
    refused = binding = 0
    for seed in range(seeds):
        system = make(seed)
        if system is None:
            continue
        plans = {}
        for m in METHODS:
            t = time.perf_counter()
            plans[m] = solve(system, problem, m)
            plans[m].solve_s = time.perf_counter() - t
            if plans[m].status != "infeasible" and check_plan(system, plans[m]):
                refused += 1
                print(f"  {name} seed {seed} {m}: REFUSED {check_plan(system, plans[m])}", flush=True)
        exact = plans["exact"]
        if exact.status != "optimal" or exact.objective is None:
            continue
        free = solve(unbudgeted(system), problem, "exact")
        binding += free.objective is not None and abs(free.objective - exact.objective) > 1e-6
        for m in METHODS:
            rows[m].append((ratio(problem, plans[m].objective, exact.objective), plans[m].solve_s or 0.0))
    n = len(rows["exact"])
    for m in METHODS[1:]:
        got = rows[m]
        found = sum(1 for r, _ in got if r > 0)
        optimal = sum(1 for r, _ in got if r >= 1 - 1e-6)
        mean = sum(r for r, _ in got) / max(n, 1)
        worst = min((r for r, _ in got), default=float("nan"))
        times = [t for _, t in got]
        print(f"| {name} | {problem} | {n} ({binding}) | {m} | {found} | {optimal} | {mean:.4f} | {worst:.4f} | "
              f"{sum(times) / max(n, 1):.3f} | {max(times, default=0):.3f} | "
              f"{sum(t for _, t in rows['exact']) / max(n, 1):.3f} |", flush=True)
    if refused:
        print(f"  {refused} plans REFUSED by the checker")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=200)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")
    print("| family | problem | instances: exact optimal (budget binds) | method | plans found | optimal | "
          "mean ratio | worst ratio | mean s | max s | exact mean s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    run("flow", 1, lambda s: flow_instance(s, 1), args.seeds)
    run("flow", 2, lambda s: flow_instance(s, 2), args.seeds)
    run("vision", 1, lambda s: vision_instance(s, 1), args.seeds)
    run("vision", 2, vision_instance, args.seeds)
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")


if __name__ == "__main__":
    main()
