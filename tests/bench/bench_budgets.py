"""Benchmark: latency budgets in the solvers (docs/solvers.md, "Latency budgets").

Vision fleets like the case study's: per robot a camera (2, 5 or 10 Hz, 230 kB frames), a
people detector (4 settings, CPU per frame; on its robot or the server) and a smoother
(coresident with the camera); per robot a link of 3,000 kB/s on one 6,000 kB/s wifi; robots
of 25, 20, 30 (and 25) CPU units, a server of 40. One chain per robot, camera -> people,
with a p95 budget at 80 %, 50 % and 30 % of the unbudgeted optimum's slowest chain. Per
budget: exact (status, objective, time, no-good cuts added), greedy+ (objective, time), and
whether the independent checker accepts both plans.

    .venv/bin/python tests/bench/bench_budgets.py [--robots 2,3,4] [--time-limit 120]
"""

from __future__ import annotations

import argparse
import time
import warnings
from typing import Any

import perfros_bag.solver.budgets as budgets
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.systemfile import parse_system

CAPACITIES = (25, 20, 30, 25)


def fleet(robots: int, budget: float | None = None) -> dict[str, Any]:
    nodes: list[dict[str, Any]] = []
    edges: list[dict[str, str]] = []
    chains: list[dict[str, Any]] = []
    for k in range(1, robots + 1):
        cam = f"/robot{k}/camera/image_raw"
        nodes.append({"name": f"robot{k}_camera", "weight": 0.4 / robots, "residence": [f"robot{k}"],
                      "parameter": {"name": "rate"}, "topics": [cam],
                      "settings": [{"value": r, "cpu": 0.5 + 0.1 * r, "performance": 10 * r, "frequency_hz": r,
                                    "bandwidth_kBps": 230 * r} for r in (2, 5, 10)]})
        nodes.append({"name": f"robot{k}_people", "weight": 0.4 / robots, "input": cam,
                      "parameter": {"name": "scale0"}, "topics": [f"/robot{k}/people/found"],
                      "residence": [f"robot{k}", "server"],
                      "settings": [{"value": v, "cpu": 0.5, "cpu_per_hz": c, "performance": p, "bytes_per_msg": 200}
                                   for v, c, p in ((1.05, 5.0, 100), (1.1, 3.5, 85), (1.2, 2.2, 60), (1.4, 1.2, 30))]})
        nodes.append({"name": f"robot{k}_smooth", "weight": 0.2 / robots, "input": cam,
                      "parameter": {"name": "kernel"}, "topics": [f"/robot{k}/smooth/image"],
                      "residence": [f"robot{k}", "server"], "coresidence": [f"robot{k}_camera"],
                      "settings": [{"value": v, "cpu": 0.3, "cpu_per_hz": c, "performance": p,
                                    "bytes_per_msg": 230000}
                                   for v, c, p in ((3, 0.5, 50), (7, 1.2, 80), (11, 2.4, 100))]})
        edges += [{"from": f"robot{k}_camera", "to": f"robot{k}_people", "topic": cam},
                  {"from": f"robot{k}_camera", "to": f"robot{k}_smooth", "topic": cam}]
        chains.append({"name": f"robot{k}_vision", "topics": [cam, f"/robot{k}/people/found"],
                       **({"budget_ms": {"p95": budget}} if budget else {})})
    return {"computers": [{"name": f"robot{k}", "kind": "robot", "capacity": CAPACITIES[k - 1]}
                          for k in range(1, robots + 1)] + [{"name": "server", "kind": "server", "capacity": 40}],
            "links": [{"between": [f"robot{k}", "server"], "bandwidth_kBps": 3000, "medium": "wifi"}
                      for k in range(1, robots + 1)],
            "media": [{"name": "wifi", "bandwidth_kBps": 6000}], "nodes": nodes, "edges": edges, "chains": chains}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--robots", default="2,3,4")
    ap.add_argument("--time-limit", type=float, default=120.0)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    count = {"cuts": 0}
    cut_of = budgets.cut_of

    def counting(*a: Any, **k: Any) -> Any:
        count["cuts"] += 1
        return cut_of(*a, **k)

    budgets.cut_of = counting  # type: ignore[assignment]
    print("| robots | budget p95 ms | exact | objective | s | cuts | greedy+ | s | checker |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for robots in (int(r) for r in args.robots.split(",")):
        free = solve(parse_system(fleet(robots)), 1, "exact")
        worst = max(c["predicted_ms"]["p95"] for c in free.chains)
        print(f"| {robots} | none | {free.status} | {free.objective:.2f} | - | - | - | - | - |")
        for share in (0.8, 0.5, 0.3):
            system = parse_system(fleet(robots, round(share * worst, 1)))
            count["cuts"] = 0
            t = time.perf_counter()
            exact = solve(system, 1, "exact", time_limit=args.time_limit)
            te, cuts = time.perf_counter() - t, count["cuts"]
            t = time.perf_counter()
            plus = solve(system, 1, "greedy+")
            tg = time.perf_counter() - t
            ok = all(check_plan(system, p) == [] for p in (exact, plus) if p.status != "infeasible")
            obj = "-" if exact.objective is None else f"{exact.objective:.2f}"
            gobj = "none" if plus.objective is None else f"{plus.objective:.2f}"
            print(f"| {robots} | {share * worst:.0f} | {exact.status} | {obj} | {te:.2f} | {cuts} | {gobj} | "
                  f"{tg:.2f} | {'ok' if ok else 'REFUSED'} |", flush=True)


if __name__ == "__main__":
    main()
