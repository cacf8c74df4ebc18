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
    with pytest.raises(InputError, match=r"no manifest.yaml \(record the runs with `perfros-bag sweep` first\)"):
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
