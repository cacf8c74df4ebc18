"""The paper's case study on real ROS 1, end to end (section V-C: RQ2 and RQ3).

    .venv/bin/python pipelines/casestudy.py [--out out/casestudy] [--duration 20]
        [--char-duration 15] [--instances 1,2,3,4,5,6] [--units-per-core 400] [--docs docs/casestudy.md]

1. characterisation: instance 1's nodes at every Table I setting of one configurable node
   (the others at their minimum), all on one uncapped computer -> OUT/characterisation/
   (run.bag + run.cpu.csv per run, manifest.yaml);
2. ``perfros-bag characterise`` -> ``fit`` (Table I's expert performance levels) per
   instance (nodes of one type share instance 1's measurements) -> ``solve`` Problem 1
   (greedy, and exact for the optimum) and Problem 2 (greedy) for instances 1-6;
3. every greedy plan deployed with ``perfros-bag casestudy run`` (computers as CPU-capped
   cgroups: 100 units = 1/units_per_core*100 core) and checked with ``perfros-bag validate``;
4. RQ3: instance 1 with the robot's nodes kept on the robot, the plan (baseline) and
   Table III's Mod. 1-3 (parameters forced above the plan): predicted robot CPU vs its
   capacity, and the run's measured CPU, throttling, frequencies and performance.

Results: OUT/results.json, OUT/fig5.png, OUT/rq3.png and the results section of
``docs/casestudy.md`` (with the commands and the date). A run whose run.json exists is
reused: delete OUT (or a run folder) to measure again.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from _common import interrupt_on_sigterm, read_rows, run_shown, write_rows, write_section
from rich.console import Console

from perfros_bag.casestudy.launcher import RunConfig, run_plan
from perfros_bag.fileio import atomic_write_json, atomic_write_text
from perfros_bag.system.plan import Assignment, Plan, Status
from perfros_bag.system.planfile import load_plan, save_plan
from perfros_bag.system.rules import build_plan
from perfros_bag.system.systemfile import load_system
from perfros_bag.system.types import Choice, Problem, System

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).with_name("perfros-bag")
FIXTURES = ROOT / "fixtures" / "casestudy"
# Table III: node kind -> value for Mod. 1, 2, 3 (the paper's baseline: 80 goals, 200 particles, 15 Hz)
TABLE_III = {"model": (200, 3500, 10000), "amcl": (300, 1000, 3000), "navigation": (16, 18, 20)}
err = Console(stderr=True)
COMMANDS: list[str] = []
BAR: list[Any] = []  # [rich Progress, task id] while the pipeline runs


def sh(args: Sequence[object], *, ok: tuple[int, ...] = (0,)) -> subprocess.CompletedProcess[str]:
    return run_shown(args, root=ROOT, program=BIN, commands=COMMANDS, console=err, ok=ok)


def kind(name: str) -> str:
    return name.rstrip("0123456789")


def table1_choice(node: Any, index: int) -> Choice:
    rows = sorted(node.settings, key=lambda s: (s.value if s.value is not None else 0.0))
    s = rows[index]
    return Choice(index, s.cpu, s.performance, s.value, s.frequency_hz, s.bandwidth_kBps, s.topics)


def rel(p: Path | str) -> str:
    return str(p).replace(str(ROOT) + "/", "")


RUN_TIMES: list[str] = []


def deploy(system: System, system_path: Path, plan: Plan, out: Path, cfg: RunConfig, label: str) -> dict[str, Any]:
    plan_path = out.with_suffix(".plan.json")
    if (out / "run.json").exists():
        err.print(f"reusing {out}")
        record: dict[str, Any] = json.loads((out / "run.json").read_text())
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        save_plan(plan, plan_path)
        err.print(f"[bold]{label}[/]: running {cfg.duration:g} s -> {out}")
        if BAR:
            BAR[0].update(BAR[1], description=label)
        record = run_plan(system, plan, out, cfg, system_path=system_path)
    cap = record["cpu_cap"]
    COMMANDS.append(f"perfros-bag casestudy run --system {rel(system_path)} --plan {rel(plan_path)} "
                    f"--duration {record['duration_s']:g} --out {rel(out)}"
                    + (" --no-cap" if "--no-cap" in cap.get("reason", "") else "")
                    + f" --units-per-core {cap['units_per_core']:g}")
    if record.get("started"):
        RUN_TIMES.append(record["started"])
    if BAR:
        BAR[0].advance(BAR[1])
    return record


# ---------------------------------------------------------------- 1. characterisation

def characterise(out: Path, args: argparse.Namespace) -> Path:
    sys_path = FIXTURES / "instance1.yaml"
    system = load_system(sys_path)
    char = out / "characterisation"
    char.mkdir(parents=True, exist_ok=True)
    configurable = [n for n in system.nodes if len(n.settings) > 1]
    entries = []
    cfg = RunConfig(duration=args.char_duration, units_per_core=args.units_per_core, cap=False)
    for target in configurable:
        for idx in range(len(target.settings)):
            choice = {n.name: table1_choice(n, idx if n.name == target.name else 0) for n in system.nodes}
            place = {n.name: "server" for n in system.nodes}
            plan = build_plan(system, Assignment(place, choice), problem=Problem.PERFORMANCE, method="characterisation",
                              status=Status.FEASIBLE)
            name = f"{target.name}_{choice[target.name].value:g}"
            deploy(system, sys_path, plan, char / name, cfg, f"characterise {name}")
            entries.append({"path": f"{name}/run.bag", "cpu": f"{name}/run.cpu.csv", "computer": "server",
                            "settings": {n.name: choice[n.name].value for n in configurable}})
    import yaml

    manifest = {"system": os.path.relpath(sys_path, char), "recordings": entries}
    atomic_write_text(char / "manifest.yaml", yaml.safe_dump(manifest, sort_keys=False))
    csv_path = out / "characterisation.csv"
    sh([BIN, "characterise", char, "--system", sys_path, "--out", csv_path])
    return csv_path


def csv_for_instance(rows: list[dict[str, str]], system: System) -> list[dict[str, str]]:
    """Instance 1's measured rows copied to every node of the same type in ``system``."""
    by_kind: dict[str, list[str]] = {}
    for n in system.nodes:
        by_kind.setdefault(kind(n.name), []).append(n.name)
    out = []
    for row in rows:
        src = row["node"]
        for dst in by_kind.get(kind(src), []):
            new = dict(row)
            new["node"] = dst
            new["topic"] = row["topic"].replace(f"/{src}/", f"/{dst}/")
            out.append(new)
    return out


