"""init drafts driven nodes (system.yaml ``input:``) from a sweep: which nodes follow their
input (the rule of perfros_bag/sweep/driven.py) and their ``cpu``, ``cpu_per_hz``,
``out_per_in`` and ``bytes_per_msg``, against numpy's least squares over the numbers the runs
were written with, from a grid and from one-at-a-time sweeps; the draft solves as it is."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.characterisation.csvfile import read_characterisation
from perfros_bag.cli import app
from perfros_bag.sweep.draft import draft_system
from perfros_bag.sweep.driven import RATIO_TOLERANCE, RunMeasure, find_inputs
from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic, write_graph
from perfros_bag.system.systemfile import load_system

T0 = 1_700_000_000_000_000_000
SPAN_S = 10
CAMERA_BYTES, DETECTOR_BYTES, RELAY_BYTES, TRACKER_BYTES = 1000, 200, 100, 50


def _detector_cpu(value: int, rate: float, k: int) -> float:
    """The detector's CPU in run ``k``: a line per own value and a little deterministic noise."""
    base, slope = {1: (2.0, 0.5), 2: (3.0, 1.5)}[value]
    return base + slope * rate + (0.3, -0.2, 0.1, -0.4, 0.25, -0.05)[k % 6]


def _messages(rate: float, offset_ns: int = 0) -> list[int]:
    n = int(SPAN_S * rate) + 1
    return [T0 + offset_ns + int(round(i * 1e9 / rate)) for i in range(n)]


def write_run_files(d: Path, name: str, topics: dict[str, tuple[str, list[int], int]],
                    cpu: dict[str, float], span_s: int = SPAN_S) -> None:
    """``d/name.bag``: per topic (callerid, receive times in ns, bytes per std_msgs/String
    message), and ``d/name.cpu.csv``: each node's CPU over ``span_s`` s (a trace of robot1, 2 CPUs)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    string = ts.types["std_msgs/msg/String"]
    msgs = sorted((t, topic) for topic, (_c, times, _b) in topics.items() for t in times)
    with Writer(d / f"{name}.bag") as w:
        conns = {topic: w.add_connection(topic, "std_msgs/msg/String", typestore=ts, callerid=caller)
                 for topic, (caller, _t, _b) in topics.items()}
        for t, topic in msgs:
            w.write(conns[topic], t,
                    ts.serialize_ros1(string(data="x" * (topics[topic][2] - 4)), "std_msgs/msg/String"))
    lines = ["# host=robot1", "# logical_cpus=2", "# interval_s=0.5", "time,pid,node,process,cpu_percent,rss_bytes"]
    for s in range(1, 2 * span_s):
        lines += [f"{T0 / 1e9 + s * 0.5:.3f},{100 + i},{node},x,{c},1000" for i, (node, c) in enumerate(cpu.items())]
    (d / f"{name}.cpu.csv").write_text("\n".join(lines) + "\n")


def _write_run(d: Path, name: str, rate: float, value: int, k: int, detector_cpu: float) -> dict[str, object]:
    """A run: the camera at ``rate`` Hz, the detector once per frame, the relay once per two
    detections, the tracker on its own 5 Hz clock (it subscribes to the camera too)."""
    topics = {"/camera/image_raw": ("/camera", _messages(rate), CAMERA_BYTES),
              "/detector/out": ("/detector", _messages(rate, 1_000_000), DETECTOR_BYTES),
              "/relay/out": ("/relay", _messages(rate / 2, 2_000_000), RELAY_BYTES),
              "/tracker/tracks": ("/tracker", _messages(5, 3_000_000), TRACKER_BYTES)}
    cpu = {"/camera": 1.0 + 0.1 * rate, "/detector": detector_cpu, "/relay": 0.5 + 0.2 * rate, "/tracker": 10.0}
    write_run_files(d, name, topics, cpu)
    return {"path": f"{name}.bag", "cpu": f"{name}.cpu.csv", "computer": "robot1", "units_per_core": 100,
            "settings": {"camera": rate, "detector": value}}


def _sweep(d: Path, runs: list[tuple[float, int]], cpu: object = _detector_cpu) -> dict[tuple[float, int], float]:
    """A sweep folder of ``runs`` (camera rate, detector value); returns each run's detector CPU."""
    d.mkdir()
    entries, written = [], {}
    for k, (rate, value) in enumerate(runs):
        written[(rate, value)] = cpu(value, rate, k)  # type: ignore[operator]
        entries.append(_write_run(d, f"run{k}", rate, value, k, written[(rate, value)]))
    (d / "manifest.yaml").write_text(yaml.safe_dump({"recordings": entries}))
    nodes = tuple(GraphNode(n, 100 + i, f"/usr/bin/{n[1:]}", True)
                  for i, n in enumerate(("/camera", "/detector", "/relay", "/tracker")))
    topics = (GraphTopic("/camera/image_raw", "std_msgs/String", ("/camera",), ("/detector", "/tracker")),
              GraphTopic("/detector/out", "std_msgs/String", ("/detector",), ("/relay",)),
              GraphTopic("/relay/out", "std_msgs/String", ("/relay",), ()),
              GraphTopic("/tracker/tracks", "std_msgs/String", ("/tracker",), ()))
    write_graph(d / "graph.yaml", Graph(nodes, topics, "run0"))
    return written


