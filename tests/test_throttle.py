"""Throttles (a driven setting's ``max_frequency_hz`` with ``step: period``): the rule against
a message-by-message simulation of topic_tools' throttle written here from its source (a
message passes when more than 1/rate s have elapsed since the last one passed), the solvers
against an enumeration of the plans, the checker's copy, the reader's refusals, and ``init``
drafting a throttle from a sweep's runs."""

from __future__ import annotations

import copy
import itertools
import random
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.errors import InputError
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import STEP_AMBIGUOUS, Setting, driven_rates, step_ambiguous
from tests.test_init_driven import T0

pytestmark = pytest.mark.filterwarnings("ignore:.*weights sum to")


def simulated(f_in: float, rate: float, seconds: float = 400.0, jitter: float = 0.01, seed: int = 1) -> float:
    """topic_tools/throttle on a stream at ``f_in`` Hz whose arrivals jitter by up to
    ``jitter`` of a period: the passed messages per second over ``seconds``."""
    rnd = random.Random(seed)
    period, last, passed = 1.0 / rate, -1e9, []
    for k in range(int(seconds * f_in)):
        t = k / f_in + rnd.uniform(-jitter, jitter) / f_in
        if t - last > period:
            passed.append(t)
            last = t
    return (len(passed) - 1) / (passed[-1] - passed[0])


def _throttle(rate: float) -> Setting:
    return Setting(0.0, 100.0, value=rate, cpu_per_hz=0.1, max_frequency_hz=rate, step="period")


@pytest.mark.parametrize("f_in", [10.0, 15.0, 30.0, 7.3])
@pytest.mark.parametrize("rate", [0.9, 2.0, 3.3, 4.2, 6.0, 9.0, 12.0, 20.0, 2.5, 3.0, 5.0, 7.5, 10.0, 15.0])
def test_the_step_rule_is_the_throttle_away_from_whole_ratios(f_in: float, rate: float) -> None:
    out = driven_rates(_throttle(rate), f_in)[1]
    sim = simulated(f_in, rate)
    n = f_in / rate
    if step_ambiguous(_throttle(rate), f_in):  # a whole ratio: jitter decides between two steps
        whole = round(n)
        assert abs(n - whole) <= STEP_AMBIGUOUS
        assert f_in / (whole + 1) * 0.99 <= sim <= f_in / max(whole, 1) * 1.01
    else:
        assert sim == pytest.approx(out, rel=0.01)
        assert out <= min(f_in, rate) + 1e-9


def test_without_step_the_cap_stays_a_minimum() -> None:
    s = Setting(0.0, 100.0, cpu_per_hz=0.1, max_frequency_hz=6.0)
    assert driven_rates(s, 15.0)[1] == 6.0 and driven_rates(s, 4.0)[1] == 4.0
    assert not step_ambiguous(s, 12.0)


SYSTEM: dict[str, Any] = {
    "computers": [{"name": "robot", "kind": "robot", "capacity": 100}],
    "nodes": [
        {"name": "camera", "weight": 0.2, "parameter": {"name": "publish_rate"}, "topics": ["/camera/image_raw"],
         "settings": [{"value": r, "cpu": 1 + 0.1 * r, "performance": 100 * r / 15, "frequency_hz": r,
                       "bandwidth_kBps": 230 * r} for r in (10, 15)]},
        {"name": "throttle", "weight": 0.4, "input": "/camera/image_raw", "parameter": {"name": "rate"},
         "topics": ["/camera/image_throttled"],
         "settings": [{"value": r, "cpu": 0.0, "cpu_per_hz": 0.08, "performance": 100 * r / 9,
                       "max_frequency_hz": r, "step": "period", "bytes_per_msg": 230000}
                      for r in (2.5, 3, 4.2, 5, 6, 7.5, 9)]},
        {"name": "flow", "weight": 0.4, "input": "/camera/image_throttled", "topics": ["/flow/flows"],
         "settings": [{"cpu": 1.0, "cpu_per_hz": 12.0, "performance": 100, "bytes_per_msg": 2000}]},
    ],
    "edges": [{"from": "camera", "to": "throttle"}, {"from": "throttle", "to": "flow"}],
}


