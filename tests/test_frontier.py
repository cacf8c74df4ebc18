"""The performance / server-capacity frontier (``solve --pareto``): its range from Problem 2,
each point against the exact solver and the checker, and the CLI's files and errors."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.casestudy.instances import table2_instance
from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.solver import fixed_choices, solve
from perfros_bag.solver.check import check_plan
from perfros_bag.solver.frontier import (
    FrontierPoint,
    capacity_range,
    frontier,
    frontier_document,
    monotone,
    parse_range,
    with_server_capacity,
)
from perfros_bag.system.plan import Status
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Problem, System

runner = CliRunner()


def table2(i: int) -> System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(table2_instance(i), f"table2-{i}.yaml")


def test_parse_range() -> None:
    assert parse_range("auto") == (None, None, 21)
    assert parse_range("300:600") == (300.0, 600.0, 21)
    assert parse_range(":600:5") == (None, 600.0, 5)
    for bad in ("600:300", "300:300", "a:b", "300", "300:600:1", "-1:5", "1:inf"):
        with pytest.raises(InputError):
            parse_range(bad)


def test_range_ends_are_where_plans_start_and_performance_stops_rising() -> None:
    system = table2(2)
    low, high = capacity_range(system)
    assert low < high
    # below the Problem 2 minimum at the lowest settings no plan exists; at it one does
    below = solve(with_server_capacity(system, low - 1), 1, "exact")
    assert below.status == "infeasible"
    at_low = solve(with_server_capacity(system, low), 1, "exact")
    assert at_low.status == "optimal"
    # at the top every node runs its best setting: Σ w·max P, the most there is
    choices = fixed_choices(system, Problem.PERFORMANCE)
    best = sum(system.node[n].weight * max(c.performance for c in opts) for n, opts in choices.items())
    at_high = solve(with_server_capacity(system, high), 1, "exact")
    assert at_high.objective == pytest.approx(best, rel=1e-9)
    # and one unit less cannot reach it
    just_below = solve(with_server_capacity(system, high - 1), 1, "exact")
    assert just_below.objective is not None and just_below.objective < best - 1e-9


def test_frontier_points_are_proven_and_rise() -> None:
    system = table2(4)
    points = frontier(system, points=5)
    values = [p.objective for p in points]
    assert all(p.status == "optimal" and p.gap == 0 for p in points)
    assert all(a is not None and b is not None and a <= b + 1e-9 for a, b in zip(values, values[1:], strict=False))
    for p in points[1:4]:
        scaled = with_server_capacity(system, p.capacity)
        assert scaled.computer["server"].capacity == pytest.approx(p.capacity)
        plan = solve(scaled, 1, "exact")
        assert check_plan(scaled, plan) == []
        assert plan.objective == pytest.approx(p.objective)


def test_cli_pareto_writes_json_and_png(tmp_path: Path) -> None:
    path = tmp_path / "inst2.yaml"
    path.write_text(yaml.safe_dump(table2_instance(2)))
    out = tmp_path / "frontier.json"
    result = runner.invoke(app, ["solve", str(path), "--method", "exact", "--pareto", "::6", "-o", str(out)])
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    assert len(doc["points"]) == 6 and doc["servers"] == ["server"]
    assert all(p["status"] == "optimal" and p["gap"] == 0 for p in doc["points"])
    assert (tmp_path / "frontier.png").read_bytes().startswith(b"\x89PNG")
    low, high = capacity_range(table2(2))
    assert doc["points"][0]["server_capacity"] == pytest.approx(low)
    assert doc["points"][-1]["server_capacity"] == pytest.approx(high)


@pytest.mark.parametrize("spec", ["500:400", "400:400", "x:5", "300:600:1001", "300:600:1000000"])
def test_cli_pareto_bad_range_is_one_line(tmp_path: Path, spec: str) -> None:
    path = tmp_path / "inst1.yaml"
    path.write_text(yaml.safe_dump(table2_instance(1)))
    out = tmp_path / "frontier.json"
    result = runner.invoke(app, ["solve", str(path), "--method", "exact", "--pareto", spec, "-o", str(out)])
    assert result.exit_code == 2
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "Traceback" not in result.output
    assert not out.exists()
    result = runner.invoke(app, ["solve", str(path), "--problem", "2", "--pareto", "auto"])
    assert result.exit_code == 2 and result.stderr.startswith("error:")


def test_too_many_points_are_refused_before_any_solve(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 33, item 7: 1,000,000 points ran past 60 s and 2 GB; the cap (1,000) is checked
    as the range is read: not one point is solved, nor the range's ends."""
    import perfros_bag.solver.frontier as frontier_mod

    def no_solve(*args: object, **kwargs: object) -> None:
        raise AssertionError("a point was solved")

    monkeypatch.setattr(frontier_mod, "solve", no_solve)
    path = tmp_path / "inst2.yaml"
    path.write_text(yaml.safe_dump(table2_instance(2)))
    for spec in ("300:600:1000000", "::200000"):
        result = runner.invoke(app, ["solve", str(path), "--method", "greedy", "--pareto", spec, "--json"])
        assert result.exit_code == 2 and "at most 1,000 points" in result.stderr, result.output
        assert result.stdout == ""
    with pytest.raises(InputError, match="at most 1,000 points"):
        frontier(table2(2), low=300, high=600, points=1001)


