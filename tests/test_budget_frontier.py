"""Performance against a chain's latency budget (``solve --pareto-budget``): every point the
optimum at its budget (recomputed by brute force on a system written with that budget), the
frontier monotone, its ends where no plan starts and where the budget stops binding, and the
CLI's JSON, CSV and PNG and its bad input."""

from __future__ import annotations

import csv
import io
import json
import math
import random
import sys
from pathlib import Path

import matplotlib.image
import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.solver import fixed_choices, solve
from perfros_bag.solver.budget_frontier import budget_frontier, budget_range, parse_target
from perfros_bag.solver.check import check_plan
from perfros_bag.system.latency import fastest_bound
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_budgets import _instance  # noqa: E402

runner = CliRunner()


@pytest.mark.parametrize("seed", range(4))
def test_each_point_is_the_optimum_at_its_budget_and_the_frontier_never_falls(seed: int) -> None:
    system = parse_system(_instance(seed))
    chain, quantile = parse_target(system, "vision")
    assert quantile == "p95"
    points = budget_frontier(system, chain, quantile, points=6, method="exact")
    assert len(points) == 6
    for p in points:
        # independently: the system written with that budget, solved by brute force
        at = parse_system(_instance(seed, {"p95": p.budget_ms}))
        brute = solve(at, 1, "bruteforce")
        assert (p.objective is None) == (brute.status == "infeasible"), (seed, p.budget_ms)
        if p.objective is None:
            continue
        assert p.objective == pytest.approx(brute.objective, abs=1e-6)
        assert p.status == "optimal" and p.carried_from is None
        assert p.predicted_ms is not None and p.predicted_ms["p95"] <= p.budget_ms * (1 + 1e-6)
        plan = solve(at, 1, "exact")  # the plan behind the point, accepted by the checker at that budget
        assert check_plan(at, plan) == []
    found = [p.objective for p in points if p.objective is not None]
    assert found, "some budget of the range has a plan"
    assert all(b >= a - 1e-9 for a, b in zip(found, found[1:], strict=False))  # monotone
    first = next(i for i, p in enumerate(points) if p.objective is not None)
    assert all(p.objective is not None for p in points[first:])  # no plan only below some budget
    # the top of the range: the optimum without the budget, the chain's latency in it
    free = solve(system, 1, "exact")
    assert points[-1].objective == pytest.approx(free.objective)
    assert points[-1].budget_ms == pytest.approx(free.chains[0]["predicted_ms"]["p95"])
    # the bottom: the chain's lower bound over every plan
    bound = fastest_bound(system, chain, fixed_choices(system, Problem.PERFORMANCE, None, 1.0))
    assert bound is not None and points[0].budget_ms == pytest.approx(bound[1])


def test_a_heuristic_frontier_is_carried_so_it_never_falls() -> None:
    system = parse_system(_instance(2))
    chain, quantile = parse_target(system, "vision:p95")
    low, high = budget_range(system, chain, quantile)
    points = budget_frontier(system, chain, quantile, low=low, high=high, points=8, method="greedy")
    found = [p for p in points if p.objective is not None]
    assert all(b.objective >= a.objective - 1e-9 for a, b in zip(found, found[1:], strict=False))  # type: ignore[operator]
    for p in found:
        if p.carried_from is not None:  # the plan of a smaller budget, which keeps this one too
            assert p.carried_from < p.budget_ms
            assert p.predicted_ms is not None and p.predicted_ms["p95"] <= p.carried_from * (1 + 1e-6)


def test_a_p50_frontier_bounds_the_p50(tmp_path: Path) -> None:
    system = parse_system(_instance(1))
    chain, quantile = parse_target(system, "vision:p50")
    points = budget_frontier(system, chain, quantile, points=4, method="exact")
    for p in points:
        if p.predicted_ms is not None:
            assert p.predicted_ms["p50"] <= p.budget_ms * (1 + 1e-6)


def _front(tmp_path: Path, spec: str) -> tuple[Path, Path]:
    """system.yaml (instance 3) and the front.json of ``solve --pareto SPEC --pareto-budget vision``."""
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(_instance(3)))
    out = tmp_path / "front.json"
    res = runner.invoke(app, ["solve", str(path), "--method", "exact", "--pareto", spec, "--pareto-budget", "vision",
                              "-o", str(out)])
    assert res.exit_code == 0, res.output
    return path, out