def _enumerate(doc: dict[str, Any]) -> float:
    """The best Problem 1 objective over every camera x throttle value (one computer), with the
    contract's rule written out here: whole ratios left out."""
    cap = doc["computers"][0]["capacity"]
    cam, thr, flow = doc["nodes"]
    best = -1.0
    for c, t in itertools.product(cam["settings"], thr["settings"]):
        f_in, rate = c["frequency_hz"], t["value"]
        n = f_in / rate
        if n >= 1 - STEP_AMBIGUOUS and abs(n - round(n)) <= STEP_AMBIGUOUS:
            continue
        k = 1
        while k * rate < f_in - 1e-9:
            k += 1
        out = f_in / k
        (fs,) = flow["settings"]
        cpu = c["cpu"] + t["cpu_per_hz"] * f_in + fs["cpu"] + fs["cpu_per_hz"] * out
        if cpu <= cap + 1e-9:
            best = max(best, cam["weight"] * c["performance"] + thr["weight"] * t["performance"]
                       + flow["weight"] * fs["performance"])
    return best


@pytest.mark.parametrize("capacity", [40, 60, 75, 100, 140])
@pytest.mark.parametrize("method", ["exact", "greedy", "greedy+"])
def test_solvers_plan_the_step_and_never_a_whole_ratio(method: str, capacity: float) -> None:
    doc = copy.deepcopy(SYSTEM)
    doc["computers"][0]["capacity"] = capacity
    s = parse_system(doc, "throttle.yaml")
    plan = solve(s, 1, method)
    assert check_plan(s, plan) == []
    thr, flow = plan.nodes["throttle"], plan.nodes["flow"]
    assert thr.input_hz is not None and thr.value is not None
    out = thr.topics["/camera/image_throttled"].frequency_hz
    assert out == pytest.approx(simulated(thr.input_hz, thr.value), rel=0.01)
    assert flow.input_hz == pytest.approx(out)
    assert not step_ambiguous(_throttle(thr.value), thr.input_hz)
    if method == "exact":
        assert plan.objective == pytest.approx(_enumerate(doc), abs=1e-6)


def test_the_checker_refuses_a_throttle_claimed_at_its_cap() -> None:
    s = parse_system(SYSTEM, "throttle.yaml")
    plan = solve(s, 1, "exact")
    thr, flow = plan.nodes["throttle"], plan.nodes["flow"]
    assert thr.value is not None
    flow.input_hz = thr.value  # what min(F_in, cap) would say
    flow.cpu = 1.0 + 12.0 * thr.value
    assert check_plan(s, plan) != []


def _throttle_setting(doc: dict[str, Any]) -> dict[str, Any]:
    setting: dict[str, Any] = doc["nodes"][1]["settings"][0]
    return setting


@pytest.mark.parametrize(("change", "expect"), [
    (lambda d: _throttle_setting(d).update(step="bytes"), "step: must be one of period"),
    (lambda d: _throttle_setting(d).pop("max_frequency_hz"), "give max_frequency_hz"),
    (lambda d: d["nodes"][0]["settings"][0].update(step="period"), "only a driven node"),
])
def test_a_bad_step_is_one_clear_error(change: Any, expect: str) -> None:
    doc = copy.deepcopy(SYSTEM)
    change(doc)
    with pytest.raises(InputError) as err:
        parse_system(doc, "throttle.yaml")
    assert expect in str(err.value) and "throttle.yaml" in str(err.value)


# --- init: a throttle from a sweep ------------------------------------------------------

SPAN_S = 20


