"""The latency model (system/latency.py), its contract (system.yaml budget_ms, plan.json
chains[].predicted_ms) and its fit (fitting/latency.py), against closed forms computed here."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.fitting.latency import fit_latency
from perfros_bag.system.latency import budget_violation, chain_hops, predict_chain
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Choice, System

SYSTEM = """
computers:
  - {name: robot, kind: robot, capacity: 100}
  - {name: server, kind: server, capacity: 200}
links:
  - {between: [robot, server], bandwidth_kBps: 3000}
nodes:
  - name: camera
    weight: 0.5
    topics: [/camera/image_raw]
    residence: [robot]
    parameter: {name: rate}
    settings:
      - {value: 5, cpu: 5, performance: 50, frequency_hz: 5, bandwidth_kBps: 1150}
      - {value: 10, cpu: 10, performance: 100, frequency_hz: 10, bandwidth_kBps: 2300}
  - name: detector
    weight: 0.4999
    input: /camera/image_raw
    topics: [/detector/found]
    parameter: {name: threshold}
    settings:
      - {value: 1, cpu: 2, cpu_per_hz: 5, performance: 100, bytes_per_msg: 100}
      - {value: 2, cpu: 2, cpu_per_hz: 2, performance: 60, bytes_per_msg: 100}
  - {name: logger, weight: 0.0001, topics: [/log], settings: [{cpu: 40, performance: 100, frequency_hz: 1}]}
edges:
  - {from: camera, to: detector, topic: /camera/image_raw}
chains:
  - name: vision
    topics: [/camera/image_raw, /detector/found]
