"""Benchmark: driven nodes (system.yaml ``input:``): the solvers on data-flow instances.

1. The random family of ``tests/test_flow.py`` (1-2 robots, a camera per robot feeding
   chains and trees of up to 3 driven nodes, throttles, links, sometimes a shared wifi):
   exact against the enumeration written from the contract (``reference``), its time per
   instance (goal < 1 s each), greedy and greedy+ as a fraction of the optimum (goal
   greedy+ within 1 %).
2. Vision fleets (:func:`vision_fleet`): per robot a camera (2, 5 or 10 Hz, 230 kB per
   image) -> a detector (3 settings, CPU per frame) -> a throttled tracker (2 caps) and a
   planner; detectors and trackers may go to the server; the robots share one wifi that
   cannot carry every camera at full rate. Every solver, its objective and time.
3. Issue 22's wifi fleet with driven cameras (``wifi_fleet_instance(driven=True)``: 1,180
   nodes, 100 computers, 10 access points; each camera's rate a knob, its detector
   following it): greedy, greedy+ and exact with ``--time-limit``, objective, bound, time.

    .venv/bin/python tests/bench/bench_flow.py [--seeds 200] [--robots 4,10] [--wifi 90] [--time-limit 60]
"""

from __future__ import annotations

import argparse
import copy
import random
import sys
import time
import warnings
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from test_flow import random_flow, reference  # noqa: E402

from perfros_bag.casestudy.instances import wifi_fleet_instance  # noqa: E402
from perfros_bag.solver import solve  # noqa: E402
from perfros_bag.solver.check import check_plan  # noqa: E402
from perfros_bag.system.systemfile import parse_system  # noqa: E402


def vision_fleet(robots: int) -> dict[str, Any]:
    computers = [{"name": f"r{i}", "kind": "robot", "capacity": 20} for i in range(robots)]
    computers.append({"name": "srv", "kind": "server", "capacity": 15 * robots})
    links = [{"between": [f"r{i}", "srv"], "bandwidth_kBps": 5000, "medium": "wifi"} for i in range(robots)]
    nodes: list[dict[str, Any]] = []
    edges: list[dict[str, str]] = []
    for i in range(robots):
        nodes += [
            {"name": f"cam{i}", "weight": 1, "residence": [f"r{i}"], "parameter": {"name": "rate", "unit": "Hz"},
             "topics": [f"/cam{i}/img"],
             "settings": [{"value": f, "cpu": 0.2 * f, "performance": 10 * f, "frequency_hz": f,
                           "bandwidth_kBps": 230 * f} for f in (2, 5, 10)]},
            {"name": f"det{i}", "weight": 2, "input": f"/cam{i}/img", "parameter": {"name": "scale0"},
             "topics": [f"/det{i}/out"],
             "settings": [{"value": s, "cpu": 0.3, "cpu_per_hz": k, "performance": p, "bytes_per_msg": 400}
                          for s, k, p in ((1.05, 3.1, 100), (1.2, 2.0, 70), (1.4, 1.2, 35))]},
            {"name": f"trk{i}", "weight": 1, "input": f"/det{i}/out", "parameter": {"name": "max_rate"},
             "topics": [f"/trk{i}/out"],
             "settings": [{"value": m, "cpu": 0.5, "cpu_per_hz": 0.3, "performance": 50 + 10 * m,
                           "max_frequency_hz": m, "bytes_per_msg": 2000} for m in (2, 4)]},
            {"name": f"plan{i}", "weight": 1, "residence": [f"r{i}"], "parameter": {"name": "hz"},
             "topics": [f"/plan{i}"],
             "settings": [{"value": v, "cpu": v, "performance": 20 * v, "frequency_hz": v, "bandwidth_kBps": 1}
                          for v in (1, 3, 5)]},
        ]
        edges += [{"from": f"cam{i}", "to": f"det{i}"}, {"from": f"det{i}", "to": f"trk{i}"}]
    return {"computers": computers, "links": links, "media": [{"name": "wifi", "bandwidth_kBps": 1150 * robots}],
            "nodes": nodes, "edges": edges}


def timed(system: Any, method: str, time_limit: float | None = None) -> tuple[Any, float]:
    t0 = time.perf_counter()
    plan = solve(system, 1, method, time_limit=time_limit)
    return plan, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--robots", default="4,10")
    ap.add_argument("--wifi", type=int, default=90, help="robots of the driven wifi fleet (0: skip part 3)")
    ap.add_argument("--time-limit", type=float, default=60.0)
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    print(f"1. random family, seeds 0-{args.seeds - 1}")
    exact_s: list[float] = []
    ratios: dict[str, list[float]] = {"greedy": [], "greedy+": []}
    feasible = 0
    for seed in range(args.seeds):
        data = random_flow(random.Random(seed))
        system = parse_system(copy.deepcopy(data), f"flow-{seed}")
        want = reference(data, 1)
        plan, seconds = timed(system, "exact")
        exact_s.append(seconds)
        if want is None:
            assert plan.status == "infeasible", seed
            continue
        feasible += 1
        assert plan.objective is not None and abs(plan.objective - want) <= 1e-6 * max(1.0, want), seed
        for method in ratios:
            h, _ = timed(system, method)
            if h.status != "infeasible":
                assert check_plan(system, h) == [], (seed, method)
            ratios[method].append((h.objective or 0.0) / want if h.status != "infeasible" else 0.0)
    exact_s.sort()
    print(f"   {feasible} of {args.seeds} with a plan; exact == enumeration on all; exact time median "
          f"{exact_s[len(exact_s) // 2]:.3f} s, max {exact_s[-1]:.3f} s")
    for method, rs in ratios.items():
        below = sum(r < 0.99 for r in rs)
        print(f"   {method:8s} / optimum: mean {100 * sum(rs) / len(rs):.2f} %, worst {100 * min(rs):.2f} %, "
              f"{below} below 99 %")

    print("2. vision fleets (camera -> detector -> throttled tracker, a planner; one wifi)")
    print(f"   {'robots':>6} {'nodes':>5} {'method':>8} {'objective':>10} {'status':>9} {'seconds':>8}")
    for robots in (int(r) for r in args.robots.split(",")):
        system = parse_system(vision_fleet(robots), f"vision-{robots}")
        for method in ("exact", "greedy", "greedy+"):
            plan, seconds = timed(system, method)
            if plan.status != "infeasible":
                assert check_plan(system, plan) == [], (robots, method)
            print(f"   {robots:>6} {len(system.nodes):>5} {method:>8} {plan.objective or 0:>10.4f} "
                  f"{plan.status:>9} {seconds:>8.2f}", flush=True)

    if args.wifi:
        servers = max(1, (args.wifi + args.wifi // 9) // 10)
        system = parse_system(wifi_fleet_instance(args.wifi, servers, driven=True), "wifi-driven")
        print(f"3. the wifi fleet with driven cameras: {len(system.nodes)} nodes, {len(system.computers)} computers")
        print(f"   {'method':>8} {'objective':>10} {'bound':>10} {'status':>9} {'seconds':>8}")
        for method in ("greedy", "greedy+", "exact"):
            plan, seconds = timed(system, method, args.time_limit if method == "exact" else None)
            if plan.status != "infeasible":
                assert check_plan(system, plan) == [], method
            bound = "-" if plan.bound is None else f"{plan.bound:.4f}"
            print(f"   {method:>8} {plan.objective or 0:>10.4f} {bound:>10} {plan.status:>9} {seconds:>8.2f}",
                  flush=True)


if __name__ == "__main__":
    main()