def _write_run(d: Path, name: str, camera_hz: float, rate: float, flow_cpu: float) -> dict[str, Any]:
    """A run: the camera at ``camera_hz``, the throttle passing what the simulated
    topic_tools throttle passes at ``rate``, the flow node once per throttled frame."""
    from tests.test_init_driven import write_run_files

    camera = [T0 + int(round(k * 1e9 / camera_hz)) for k in range(int(SPAN_S * camera_hz) + 1)]
    passed, last = [], -1e18
    for t in camera:
        if t - last > 1e9 / rate:
            passed.append(t)
            last = t
    topics = {"/camera/image_raw": ("/camera", camera, 1000),
              "/camera/image_throttled": ("/throttle", [t + 500_000 for t in passed], 1000),
              "/flow/flows": ("/flow", [t + 3_000_000 for t in passed], 100)}
    write_run_files(d, name, topics, {"/camera": 1.0, "/throttle": 0.05 * camera_hz, "/flow": flow_cpu}, SPAN_S)
    return {"path": f"{name}.bag", "cpu": f"{name}.cpu.csv", "computer": "robot1", "units_per_core": 100,
            "settings": {"camera": camera_hz, "throttle": rate}}


def _sweep(d: Path, runs: list[tuple[float, float]]) -> None:
    from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic, write_graph

    d.mkdir()
    entries = []
    for k, (camera_hz, rate) in enumerate(runs):
        out = camera_hz / -(-camera_hz // rate) if camera_hz > rate else camera_hz
        entries.append(_write_run(d, f"run{k}", camera_hz, rate, 2.0 + 10.0 * out))
    (d / "manifest.yaml").write_text(yaml.safe_dump({"recordings": entries}))
    nodes = tuple(GraphNode(n, 100 + i, f"/usr/lib/x{n}", True)
                  for i, n in enumerate(("/camera", "/throttle", "/flow")))
    topics = (GraphTopic("/camera/image_raw", "std_msgs/String", ("/camera",), ("/throttle",)),
              GraphTopic("/camera/image_throttled", "std_msgs/String", ("/throttle",), ("/flow",)),
              GraphTopic("/flow/flows", "std_msgs/String", ("/flow",), ()))
    write_graph(d / "graph.yaml", Graph(nodes, topics, "run0"))


@pytest.mark.parametrize("cameras", [(15.0,), (10.0, 15.0)])
def test_init_drafts_a_throttle_as_driven_with_the_step(tmp_path: Path, cameras: tuple[float, ...]) -> None:
    from perfros_bag.sweep.draft import draft_system
    from perfros_bag.system.systemfile import load_system

    rates = (4.2, 6.0, 9.0, 20.0)
    _sweep(tmp_path / "sweep", [(c, r) for c in cameras for r in rates])
    draft_system(tmp_path / "sweep", tmp_path / "system.yaml")
    s = load_system(tmp_path / "system.yaml")
    thr = s.node["throttle"]
    assert thr.input == "/camera/image_raw"
    assert [x.value for x in thr.settings] == list(rates)
    assert all(x.step == "period" and x.max_frequency_hz == x.value for x in thr.settings)
    assert s.node["flow"].input == "/camera/image_throttled"  # driven by the throttle's output
    assert s.node["camera"].input is None
    for c in cameras:  # the drafted throttle gives the simulation's output at every rate
        for x in thr.settings:
            assert x.value is not None
            assert driven_rates(x, c)[1] == pytest.approx(simulated(c, x.value, jitter=0.0), rel=0.01)


def test_init_keeps_a_node_on_its_own_clock_that_is_no_throttle(tmp_path: Path) -> None:
    """The rule's refusal: a 'throttle' whose output at its value 6 is 6 Hz from a 15 Hz input
    (min(F_in, value), an averaging throttle) is drafted with the min rule, no step."""
    from perfros_bag.sweep.driven import RunMeasure, throttle_rule

    runs = {f"r{k}": RunMeasure(v, 1.0, {"/o": (min(15.0, v), None)}) for k, v in enumerate((3.0, 6.0, 9.0, 20.0))}
    assert throttle_rule(["/o"], runs, dict.fromkeys(runs, 15.0)) == ("min", pytest.approx(0.0))
    step = {f"r{k}": RunMeasure(v, 1.0, {"/o": (15.0 / -(-15.0 // v), None)}) for k, v in enumerate((4.2, 6.0, 9.0))}
    assert throttle_rule(["/o"], step, dict.fromkeys(step, 15.0)) == ("period", pytest.approx(0.0))
    own = {f"r{k}": RunMeasure(v, 1.0, {"/o": (f, None)})
           for k, (v, f) in enumerate(((4.2, 2.0), (6.0, 3.0), (9.0, 4.0)))}
    assert throttle_rule(["/o"], own, dict.fromkeys(own, 15.0)) is None  # neither rule gives its output
    above = {f"r{k}": RunMeasure(v, 1.0, {"/o": (f, None)}) for k, (v, f) in enumerate(((4.2, 3.75), (30.0, 16.0)))}
    assert throttle_rule(["/o"], above, dict.fromkeys(above, 15.0)) is None  # ran above its input


def test_init_takes_a_run_at_a_whole_ratio_anywhere_between_its_two_steps() -> None:
    """The issue's sweep: 15 Hz at rates 3, 6, 12 gave 2.74, 5.00, 7.50 (rate 3 divides 15: the
    node lands between 15 / 5 and 15 / 6); and rate 15 from 15 Hz, between 15 and 7.5 (9.555
    measured on Debian's throttle)."""
    from perfros_bag.sweep.driven import RunMeasure, throttle_rule

    for runs in ({"a": RunMeasure(3.0, 1.0, {"/o": (2.74, None)}), "b": RunMeasure(6.0, 1.0, {"/o": (5.0, None)}),
                  "c": RunMeasure(12.0, 1.0, {"/o": (7.5, None)})},
                 {"a": RunMeasure(4.2, 1.0, {"/o": (3.75, None)}), "b": RunMeasure(15.0, 1.0, {"/o": (9.555, None)})}):
        assert throttle_rule(["/o"], runs, dict.fromkeys(runs, 15.0)) == ("period", pytest.approx(0.0))


def test_a_throttle_swept_at_whole_rates_fits_a_whole_grid_and_plans_a_step(tmp_path: Path) -> None:
    """The issue's sweep (15 Hz, rates 3, 6, 12): fit's grid between them is whole (deploy runs
    a parameter swept at whole values at whole values), each capped at its value with the step,
    and the plan is a step, never a whole ratio of 15."""
    import json

    from typer.testing import CliRunner

    from perfros_bag.cli import app
    from perfros_bag.sweep.draft import draft_system

    _sweep(tmp_path / "sweep", [(15.0, r) for r in (3.0, 6.0, 12.0)])
    draft_system(tmp_path / "sweep", tmp_path / "system.yaml")
    runner = CliRunner()
    for args in (["characterise", str(tmp_path / "sweep"), "--system", str(tmp_path / "system.yaml"),
                  "--out", str(tmp_path / "c.csv")],
                 ["fit", str(tmp_path / "system.yaml"), str(tmp_path / "c.csv"), "--out", str(tmp_path / "model.json")],
                 ["solve", str(tmp_path / "model.json"), "--problem", "1", "--method", "exact",
                  "--out", str(tmp_path / "plan.json")]):
        res = runner.invoke(app, args)
        assert res.exit_code == 0, res.output
    model = json.loads((tmp_path / "model.json").read_text())
    (thr,) = (n for n in model["system"]["nodes"] if n["name"] == "throttle")
    values = [s["value"] for s in thr["settings"]]
    assert len(values) > 3 and all(float(v).is_integer() for v in values)
    assert all(s["step"] == "period" and s["max_frequency_hz"] == s["value"] for s in thr["settings"])
    plan = json.loads((tmp_path / "plan.json").read_text())["nodes"]
    f_in, value = plan["throttle"]["input_hz"], plan["throttle"]["value"]
    assert not step_ambiguous(_throttle(value), f_in)
    assert plan["throttle"]["topics"]["/camera/image_throttled"]["frequency_hz"] == pytest.approx(
        simulated(f_in, value, jitter=0.0), rel=0.01)