"""


def _system(text: str = SYSTEM, **chain: object) -> System:
    data = yaml.safe_load(text)
    data["chains"][0].update(chain)
    return parse_system(data)


def _choices(system: System, rate: float, setting: int) -> dict[str, Choice]:
    cam = next(c for c in system.node["camera"].choices() if c.value == rate)
    det = system.driven_choice(system.node["detector"], setting, rate)
    return {"camera": cam, "detector": det, "logger": system.node["logger"].choices()[0]}


# ---- the closed form, written out here (docs/solvers.md "Latency") -----------------------
def _wait(mean: float, rho: float, q: float) -> float:
    return 0.0 if rho <= 1 - q or mean <= 0 else mean / rho * math.log(rho / (1 - q))


def _hop(w: float, lam: float, speed: float, size_kB: float = 0.0, bw: float | None = None,
         overhead_ms: float = 1.0, ratio: float = 1.3, queue: int = 1, backlog: float = 2.0) -> tuple[float, float]:
    s = w / speed
    rho = lam * s
    w50 = w95 = 0.0  # periodic input below utilisation 1: the node is idle when a message comes
    if rho >= 1:  # the oldest of the full queue and socket backlog: held - 1 periods and a uniform part of one
        held = queue + backlog
        w50 = min((held - 1 + 0.5) / lam, held * s)
        w95 = min((held - 1 + 0.95) / lam, held * s)
    t = 0.0 if bw is None else size_kB / (0.96 * bw)
    return 1000 * (overhead_ms / 1000 + t + w50 + s), 1000 * (overhead_ms / 1000 + t + w95 + ratio * s)


def test_a_hop_across_a_link_is_service_wait_and_transfer() -> None:
    system = _system()
    choice = _choices(system, 10, 0)
    placement = {"camera": "robot", "detector": "server", "logger": "robot"}
    got = predict_chain(system, system.chains[0], placement, choice, {"robot": 100, "server": 200})
    # detector: 2 + 5 x 10 Hz = 52 units, 5.2 unit-seconds per frame, alone on the server: one core (100)
    want = _hop(52 / 10, 10, 100, size_kB=230, bw=3000)
    assert (got.p50_ms, got.p95_ms) == pytest.approx(want, rel=1e-9)
    assert [h.node for h in got.hops] == ["detector"] and got.hops[0].transfer_ms == pytest.approx(230 / 2880 * 1000)


def test_a_shared_capped_computer_slows_the_hop_by_its_fair_share() -> None:
    system = _system()
    choice = _choices(system, 10, 0)
    placement = {"camera": "robot", "detector": "robot", "logger": "robot"}
    # robot of 60 units: camera needs 10, logger 40, detector as much as a core (100):
    # max-min fair per thread: camera's 10 met, then 50 left for two -> 25 each < logger's 40
    got = predict_chain(system, system.chains[0], placement, choice, {"robot": 60, "server": 200})
    want = _hop(52 / 10, 10, 25)  # rho = 52 / 25 > 1: the newest frame waits for the running one
    assert (got.p50_ms, got.p95_ms) == pytest.approx(want, rel=1e-9)
    assert got.hops[0].wait_ms == pytest.approx(250.0) and got.hops[0].wait_p95_ms == pytest.approx(295.0)
    # the checker's own copy gives the same numbers for the plan built on this (overloaded) placement
    from perfros_bag.solver.check import check_plan
    from perfros_bag.system.plan import Assignment, Status
    from perfros_bag.system.rules import build_plan
    from perfros_bag.system.types import Problem

    tight = parse_system({**yaml.safe_load(SYSTEM), "computers": [
        {"name": "robot", "kind": "robot", "capacity": 60}, {"name": "server", "kind": "server", "capacity": 200}]})
    plan = build_plan(tight, Assignment(placement, choice), problem=Problem.PERFORMANCE, method="test",
                      status=Status.FEASIBLE)
    assert plan.chains[0]["predicted_ms"] == {"p50": pytest.approx(want[0]), "p95": pytest.approx(want[1])}
    assert not [m for m in check_plan(tight, plan) if "the model gives" in m]
    roomy = predict_chain(system, system.chains[0], placement, choice, {"robot": 300, "server": 200})
    assert (roomy.p50_ms, roomy.p95_ms) == pytest.approx(_hop(52 / 10, 10, 100), rel=1e-9)


@pytest.mark.parametrize("burst_ms", [10.0, 100.0])
def test_a_shaped_links_bucket_lets_a_message_start_sooner_below_its_rate(burst_ms: float) -> None:
    """``latency.link_burst_ms``: a link below its rate has its bucket full when a periodic
    message comes, so the message crosses ``burst_ms`` sooner (never below 0); a link at or
    above its rate has no bucket left; the wait behind other traffic is unchanged. The
    checker's own copy agrees on the plan."""
    from perfros_bag.solver.check import check_plan
    from perfros_bag.system.plan import Assignment, Status
    from perfros_bag.system.rules import build_plan
    from perfros_bag.system.types import Problem

    data = yaml.safe_load(SYSTEM)
    data["latency"] = {"link_burst_ms": burst_ms}
    system = parse_system(data)
    choice = _choices(system, 10, 0)
    placement = {"camera": "robot", "detector": "server", "logger": "robot"}
    got = predict_chain(system, system.chains[0], placement, choice, {"robot": 100, "server": 200})
    t = 230 / (0.96 * 3000)  # 79.9 ms at the link's rate; the stream, 2300 kB/s, is below 3000
    want = _hop(52 / 10, 10, 100)
    sooner = max(0.0, t - burst_ms / 1000)
    assert got.hops[0].transfer_ms == pytest.approx(1000 * sooner)
    assert (got.p50_ms, got.p95_ms) == pytest.approx((want[0] + 1000 * sooner, want[1] + 1000 * sooner), rel=1e-9)
    plan = build_plan(system, Assignment(placement, choice), problem=Problem.PERFORMANCE, method="test",
                      status=Status.FEASIBLE)
    assert plan.chains[0]["predicted_ms"]["p50"] == pytest.approx(got.p50_ms)
    assert not [m for m in check_plan(system, plan) if "the model gives" in m]
    # a link at its rate: 2300 kB/s of images and 700 of another stream fill 3000 kB/s
    full = yaml.safe_load(SYSTEM.replace("  - {from: camera, to: detector, topic: /camera/image_raw}",
                                         "  - {from: camera, to: detector, topic: /camera/image_raw}\n"
                                         "  - {from: logger, to: detector, bandwidth_kBps: 700}"))
    full["latency"] = {"link_burst_ms": burst_ms}
    busy = parse_system(full)
    got = predict_chain(busy, busy.chains[0], placement, choice, {"robot": 100, "server": 200})
    # the whole transfer (the other stream's p50 wait is 0 at its utilisation 0.23; its p95 is not)
    assert got.hops[0].transfer_ms == pytest.approx(1000 * t) and got.hops[0].transfer_p95_ms > 1000 * t
    no_burst = parse_system({**full, "latency": {}})
    again = predict_chain(no_burst, no_burst.chains[0], placement, choice, {"robot": 100, "server": 200})
    assert got.p50_ms == pytest.approx(again.p50_ms) and got.p95_ms == pytest.approx(again.p95_ms)


