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


DRIVEN_SYSTEM = {
    "computers": [{"name": "robot1", "kind": "robot", "capacity": 20}, {"name": "server", "kind": "server",
                                                                          "capacity": 40}],
    "links": [{"between": ["robot1", "server"], "bandwidth_kBps": 3000}],
    "nodes": [
        {"name": "robot1_camera", "weight": 0.2, "residence": ["robot1"], "topics": ["/robot1/camera/image_raw"],
         "parameter": {"name": "publish_rate", "unit": "Hz"},
         "settings": [{"value": 5.0, "cpu": 0.4, "performance": 60, "frequency_hz": 5, "bandwidth_kBps": 1150},
                      {"value": 10.0, "cpu": 0.8, "performance": 100, "frequency_hz": 10, "bandwidth_kBps": 2300}]},
        {"name": "robot1_people", "weight": 0.8, "input": "/robot1/camera/image_raw",
         "topics": ["/robot1/people/found"], "parameter": {"name": "scale0", "unit": ""},
         "settings": [{"value": 1.1, "cpu": 0.5, "cpu_per_hz": 2.0, "performance": 85, "bytes_per_msg": 100},
                      {"value": 1.4, "cpu": 0.5, "cpu_per_hz": 0.8, "performance": 30, "bytes_per_msg": 100}]},
    ],
    "edges": [{"from": "robot1_camera", "to": "robot1_people"}],
}


def test_rq3_forced_plan_of_driven_nodes_follows_the_forced_camera_rate(tmp_path: Path) -> None:
    """A detector forced onto the robot with its camera forced to 10 Hz: its CPU is the
    data-flow rule's cpu + cpu_per_hz x 10, computed here from the system's numbers."""
    from perfros_bag.solver import solve
    from perfros_bag.system.planfile import save_plan
    from perfros_bag.system.systemfile import load_system

    d = tmp_path / "inst"
    d.mkdir()
    (d / "model.json").write_text(json.dumps(DRIVEN_SYSTEM))
    base = d / "plan.json"
    save_plan(solve(load_system(d / "model.json"), 1, "exact"), base)
    path = cs.forced(tmp_path, "over", base, {"robot1_camera": (None, 10.0), "robot1_people": ("robot1", 1.1)})
    plan = load_plan(path)
    people = plan.nodes["robot1_people"]
    assert people.computer == "robot1" and people.value == 1.1
    assert people.input_hz == 10.0
    assert people.cpu == pytest.approx(0.5 + 2.0 * 10.0)
    assert plan.computers["robot1"].cpu == pytest.approx(0.8 + 0.5 + 2.0 * 10.0)
    # at 5 Hz the same detector needs what the rule gives at 5 Hz
    path5 = cs.forced(tmp_path, "five", base, {"robot1_camera": (None, 5.0), "robot1_people": ("robot1", 1.1)})
    assert load_plan(path5).nodes["robot1_people"].cpu == pytest.approx(0.5 + 2.0 * 5.0)


def test_cpu_against_rate_reads_the_default_runs_and_the_drafted_line(tmp_path: Path) -> None:
    fields = ["recording", "node", "parameter", "value", "topic", "msgtype", "messages", "duration_s",
              "frequency_hz", "bandwidth_kBps", "cpu_units_mean", "cpu_units_p95", "cpu_samples"]

    def row(rec: str, node: str, value: str, cpu: str, topic: str = "", hz: str = "") -> dict[str, str]:
        r = dict.fromkeys(fields, "")
        r.update(recording=rec, node=node, value=value, cpu_units_mean=cpu, topic=topic, frequency_hz=hz)
        return r

    rows = []
    for rec, (rate, scale, kernel, people_cpu) in {"a": (5.0, 1.1, 7, 11.0), "b": (10.0, 1.1, 7, 21.0),
                                                   "c": (10.0, 1.4, 7, 9.0)}.items():
        rows += [row(rec, "robot1_camera", str(rate), "0.5"),
                 row(rec, "robot1_people", str(scale), str(people_cpu), "/robot1/people/found", str(rate)),
                 row(rec, "robot1_smooth", str(kernel), "3.0")]
    csv_path = tmp_path / "c.csv"
    cs.write_rows(csv_path, fields, rows)
    draft = {"nodes": [{"name": "robot1_people", "settings": [{"value": 1.1, "cpu": 1.0, "cpu_per_hz": 2.0}]},
                       {"name": "robot1_smooth", "settings": [{"value": 7, "cpu": 0.0, "cpu_per_hz": 0.3}]}]}
    got = cs.cpu_against_rate(csv_path, draft)
    assert [g["rate_hz"] for g in got] == [5.0, 10.0]  # run c has people at 1.4: not a default run
    assert got[0]["people"] == 11.0 and got[1]["people"] == 21.0 and got[1]["people_hz"] == 10.0
    assert got[0]["people_line"] == pytest.approx(1.0 + 2.0 * 5.0)
    assert got[1]["smooth_line"] == pytest.approx(0.3 * 10.0)


def test_rq3_kept_cell_states_predicted_and_measured_shares() -> None:
    row = {"kept": [{"node": "robot1_people", "predicted": 0.5, "measured": 0.53},
                    {"node": "robot1_smooth", "predicted": 1.0, "measured": 0.98}]}
    assert cs.kept_cell(row) == "people 50 / 53 %; smooth 100 / 98 %"
    assert cs.kept_cell({}) == "-"


def test_rq2_leaves_the_no_headroom_contrast_out_and_tune_shares_a_deployment() -> None:
    rows = [_row("i1/run-p1-exact", "p1-exact", 1.0), _row("i1/tune/round-1", "p1-tuned-r1", 1.5),
            _row("i1/run-p1-exact-nomargin", "p1-exact-nomargin", 9.0), _row("i1/run-p1-exact", "p2-exact", 3.0)]
    assert cs.rq2_distinct(rows) == {"deployments": 2, "plans": 3, "mean_abs_deviation_pct": (1.0 + 1.5) / 2}


def test_signature_ignores_float_noise_in_values() -> None:
    a = {"nodes": {"n": {"computer": "r", "value": 1.09375}}, "computers": {"r": {"capacity": 15.0}}}
    b = {"nodes": {"n": {"computer": "r", "value": 1.09375 + 1e-12}}, "computers": {"r": {"capacity": 15.0}}}
    c = {"nodes": {"n": {"computer": "r", "value": 1.1}}, "computers": {"r": {"capacity": 15.0}}}
    assert cs.signature(a) == cs.signature(b) != cs.signature(c)


def test_fairness_lines_state_each_cap_and_the_leftovers() -> None:
    doc = {"factors": [1.0, 1.25], "wall_s": 90.0, "leftover_processes": [], "leftover_cgroups": [],
           "nodes": {"people": {"executable": "people_detect", "need_cores": 0.416, "need_after_cores": 0.38,
                                "capped": [{"factor": 1.0, "kept": 0.912}, {"factor": 1.25, "kept": 1.0}]}}}
    lines = cs.fairness_lines(doc)
    assert "| people (people_detect) | 41.6 / 38.0 | 91.2 % | 100.0 % |" in lines
    assert any(line.startswith("Leftover processes: 0, leftover cgroups: 0") for line in lines)
