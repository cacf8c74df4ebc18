"""The paper's Fig. 5 as a table: Table II instances 1-6, both problems, greedy and greedy+
against the exact optimum, with solve times.

    .venv/bin/python pipelines/paper.py [--out out/paper] [--time-limit 120]

Writes OUT/fig5.md (the table), OUT/fig5.json (every number) and OUT/fig5.png (bars of
heuristic / optimum), and prints the table. Every plan goes through the independent
checker; a violation fails the run. When the exact solver is not available the optimum
columns say so and only the heuristics run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import Progress

from perfros_bag.casestudy.instances import TABLE_II
from perfros_bag.fileio import atomic_write_json, atomic_write_text
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.systemfile import load_system

ROOT = Path(__file__).resolve().parent.parent
HEURISTICS = ("greedy", "greedy+")


def exact_available() -> bool:
    try:
        import perfros_bag.solver.exact  # noqa: F401
    except ImportError:
        return False
    return True


def run(instances: Path, time_limit: float, err: Console) -> list[dict[str, Any]]:
    methods = [*HEURISTICS, *(["exact"] if exact_available() else [])]
    rows: list[dict[str, Any]] = []
    with Progress(console=err, transient=True) as bar:
        task = bar.add_task("solving", total=len(TABLE_II) * 2 * len(methods))
        for i in TABLE_II:
            path = instances / f"instance{i}.yaml"
            system = load_system(path)
            for problem in (1, 2):
                row: dict[str, Any] = {"instance": i, "problem": problem, "nodes": len(system.nodes),
                                       "computers": len(system.computers)}
                for method in methods:
                    bar.update(task, description=f"instance {i} · problem {problem} · {method}")
                    plan = solve(system, problem, method, time_limit=time_limit if method == "exact" else None)
                    bad = check_plan(system, plan)
                    if bad:
                        raise SystemExit(f"error: {path}: {method} plan fails the checker: {bad}")
                    row[method] = {"status": plan.status, "objective": plan.objective, "bound": plan.bound,
                                   "solve_s": plan.solve_s}
                    bar.advance(task)
                opt = row.get("exact", {})
                for method in HEURISTICS:
                    h = row[method]["objective"]
                    proven = opt.get("status") == "optimal" and opt.get("objective")
                    row[method]["ratio"] = h / opt["objective"] if proven and h is not None else None
                rows.append(row)
    return rows


def fmt_ratio(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.4f}"


def fmt_s(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def table_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    out = []
    for r in rows:
        opt = r.get("exact")
        out.append([
            str(r["instance"]), str(r["problem"]), f"{r['nodes']}/{r['computers']}",
            "n/a" if opt is None else f"{opt['objective']:.4f} ({opt['status']})",
            f"{r['greedy']['objective']:.4f}", fmt_ratio(r["greedy"]["ratio"]),
            f"{r['greedy+']['objective']:.4f}", fmt_ratio(r["greedy+"]["ratio"]),
            fmt_s(r["greedy"]["solve_s"]), fmt_s(r["greedy+"]["solve_s"]),
            fmt_s(None if opt is None else opt["solve_s"]),
        ])
    for problem in (1, 2):
        mine = [r for r in rows if r["problem"] == problem]
        avg = []
        for m in HEURISTICS:
            ratios = [r[m]["ratio"] for r in mine if r[m]["ratio"] is not None]
            avg.append(fmt_ratio(sum(ratios) / len(ratios)) if ratios else "n/a")
        out.append(["mean", str(problem), "", "", "", avg[0], "", avg[1], "", "", ""])
    return out


HEAD = ["instance", "problem", "nodes/computers", "optimum (exact)", "greedy", "greedy/opt", "greedy+",
        "greedy+/opt", "greedy s", "greedy+ s", "exact s"]


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "# Fig. 5 of the paper as a table: heuristic / optimum on Table II",
        "",
        "Problem 1 maximises Σ w·P (ratio <= 1 is the share of the optimum reached);",
        "Problem 2 minimises the total server capacity (ratio >= 1 is the excess).",
        "Made by `make paper` (pipelines/paper.py).",
        "",
        "| " + " | ".join(HEAD) + " |",
        "|" + "---|" * len(HEAD),
    ]
    lines += ["| " + " | ".join(r) + " |" for r in table_rows(rows)]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, problem in zip(axes, (1, 2), strict=True):
        mine = [r for r in rows if r["problem"] == problem]
        xs = range(len(mine))
        for k, m in enumerate(HEURISTICS):
            ys = [r[m]["ratio"] if r[m]["ratio"] is not None else 0.0 for r in mine]
            ax.bar([x + (k - 0.5) * 0.38 for x in xs], ys, width=0.38, label=m)
        ax.axhline(1.0, color="black", linewidth=0.8)
        ax.set_xticks(list(xs), [str(r["instance"]) for r in mine])
        ax.set_xlabel("Table II instance")
        ax.set_ylabel("heuristic / optimum")
        ax.set_title(f"Problem {problem}: " + ("max Σ w·P" if problem == 1 else "min server capacity"))
        lo = min([r[m]["ratio"] for r in mine for m in HEURISTICS if r[m]["ratio"] is not None] or [1.0])
        hi = max([r[m]["ratio"] for r in mine for m in HEURISTICS if r[m]["ratio"] is not None] or [1.0])
        ax.set_ylim(min(lo, 1.0) - 0.02, max(hi, 1.0) + 0.03)
        ax.legend(loc="upper center", ncol=2, fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "paper")
    ap.add_argument("--instances", type=Path, default=ROOT / "fixtures" / "casestudy")
    ap.add_argument("--time-limit", type=float, default=120.0, help="per exact solve (seconds)")
    args = ap.parse_args(argv)
    out, err = Console(), Console(stderr=True)
    rows = run(args.instances, args.time_limit, err)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / "fig5.json", rows)
    atomic_write_text(args.out / "fig5.md", markdown(rows))
    plot(rows, args.out / "fig5.png")
    print(markdown(rows))
    out.print(f"written: {args.out / 'fig5.md'}, fig5.json, fig5.png", highlight=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