def test_another_stream_on_the_link_adds_its_wait() -> None:
    text = SYSTEM.replace("  - {from: camera, to: detector, topic: /camera/image_raw}",
                          "  - {from: camera, to: detector, topic: /camera/image_raw}\n"
                          "  - {from: logger, to: detector, bandwidth_kBps: 1500}")
    system = _system(text)
    choice = _choices(system, 5, 1)
    placement = {"camera": "robot", "detector": "server", "logger": "robot"}
    got = predict_chain(system, system.chains[0], placement, choice, {"robot": 100, "server": 200})
    t = 230 / (0.96 * 3000)
    u = 1500 / 3000  # the logger's traffic: the camera's own stream does not queue behind itself
    mean = u * t / (2 * (1 - u))
    base50, base95 = _hop(12 / 5, 5, 100)
    assert got.p50_ms == pytest.approx(base50 + 1000 * (t + _wait(mean, u, 0.5)), rel=1e-9)
    assert got.p95_ms == pytest.approx(base95 + 1000 * (t + _wait(mean, u, 0.95)), rel=1e-9)


def test_budget_violation_names_the_chain_and_the_quantile() -> None:
    system = _system(budget_ms={"p95": 140})
    choice = _choices(system, 10, 0)
    far = {"camera": "robot", "detector": "server", "logger": "robot"}
    near = {"camera": "robot", "detector": "robot", "logger": "server"}
    caps = {"robot": 100, "server": 200}
    assert budget_violation(system, far, choice, caps) == (
        f"chain 'vision': predicted p95 {_hop(5.2, 10, 100, 230, 3000)[1]:.4g} ms > budget 140 ms")
    assert _hop(5.2, 10, 90)[1] < 140  # on the robot beside the camera: 90 units left, no link
    assert budget_violation(system, near, choice, caps) is None