def _settings(system_path: Path, node: str) -> list[dict[str, float]]:
    doc = yaml.safe_load(system_path.read_text())
    return next(n for n in doc["nodes"] if n["name"] == node)["settings"]


def _bytes_per_msg(size: int, rate: float) -> float:
    """bandwidth x 1000 / F_out as characterise measures them: n x size / span over (n - 1) / span."""
    n = int(SPAN_S * rate) + 1
    return n * size / (n - 1)


def _lstsq(points: list[tuple[float, float]]) -> tuple[float, float]:
    f = np.array([p[0] for p in points])
    c = np.array([p[1] for p in points])
    (a, b), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(f), f]), c, rcond=None)
    return float(a), float(b)


def _solve(system_path: Path, tmp_path: Path) -> dict[str, dict[str, object]]:
    plan = tmp_path / "plan.json"
    res = CliRunner().invoke(app, ["solve", str(system_path), "--problem", "1", "--method", "exact",
                                   "--out", str(plan)])
    assert res.exit_code == 0, res.output
    nodes: dict[str, dict[str, object]] = json.loads(plan.read_text())["nodes"]
    return nodes


def test_a_grid_drafts_one_least_squares_line_per_own_setting(tmp_path: Path) -> None:
    runs = [(rate, value) for value in (1, 2) for rate in (4.0, 8.0, 12.0)]
    written = _sweep(tmp_path / "sweep", runs)
    system_path = tmp_path / "system.yaml"
    draft_system(tmp_path / "sweep", system_path)
    system = load_system(system_path)
    assert system.node["detector"].input == "/camera/image_raw"
    assert system.node["relay"].input == "/detector/out"  # chains: driven by a driven node
    assert system.node["camera"].input is None  # the source keeps its rate settings
    assert [s.value for s in system.node["camera"].settings] == [4, 8, 12]
    assert system.node["tracker"].input is None  # subscribes to the camera, keeps its own clock
    # one chain along the data flow, from the source's topic through every driven node, no budget
    assert [(c.name, c.topics, c.budget_ms) for c in system.chains] == [
        ("relay", ("/camera/image_raw", "/detector/out", "/relay/out"), None)]
    assert "# budget_ms: {p95: 250}  # REPLACE" in system_path.read_text()
    detector = _settings(system_path, "detector")
    assert [s["value"] for s in detector] == [1, 2]
    for s in detector:
        a, b = _lstsq([(rate, c) for (rate, value), c in written.items() if value == s["value"]])
        assert a > 0 and b > 0
        assert s["cpu"] == pytest.approx(a, rel=1e-3) and s["cpu_per_hz"] == pytest.approx(b, rel=1e-3)
        assert s["out_per_in"] == pytest.approx(1.0, rel=1e-3)
        expected = np.mean([_bytes_per_msg(DETECTOR_BYTES, rate) for rate in (4.0, 8.0, 12.0)])
        assert s["bytes_per_msg"] == pytest.approx(expected, rel=1e-3)
        assert "frequency_hz" not in s
    (relay,) = _settings(system_path, "relay")  # not varied: one setting, a line over every run
    a, b = _lstsq([(rate, 0.5 + 0.2 * rate) for rate, _v in runs])
    assert relay["cpu"] == pytest.approx(a, rel=1e-3) and relay["cpu_per_hz"] == pytest.approx(b, rel=1e-3)
    assert relay["out_per_in"] == pytest.approx(0.5, rel=2e-3)
    assert relay["bytes_per_msg"] == pytest.approx(
        np.mean([_bytes_per_msg(RELAY_BYTES, rate / 2) for rate, _v in runs]), rel=1e-3)

    # it solves as drafted: the plan propagates the camera's rate down the chain
    plan = _solve(system_path, tmp_path)
    camera_hz = plan["camera"]["topics"]["/camera/image_raw"]["frequency_hz"]  # type: ignore[index]
    assert plan["detector"]["input_hz"] == pytest.approx(camera_hz)
    detector_hz = plan["detector"]["topics"]["/detector/out"]["frequency_hz"]  # type: ignore[index]
    assert plan["relay"]["input_hz"] == pytest.approx(detector_hz)
    s = next(x for x in detector if x["value"] == plan["detector"]["value"])
    assert plan["detector"]["cpu"] == pytest.approx(s["cpu"] + s["cpu_per_hz"] * camera_hz)

    # and it characterises (input_hz: the camera's rate as written), fits and solves as drafted
    char, model = tmp_path / "c.csv", tmp_path / "model.json"
    runner = CliRunner()
    res = runner.invoke(app, ["characterise", str(tmp_path / "sweep"), "--system", str(system_path),
                              "--out", str(char)])
    assert res.exit_code == 0, res.output
    rates = {f"run{k}.bag": rate for k, (rate, _v) in enumerate(runs)}
    inputs = {r.recording: r.input_hz for r in read_characterisation(char).rows if r.node == "detector"}
    assert inputs == pytest.approx(rates)
    res = runner.invoke(app, ["fit", str(system_path), str(char), "--out", str(model)])
    assert res.exit_code == 0, res.output
    plan = _solve(model, tmp_path)
    assert plan["detector"]["input"] == "/camera/image_raw"


