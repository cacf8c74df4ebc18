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


def test_rq3_leaves_out_an_instance_without_a_problem_1_optimum(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The 14:34 run of 2026-11-28: instance 4 had no Problem 1 plan at headroom auto (robot1
    would need 20.11 of 20 units), and RQ3 stopped the pipeline on a KeyError after 21 minutes.
    Now RQ3 records the failure, forces nothing from the missing plan and deploys nothing."""
    deployed: list[Any] = []
    monkeypatch.setattr(cs, "deploy", lambda *a, **k: deployed.append(a))
    monkeypatch.setattr(cs, "FAILED", [])
    rows = cs.rq3(tmp_path, tmp_path / "app", {2: {}, 4: {"p1-greedy": tmp_path / "g.json"}}, None, None)
    assert rows == [] and deployed == []
    assert [(f["instance"], f["plan"]) for f in cs.FAILED] == [(2, "rq3"), (4, "rq3")]
    assert not list((tmp_path / "rq3").iterdir())  # no forced plan written


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


DRAFT = {"nodes": [
    {"name": "robot1_camera", "topics": ["/robot1/camera/image_raw"],
     "settings": [{"value": 10.0, "cpu": 0.8, "performance": 100}]},
    {"name": "robot1_people", "input": "/robot1/camera/image_raw", "topics": ["/robot1/people/found"],
     "settings": [{"value": 1.1, "cpu": 0.5, "cpu_per_hz": 2.0, "performance": 85}]},
    {"name": "robot1_smooth", "input": "/robot1/camera/image_raw", "topics": ["/robot1/smooth/image"],
     "settings": [{"value": 7, "cpu": 0.0, "cpu_per_hz": 0.3, "performance": 55}]}],
    "edges": []}


def test_each_robot_declares_its_two_chains_and_the_budget_only_where_asked() -> None:
    budgeted = cs.instance_system(cs.INSTANCES[3], DRAFT, {"p95": 90.0}, budgeted=(3,))
    assert budgeted["chains"] == [
        {"name": "robot1_people", "topics": ["/robot1/camera/image_raw", "/robot1/people/found"],
         "budget_ms": {"p95": 90.0}},
        {"name": "robot1_smooth", "topics": ["/robot1/camera/image_raw", "/robot1/smooth/image"]},
        {"name": "robot2_people", "topics": ["/robot2/camera/image_raw", "/robot2/people/found"],
         "budget_ms": {"p95": 90.0}},
        {"name": "robot2_smooth", "topics": ["/robot2/camera/image_raw", "/robot2/smooth/image"]}]
    free = cs.instance_system(cs.INSTANCES[3], DRAFT, {"p95": 90.0}, budgeted=(1,))
    assert all("budget_ms" not in c for c in free["chains"]) and len(free["chains"]) == 4
    # every chain's topics are the instance's nodes' own topics
    topics = {t for n in budgeted["nodes"] for t in n["topics"]}
    assert all(c["topics"][1] in topics for c in budgeted["chains"])
    assert len(cs.BUDGET_INSTANCES) >= 2  # the issue: a budget that binds on at least two instances


def _chain(name: str, p50: float | None, p95: float | None, pred: tuple[float, float] | None,
           budget: float | None = None) -> dict[str, Any]:
    c: dict[str, Any] = {"name": name, "matched": 100, "p50_s": None if p50 is None else p50 / 1e3,
                         "p95_s": None if p95 is None else p95 / 1e3}
    if pred is not None:
        c["predicted_ms"] = {"p50": pred[0], "p95": pred[1]}
    if budget is not None:
        c["budget_ms"] = {"p95": budget}
    return c


def test_rq2l_rows_summary_and_line_against_a_hand_count() -> None:
    """Two deployments (a third plan shares the first), one no-headroom contrast left out:
    the errors and the budgets counted by hand."""
    val_a = {"chains": [_chain("robot1_people", 50.0, 80.0, (55.0, 60.0), budget=100.0),
                        _chain("robot1_smooth", 10.0, 16.0, (13.0, 14.0))]}
    val_b = {"chains": [_chain("robot1_people", 100.0, 200.0, (80.0, 250.0), budget=190.0),
                        _chain("robot1_smooth", 40.0, None, (30.0, 35.0))]}
    val_c = {"chains": [_chain("robot1_people", 1.0, 1.0, (900.0, 900.0), budget=1.0)]}
    rows = [{**_row("i1/run-a", "p1-exact", 1.0), "chains": cs.chain_rows(val_a)},
            {**_row("i1/run-a", "p2-exact", 1.0), "chains": cs.chain_rows(val_a)},
            {**_row("i1/run-b", "p1-greedy", 1.0), "chains": cs.chain_rows(val_b)},
            {**_row("i1/run-n", "p1-exact-nomargin", 1.0), "chains": cs.chain_rows(val_c)}]
    lat = cs.latency_rows(rows)
    assert [(r["run"], r["chain"]) for r in lat] == [("i1/run-a", "robot1_people"), ("i1/run-a", "robot1_smooth"),
                                                    ("i1/run-b", "robot1_people"), ("i1/run-b", "robot1_smooth")]
    assert lat[0]["p95_ms"] == pytest.approx(80.0) and lat[0]["pred_p95_ms"] == 60.0 \
        and lat[0]["budget_p95_ms"] == 100.0
    got = cs.latency_summary(lat)
    # p50: measured >= 20 ms: a 5/50, b 20/100, b-smooth 10/40 -> (10 + 20 + 25) / 3 %; a-smooth 10 ms: 3 ms off
    assert got["p50"]["error_pct"] == pytest.approx((10 + 20 + 25) / 3)
    assert got["p50"]["n_small"] == 1 and got["p50"]["error_ms_small"] == pytest.approx(3.0)
    # p95: a 20/80 = 25 %, b 50/200 = 25 %; a-smooth 16 ms: 2 ms off; b-smooth not measured
    assert got["p95"]["error_pct"] == pytest.approx(25.0) and got["p95"]["n_pct"] == 2
    assert got["p95"]["error_ms_small"] == pytest.approx(2.0)
    # budgets: a 80 <= 1.05 x 100 held; b 200 > 1.05 x 190 = 199.5 broken
    assert (got["budgets_held"], got["budgets"], got["chain_deployments"]) == (1, 2, 4)
    line = cs.latency_line("2026-11-27 18:00 UTC", got)
    assert line.startswith("full run 2026-11-27 18:00 UTC: latency p50 |error| 18.3 % p95 |error| 25.0 % "
                           "over 4 chain-deployments; budgets held 1 of 2")
    section = "\n".join(cs.rq2l_lines(rows, "2026-11-27 18:00"))
    assert "### RQ2-L" in section \
        and "| 1 | p1-greedy | robot1_people | 80.0 | 100.0 | 250.0 | 200.0 | 190 | **no** |" in section
    assert "This run 2026-11-27 18:00 UTC: latency p50 |error| 18.3 %" in section
    assert "nomargin" not in section


def test_chain_rows_take_prediction_and_budget_from_the_plan_when_validation_lacks_them() -> None:
    plan = {"chains": [{"name": "robot1_people", "predicted_ms": {"p50": 40.0, "p95": 70.0},
                        "budget_ms": {"p50": 60.0, "p95": 120.0}}]}
    (row,) = cs.chain_rows({"chains": [_chain("robot1_people", 45.0, 75.0, None)]}, plan)
    assert (row["pred_p50_ms"], row["pred_p95_ms"], row["budget_p50_ms"], row["budget_p95_ms"]) \
        == (40.0, 70.0, 60.0, 120.0)
    (bare,) = cs.chain_rows({"chains": [_chain("robot1_people", 45.0, 75.0, None)]})
    assert bare["pred_p95_ms"] is None and cs.latency_summary([bare])["chain_deployments"] == 0


def test_rq3_kept_errors_in_points_per_node() -> None:
    rows = [{"kept": [{"node": "robot1_people", "predicted": 0.35, "measured": 0.24},
                      {"node": "robot1_smooth", "predicted": 0.65, "measured": 0.65}]},
            {"kept": [{"node": "robot1_people", "predicted": 0.5, "measured": 0.55}]}]
    got = cs.kept_errors(rows)
    assert got["people"]["n"] == 2 and got["people"]["mean_abs_points"] == pytest.approx((11 + 5) / 2)
    assert got["smooth"]["mean_abs_points"] == pytest.approx(0.0)


def test_the_budget_is_chosen_on_the_fitted_model_to_bind_and_be_kept(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """binding_budget: the unbudgeted plan predicts 300 ms p95; a plan exists for a budget of
    250 ms or more (a fake solve): the given 200 and 0.8 x 300 = 240 cannot be kept, 0.9 x 300 can.
    It never fits: each try is the fitted model with the budget written into its people chains
    (and nothing else of the model changed)."""
    fitted = {"format": 1, "system": {"nodes": [], "chains": [
        {"name": "robot1_people", "topics": ["/robot1/camera/image_raw", "/robot1/people/found"]},
        {"name": "robot1_smooth", "topics": ["/robot1/camera/image_raw", "/robot1/smooth/image"]}]},
        "fits": {"x": 1}}
    model = tmp_path / "model.json"
    model.write_text(json.dumps(fitted))
    tried: list[float | None] = []
    calls: list[str] = []

    class Done:
        def __init__(self, code: int) -> None:
            self.returncode, self.stderr = code, "error: infeasible\n"

    def fake_sh(args: Any, *, ok: tuple[int, ...] = (0,)) -> Done:
        words = [str(a) for a in args]
        calls.append(words[1])
        doc = json.loads(Path(words[2]).read_text())
        assert doc["fits"] == fitted["fits"]
        by_name = {c["name"]: c for c in doc["system"]["chains"]}
        assert "budget_ms" not in by_name["robot1_smooth"]
        budget = (by_name["robot1_people"].get("budget_ms") or {}).get("p95")
        tried.append(budget)
        if budget is not None and budget < 250:
            return Done(2)
        out = Path(words[words.index("--out") + 1])
        out.write_text(json.dumps({"chains": [{"name": "robot1_people", "predicted_ms": {"p50": 100, "p95": 300}}]}))
        return Done(0)

    monkeypatch.setattr(cs, "sh", fake_sh)
    (tmp_path / "i").mkdir()
    chosen = cs.binding_budget(tmp_path / "i", cs.INSTANCES[1], model, {"p95": 200.0})
    assert chosen == {"p95": 270.0}
    assert tried == [None, 200.0, 240.0, 270.0]
    assert set(calls) == {"solve"}  # no fit per budget
    cs.with_budget(model, tmp_path / "b.json", chosen)
    assert json.loads((tmp_path / "b.json").read_text())["system"]["chains"][0]["budget_ms"] == {"p95": 270.0}


def test_rq4_recovery_is_never_a_window_that_could_not_read_some_node() -> None:
    """watch's overall over the readable nodes only (`unreadable` listed) judges part of the
    plan: it is neither the recovery nor a window within the goal."""
    import casestudy_rq4 as rq4

    log = [{"t": 100.0, "applied": "sent", "changes": [], "objective_before": 80.0, "objective_after": 85.0}]

    def w(t: float, dev: float, unreadable: list[str] | None = None) -> dict[str, Any]:
        overall: dict[str, Any] = {"expected": 85.0, "measured": 85.0 * (1 - dev / 100), "deviation_pct": dev}
        if unreadable:
            overall["unreadable"] = unreadable
        return {"t": t, "seconds": 5.0, "overall": overall, "alarms": []}

    ws = [w(110.0, 0.5, ["robot2_camera"]), w(115.0, 1.0), w(120.0, 9.0)]
    out = rq4.recovery(ws, log, 90.0, 80.0)
    assert out["recover_s"] == 115.0 - 90.0 and out["within_share"] == round(1 / 3, 2)
    assert rq4.recovery(ws[:1], log, 90.0, 80.0)["recover_s"] is None


def test_rq4_old_plan_after_the_change_stops_where_the_re_plan_was_sent(tmp_path: Path) -> None:
    """Both watchers watch one deploy: once the adapt watcher's re-plan is sent, the alone
    watcher's windows measure the re-planned nodes against the old plan, so "the old plan
    measured after the change" takes only the windows that began before it."""
    import casestudy_rq4 as rq4

    def w(t: float, measured: float, alarm: bool) -> dict[str, Any]:
        return {"t": t, "seconds": 5.0, "overall": {"expected": 80.0, "measured": measured, "deviation_pct": 1.0},
                "alarms": [{"node": "cam", "quantity": "rate_hz", "line": "alarm: node cam"}] if alarm else []}

    (tmp_path / "alone").mkdir()
    (tmp_path / "adapt").mkdir()
    alone = [w(95.0, 80.0, False), w(100.0, 70.0, False), w(105.0, 60.0, True), w(110.0, 62.0, True),
             w(115.0, 90.0, True), w(120.0, 95.0, True)]
    (tmp_path / "alone" / "windows.jsonl").write_text("".join(json.dumps(x) + "\n" for x in alone))
    (tmp_path / "adapt" / "windows.jsonl").write_text("".join(json.dumps(x) + "\n" for x in alone))
    log = {"t": 109.0, "asked_t": 105.5, "applied": "sent", "changes": ["cam: moved"], "objective_before": 80.0,
           "objective_after": 66.0}
    (tmp_path / "adapt" / "adapt.jsonl").write_text(json.dumps(log) + "\n")
    res = rq4.analyse({"t_change": 98.0, "t_until": 200.0}, tmp_path, {"objective": 80.0})
    assert res["alone"]["t"] == 105.0 and res["adapt"]["replan_t"] == 109.0
    # 105 and 110 (began at 105 < 109) measured the old plan; 115 and 120 the re-planned one
    assert res["old_windows"] == 2 and res["old_measured_after"] == (60.0 + 62.0) / 2
    assert rq4.goals(res)["not_worse"] is True  # 66 predicted >= 61 measured
    (tmp_path / "adapt" / "adapt.jsonl").write_text("")  # no re-plan: every window from the detection on
    res = rq4.analyse({"t_change": 98.0, "t_until": 200.0}, tmp_path, {"objective": 80.0})
    assert res["old_windows"] == 4 and res["old_measured_after"] == (60.0 + 62.0 + 90.0 + 95.0) / 4
    # two passes (the alone watcher in a deployment of its own, nothing re-planning it): every
    # window from its own detection on, on its own clock, whatever the adapt pass did
    (tmp_path / "adapt" / "adapt.jsonl").write_text(json.dumps(log) + "\n")
    alone2 = [w(1000.0 + x["t"], x["overall"]["measured"], bool(x["alarms"])) for x in alone]
    (tmp_path / "alone" / "windows.jsonl").write_text("".join(json.dumps(x) + "\n" for x in alone2))
    res = rq4.analyse({"t_change": 98.0, "t_until": 200.0, "alone_t_change": 1098.0, "alone_t_until": 1200.0},
                      tmp_path, {"objective": 80.0})
    assert res["alone"]["t"] == 1105.0 and res["alone"]["windows"] == 2
    assert res["old_windows"] == 4 and res["old_measured_after"] == (60.0 + 62.0 + 90.0 + 95.0) / 4
    assert res["adapt"]["replan_t"] == 109.0 and rq4.goals(res)["not_worse"] is False  # 66 < 76.75
    # the same re-plan, held back by --adapt's guard (it predicted less than the running plan
    # measured): the old plan ran on, nothing was made worse, and the table says it was kept
    kept = {**log, "applied": "not sent: it predicts Σ w·P 66, below the 76 the running plan measured in "
                              "window(s) 2-3: the running plan is kept"}
    (tmp_path / "adapt" / "adapt.jsonl").write_text(json.dumps(kept) + "\n")
    res = rq4.analyse({"t_change": 98.0, "t_until": 200.0, "alone_t_change": 1098.0, "alone_t_until": 1200.0},
                      tmp_path, {"objective": 80.0})
    assert rq4.kept_running(res["adapt"]) and rq4.goals(res)["not_worse"] is True
    stale = {**log, "applied": "not sent: the plan in force changed while it was refitted (a -> b)"}
    assert not rq4.kept_running({**res["adapt"], "applied": stale["applied"]})


def test_rq4_the_old_plan_under_the_operator_s_rate_is_judged_against_the_rates_it_then_runs() -> None:
    """Eq 10 against the operator plan (the camera at its new rate and the rates it gives the
    nodes it drives), not against the old plan's: a detector kept up at 7.5 Hz is its setting's
    performance, not 1.5 times it."""
    import casestudy_rq4 as rq4

    def node(w: float, p: float, hz: float) -> dict[str, Any]:
        return {"weight": w, "performance": p, "topics": {"/x": {"frequency_hz": hz}, "/y": {"frequency_hz": None}}}

    old = {"nodes": {"cam": node(0.25, 60.0, 5.0), "det": node(0.5, 80.0, 5.0), "lone": {"weight": 0.25,
                                                                                        "performance": 100.0}}}
    op = {"nodes": {"cam": node(0.25, 90.0, 7.5), "det": node(0.5, 80.0, 7.5), "lone": old["nodes"]["lone"]}}
    window = {"nodes": {"cam": {"measured_hz": 7.5}, "det": {"measured_hz": 6.0}}}
    # against the old plan: the camera 60 x 1.5, the detector 80 x 1.2 (credited for frames
    # it was never planned to get); against the operator plan: 90 x 1, 80 x 0.8
    assert rq4.against(old, window) == 0.25 * 90.0 + 0.5 * 96.0 + 25.0
    assert rq4.against(op, window) == 0.25 * 90.0 + 0.5 * 64.0 + 25.0
    assert rq4.against(op, {"nodes": {"cam": {"measured_hz": 7.5}}}) is None  # the detector unread


class _FakeHost:
    """A host whose speed follows a list, one reading per measure(); time moves only by sleep()."""

    def __init__(self, speeds: list[float]) -> None:
        self.speeds, self.now, self.reads = list(speeds), 0.0, 0

    def measure(self) -> float:
        self.reads += 1
        return self.speeds.pop(0)

    def sleep(self, s: float) -> None:
        self.now += s

    def clock(self) -> float:
        return self.now


def test_speed_gate_waits_while_the_host_is_slow_and_stops_at_its_limits() -> None:
    # the sweep ran at 0.76: the floor is 0.85 x 0.76 = 0.646
    host = _FakeHost([0.45, 0.50, 0.74, 0.2])
    got = cs.speed_gate(0.76, host.measure, host.sleep, host.clock, wait_s=120, budget_s=900, step_s=5)
    assert got == {"speed": 0.74, "waited_s": 10.0, "held": True} and host.reads == 3
    host = _FakeHost([1.2, 0.80])  # faster than 0.76 / 0.85 = 0.894 is off speed too
    assert cs.speed_gate(0.76, host.measure, host.sleep, host.clock, wait_s=120, budget_s=900, step_s=5) == {
        "speed": 0.80, "waited_s": 5.0, "held": True}
    host = _FakeHost([0.75])  # at speed: measured once, no wait
    assert cs.speed_gate(0.76, host.measure, host.sleep, host.clock, wait_s=120, budget_s=900, step_s=5) == {
        "speed": 0.75, "waited_s": 0.0, "held": True}
    host = _FakeHost([0.4] * 100)  # slow throughout: gives up at the per-deployment limit
    got = cs.speed_gate(0.76, host.measure, host.sleep, host.clock, wait_s=12, budget_s=900, step_s=5)
    assert got == {"speed": 0.4, "waited_s": 10.0, "held": False}
    host = _FakeHost([0.4] * 100)  # ... or at what is left of the run's budget
    got = cs.speed_gate(0.76, host.measure, host.sleep, host.clock, wait_s=120, budget_s=4, step_s=5)
    assert got == {"speed": 0.4, "waited_s": 0.0, "held": False} and host.reads == 1
    assert cs.speed_gate(None, host.measure, host.sleep, host.clock, wait_s=120, budget_s=900)["held"]


def test_sweep_speed_is_the_median_of_the_manifests_factors(tmp_path: Path) -> None:
    from perfros_bag.characterisation.manifest import write_manifest

    entries = [{"path": f"r{k}.bag", "cpu": f"r{k}.cpu.csv", "computer": "vm", "settings": {"a": k}, "speed_factor": f}
               for k, f in enumerate([0.77, 0.41, 0.75, 0.78])]
    write_manifest(tmp_path / "manifest.yaml", entries)
    assert cs.sweep_speed(tmp_path / "manifest.yaml") == pytest.approx((0.75 + 0.77) / 2)
    write_manifest(tmp_path / "none.yaml", [{k: v for k, v in e.items() if k != "speed_factor"} for e in entries])
    assert cs.sweep_speed(tmp_path / "none.yaml") is None


def test_latency_split_by_the_hosts_speed_against_a_hand_count() -> None:
    def row(speed: float | None, meas: float, pred: float) -> dict[str, Any]:
        return {"speed_factor": speed, "p50_ms": meas, "pred_p50_ms": pred, "p95_ms": meas, "pred_p95_ms": pred}

    rows = [row(0.76, 100.0, 110.0), row(0.70, 200.0, 180.0), row(0.45, 300.0, 150.0), row(None, 100.0, 100.0),
            row(0.95, 100.0, 130.0)]
    split = cs.latency_by_speed(rows, 0.8)  # at speed: 0.68-0.941
    assert split is not None and split["floor"] == pytest.approx(0.68) and split["ceiling"] == pytest.approx(0.8 / 0.85)
    assert split["at_speed"]["p50"]["error_pct"] == pytest.approx((10.0 + 10.0) / 2)
    assert split["off_speed"]["p50"]["error_pct"] == pytest.approx((50.0 + 0.0 + 30.0) / 3)
    assert split["at_speed"]["chain_deployments"] == 2 and split["off_speed"]["chain_deployments"] == 3
    line = cs.speed_split_line(split)
    assert line is not None and "at speed p50 10.0 %" in line and "off speed p50 26.7 %" in line
    assert cs.latency_by_speed(rows, None) is None


def test_at_speed_and_the_nearest_attempt() -> None:
    assert cs.at_speed(0.70, 0.76) and not cs.at_speed(0.60, 0.76) and not cs.at_speed(0.95, 0.76)
    assert cs.at_speed(None, 0.76) and cs.at_speed(0.1, None)  # nothing to hold to
    a, b, c = Path("a"), Path("b"), Path("c")
    assert cs.nearest_speed([(0.45, a), (0.95, b), (0.60, c)], 0.76) == b  # log ratio 0.221 < 0.237 < 0.524
    assert cs.nearest_speed([(None, a), (None, b)], 0.76) == b and cs.nearest_speed([(0.5, a)], None) == a


def test_an_off_speed_deployment_is_deployed_again_and_the_nearest_kept(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    speeds = [0.41, 0.74]  # the first attempt ran on the slow host, the second at the sweep's speed

    def fake_sh(args: list[object], *, ok: tuple[int, ...] = (0,)) -> Any:
        out = Path(str(args[args.index("--out") + 1]))
        out.mkdir(parents=True)
        (out / "deploy.json").write_text(json.dumps({"speed_factor": speeds.pop(0)}))
        (out / "validation.json").write_text(json.dumps({"attempt": 2 - len(speeds), "chains": []}))
        return None

    monkeypatch.setattr(cs, "sh", fake_sh)
    monkeypatch.setattr(cs, "wait_for_speed", lambda label: None)
    monkeypatch.setitem(cs.SPEED_GATE, "reference", 0.76)
    monkeypatch.setattr(cs, "SPEED_REPEATS", 2)
    monkeypatch.setattr(cs, "REDEPLOYS", [])
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"nodes": {}, "computers": {}}))
    run_dir = tmp_path / "run-p1"
    got = cs.deploy(plan, 1, tmp_path / "model.json", run_dir, tmp_path, None, "instance 1 p1")  # type: ignore[arg-type]
    assert got["record"]["speed_factor"] == 0.74 and got["validation"] == {"attempt": 2, "chains": []}
    assert json.loads((tmp_path / "run-p1.off-speed-1" / "deploy.json").read_text())["speed_factor"] == 0.41
    assert cs.REDEPLOYS == [{"deployment": "instance 1 p1", "speeds": [0.41, 0.74], "kept": 1,
                             "set_aside_chains": []}]
    # off speed every time: the nearest attempt is the run, the others stay beside it
    speeds[:] = [0.45, 0.95, 0.60]
    cs.REDEPLOYS.clear()
    run2 = tmp_path / "run-p2"
    got = cs.deploy(plan, 1, tmp_path / "model.json", run2, tmp_path, None, "instance 1 p2")  # type: ignore[arg-type]
    assert got["record"]["speed_factor"] == 0.95
    assert sorted(json.loads((tmp_path / f"run-p2.off-speed-{k}" / "deploy.json").read_text())["speed_factor"]
                  for k in (1, 3)) == [0.45, 0.60]
    assert cs.REDEPLOYS == [{"deployment": "instance 1 p2", "speeds": [0.45, 0.95, 0.60], "kept": 1,
                             "set_aside_chains": []}]


def test_a_deployments_speed_is_its_reading_farther_from_the_sweeps() -> None:
    assert cs.run_speed({"speed_factor": 0.75, "speed_factor_end": 0.45}, 0.76) == 0.45  # slowed mid-run
    assert cs.run_speed({"speed_factor": 0.74, "speed_factor_end": 0.78}, 0.76) == 0.74
    assert cs.run_speed({"speed_factor": 0.60, "speed_factor_end": None}, 0.76) == 0.60
    assert cs.run_speed({"speed_factor": None}, 0.76) is None and cs.run_speed({"speed_factor": 0.5}, None) == 0.5