def test_pareto_keeps_the_headroom_at_every_point(tmp_path: Path) -> None:
    """Issue 33, item 3: --pareto with --headroom 0.5 was the frontier without it. Each point
    must equal Problem 1 on the system with every computer's capacity halved (the robots'
    and the servers' at that point), solved exactly here without any headroom."""
    data = table2_instance(2)
    path = tmp_path / "inst2.yaml"
    path.write_text(yaml.safe_dump(data))
    runs = {}
    for headroom in ("0", "0.5"):
        result = runner.invoke(app, ["solve", str(path), "--method", "exact", "--pareto", "500:800:4",
                                     "--headroom", headroom, "--json"])
        assert result.exit_code == 0, result.output
        runs[headroom] = json.loads(result.stdout)
    assert runs["0.5"]["headroom"] == 0.5 and runs["0"]["headroom"] == 0
    for point in runs["0.5"]["points"]:
        halved = json.loads(json.dumps(data))
        for c in halved["computers"]:
            c["capacity"] = (point["server_capacity"] if c["kind"] == "server" else c["capacity"]) * 0.5
        plan = solve(parse_system(halved, "halved.yaml"), 1, "exact")
        assert point["objective"] == pytest.approx(plan.objective, rel=1e-6), point
    assert [p["objective"] for p in runs["0.5"]["points"]] != [p["objective"] for p in runs["0"]["points"]]


def test_report_frontier_section_and_reader(tmp_path: Path) -> None:
    from perfros_bag.report.html import build_report
    from perfros_bag.solver.frontier import read_frontier

    path = tmp_path / "inst1.yaml"
    path.write_text(yaml.safe_dump(table2_instance(1)))
    out = tmp_path / "frontier.json"
    result = runner.invoke(app, ["solve", str(path), "--method", "exact", "--pareto", "::3", "-o", str(out)])
    assert result.exit_code == 0, result.output
    doc = read_frontier(out)
    result = runner.invoke(app, ["report", "--out", str(tmp_path / "rep"), "--frontier", str(out)])
    assert result.exit_code == 0, result.output
    page = (tmp_path / "rep" / "index.html").read_text()
    assert 'id="frontier"' in page and (tmp_path / "rep" / "frontier.png").read_bytes().startswith(b"\x89PNG")
    assert page.count("<tr>") >= len(doc["points"])
    # the reader names the broken place
    doc["points"][1]["status"] = "great"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"points\[1\]\.status"):
        read_frontier(bad)
    bad.write_text(json.dumps({"format": "perfros-bag frontier 1", "points": [{"server_capacity": "<b>"}]}))
    with pytest.raises(InputError, match="server_capacity"):
        build_report(tmp_path / "rep2", frontier=bad)
    assert not (tmp_path / "rep2").exists()


def test_range_with_several_servers_in_proportion() -> None:
    from perfros_bag.casestudy.instances import fleet_instance

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        system = parse_system(fleet_instance(40, 20, seed=2, continuous=False), "fleet.yaml")
    servers = [c for c in system.computers if c.kind == "server"]
    assert len(servers) == 2
    low, high = capacity_range(system)
    scaled = with_server_capacity(system, low)
    total = sum(c.capacity or 0 for c in servers)
    for c in servers:  # each server keeps its share
        assert scaled.computer[c.name].capacity == pytest.approx(low * (c.capacity or 0) / total)
    at_low = solve(scaled, 1, "exact")
    assert at_low.status == "optimal" and check_plan(scaled, at_low) == []
    choices = fixed_choices(system, Problem.PERFORMANCE)
    best = sum(system.node[n].weight * max(c.performance for c in opts) for n, opts in choices.items())
    at_high = solve(with_server_capacity(system, high), 1, "exact")
    assert at_high.objective == pytest.approx(best, rel=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 3, 6])
