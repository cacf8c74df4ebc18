"""pipelines/casestudy_real.py without ROS: RQ2 counted over distinct deployments, the full
run's line for docs/casestudy-real.md, and RQ3's forced plans marked so deploy accepts them."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from perfros_bag.errors import InputError
from perfros_bag.system.planfile import is_forced, load_plan, parse_plan

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "pipelines"))

import casestudy_real as cs  # noqa: E402


def _row(run: str, plan: str, dev: float) -> dict[str, Any]:
    return {"run": run, "plan": plan, "deviation_pct": dev, "instance": 1, "problem": 1}


def test_rq2_counts_each_deployment_once_with_the_plan_that_deployed_it() -> None:
    rows = [_row("i1/run-a", "p1-greedy", 4.0), _row("i1/run-a", "p1-exact", 9.0),  # same deployment
            _row("i1/run-b", "p2-greedy", -2.0), _row("i2/run-a", "p1-greedy", 1.0), _row("i2/run-a", "p2", 7.0)]
    summary = cs.rq2_distinct(rows)
    assert summary == {"deployments": 3, "plans": 5, "mean_abs_deviation_pct": (4.0 + 2.0 + 1.0) / 3}
    assert cs.full_run_line("2026-11-26 12:00 UTC", summary) == (
        "full run 2026-11-26 12:00 UTC: RQ2 mean |deviation| 2.33 % over 3 distinct deployments")
    assert cs.rq2_distinct([]) == {"deployments": 0, "plans": 0, "mean_abs_deviation_pct": None}


def test_full_run_lines_are_kept_across_runs_outside_the_results_section(tmp_path: Path) -> None:
    docs = tmp_path / "page.md"
    docs.write_text("# page\n\n<!-- casestudy-real-results:begin -->\nold\n<!-- casestudy-real-results:end -->\n")
    cs.append_full_run(docs, "full run A: RQ2 mean |deviation| 1.00 % over 12 distinct deployments")
    cs.write_section(docs, "casestudy-real", "new results", tmp_path, (), "t")
    cs.append_full_run(docs, "full run B UTC: failed after 3.0 min: boom")
    text = docs.read_text()
    assert "new results" in text and "old" not in text
    block = text.split(cs.FULL_RUNS_BEGIN, 1)[1].split(cs.FULL_RUNS_END, 1)[0]
    assert [line for line in block.splitlines() if line.strip()] == [
        "full run A: RQ2 mean |deviation| 1.00 % over 12 distinct deployments",
        "full run B UTC: failed after 3.0 min: boom"]


def test_rq3_forced_plans_exceed_their_computer_and_are_marked(tmp_path: Path) -> None:
    """The forced builder on instance 2's Table-like system: a setting above the robot's
    capacity gives a plan the reader accepts because it says ``"forced": true``."""
    from perfros_bag.solver import solve
    from perfros_bag.system.planfile import save_plan
    from perfros_bag.system.systemfile import load_system

    src = ROOT / "fixtures" / "casestudy" / "instance2.yaml"
    d = tmp_path / "inst"
    d.mkdir()
    import yaml

    # forced() reads the fitted model beside the plan: here the system itself, as JSON
    (d / "model.json").write_text(json.dumps(yaml.safe_load(src.read_text())))
    system = load_system(d / "model.json")
    base = d / "plan.json"
    save_plan(solve(system, 1, "exact"), base)
    robot = next(c.name for c in system.computers if c.kind == "robot")
    # the most CPU-hungry node at its most CPU-hungry setting, forced onto the robot
    hungry = max(system.nodes, key=lambda n: max(s.cpu for s in n.settings))
    top = max(hungry.settings, key=lambda s: s.cpu)
    assert top.cpu > (system.computer[robot].capacity or 0)
    path = cs.forced(tmp_path, "over", base, {hungry.name: (robot, top.value)})
    plan = load_plan(path)
    assert is_forced(plan) and plan.nodes[hungry.name].computer == robot
    assert plan.nodes[hungry.name].cpu == top.cpu > (plan.computers[robot].capacity or 0)
    unmarked = json.loads(path.read_text())
    del unmarked["forced"]
    with pytest.raises(InputError, match=f"node '{hungry.name}': 'cpu' .* exceeds the capacity"):
        parse_plan(unmarked, str(path))