# ---------------------------------------------------------------- 2. fit + solve

def fit_and_solve(out: Path, char_csv: Path, instances: list[int]) -> dict[int, dict[str, Path]]:
    fields, rows = read_rows(char_csv)
    plans: dict[int, dict[str, Path]] = {}
    for i in instances:
        sys_path = FIXTURES / f"instance{i}.yaml"
        system = load_system(sys_path)
        d = out / f"instance{i}"
        d.mkdir(parents=True, exist_ok=True)
        inst_csv = d / "characterisation.csv"
        write_rows(inst_csv, fields, csv_for_instance(rows, system))
        model = d / "model.json"
        sh([BIN, "fit", sys_path, inst_csv, "--out", model] + (["--plots", d / "fit-plots"] if i == 1 else []))
        plans[i] = {}
        for problem, method in ((1, "greedy"), (1, "exact"), (2, "greedy")):
            p = d / f"plan-p{problem}-{method}.json"
            sh([BIN, "solve", model, "--problem", str(problem), "--method", method, "--out", p])
            plans[i][f"p{problem}-{method}"] = p
    return plans


# ---------------------------------------------------------------- 3. deploy + validate

def validate(run_dir: Path, plan: Path, system: Path) -> dict[str, Any]:
    out = run_dir / "validation.json"
    sh([BIN, "validate", run_dir / "run.bag", plan, "--system", system, "--json", "--out", out], ok=(0, 1))
    return json.loads(out.read_text())


def summarise(val: dict[str, Any], record: dict[str, Any]) -> dict[str, Any]:
    ratios = [abs(t["ratio"] - 1) * 100 for n in val["nodes"] for t in n["topics"] if t.get("ratio") is not None]
    comps = {c["computer"]: {"capacity": c["capacity"], "expected": c["cpu_expected"], "measured": c["cpu_measured"]}
             for c in val["computers"]}
    thr = {c: (t["nr_throttled"] / t["nr_periods"] if t.get("nr_periods") else None)
           for c, t in record.get("throttling", {}).items()}
    return {"expected": val["overall"]["expected"], "measured": val["overall"]["measured"],
            "deviation_pct": val["overall"]["deviation_pct"],
            "freq_dev_mean_pct": sum(ratios) / len(ratios) if ratios else None,
            "cpu_cap": record["cpu_cap"]["mode"], "units_per_core": record["cpu_cap"]["units_per_core"],
            "cores": sum(record["cpu_cap"]["cores"].values()), "computers": comps, "throttled": thr,
            "nodes": {n["node"]: {"value": n["value"], "p_expected": n["p_expected"], "p_measured": n["p_measured"],
                                  "f_ratio": n["ratio"]} for n in val["nodes"]}}


