"""Benchmark: planning fleets, every solver side by side in one run (issue 15).

On ``fleet_instance`` at 200 x 20, 500 x 50 and 1,000 x 100 (robots running the robot stack,
camera trackers on the servers, one wifi) and on random case-study-like instances, Problem 1:

- ``greedy``     the paper's greedy (solver/greedy.py)
- ``greedy+``    greedy + local search, ``time_budget`` = the limit (solver/local.py)
- ``highs``      plain HiGHS on the whole x-form MILP, no start (``solve_exact``)
- ``exact``      what ``solve --method exact`` runs: on the fleets the decomposition
                 (solver/decompose.py), on small instances the MILP
- ``decompose``  the decomposition called directly, where ``exact`` is the MILP
- ``cp-sat``     OR-Tools CP-SAT, 2 workers, in its own process (``--cpsat-python``: a
                 Python with ortools; cpsat_worker.py), on the same pruned choices

Every plan goes through ``check_plan``; the gap of each row is against the best proven
bound of the instance (the best of the solvers' bounds). Then Problem 2 at 1,000 x 100,
and the end-to-end CLI run ``perfros-bag solve FLEET.yaml --method exact --time-limit S``
under ``/usr/bin/time`` (wall, peak RSS).

    .venv/bin/python tests/bench/bench_fleet_plan.py [--sizes 200x20,500x50,1000x100]
        [--limits 10,30,60] [--random 5] [--cpsat-python /path/to/python]
    .venv/bin/python tests/bench/bench_fleet_plan.py --sizes 1000x100,200x20 --time-limits 1,2,5,10,30
    .venv/bin/python tests/bench/bench_fleet_plan.py --wifi only [--wifi-parts solvers,p2,cli]
        [--wifi-limit 60] [--wifi-plus 10]

With ``--wifi also`` (the default) the 1,180-node fleet whose access points bind
(``wifi_fleet_instance()``, issue 22) runs first: greedy, greedy+ (10 s), plain HiGHS,
exact (the decomposition with network rows), Problem 2 and the CLI run.
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

from perfros_bag.casestudy.instances import fleet_instance, random_instance, wifi_fleet_instance
from perfros_bag.solver import DECOMPOSE_COLUMNS, exact_columns, fixed_choices, solve
from perfros_bag.solver import instance as instance_mod
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.decompose import solve_decomposed
from perfros_bag.solver.exact import solve_exact
from perfros_bag.solver.greedy import solve_greedy
from perfros_bag.solver.local import solve_greedy_plus
from perfros_bag.system.plan import Assignment, Plan, Status
from perfros_bag.system.rules import build_plan
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem, System

WORKER = Path(__file__).with_name("cpsat_worker.py")


def system_of(data: dict[str, Any], name: str) -> System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(data, name)


def cpsat(system: System, limit: float, python: str) -> tuple[Plan | None, float, str]:
    """CP-SAT in a subprocess on the pruned choices; the plan (checked by the caller)."""
    choices = fixed_choices(system, Problem.PERFORMANCE)
    inst = instance_mod.prepare_instance(system, Problem.PERFORMANCE, choices)
    assert not isinstance(inst, str)
    assert not instance_mod.active_links(inst), "the CP-SAT worker has no network rows"
    doc = {"time_limit": limit, "workers": 2,
           "capacity": {c.name: inst.cap[c.name] for c in system.computers},
           "groups": [{"members": list(g.members), "allowed": list(g.allowed)} for g in inst.groups],
           "choices": {n: [[ch.cpu, system.node[n].weight * ch.performance] for ch in inst.choices[n]]
                       for n in inst.choices}}
    t = time.perf_counter()
    run = subprocess.run([python, str(WORKER)], input=json.dumps(doc), capture_output=True, text=True,
                         timeout=limit * 3 + 120, check=False)
    wall = time.perf_counter() - t
    if run.returncode != 0:
        return None, wall, f"worker failed: {run.stderr.strip()[-200:]}"
    ans = json.loads(run.stdout)
    if "placement" not in ans:
        return None, wall, ans["status"]
    assignment = Assignment(ans["placement"], {n: inst.choices[n][k] for n, k in ans["level"].items()}, {})
    plan = build_plan(system, assignment, problem=Problem.PERFORMANCE, method="cp-sat",
                      status=Status.OPTIMAL if ans["status"] == "OPTIMAL" else Status.FEASIBLE,
                      bound=ans["bound_scaled"])
    return plan, wall, f"{ans['status']}, scaled bound {ans['bound_scaled']:.6f}"


def run_instance(label: str, system: System, limit: float, cpsat_python: str | None, highs: bool,
                 plus_budget: float | None = None) -> Plan | None:
    print(f"\n### {label}: {len(system.nodes)} nodes x {len(system.computers)} computers, limit {limit:g} s",
          flush=True)
    choices = fixed_choices(system, Problem.PERFORMANCE)
    rows: list[tuple[str, Plan | None, float, float, str]] = []

    def timed(name: str, fn: Any, *args: Any, **kw: Any) -> None:
        w, c = time.perf_counter(), time.process_time()
        plan = fn(*args, **kw)
        rows.append((name, plan, time.perf_counter() - w, time.process_time() - c, ""))
        print(f"  ran {name}: {time.perf_counter() - w:.1f} s", file=sys.stderr, flush=True)

    timed("greedy", solve_greedy, system, Problem.PERFORMANCE, choices)
    timed("greedy+", solve_greedy_plus, system, Problem.PERFORMANCE, choices,
          time_budget=limit if plus_budget is None else plus_budget)
    if highs:
        timed("highs", solve_exact, system, Problem.PERFORMANCE, choices, time_limit=limit)
    timed("exact", solve, system, 1, "exact", time_limit=limit)  # what `solve --method exact` runs
    if exact_columns(system, choices) <= DECOMPOSE_COLUMNS:  # there `exact` is the MILP: the decomposition too
        timed("decompose", solve_decomposed, system, Problem.PERFORMANCE, choices, time_limit=limit)
    if cpsat_python:
        c0 = time.process_time()
        plan, wall, note = cpsat(system, limit, cpsat_python)
        rows.append(("cp-sat", plan, wall, time.process_time() - c0, note))
    bounds = [p.bound for _, p, _, _, _ in rows if p is not None and p.bound is not None
              and p.status != Status.INFEASIBLE and p.method != "cp-sat"]
    bounds += [p.bound for _, p, _, _, _ in rows if p is not None and p.method == "cp-sat" and p.bound is not None]
    best_bound = min(bounds) if bounds else None
    print(f"{'method':<10} {'status':<10} {'objective':>10} {'own bound':>10} {'gap to best bound':>17} "
          f"{'wall s':>7} {'cpu s':>7}  checker")
    for name, plan, wall, cpu, note in rows:
        if plan is None or plan.status == Status.INFEASIBLE or plan.objective is None:
            print(f"{name:<10} {'none':<10} {'-':>10} {'-':>10} {'-':>17} {wall:>7.2f} {cpu:>7.2f}  "
                  f"{note or (plan.reason if plan else '')}")
            continue
        problems = check_plan(system, plan)
        gap = "-" if best_bound is None else f"{100 * (best_bound - plan.objective) / plan.objective:.4f} %"
        own = "-" if plan.bound is None else f"{plan.bound:.4f}"
        print(f"{name:<10} {plan.status!s:<10} {plan.objective:>10.4f} {own:>10} {gap:>17} {wall:>7.2f} "
              f"{cpu:>7.2f}  {'ok' if not problems else problems[:2]} {note}", flush=True)
    print(f"best proven bound {best_bound}")
    return next((p for name, p, _, _, _ in rows if name == "exact"), None)


def problem2(system: System, limit: float, settings: dict[str, float] | None = None) -> None:
    w = time.perf_counter()
    plan = solve(system, 2, "exact", time_limit=limit, settings=settings)
    ok = check_plan(system, plan) if plan.status != Status.INFEASIBLE else ["infeasible"]
    print(f"\nProblem 2, {len(system.nodes)} x {len(system.computers)}: {plan.status}, objective {plan.objective}, "
          f"bound {plan.bound}, {time.perf_counter() - w:.2f} s wall, checker {'ok' if not ok else ok}", flush=True)


def wifi(limit: float, plus_budget: float, parts: set[str]) -> None:
    """The 1,180-node fleet whose access points bind (issue 22, ``wifi_fleet_instance()``).
    ``solvers``: greedy, greedy+ (``plus_budget``), plain HiGHS on the whole MILP, exact (the
    decomposition with network rows), each ``limit``; ``p2``: Problem 2 (``limit``) at the
    settings of exact's Problem 1 plan (exact at a third of ``limit``); ``cli``: ``solve
    --method exact --time-limit limit`` end to end. No CP-SAT: its worker has no network rows."""
    from perfros_bag.solver import settings_from_plan

    data = wifi_fleet_instance()
    system = system_of(data, "wifi-fleet")
    if "solvers" in parts:
        run_instance("wifi_fleet_instance() (90 robots, 10 servers, 10 access points)", system, limit, None, True,
                     plus_budget=plus_budget)
    if "p2" in parts:
        first = solve(system, 1, "exact", time_limit=limit / 3)
        print(f"\nProblem 1 for the settings (exact, {limit / 3:g} s): {first.status}, {first.objective}", flush=True)
        if first.objective is not None:
            problem2(system, limit, settings_from_plan(first))
    if "cli" in parts:
        cli_run(data, limit)


def cli_solve(path: Path, system: System, limit: float) -> dict[str, Any]:
    """``perfros-bag solve PATH --method exact --time-limit LIMIT --json -o plan.json`` under
    ``/usr/bin/time``: the plan's fields, the process's wall and peak RSS, the checker's verdict."""
    from perfros_bag.system.planfile import load_plan

    out = path.with_name("plan.json")
    cmd = ["/usr/bin/time", "-f", "%e %M", sys.executable, "-m", "perfros_bag", "solve", str(path),
           "--method", "exact", "--time-limit", f"{limit:g}", "--json", "-o", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall, rss = run.stderr.strip().splitlines()[-1].split()
    doc = json.loads(out.read_text())
    problems = check_plan(system, load_plan(out))
    return {**doc, "exit": run.returncode, "wall": float(wall), "rss_mb": int(rss) / 1024,
            "gap": (doc["bound"] - doc["objective"]) / doc["objective"], "checker": problems or "ok"}


def cli_run(system_data: dict[str, Any], limit: float) -> None:
    import yaml

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fleet.yaml"
        path.write_text(yaml.safe_dump(system_data))
        r = cli_solve(path, system_of(system_data, str(path)), limit)
        print(f"\nCLI `perfros-bag solve fleet.yaml --method exact --time-limit {limit:g} --json -o plan.json`: "
              f"{r['status']}, objective {r['objective']:.4f}, bound {r['bound']:.4f}, gap {100 * r['gap']:.4f} %, "
              f"solve_s {r['solve_s']:.2f}, {r['wall']} s wall end to end, peak RSS {r['rss_mb']:.0f} MB, "
              f"checker {r['checker']}", flush=True)


def time_limits(sizes: list[tuple[int, int]], limits: list[float]) -> None:
    """``--time-limit`` against the clock, end to end from the CLI: per size and limit, the
    process's wall, the solve part (plan.json's ``solve_s``: from the start of ``solve()``,
    after reading the system, to the plan), the rest (start-up, reading, writing), the
    plan's gap to its own bound."""
    import yaml

    print("| instance | --time-limit s | solve_s | solve_s / limit | process wall s | wall - solve_s | "
          "status | objective | bound | gap | peak RSS MB | checker |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n, c in sizes:
        data = fleet_instance(n, c)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "fleet.yaml"
            path.write_text(yaml.safe_dump(data))
            system = system_of(data, str(path))
            for limit in limits:
                r = cli_solve(path, system, limit)
                print(f"| {n} x {c} | {limit:g} | {r['solve_s']:.2f} | {r['solve_s'] / limit:.3f} | {r['wall']:.2f} | "
                      f"{r['wall'] - r['solve_s']:.2f} | {r['status']} | {r['objective']:.4f} | {r['bound']:.4f} | "
                      f"{100 * r['gap']:.4f} % | {r['rss_mb']:.0f} | {r['checker']} |", flush=True)


def other_paths(sizes: list[tuple[int, int]], limits: list[float]) -> None:
    """``--time-limit`` on the exact paths other than the decomposition, in-process: Problem 2
    (the MILP, no start) and Problem 1 with the wifi halved so the network can bind (the
    MILP with greedy+'s start)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the binding fleet
    from test_fleet import binding_network

    print("\n| path | instance | limit s | wall s | status | objective | bound | checker |")
    print("|---|---|---|---|---|---|---|---|")
    for n, c in sizes:
        data = fleet_instance(n, c)
        for label, system, problem in (("Problem 2", system_of(data, "fleet"), 2),
                                       ("Problem 1, binding wifi", system_of(binding_network(data), "binding"), 1)):
            for limit in limits:
                w = time.perf_counter()
                plan = solve(system, problem, "exact", time_limit=limit)
                wall = time.perf_counter() - w
                ok = check_plan(system, plan) or "ok" if plan.objective is not None else plan.reason
                print(f"| {label} | {n} x {c} | {limit:g} | {wall:.2f} | {plan.status} | {plan.objective} | "
                      f"{plan.bound} | {ok} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="200x20,500x50,1000x100")
    ap.add_argument("--limits", default="10,30,60", help="seconds per solver, one per size")
    ap.add_argument("--random", type=int, default=5, help="random case-study-like instances (limit 10 s)")
    ap.add_argument("--cpsat-python", default=None, help="a Python with ortools installed (else no CP-SAT rows)")
    ap.add_argument("--no-highs-above", type=int, default=10_000_000,
                    help="skip plain HiGHS above this many nodes x computers")
    ap.add_argument("--time-limits", default=None,
                    help="only the --time-limit table: these limits (e.g. 1,2,5,10,30) at every size, from the CLI")
    ap.add_argument("--wifi", choices=("also", "only", "no"), default="also",
                    help="the 1,180-node fleet whose access points bind (issue 22): also, only it, or not")
    ap.add_argument("--wifi-limit", type=float, default=60.0, help="seconds per exact solver on the wifi fleet")
    ap.add_argument("--wifi-plus", type=float, default=10.0, help="greedy+'s time budget on the wifi fleet")
    ap.add_argument("--wifi-parts", default="solvers,p2,cli", help="solvers (greedy, greedy+, highs, exact), p2, cli")
    args = ap.parse_args()
    t = time.perf_counter()
    if args.wifi != "no":
        wifi(args.wifi_limit, args.wifi_plus, set(args.wifi_parts.split(",")))
        if args.wifi == "only":
            print(f"\ntotal {time.perf_counter() - t:.1f} s")
            return 0
    sizes = [(int(s.split("x")[0]), int(s.split("x")[1])) for s in args.sizes.split(",") if s]
    if args.time_limits:
        time_limits(sizes, [float(v) for v in args.time_limits.split(",")])
        other_paths(sizes, [float(v) for v in args.time_limits.split(",")])
        return 0
    limits = [float(v) for v in args.limits.split(",")]
    for (n, c), limit in zip(sizes, limits, strict=True):
        data = fleet_instance(n, c)
        run_instance(f"fleet_instance({n}, {c})", system_of(data, f"fleet-{n}x{c}"), limit, args.cpsat_python,
                     n * c <= args.no_highs_above)
        if (n, c) == sizes[-1]:
            problem2(system_of(data, f"fleet-{n}x{c}"), limit)
            cli_run(data, limit)
    for seed in range(args.random):
        run_instance(f"random_instance(Random({seed}))", system_of(random_instance(random.Random(seed)), f"r{seed}"),
                     10.0, args.cpsat_python, True)
    print(f"\ntotal {time.perf_counter() - t:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