def test_enumerated_frontier_matches_the_milp_point_by_point(seed: int) -> None:
    import math
    import random

    from perfros_bag.casestudy.instances import random_instance
    from perfros_bag.solver.frontier import frontier_values

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        system = parse_system(random_instance(random.Random(seed), robots=(1, 2)), "random.yaml")
    low, high = capacity_range(system)
    table = frontier_values(system, high)  # Table II-sized: (2 robots + 1) ** 10 groups at most
    assert table is not None
    values, scale = table
    rng = random.Random(seed)
    for capacity in [low - 1, low, high, *(rng.randint(int(low), int(high)) for _ in range(3))]:
        plan = solve(with_server_capacity(system, capacity), 1, "exact", time_limit=60)
        v = values[int(math.floor(capacity * scale + 1e-6))] if capacity >= 0 else -math.inf
        if plan.status == "infeasible":
            assert v == -math.inf
        else:
            assert plan.status == "optimal"
            assert v == pytest.approx(plan.objective, rel=1e-9, abs=1e-9)


def test_a_heuristic_frontier_states_no_bound_and_never_falls(tmp_path: Path) -> None:
    """Issue 22: greedy's frontier on Table II instance 6 stated its own objective as a proven
    bound (gap 0 %) and fell from 415 to 444 units. Now: no bound, no gap, and each point at
    least the best plan of any smaller capacity (carried forward, and said so), never above
    the exact frontier."""
    system = table2(6)
    path = tmp_path / "t6.yaml"
    path.write_text(yaml.safe_dump(table2_instance(6)))
    out = tmp_path / "frontier.json"
    result = runner.invoke(app, ["solve", str(path), "--pareto", "auto", "-o", str(out)])  # default method: greedy
    assert result.exit_code == 0, result.output
    assert "0.000 %" not in result.output
    doc = json.loads(out.read_text())
    assert doc["method"] == "greedy"
    exact = {round(p.capacity, 6): p for p in frontier(system, method="exact")}
    running = -1.0
    carried = 0
    for p in doc["points"]:
        assert p["bound"] is None and p["gap"] is None
        raw = solve(with_server_capacity(system, p["server_capacity"]), 1, "greedy").objective
        assert raw is not None
        if raw < running - 1e-12:  # the greedy's own plan here is worse than one that fits
            carried += 1
            assert p["carried_from"] is not None and p["carried_from"] < p["server_capacity"]
            assert p["objective"] == pytest.approx(running)
        else:
            assert p["carried_from"] is None and p["objective"] == pytest.approx(raw)
        running = max(running, raw)
        best = exact[round(p["server_capacity"], 6)]
        assert best.status == "optimal" and best.objective is not None
        assert p["objective"] <= best.objective + 1e-9
    assert carried >= 1  # the instance of the issue: greedy's plan at 444 is worse than at 415


def test_the_picture_labels_only_proven_bounds(monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib.axes

    from perfros_bag.report.frontier_plots import plot_frontier

    labels: list[str] = []
    real = matplotlib.axes.Axes.plot

    def spy(self: matplotlib.axes.Axes, *args: object, **kw: object) -> object:
        labels.append(str(kw.get("label")))
        return real(self, *args, **kw)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", spy)
    system = table2(6)
    heuristic = frontier(system, method="greedy", points=4)
    plot_frontier(frontier_document(system, heuristic, "greedy")["points"])
    assert labels and not any("bound" in label for label in labels)
    labels.clear()
    unproven = [FrontierPoint(300.0, Status.FEASIBLE, 70.0, 72.0, 1.0),
                FrontierPoint(400.0, Status.OPTIMAL, 80.0, 80.0, 1.0)]
    plot_frontier(frontier_document(system, unproven, "exact")["points"])
    assert "proven bound" in labels


def test_monotone_carries_plans_up_and_bounds_down() -> None:
    """A plan found at a smaller capacity fits at a larger one; a bound proven at a larger
    capacity holds at a smaller one. Points without a plan below every plan stay as they are."""
    pts = [FrontierPoint(100.0, Status.INFEASIBLE, None, None, 0.1),
           FrontierPoint(200.0, Status.FEASIBLE, 50.0, 60.0, 0.1),
           FrontierPoint(300.0, Status.FEASIBLE, 45.0, 58.0, 0.1),  # worse plan, tighter bound
           FrontierPoint(400.0, Status.FEASIBLE, 55.0, 55.0, 0.1)]
    out = monotone(pts)
    assert [p.objective for p in out] == [None, 50.0, 50.0, 55.0]
    assert [p.carried_from for p in out] == [None, None, 200.0, None]
    assert [p.bound for p in out] == [None, 55.0, 55.0, 55.0]
    assert [str(p.status) for p in out] == ["infeasible", "feasible", "feasible", "optimal"]
    heuristic = monotone([FrontierPoint(1.0, Status.FEASIBLE, 3.0, None, 0.0),
                          FrontierPoint(2.0, Status.FEASIBLE, 2.0, None, 0.0)])
    assert [p.bound for p in heuristic] == [None, None] and [p.gap for p in heuristic] == [None, None]
    assert heuristic[1].objective == 3.0 and heuristic[1].carried_from == 1.0