def scaled(plan: Plan, args: argparse.Namespace) -> RunConfig:
    """The run's scale: ``--units-per-core``, or more units per core when the plan's computers
    would need more than ``--max-cores`` (Problem 2 sizes big servers): every capacity shrinks
    by the same factor, so the instance fits on this machine."""
    total = sum(c.capacity or 0.0 for name, c in plan.computers.items()
                if any(pn.computer == name for pn in plan.nodes.values()))
    upc = max(args.units_per_core, total / args.max_cores)
    return RunConfig(duration=args.duration, units_per_core=round(upc, 1))


def deploy_all(out: Path, plans: dict[int, dict[str, Path]], args: argparse.Namespace) -> list[dict[str, Any]]:
    results = []
    for i, ps in plans.items():
        sys_path = FIXTURES / f"instance{i}.yaml"
        system = load_system(sys_path)
        optimum = load_plan(ps["p1-exact"]).objective
        for key in ("p1-greedy", "p2-greedy"):
            plan = load_plan(ps[key])
            run_dir = out / f"instance{i}" / f"run-{key}"
            cfg = scaled(plan, args)
            record = deploy(system, sys_path, plan, run_dir, cfg, f"instance {i} {key}")
            val = validate(run_dir, ps[key], sys_path)
            row = {"instance": i, "problem": plan.problem, "method": plan.method, "objective": plan.objective,
                   "optimum": optimum if plan.problem == 1 else None, **summarise(val, record)}
            results.append(row)
            err.print(f"instance {i} P{plan.problem}: expected {row['expected']:.2f} measured {row['measured']:.2f} "
                      f"({row['deviation_pct']:.2f} %)")
    return results


# ---------------------------------------------------------------- 4. RQ3

def forced_choice(system: System, name: str, value: float) -> Choice:
    """What the fitted model predicts for ``name`` at parameter ``value`` (the relations
    parameter->cpu/performance/frequency/bandwidth, unclamped in CPU: an overload must show)."""
    rel = system.node[name].relations

    def at(key: str) -> float | None:
        r = rel.get(key)
        return None if r is None else r(min(max(value, r.domain[0]), r.domain[1]))

    cpu = rel["parameter->cpu"](value)
    return Choice(0, cpu, at("parameter->performance") or 0.0, value, at("parameter->frequency"),
                  at("parameter->bandwidth"))


def baseline_choice(system: System, plan: Plan, name: str) -> Choice:
    pn = plan.nodes[name]
    topic = next(iter(pn.topics.values()), None)
    return Choice(0, pn.cpu, pn.performance, pn.value, topic.frequency_hz if topic else None,
                  topic.bandwidth_kBps if topic else None)


