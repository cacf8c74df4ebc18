"""init's and graph.yaml's bad input: one InputError naming the file and the problem."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from perfros_bag.errors import InputError
from perfros_bag.sweep.draft import draft_system
from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic, read_graph, write_graph


def test_graph_yaml_round_trips(tmp_path: Path) -> None:
    graph = Graph((GraphNode("/cam: era", 12, "/usr/lib/x/cam", True), GraphNode("/rosout", None, None, False)),
                  (GraphTopic("/cam/image", "sensor_msgs/Image", ("/cam: era",), ("/det",)),), "run-1")
    path = tmp_path / "graph.yaml"
    write_graph(path, graph)
    assert yaml.safe_load(path.read_text())["format"] == "perfros-bag/graph@1"
    assert read_graph(path) == graph


@pytest.mark.parametrize(("doc", "expected"), [
    ({"nodes": []}, "not a graph.yaml (format None"),
    ({"format": "perfros-bag/graph@1", "nodes": [{"pid": 3}]}, "nodes[0]: expected {name, pid, executable}"),
    ({"format": "perfros-bag/graph@1", "nodes": [{"name": "/a", "pid": "x"}]}, "nodes[0].pid: must be a whole number"),
    ({"format": "perfros-bag/graph@1", "topics": [{"name": "/t", "publishers": "/a"}]},
     "topics[0].publishers: must be a list of node names"),
])
def test_bad_graph_yaml(tmp_path: Path, doc: object, expected: str) -> None:
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError) as info:
        read_graph(path)
    assert str(info.value).startswith(f"{path}: ") and expected in str(info.value)


def test_init_needs_a_sweep_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a directory"):
        draft_system(tmp_path / "nope", tmp_path / "system.yaml")
    with pytest.raises(InputError, match=r"no manifest.yaml: not a folder of recorded runs \(a sweep writes one\)"):
        draft_system(tmp_path, tmp_path / "system.yaml")
    (tmp_path / "manifest.yaml").write_text("recordings: []\n")
    with pytest.raises(InputError, match="manifest.yaml: lists no recording"):
        draft_system(tmp_path, tmp_path / "system.yaml")
    assert not (tmp_path / "system.yaml").exists()


def test_init_needs_numeric_values(tmp_path: Path) -> None:
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(
        {"recordings": [{"path": "a.bag", "settings": {"camera": "fast"}}]}))
    with pytest.raises(InputError, match="recording 'a.bag': node camera: value 'fast' is not a number"):
        draft_system(tmp_path, tmp_path / "system.yaml")


def test_bus_stats_of_both_client_libraries() -> None:
    """Message bytes per published topic; a connection's handshake header is not a message."""
    from perfros_bag.sweep.runner import _published_bytes

    roscpp = [[["/rosout", [[0, 0, 0, 0, 0]]], ["/cam/image", [[4, 900, 900, 3, 0], [6, 600, 600, 2, 0]]]], [], []]
    rospy = [[["/rosout", 0, [[1, 1257, 0, True]]], ["/q/never", 0, [[3, 161, 0, True]]],
              ["/q/x", 12, [[3, 173, 1, True]]]],
             [], []]
    assert _published_bytes(roscpp) == {"/rosout": 0, "/cam/image": 1500}
    assert _published_bytes(rospy) == {"/rosout": 0, "/q/never": 0, "/q/x": 12}
    assert _published_bytes(None) == {} and _published_bytes([1, "", []]) == {}


