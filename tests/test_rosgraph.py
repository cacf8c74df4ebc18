"""Node names and parameter values from the recording itself (/rosout, /parameter_events,
ROS 1 callerid) for recordings without a manifest (perfros_bag/ingest/rosgraph.py)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
from conftest import REALBAGS
from contents_gen import PARAMETER_EVENTS, ROSOUT_NAMES, write_graph_ros1, write_graph_rosbag2
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import PerfrosWarning
from perfros_bag.ingest import read_recording
from perfros_bag.ingest.rosgraph import read_graph

SYSTEM = """
computers: [{name: robot1, kind: robot, capacity: 100}]
nodes:
  - {name: detector, weight: 1, parameter: {name: rate}, topics: [/detector/plain],
     settings: [{value: 1, cpu: 10, performance: 10}, {value: 2, cpu: 20, performance: 20}]}
  - {name: tracker, weight: 1, parameter: {name: gain},
     settings: [{value: 1, cpu: 10, performance: 10}, {value: 2.5, cpu: 20, performance: 20}]}
"""


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_parameters_and_names_as_written(tmp_path: Path, storage: str) -> None:
    path = write_graph_rosbag2(tmp_path / "rec", storage)
    graph = read_graph(path, read_recording(path))
    assert {"/" + n for n in ROSOUT_NAMES} <= set(graph.nodes)
    for node in {n for _, n, _, _ in PARAMETER_EVENTS}:
        written: dict[str, list[object]] = {}
        for _, n, name, value in PARAMETER_EVENTS:
            if n == node:
                written.setdefault(name, []).append(value)
        assert {k: [v for _, v in h] for k, h in graph.parameters[node].items()} == written
    assert graph.value("/detector", "rate") == 2
    with pytest.warns(PerfrosWarning, match=r"/tracker parameter gain changed during the recording \(1.0 -> 2.5\)"):
        assert graph.value("/tracker", "gain") == 1.0  # held 8 of the 10 s


def test_characterise_takes_settings_from_parameter_events(tmp_path: Path) -> None:
    from perfros_bag.characterisation.csvfile import read_characterisation

    d = tmp_path / "recs"
    d.mkdir()
    write_graph_rosbag2(d / "run")
    system = tmp_path / "system.yaml"
    system.write_text(SYSTEM)
    out = tmp_path / "c.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--system", str(system), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "parameter gain changed during the recording" in res.stderr
    rows = {r.node: r for r in read_characterisation(out).rows if r.node in ("detector", "tracker")}
    assert (rows["detector"].parameter, rows["detector"].value) == ("rate", 2)
    # the tracker has no topic and no CPU in this recording: no row, nothing to carry


def test_the_manifest_wins_over_parameter_events(tmp_path: Path) -> None:
    from perfros_bag.characterisation.csvfile import read_characterisation

    d = tmp_path / "recs"
    d.mkdir()
    write_graph_rosbag2(d / "run")
    (tmp_path / "system.yaml").write_text(SYSTEM)
    (d / "manifest.yaml").write_text("system: ../system.yaml\nrecordings:\n  - {path: run, settings: {detector: 1}}\n")
    out = tmp_path / "c.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert {r.value for r in read_characterisation(out).rows if r.node == "detector"} == {1}


def test_ros1_names_from_callerid_and_rosout(tmp_path: Path) -> None:
    path = write_graph_ros1(tmp_path / "a.bag")
    graph = read_graph(path, read_recording(path))
    assert set(graph.nodes) == {"/logger", "/detector", "/helper", "/planner"}
    assert graph.parameters == {}


def test_realbag_rosout_names_equal_the_library() -> None:
    """Reference: the mcap package's linear reader (no index) and rosbags deserialising with
    the file's own schema. (rosbags' AnyReader yields no message of this file at all.)"""
    from mcap.reader import NonSeekingReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    path = REALBAGS / "rosbag2_mcap_talker"
    if not path.is_dir():
        pytest.skip("no shared/realbags")
    names = set()
    with (path / "talker.mcap").open("rb") as f:
        for schema, channel, message in NonSeekingReader(f).iter_messages():
            if channel.topic == "/rosout":
                ts = get_typestore(Stores.EMPTY)
                ts.register(get_types_from_msg(schema.data.decode(), schema.name))
                names.add(ts.deserialize_cdr(message.data, schema.name).name)
    with warnings.catch_warnings():
        warnings.simplefilter("error", PerfrosWarning)
        graph = read_graph(path, read_recording(path))
    assert names and set(graph.nodes) == {"/" + n.lstrip("/") for n in names}