def rq3(out: Path, args: argparse.Namespace) -> list[dict[str, Any]]:
    from perfros_bag.solver import solve

    d = out / "rq3"
    d.mkdir(parents=True, exist_ok=True)
    model_doc = json.loads((out / "instance1" / "model.json").read_text())
    for node in model_doc["system"]["nodes"]:
        if re.fullmatch(r"(environment|model|planner|amcl|navigation)1", node["name"]):
            node["residence"] = ["robot1"]
    model_path = d / "model-robot.json"
    atomic_write_json(model_path, model_doc)
    system = load_system(model_path)
    baseline = solve(system, 1, "greedy")
    save_plan(baseline, d / "plan-baseline.json")
    COMMANDS.append(f"perfros-bag solve {rel(model_path)} --problem 1 --method greedy "
                    f"--out {rel(d / 'plan-baseline.json')}"
                    "   # RQ3 baseline (done in-process)")
    truth_path = FIXTURES / "instance1.yaml"
    truth = load_system(truth_path)
    cfg = RunConfig(duration=args.duration, units_per_core=args.units_per_core)
    configs: list[tuple[str, Plan]] = [("Baseline", baseline)]
    base_values = {n: pn.value for n, pn in baseline.nodes.items() if pn.value is not None}
    for m in range(3):
        values = {f"{k}1": max(float(v[m]), float(base_values.get(f"{k}1", 0.0))) for k, v in TABLE_III.items()}
        choice = {n: baseline_choice(system, baseline, n) for n in baseline.nodes}
        for name, v in values.items():
            choice[name] = forced_choice(system, name, v)
        placement = {n: pn.computer for n, pn in baseline.nodes.items()}
        plan = build_plan(system, Assignment(placement, choice), problem=Problem.PERFORMANCE,
                          method=f"forced (Table III Mod. {m + 1})", status=Status.FEASIBLE)
        configs.append((f"Mod. {m + 1}", plan))
    rows = []
    for label, plan in configs:
        slug = label.lower().replace(". ", "").replace(" ", "")
        run_dir = d / f"run-{slug}"
        record = deploy(truth, truth_path, plan, run_dir, cfg, f"RQ3 {label}")
        plan_path = run_dir.with_suffix(".plan.json")
        val = validate(run_dir, plan_path, truth_path)
        s = summarise(val, record)
        robot = plan.computers["robot1"]
        rows.append({"config": label, "values": {n: plan.nodes[n].value for n in ("model1", "amcl1", "navigation1")},
                     "robot_cpu_predicted": robot.cpu, "robot_capacity": robot.capacity,
                     "predicted_overload": robot.cpu > (robot.capacity or 0) + 1e-9,
                     "robot_cpu_measured": s["computers"]["robot1"]["measured"],
                     "robot_throttled": s["throttled"].get("robot1"),
                     **{k: s[k] for k in ("expected", "measured", "deviation_pct", "freq_dev_mean_pct", "cpu_cap")},
                     "nodes": s["nodes"]})
    return rows


# ---------------------------------------------------------------- report

def plots(out: Path, results: list[dict[str, Any]], rq3_rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, problem in zip(axes, (1, 2), strict=True):
        rows = [r for r in results if r["problem"] == problem]
        xs = list(range(len(rows)))
        ref = [r["optimum"] if problem == 1 and r["optimum"] else r["expected"] for r in rows]
        ax.bar([x - 0.2 for x in xs], [r["expected"] / f for r, f in zip(rows, ref, strict=True)], 0.4,
               label="expected")
        ax.bar([x + 0.2 for x in xs], [r["measured"] / f for r, f in zip(rows, ref, strict=True)], 0.4,
               label="measured")
        ax.set_xticks(xs, [str(r["instance"]) for r in rows])
        ax.set_xlabel("instance")
        ax.set_ylim(0.8, 1.05)
        ax.set_title(f"Problem {problem}: performance / " + ("optimum" if problem == 1 else "expected"))
        ax.axhline(1.0, color="grey", lw=0.8)
    axes[0].legend(loc="lower left")
    fig.tight_layout()
    fig.savefig(out / "fig5.png", dpi=110)
    plt.close(fig)
    if rq3_rows:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6))
        labels = [r["config"] for r in rq3_rows]
        xs = list(range(len(labels)))
        a1.bar([x - 0.2 for x in xs], [r["robot_cpu_predicted"] for r in rq3_rows], 0.4, label="predicted")
        a1.bar([x + 0.2 for x in xs], [r["robot_cpu_measured"] for r in rq3_rows], 0.4, label="measured")
        a1.axhline(rq3_rows[0]["robot_capacity"], color="red", lw=1, label="capacity")
        a1.set_xticks(xs, labels)
        a1.set_title("robot CPU (units)")
        a1.legend()
        a2.bar([x - 0.2 for x in xs], [r["expected"] for r in rq3_rows], 0.4, label="expected (model)")
        a2.bar([x + 0.2 for x in xs], [r["measured"] for r in rq3_rows], 0.4, label="measured (eq 10)")
        a2.set_xticks(xs, labels)
        a2.set_title("overall performance Σ w·P")
        a2.legend(loc="lower left")
        fig.tight_layout()
        fig.savefig(out / "rq3.png", dpi=110)
        plt.close(fig)


