"""Benchmark (issue 32): the solvers side by side on the driven wifi fleet
(``wifi_fleet_instance(driven=True)``: every camera's rate a knob, its detector driven,
on its robot or a server across the access points) at 236, 590 and 1,180 nodes.

Each (size, method) runs in its own process (its whole time: start-up, the choices, the
solve; its peak RSS from ``getrusage``): greedy, greedy+, ``exact --time-limit`` (the
decomposition, whose blocks carry the data flow) and plain HiGHS on the whole MILP (no
start, same limit). Every plan goes through the independent checker. The gap is to the
best proven bound of the row (exact's or HiGHS's).

    .venv/bin/python tests/bench/bench_driven_fleet.py [--sizes 18,45,90] [--time-limit 60]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import warnings
from typing import Any

METHODS = ("greedy", "greedy+", "exact", "highs")


def one(robots: int, method: str, limit: float) -> dict[str, Any]:
    """One solve in this process (the worker's side)."""
    from perfros_bag.casestudy.instances import wifi_fleet_instance
    from perfros_bag.solver import fixed_choices, solve
    from perfros_bag.solver.check import check_plan
    from perfros_bag.system.systemfile import parse_system
    from perfros_bag.system.types import Problem

    servers = max(1, (robots + robots // 9) // 10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        system = parse_system(wifi_fleet_instance(robots, servers, driven=True), "wifi-driven.yaml")
    if method == "highs":
        from perfros_bag.solver.exact import solve_exact

        plan = solve_exact(system, Problem.PERFORMANCE, fixed_choices(system, Problem.PERFORMANCE), time_limit=limit)
    else:
        plan = solve(system, 1, method, time_limit=limit if method == "exact" else None)
    feasible = plan.status != "infeasible" and plan.objective is not None
    return {"nodes": len(system.nodes), "status": str(plan.status), "objective": plan.objective,
            "bound": plan.bound, "check": check_plan(system, plan) if feasible else [plan.reason],
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="18,45,90", help="robots per fleet (18, 45, 90: 236, 590, 1,180 nodes)")
    ap.add_argument("--time-limit", type=float, default=60.0, help="exact's and plain HiGHS's limit (s)")
    ap.add_argument("--one", nargs=2, metavar=("ROBOTS", "METHOD"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(int(args.one[0]), args.one[1], args.time_limit)))
        return 0
    bad = 0
    for robots in (int(x) for x in args.sizes.split(",")):
        rows: list[tuple[str, dict[str, Any], float]] = []
        for method in METHODS:
            t = time.perf_counter()
            run = subprocess.run([sys.executable, __file__, "--one", str(robots), method,
                                  "--time-limit", str(args.time_limit)],
                                 capture_output=True, text=True, check=False, timeout=10 * args.time_limit + 300)
            wall = time.perf_counter() - t
            if run.returncode != 0:
                print(f"{method}: failed: {run.stderr.strip()[-300:]}", flush=True)
                bad += 1
                continue
            rows.append((method, json.loads(run.stdout.strip().splitlines()[-1]), wall))
        if not rows:
            continue
        proven = [r["bound"] for m, r, _ in rows if m in ("exact", "highs") and r["bound"] is not None]
        best = min(proven) if proven else None
        print(f"\n{rows[0][1]['nodes']} nodes ({robots} robots), limit {args.time_limit:g} s; "
              f"best proven bound {best if best is None else f'{best:.4f}'}")
        print(f"{'method':<8} {'status':<9} {'objective':>10} {'own bound':>10} {'gap':>8} {'wall s':>7} "
              f"{'peak MB':>8}  checker")
        for method, r, wall in rows:
            obj, own = r["objective"], r["bound"]
            gap = "-" if obj is None or best is None else f"{100 * (best - obj) / best:.2f} %"
            ok = "ok" if not r["check"] else r["check"][:2]
            bad += bool(r["check"])
            print(f"{method:<8} {r['status']:<9} {'-' if obj is None else f'{obj:.4f}':>10} "
                  f"{'-' if own is None else f'{own:.4f}':>10} {gap:>8} {wall:>7.1f} {r['peak_mb']:>8.0f}  {ok}",
                  flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