def test_cli_writes_json_csv_and_png(tmp_path: Path) -> None:
    path, out = _front(tmp_path, "::5")
    doc = json.loads(out.read_text())
    assert doc["format"] == "perfros-bag budget frontier 1" and doc["chain"] == "vision" and doc["quantile"] == "p95"
    assert len(doc["points"]) == 5
    rows = list(csv.DictReader(io.StringIO((tmp_path / "front.csv").read_text())))
    assert len(rows) == 5
    for row, p in zip(rows, doc["points"], strict=True):
        assert float(row["budget_ms"]) == pytest.approx(p["budget_ms"])
        assert row["status"] == p["status"]
        if p["objective"] is None:
            assert row["objective"] == "" and row["predicted_p95_ms"] == ""
        else:
            assert float(row["objective"]) == pytest.approx(p["objective"])
            assert float(row["predicted_p95_ms"]) == pytest.approx(p["predicted_ms"]["p95"])
    image = matplotlib.image.imread(tmp_path / "front.png")  # decodes as a PNG
    assert image.shape[0] > 100 and image.shape[1] > 200
    res = runner.invoke(app, ["solve", str(path), "--method", "greedy+", "--pareto", "60:150:3", "--pareto-budget",
                              "vision:p95", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert [p["budget_ms"] for p in doc["points"]] == pytest.approx([60, 105, 150])


@pytest.mark.parametrize(("args", "says"), [
    (["--pareto-budget", "nosuch"], "no chain 'nosuch'"),
    (["--pareto-budget", "vision:p99"], "p50 or p95"),
    (["--pareto-budget", "vision", "--pareto", "0:50:3"], "not above 0"),
    (["--pareto-budget", "vision", "--pareto", "50:20"], "empty or inverted"),
    (["--pareto-budget", "vision", "--problem", "2"], "--pareto solves Problem 1"),
])
def test_bad_input_is_one_line_exit_2_nothing_written(tmp_path: Path, args: list[str], says: str) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(_instance(3)))
    out = tmp_path / "front.json"
    res = runner.invoke(app, ["solve", str(path), "--method", "exact", *args, "-o", str(out)])
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and says in lines[0], res.stderr
    assert list(tmp_path.iterdir()) == [path]


def test_points_are_evenly_spaced_between_the_given_ends() -> None:
    system = parse_system(_instance(0))
    chain, quantile = parse_target(system, "vision")
    low, high = 40.0 + random.Random(0).random(), 300.0
    points = budget_frontier(system, chain, quantile, low=low, high=high, points=4, method="greedy")
    assert [p.budget_ms for p in points] == pytest.approx([low + (high - low) * i / 3 for i in range(4)])
    assert all(math.isfinite(p.solve_s) for p in points)


def test_report_shows_a_budget_frontier_and_refuses_a_broken_one(tmp_path: Path) -> None:
    _, front = _front(tmp_path, "::4")
    out = tmp_path / "report"
    res = runner.invoke(app, ["report", "--frontier", str(front), "--out", str(out)])
    assert res.exit_code == 0, res.output
    page = (out / "index.html").read_text()
    assert "What latency costs: chain vision" in page and 'id="budget-frontier"' in page
    doc = json.loads(front.read_text())
    rows = page.split('id="budget-frontier-points"')[1].split("</table>")[0]
    assert rows.count("<tr>") == 1 + len(doc["points"])  # the header and one row a point
    assert rows.count(">optimal<") + rows.count(">infeasible<") == len(doc["points"])
    assert matplotlib.image.imread(out / "budget_frontier.png").shape[0] > 100
    doc["points"][1]["budget_ms"] = "fast"
    front.write_text(json.dumps(doc))
    res = runner.invoke(app, ["report", "--frontier", str(front), "--out", str(tmp_path / "r2")])
    assert res.exit_code == 2
    [line] = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert "points[1].budget_ms: not a finite number" in line and "front.json" in line
    assert not (tmp_path / "r2").exists()