def markdown(results: list[dict[str, Any]], rq3_rows: list[dict[str, Any]], args: argparse.Namespace,
             argv: list[str]) -> str:
    def f(x: Any, nd: int = 2) -> str:
        return "-" if x is None else f"{x:.{nd}f}"

    span = f"{min(RUN_TIMES)} to {max(RUN_TIMES)}" if RUN_TIMES else "-"
    lines = [f"Runs recorded {span} (UTC), "
             f"report written {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}, on this machine "
             f"({args.units_per_core:g} CPU units per core: a robot of 100 = {100 / args.units_per_core:g} core, "
             f"the server of 400 = {400 / args.units_per_core:g} core; a deployment whose computers would need more "
             f"than {args.max_cores:g} cores is shrunk further, see the last column; {args.duration:g} s per run).", "",
             "### RQ2: expected vs measured (Fig. 5)", "",
             "| instance | problem | greedy objective | optimum | greedy/optimum | expected Σ w·P | measured Σ w·P "
             "| deviation % | mean freq. dev. % | CPU cap | cores (units/core) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        opt = r["optimum"]
        ratio = r["expected"] / opt if opt else None
        lines.append(f"| {r['instance']} | {r['problem']} | {f(r['objective'])} | {f(opt)} | {f(ratio, 4)} | "
                     f"{f(r['expected'])} | {f(r['measured'])} | {f(r['deviation_pct'])} | "
                     f"{f(r['freq_dev_mean_pct'])} | {r['cpu_cap']} | {r['cores']:.2f} ({r['units_per_core']:g}) |")
    for problem in (1, 2):
        devs = [r["deviation_pct"] for r in results if r["problem"] == problem]
        if devs:
            lines.append(f"\nProblem {problem}: mean deviation of measured from expected performance "
                         f"**{sum(devs) / len(devs):.2f} %** over {len(devs)} instances (paper: 2.5 %).")
    lines += ["", "Problem 2's objective is the server capacity it sized (CPU units).", "",
              "![expected vs measured](casestudy/fig5.png)", ""]
    if rq3_rows:
        lines += ["### RQ3: parameters forced above the plan (Table III), instance 1, robot nodes on the robot", "",
                  "| config | model goals | AMCL particles | nav. Hz | robot CPU predicted | capacity "
                  "| overload predicted "
                  "| robot CPU measured | robot throttled periods | expected Σ w·P | measured Σ w·P | deviation % |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rq3_rows:
            v = r["values"]
            thr = r["robot_throttled"]
            lines.append(f"| {r['config']} | {f(v['model1'], 0)} | {f(v['amcl1'], 0)} | {f(v['navigation1'], 1)} | "
                         f"{f(r['robot_cpu_predicted'], 1)} | {f(r['robot_capacity'], 0)} | "
                         f"{'yes' if r['predicted_overload'] else 'no'} | {f(r['robot_cpu_measured'], 1)} | "
                         f"{'-' if thr is None else f'{thr:.0%}'} | {f(r['expected'])} | {f(r['measured'])} | "
                         f"{f(r['deviation_pct'])} |")
        lines += ["", "![RQ3](casestudy/rq3.png)", ""]
    lines += ["### Commands", "", "```",
              f"make casestudy   # = .venv/bin/python pipelines/casestudy.py {' '.join(argv)}",
              *dict.fromkeys(COMMANDS), "```", ""]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "casestudy")
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--char-duration", type=float, default=15.0)
    ap.add_argument("--instances", default="1,2,3,4,5,6")
    ap.add_argument("--units-per-core", type=float, default=400.0)
    ap.add_argument("--max-cores", type=float, default=1.6,
                    help="shrink a deployment's capacities until its computers fit in this many cores")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs" / "casestudy.md")
    ap.add_argument("--skip-rq3", action="store_true")
    args = ap.parse_args(argv)
    interrupt_on_sigterm()
    instances = [int(x) for x in args.instances.split(",") if x.strip()]
    out: Path = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=err) as bar:
        BAR[:] = [bar, bar.add_task("runs", total=13 + 2 * len(instances) + (0 if args.skip_rq3 else 4))]
        char_csv = characterise(out, args)
        plans = fit_and_solve(out, char_csv, instances)
        results = deploy_all(out, plans, args)
        rq3_rows = [] if args.skip_rq3 or 1 not in instances else rq3(out, args)
        BAR.clear()
    atomic_write_json(out / "results.json", {"rq2": results, "rq3": rq3_rows,
                                             "args": vars(args) | {"out": str(out), "docs": str(args.docs)}})
    plots(out, results, rq3_rows)
    section = markdown(results, rq3_rows, args, argv)
    atomic_write_text(out / "results.md", section)
    if args.docs:
        write_section(args.docs, "casestudy", section, out, ("fig5.png", "rq3.png"), "Case study")
    err.print(section)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