@pytest.mark.parametrize(("budget", "problem"), [
    ("{p95: -5}", r"budget_ms.p95: must be > 0"),
    ("{p50: 0}", r"budget_ms.p50: must be > 0"),
    ("{p95: .inf}", r"budget_ms.p95: must be a finite number"),
    ("{p95: fast}", r"budget_ms.p95: must be a finite number"),
    ("{p99: 5}", r"budget_ms: unknown"),
    ("{}", r"budget_ms: give p50, p95 or both"),
    ("{p50: 90, p95: 50}", r"budget_ms: p95 50 ms is below p50 90 ms"),
    ("120", r"budget_ms: expected a mapping"),
])
def test_a_bad_budget_is_one_line_exit_2_and_nothing_written(budget: str, problem: str, tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(SYSTEM.replace("    topics: [/camera/image_raw, /detector/found]\n",
                                   f"    topics: [/camera/image_raw, /detector/found]\n    budget_ms: {budget}\n"))
    res = CliRunner().invoke(app, ["solve", str(path), "--problem", "1", "--out", str(tmp_path / "plan.json")])
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "chain 'vision': " in lines[0], res.stderr
    assert re.search(problem, lines[0]), lines[0]
    assert not (tmp_path / "plan.json").exists()


def test_a_budget_on_a_chain_whose_hops_cannot_be_followed_is_refused() -> None:
    text = SYSTEM.replace("topics: [/camera/image_raw, /detector/found]", "topics: [/camera/image_raw, /log]")
    unbudgeted = _system(text)
    assert isinstance(chain_hops(unbudgeted, unbudgeted.chains[0]), str)
    with pytest.raises(InputError, match=r"chain 'vision': budget_ms: its latency cannot be predicted: hop "
                                         r"/camera/image_raw -> /log: /log is published by 'logger', not driven"):
        _system(text, budget_ms={"p50": 50})


def test_plan_json_states_each_chain_and_hop_prediction(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    data = yaml.safe_load(SYSTEM)
    data["chains"][0]["budget_ms"] = {"p50": 500, "p95": 800}
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "plan.json"
    res = CliRunner().invoke(app, ["solve", str(path), "--problem", "1", "--method", "exact", "--out", str(out)])
    assert res.exit_code == 0, res.output
    plan = json.loads(out.read_text())
    [chain] = plan["chains"]
    system = parse_system(data)
    nodes = plan["nodes"]
    choice = _choices(system, nodes["camera"]["value"],
                      system.node["detector"].setting_index(nodes["detector"]["value"]))
    placement = {n: v["computer"] for n, v in nodes.items()}
    want = predict_chain(system, system.chains[0], placement, choice, {"robot": 100, "server": 200})
    assert chain["predicted_ms"] == pytest.approx({"p50": want.p50_ms, "p95": want.p95_ms}, rel=1e-6)
    assert chain["budget_ms"] == {"p50": 500, "p95": 800}
    assert chain["hops"][0]["predicted_ms"] == chain["predicted_ms"] and chain["hops"][0]["node"] == "detector"
    assert "chains: predicted latency" in res.output


def _row(rec: str, node: str, topic: str, cpu: float, hz: float, p50: float, p95: float,
         input_hz: float | None = None) -> Row:
    return Row(rec, node, None, None, topic, None, 100, 10.0, hz, 1.0, cpu, cpu, 10,
               latency_p50_s=p50, latency_p95_s=p95, input_hz=input_hz)


def test_the_fit_recovers_overhead_scale_and_p95_ratio_from_sweep_rows() -> None:
    system = _system()
    overhead, scale, ratio = 0.003, 1.5, 1.4
    rows = []
    for i, (rate, cpu) in enumerate([(5, 2.0), (10, 4.0), (5, 1.0), (10, 3.0)]):
        s = cpu / rate / 100  # seconds of one core per frame; rho = rate x s <= 0.04: no wait
        rec = f"run{i}"
        rows.append(_row(rec, "camera", "/camera/image_raw", 5, rate, 0.0005, 0.001))
        rows.append(_row(rec, "detector", "/detector/found", cpu, rate,
                         overhead + scale * s, overhead + ratio * scale * s, input_hz=rate))
    # a run whose detector fell behind (4 of 10 frames): the sweep machine's contention, not fitted
    rows.append(_row("behind", "camera", "/camera/image_raw", 5, 10, 0.0005, 0.001))
    rows.append(_row("behind", "detector", "/detector/found", 8.5, 4.0, 0.48, 0.75, input_hz=10))
    fit = fit_latency(rows, system)
    assert fit.params.overhead_ms == pytest.approx(1000 * overhead, rel=1e-6)
    assert fit.params.service_scale["detector"] == pytest.approx(scale, rel=1e-6)
    assert fit.params.node_p95_ratio["detector"] == pytest.approx(ratio, rel=1e-6)
    assert fit.p50_error_pct == pytest.approx(0, abs=1e-6) and len(fit.samples) == 4


def test_a_hop_never_measured_is_a_warning_naming_the_chain() -> None:
    system = _system()
    rows = [_row("run0", "camera", "/camera/image_raw", 5, 10, 0.001, 0.002)]
    fit = fit_latency(rows, system)
    assert fit.samples == [] and len(fit.warnings) == 1
    assert "chain 'vision': no measured latency for its hop node(s) detector" in fit.warnings[0]


@pytest.mark.parametrize(("p95_s", "planned_cpu"), [(0.12, None), (0.14, None), (0.12, 40.0), (0.14, 65.0)])
def test_tune_refits_scale_and_p95_ratio_from_a_deployment(p95_s: float, planned_cpu: float | None,
                                                           tmp_path: Path) -> None:
    from perfros_bag.tune.loop import _recalibrate_latency

    data = yaml.safe_load(SYSTEM)
    data["latency"] = {"overhead_ms": 2.0, "service_scale": {"detector": 3.0}, "queue_factor": 0.8}
    (tmp_path / "model-0.json").write_text(json.dumps({"format": "perfros-bag/model@1", "system": data}))
    (tmp_path / "round-1").mkdir()
    hop = {"from": "/camera/image_raw", "node": "detector", "to": "/detector/found", "computer": "server",
           "predicted_ms": {"p50": 140.0, "p95": 200.0}, "service_ms": 50.0, "wait_ms": 8.0, "transfer_ms": 80.0,
           "wait_p95_ms": 30.0, "transfer_p95_ms": 80.0}
    plan: dict[str, Any] = {"chains": [{"name": "vision", "hops": [hop]}]}
    if planned_cpu is not None:  # the round's plan gave the detector this CPU at threshold 1, 10 Hz in
        plan["nodes"] = {"detector": {"computer": "server", "value": 1, "cpu": planned_cpu, "input_hz": 10.0}}
    (tmp_path / "round-1" / "plan.json").write_text(json.dumps(plan))
    measured = {"name": "vision", "p50_s": 0.1, "hops": [{"from": "/camera/image_raw", "to": "/detector/found",
                                                          "p50_s": 0.1, "p95_s": p95_s}]}
    (tmp_path / "round-1" / "validation.json").write_text(json.dumps({"chains": [measured]}))
    doc_system = json.loads(json.dumps(data))
    doc_system["latency"] = {"overhead_ms": 2.0, "service_scale": {"detector": 2.5}, "queue_factor": 0.7}
    from perfros_bag.tune.tunefile import TuneRound

    done = TuneRound.from_json({"round": 1, "dir": "round-1", "model": "model-0.json", "values": {}, "placement": {},
                                "expected": 0.0, "measured": 0.0, "deviation_pct": 0.0, "within_tolerance": None,
                                "computers": {}, "nodes": {}})
    _recalibrate_latency(tmp_path, doc_system, [done])
    got = doc_system["latency"]
    # the round's service at scale 1: 50 ms predicted at scale 3; restated at the refitted
    # model's CPU (threshold 1 at 10 Hz: 2 + 5 x 10 = 52 units) over the plan's
    service = 50.0 / 3.0 * (1.0 if planned_cpu is None else 52.0 / planned_cpu)
    # p50: 100 ms measured - 2 ms overhead - 80 ms transfer - 8 ms wait (a share of the input
    # period: it does not grow with the scale) = 10 ms of the node's own; the new fit's scale
    # (2.5) counts once beside it: their geometric mean
    scale = math.sqrt(2.5 * 10.0 / service)
    assert got["service_scale"]["detector"] == pytest.approx(scale, rel=1e-6)
    # p95: what the measured p95 leaves after overhead, transfer and the p95 wait, over what
    # the p50 left (10 ms): the node's own spread in that round
    left = 1000 * p95_s - 2 - 80 - 30
    assert got["node_p95_ratio"]["detector"] == pytest.approx(max(1.0, left / 10.0), rel=1e-6)
    assert got["queue_factor"] == pytest.approx(0.7)  # only the links' wait uses it: kept
    assert got["source"] == "tune"


def test_a_node_with_two_busy_threads_runs_on_two_cores_and_takes_two_slices() -> None:
    system = _system(SYSTEM.replace("    input: /camera/image_raw\n", "    input: /camera/image_raw\n    threads: 2\n"))
    choice = _choices(system, 10, 0)
    placement = {"camera": "robot", "detector": "server", "logger": "robot"}
    roomy = predict_chain(system, system.chains[0], placement, choice, {"robot": 100, "server": 300})
    assert (roomy.p50_ms, roomy.p95_ms) == pytest.approx(_hop(5.2, 10, 200, size_kB=230, bw=3000), rel=1e-9)
    # on a robot of 70 beside the camera (10) and the logger (40): per thread, the camera's 10 is met,
    # then 60 over 3 slices = 20 each: the logger 20, the detector 2 x 20 = 40
    shared = {"camera": "robot", "detector": "robot", "logger": "robot"}
    got = predict_chain(system, system.chains[0], shared, choice, {"robot": 70, "server": 300})
    assert (got.p50_ms, got.p95_ms) == pytest.approx(_hop(5.2, 10, 40), rel=1e-9)
    # the checker's own copy weighs threads alike: a solved plan's stated latency agrees with it
    from perfros_bag.solver import solve
    from perfros_bag.solver.check import check_plan

    plan = solve(system, 1, "exact")
    assert plan.chains[0]["predicted_ms"] is not None and check_plan(system, plan) == []


def test_nodes_fed_the_same_message_run_at_once_and_share_the_computer() -> None:
    """A smoother beside the detector, both driven by the camera's frames (5 Hz) on one robot
    of 60: each frame reaches both at once. By hand: the camera's 5 is met, the other 55 split
    evenly while both run: the smoother's 1.0 unit-s per frame ends after 1.0 / 27.5 s, by
    then the detector did 1.0 of its 5.4 (2 + 5 x 5 Hz = 27 units over 5 Hz); then it gets
    the 55 left for its 4.4. (The old rule, the others at their mean CPU, gave the smoother
    60 - 5 - 27 = 28 units throughout and the detector 60 - 5 - 5 = 50.)"""
    text = SYSTEM.replace("  - {name: logger,", """  - name: smoother
    weight: 0.00005
    input: /camera/image_raw
    topics: [/smooth]
    settings: [{cpu: 0, cpu_per_hz: 1, performance: 100, bytes_per_msg: 100}]
  - {name: logger,""")
    text = text.replace("weight: 0.0001, topics: [/log]", "weight: 0.00005, topics: [/log]")
    vision_chain = "chains:\n  - name: vision\n    topics: [/camera/image_raw, /detector/found]\n"
    text = text.replace(vision_chain, vision_chain + "  - name: smooth\n    topics: [/camera/image_raw, /smooth]\n")
    system = _system(text.replace("{name: robot, kind: robot, capacity: 100}",
                                  "{name: robot, kind: robot, capacity: 60}"))
    choice = {**_choices(system, 5, 0), "smoother": system.driven_choice(system.node["smoother"], 0, 5)}
    placement = {"camera": "robot", "detector": "robot", "smoother": "robot", "logger": "server"}
    caps = {"robot": 60, "server": 200}
    vision = predict_chain(system, system.chains[0], placement, choice, caps)
    smooth = predict_chain(system, system.chains[1], placement, choice, caps)
    s_smooth = 1.0 / 27.5
    s_vision = s_smooth + (5.4 - 1.0) / 55
    assert smooth.hops[0].service_ms == pytest.approx(1000 * s_smooth)
    assert vision.hops[0].service_ms == pytest.approx(1000 * s_vision)
    # the hop as _hop states it at the speed that gives that service time
    assert (vision.p50_ms, vision.p95_ms) == pytest.approx(_hop(5.4, 5, 5.4 / s_vision), rel=1e-9)
    assert (smooth.p50_ms, smooth.p95_ms) == pytest.approx(_hop(1.0, 5, 1.0 / s_smooth), rel=1e-9)
    # the checker's own copy (its own water level, stepped finish to finish) agrees on the plan
    from perfros_bag.solver.check import check_plan
    from perfros_bag.system.plan import Assignment, Status
    from perfros_bag.system.rules import build_plan
    from perfros_bag.system.types import Problem

    plan = build_plan(system, Assignment(placement, choice), problem=Problem.PERFORMANCE, method="test",
                      status=Status.FEASIBLE)
    assert [c["predicted_ms"]["p50"] for c in plan.chains] == pytest.approx([vision.p50_ms, smooth.p50_ms])
    assert not [m for m in check_plan(system, plan) if "the model gives" in m]