def test_one_at_a_time_scales_the_default_settings_line(tmp_path: Path) -> None:
    """The camera's rate varied at the detector's value 2, the detector's value varied at 8 Hz."""
    runs = [(4.0, 2), (8.0, 2), (12.0, 2), (8.0, 1)]
    written = _sweep(tmp_path / "sweep", runs)
    system_path = tmp_path / "system.yaml"
    draft_system(tmp_path / "sweep", system_path)
    assert load_system(system_path).node["detector"].input == "/camera/image_raw"
    by_value = {s["value"]: s for s in _settings(system_path, "detector")}
    a2, b2 = _lstsq([(rate, c) for (rate, value), c in written.items() if value == 2])
    assert by_value[2]["cpu"] == pytest.approx(a2, rel=1e-3)
    assert by_value[2]["cpu_per_hz"] == pytest.approx(b2, rel=1e-3)
    k = written[(8.0, 1)] / (a2 + b2 * 8.0)
    assert by_value[1]["cpu"] == pytest.approx(k * a2, rel=1e-3)
    assert by_value[1]["cpu_per_hz"] == pytest.approx(k * b2, rel=1e-3)
    # the scaled line goes through the CPU measured at value 1
    assert by_value[1]["cpu"] + 8.0 * by_value[1]["cpu_per_hz"] == pytest.approx(written[(8.0, 1)], rel=1e-3)
    assert "input rate not varied here: the line at value 2 scaled" in system_path.read_text()
    _solve(system_path, tmp_path)


def test_a_negative_base_is_clipped_and_the_line_goes_through_the_origin(tmp_path: Path) -> None:
    def cpu(value: int, rate: float, k: int) -> float:
        return -2.0 + 1.0 * rate + (0.2, -0.1, 0.05)[k % 3]

    runs = [(4.0, 1), (8.0, 1), (12.0, 1)]
    written = _sweep(tmp_path / "sweep", runs, cpu)
    system_path = tmp_path / "system.yaml"
    draft_system(tmp_path / "sweep", system_path)
    (s,) = _settings(system_path, "detector")
    f = np.array([r for r, _v in written])
    c = np.array(list(written.values()))
    assert _lstsq(list(zip(f, c, strict=True)))[0] < 0
    assert s["cpu"] == 0
    assert s["cpu_per_hz"] == pytest.approx(float(f @ c / (f @ f)), rel=1e-3)
    assert "the fitted base cpu was below 0: clipped to 0, cpu_per_hz fitted through the origin" \
        in system_path.read_text()
    _solve(system_path, tmp_path)


def _runs(ratios: list[float], rates: list[float]) -> tuple[dict[str, RunMeasure], dict[str, float]]:
    runs = {f"r{i}": RunMeasure(1, 5.0, {"/out": (q * f, 1.0)})
            for i, (q, f) in enumerate(zip(ratios, rates, strict=True))}
    return runs, {f"r{i}": f for i, f in enumerate(rates)}