def test_deploy_sets_each_varied_node_to_its_plan_value(tmp_path: Path) -> None:
    from perfros_bag.rosrun.cgroups import computer_cores
    from perfros_bag.sweep.deploy import plan_run
    from perfros_bag.sweep.space import load_space
    from perfros_bag.system.plan import Plan, PlannedComputer, PlannedNode

    space_path = tmp_path / "space.yaml"
    space_path.write_text(yaml.safe_dump({"vary": [
        {"node": "camera", "parameter": {"name": "rate"}, "arg": "camera_rate", "values": [5, 10]},
        {"node": "detector", "parameter": {"name": "thr"}, "param": "thr", "values": [100, 200]},
        {"node": "other", "parameter": {"name": "gain"}, "arg": "gain", "values": [0.5, 1.5]}]}))
    space = load_space(space_path)
    plan = Plan(1, "exact", "optimal",
                computers={"robot": PlannedComputer("robot", 150.0, 10.0),
                           "server": PlannedComputer("server", 400.0, 5.0)},
                nodes={"camera": PlannedNode("robot", 1.0, 50.0, 0.5, "rate", 7.6),
                       "detector": PlannedNode("server", 5.0, 90.0, 0.5, "thr", 150.0)})
    run = plan_run(plan, space, {"camera_rate": "10", "gain": "1.5"})
    # whole-number parameters rounded; a node the plan leaves out at its launch default
    assert dict(run.values) == {"camera": 8, "detector": 150, "other": 1.5}
    assert dict(run.args) == {"camera_rate": "8", "gain": "1.5"}
    assert dict(run.params) == {"/detector/thr": 150}
    assert computer_cores(plan, 100.0) == {"robot": 1.5, "server": 4.0}


# --------------------------------------------------------------------------- init without graph.yaml

T0 = 1_700_000_000_000_000_000


