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
    rospy = [[["/rosout", 0, [[1, 1257, 0, True]]], ["/q/never", 0, [[3, 161, 0, True]]], ["/q/x", 12, [[3, 173, 1, True]]]],
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
                computers={"robot": PlannedComputer("robot", 150.0, 10.0), "server": PlannedComputer("server", 400.0, 5.0)},
                nodes={"camera": PlannedNode("robot", 1.0, 50.0, 0.5, "rate", 7.6),
                       "detector": PlannedNode("server", 5.0, 90.0, 0.5, "thr", 150.0)})
    run = plan_run(plan, space, {"camera_rate": "10", "gain": "1.5"})
    # whole-number parameters rounded; a node the plan leaves out at its launch default
    assert dict(run.values) == {"camera": 8, "detector": 150, "other": 1.5}
    assert dict(run.args) == {"camera_rate": "8", "gain": "1.5"}
    assert dict(run.params) == {"/detector/thr": 150}
    assert computer_cores(plan, 100.0) == {"robot": 1.5, "server": 4.0}