class _Node:
    def __init__(self, name: str, topics: tuple[str, ...]) -> None:
        self.name, self.topics = name, topics


@pytest.mark.parametrize(("ratios", "rates", "driven"), [
    ([1.0, 1.0], [5.0, 10.0], True),
    ([1.0, 1.09], [5.0, 10.0], True),  # within 10 %
    ([1.0, 1.11], [5.0, 10.0], False),  # beyond
    ([1.0, 0.5], [5.0, 10.0], False),  # its own 5 Hz clock
    ([1.0, 1.0], [10.0, 11.9], False),  # the input varied by less than 20 %
    ([1.0, 1.0], [10.0, 12.1], True),
])
def test_the_rule_and_its_tolerance(ratios: list[float], rates: list[float], driven: bool) -> None:
    runs, input_hz = _runs(ratios, rates)
    upstream = {r: RunMeasure(5, 1.0, {"/in": (f, 1.0)}) for r, f in input_hz.items()}
    graph = Graph((GraphNode("/a", None, None), GraphNode("/b", None, None)),
                  (GraphTopic("/in", None, ("/a",), ("/b",)), GraphTopic("/out", None, ("/b",), ())))
    found = find_inputs([_Node("a", ("/in",)), _Node("b", ("/out",))], graph, {"a": upstream, "b": runs},
                        {"a": "/a", "b": "/b"})
    assert ("b" in found) == driven
    if driven:
        assert found["b"].topic == "/in" and found["b"].spread <= RATIO_TOLERANCE


def test_an_input_without_a_rate_in_some_run_drives_nothing() -> None:
    runs, input_hz = _runs([1.0, 1.0, 1.0], [5.0, 10.0, 10.0])
    input_hz["r2"] = 0.0  # the camera published one message in that run
    upstream = {r: RunMeasure(5, 1.0, {"/in": (f, 1.0)}) for r, f in input_hz.items()}
    graph = Graph((GraphNode("/a", None, None), GraphNode("/b", None, None)),
                  (GraphTopic("/in", None, ("/a",), ("/b",)), GraphTopic("/out", None, ("/b",), ())))
    assert find_inputs([_Node("a", ("/in",)), _Node("b", ("/out",))], graph, {"a": upstream, "b": runs},
                       {"a": "/a", "b": "/b"}) == {}


def test_no_cycle_of_inputs_is_drafted() -> None:
    """Two nodes each subscribed to the other's output, both at the same varying rate: the first
    (graph order) is driven by the second, and the second stays a paper node."""
    a = {f"r{i}": RunMeasure(1, 1.0, {"/a/out": (f, 1.0)}) for i, f in enumerate((5.0, 10.0))}
    b = {f"r{i}": RunMeasure(1, 1.0, {"/b/out": (f, 1.0)}) for i, f in enumerate((5.0, 10.0))}
    graph = Graph((GraphNode("/a", None, None), GraphNode("/b", None, None)),
                  (GraphTopic("/a/out", None, ("/a",), ("/b",)), GraphTopic("/b/out", None, ("/b",), ("/a",))))
    found = find_inputs([_Node("a", ("/a/out",)), _Node("b", ("/b/out",))], graph, {"a": a, "b": b},
                        {"a": "/a", "b": "/b"})
    assert {n: f.topic for n, f in found.items()} == {"a": "/b/out"}


def test_runs_in_several_cpu_scales_are_one_error(tmp_path: Path) -> None:
    from perfros_bag.errors import InputError

    _sweep(tmp_path / "sweep", [(4.0, 1), (8.0, 1)])
    doc = yaml.safe_load((tmp_path / "sweep" / "manifest.yaml").read_text())
    doc["recordings"][1]["units_per_core"] = 50
    (tmp_path / "sweep" / "manifest.yaml").write_text(yaml.safe_dump(doc))
    res = CliRunner().invoke(app, ["init", str(tmp_path / "sweep"), "--out", str(tmp_path / "s.yaml")])
    assert res.exit_code == 2
    assert "several scales (units_per_core 50, 100): init drafts one machine" in " ".join(res.output.split())
    assert not (tmp_path / "s.yaml").exists()
    with pytest.raises(InputError):
        draft_system(tmp_path / "sweep", tmp_path / "s.yaml")