def _write_run(path: Path, kind: str, rate_hz: float) -> Path:
    """10 s of /detector/out at ``rate_hz`` and /tracker/tracks at 5 Hz, and /rosout lines
    from detector, tracker and a node that publishes nothing (quiet). ROS 1: the data
    topics' callerids name their publishers; ROS 2: only /rosout names nodes."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    time_t = ts.types["builtin_interfaces/msg/Time"]
    log_type = "rosgraph_msgs/msg/Log" if ros1 else "rcl_interfaces/msg/Log"
    msgs: list[tuple[str, int, object]] = []
    for i, name in enumerate(["detector", "tracker", "quiet"]):
        t = T0 + (i + 1) * 10**9
        if ros1:
            header = ts.types["std_msgs/msg/Header"](seq=0, stamp=time_t(sec=t // 10**9, nanosec=0), frame_id="")
            log = ts.types[log_type](header=header, level=2, name="/" + name, msg="hi", file="a.py", function="f",
                                     line=1, topics=[])
        else:
            log = ts.types[log_type](stamp=time_t(sec=t // 10**9, nanosec=0), level=20, name=name, msg="hi",
                                     file="a.cpp", function="f", line=1)
        msgs.append(("/rosout", t, log))
    n = int(10 * rate_hz) + 1
    msgs += [("/detector/out", T0 + int(k * 1e9 / rate_hz), ts.types["std_msgs/msg/String"](data="x" * 100))
             for k in range(n)]
    msgs += [("/tracker/tracks", T0 + k * 200_000_000, ts.types["std_msgs/msg/String"](data="y" * 50))
             for k in range(51)]
    msgs.sort(key=lambda m: m[1])
    types = {"/rosout": log_type, "/detector/out": "std_msgs/msg/String", "/tracker/tracks": "std_msgs/msg/String"}
    callers = {"/rosout": "/detector", "/detector/out": "/detector", "/tracker/tracks": "/tracker"}
    if ros1:
        from rosbags.rosbag1 import Writer as W1

        with W1(path) as w1:
            c1 = {t: w1.add_connection(t, m, typestore=ts, callerid=callers[t]) for t, m in types.items()}
            for topic, t, msg in msgs:
                w1.write(c1[topic], t, ts.serialize_ros1(msg, types[topic]))
        return path
    from rosbags.rosbag2 import Writer

    with Writer(path, version=9) as w:
        c2 = {t: w.add_connection(t, m, typestore=ts) for t, m in types.items()}
        for topic, t, msg in msgs:
            w.write(c2[topic], t, ts.serialize_cdr(msg, types[topic]))
    return path


def _write_trace(path: Path, cpu: dict[str, float]) -> None:
    lines = ["# host=robot1", "# logical_cpus=2", "# interval_s=0.5", "time,pid,node,process,cpu_percent,rss_bytes"]
    for k in range(1, 20):
        t = T0 / 1e9 + k * 0.5
        lines += [f"{t:.3f},{100 + i},{node},python3,{c},1000" for i, (node, c) in enumerate(cpu.items())]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_init_without_graph_yaml_drafts_nodes_from_callerid_and_rosout(tmp_path: Path, kind: str) -> None:
    import json

    from typer.testing import CliRunner

    from perfros_bag.cli import app
    from perfros_bag.system.systemfile import load_system

    d = tmp_path / "sweep"
    d.mkdir()
    entries = []
    for rate in (5, 10):
        name = f"run{rate}" + (".bag" if kind == "ros1" else "")
        _write_run(d / name, kind, rate)
        _write_trace(d / f"run{rate}.cpu.csv", {"detector": 10.0 * rate, "tracker": 20.0, "quiet": 1.0})
        entries.append({"path": name, "cpu": f"run{rate}.cpu.csv", "computer": "robot1",
                        "settings": {"detector": rate}})
    (d / "manifest.yaml").write_text(yaml.safe_dump({"recordings": entries}))
    assert not (d / "graph.yaml").exists()

    system_path = tmp_path / "system.yaml"
    runner = CliRunner()
    res = runner.invoke(app, ["init", str(d), "--out", str(system_path)])
    assert res.exit_code == 0, res.output
    assert "3 node(s)" in " ".join(res.output.split())
    system = load_system(system_path)
    assert {n.name for n in system.nodes} == {"detector", "tracker", "quiet"}
    assert system.node["detector"].topics == ("/detector/out",)  # callerid (ROS 1) or namespace (ROS 2)
    assert system.node["tracker"].topics == ("/tracker/tracks",)
    assert system.node["quiet"].topics == ()
    detector = system.node["detector"]
    assert [s.value for s in detector.settings] == [5, 10]
    # the measured numbers, against the runs as written: (n - 1) / span Hz; CPU units
    # cpu_percent / (100 x 2 logical CPUs) x the drafted capacity (2 x 100) = cpu_percent
    assert [s.frequency_hz for s in detector.settings] == pytest.approx([5.0, 10.0], rel=1e-3)
    assert [s.cpu for s in detector.settings] == pytest.approx([50.0, 100.0], rel=1e-3)
    assert not system.edges and "no graph.yaml: no edges" in system_path.read_text()

    char, model, plan = tmp_path / "c.csv", tmp_path / "model.json", tmp_path / "plan.json"
    for args in (["characterise", str(d), "--system", str(system_path), "--out", str(char)],
                 ["fit", str(system_path), str(char), "--out", str(model)],
                 ["solve", str(model), "--problem", "1", "--method", "exact", "--out", str(plan)]):
        res = runner.invoke(app, args)
        assert res.exit_code == 0, (args[0], res.output)
    assert set(json.loads(plan.read_text())["nodes"]) == {"detector", "tracker", "quiet"}


def test_init_without_graph_yaml_or_any_node_is_one_error(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(tmp_path / "run", version=9) as w:
        c = w.add_connection("/data", "std_msgs/msg/String", typestore=ts)
        w.write(c, T0, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    _write_trace(tmp_path / "run.cpu.csv", {"a": 1.0})
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump({"recordings": [{"path": "run", "cpu": "run.cpu.csv"}]}))
    with pytest.raises(InputError, match=r"run: no graph.yaml beside it and no node in the recordings"):
        draft_system(tmp_path, tmp_path / "system.yaml")
    assert not (tmp_path / "system.yaml").exists()
