"""space.yaml ``replay:`` without ROS: its checks (one InputError line each), the runs (every
run of the design at every factor), the recording read before anything starts (rates and
loop times against an independent reading with rosbags), the conversion of rosbag2 and MCAP
recordings to a ROS 1 bag (messages compared field by field with rosbags' own reader of the
original), the cache, and graph.yaml's ``replay`` field."""

from __future__ import annotations

import itertools
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from perfros_bag.errors import InputError
from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic, Replayed, read_graph, write_graph
from perfros_bag.sweep.replay import inspect_recording, player_argv, prepare
from perfros_bag.sweep.space import LOOP_TOPIC, load_space, parse_space, plan_runs
from tests.conftest import FIXTURES

CAMERA_BAG = FIXTURES / "app" / "camera.bag"
IMAGE = "/camera/image_raw"
INFO = "/camera/camera_info"


def _space(tmp_path: Path, replay: Any, **top: Any) -> Path:
    doc = {"duration_s": 4, "settle_s": 1, "replay": replay, **top}
    p = tmp_path / "space.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def _replay(recording: str | Path = CAMERA_BAG, **kw: Any) -> dict[str, Any]:
    return {"recording": str(recording), "replaces": ["camera"], "rates": [0.5, 2], **kw}


VARY = [{"node": "detector", "parameter": {"name": "canny_threshold"}, "arg": "canny_threshold",
         "values": [100, 200]}]

BAD = [
    ("not a mapping", [1], "replay: expected a mapping"),
    ("unknown key", _replay(speed=2), "replay: unknown key(s) 'speed'"),
    ("no recording", {"replaces": ["camera"]}, "replay.recording: must be the path of a recording"),
    ("no replaces", {"recording": "x.bag"}, "replay.replaces: must be a non-empty list"),
    ("replaces empty", _replay(replaces=[]), "replay.replaces: must be a non-empty list"),
    ("replaces bad name", _replay(replaces=["cam era"]), "replay.replaces: 'cam era'"),
    ("replaces twice", _replay(replaces=["camera", "/camera"]), "replay.replaces: lists a node twice"),
    ("topics relative", _replay(topics=["image"]), "replay.topics: 'image': must be an absolute topic name"),
    ("topics the loop topic", _replay(topics=[LOOP_TOPIC]), "replay.topics"),
    ("topics twice", _replay(topics=[IMAGE, IMAGE]), "replay.topics: lists a topic twice"),
    ("factor zero", _replay(rates=[0, 1]), "replay.rates: a factor must be a number > 0, got 0"),
    ("factor negative", _replay(rates=[-1]), "replay.rates: a factor must be a number > 0, got -1"),
    ("factor text", _replay(rates=["fast"]), "replay.rates: a factor must be a number > 0"),
    ("factor bool", _replay(rates=[True]), "replay.rates: a factor must be a number > 0"),
    ("factor nan", _replay(rates=[float("nan")]), "replay.rates: a factor must be a number > 0"),
    ("rates empty", _replay(rates=[]), "replay.rates: must be a non-empty list"),
    ("factor twice", _replay(rates=[1, 1.0]), "replay.rates: lists a factor twice"),
]


@pytest.mark.parametrize(("label", "replay", "expected"), BAD, ids=[b[0] for b in BAD])
def test_every_bad_replay_field_is_one_line_naming_the_file(tmp_path: Path, label: str, replay: Any,
                                                            expected: str) -> None:
    path = _space(tmp_path, replay)
    with pytest.raises(InputError) as err:
        load_space(path)
    text = str(err.value)
    assert "\n" not in text and str(path) in text and expected in text, (label, text)


def test_a_varied_node_cannot_be_replaced(tmp_path: Path) -> None:
    vary = [{"node": "camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate", "values": [5]}]
    with pytest.raises(InputError, match="node /camera is replaced by the replay"):
        load_space(_space(tmp_path, _replay(), vary=vary))


def test_every_run_of_the_design_is_played_at_every_factor(tmp_path: Path) -> None:
    space = load_space(_space(tmp_path, _replay(rates=[0.5, 1, 4]), vary=VARY, design="grid", repeats=2))
    runs = plan_runs(space, {"canny_threshold": "200"})
    expected = [(v, f, r) for v, f, r in itertools.product([100, 200], [0.5, 1.0, 4.0], [1, 2])]
    assert [(r.values["detector"], r.factor, r.repeat) for r in runs] == expected
    assert len({r.name for r in runs}) == len(runs)
    assert runs[0].name == "detector-canny_threshold-100__replay-x0.5_r1"
    assert all(r.args == {"canny_threshold": str(r.values["detector"])} for r in runs)
    # without vary: the factors alone; the recording resolves against space.yaml's folder
    alone = load_space(_space(tmp_path, _replay(recording="rec/camera.bag", rates=[2, 0.25])))
    assert [(r.name, r.factor, dict(r.values)) for r in plan_runs(alone, {})] == [
        ("replay-x2", 2.0, {}), ("replay-x0.25", 0.25, {})]
    assert alone.replay is not None and alone.replay.recording == (tmp_path / "rec" / "camera.bag").absolute()
    assert alone.parameters() == {"camera": alone.parameters()["camera"]}
    assert (alone.parameters()["camera"].name, alone.parameters()["camera"].unit) == ("rate", "Hz")
    # the loop topic is never recorded, whatever exclude says
    assert not alone.recorded(LOOP_TOPIC) and alone.recorded(IMAGE)
    assert alone.record_exclude == r"/perfros_replay/loop"
    user = load_space(_space(tmp_path, _replay(), exclude=".*/debug"))
    assert user.record_exclude == r"(?:.*/debug)|/perfros_replay/loop"


def _independent(path: Path) -> dict[str, np.ndarray]:
    """Every topic's receive times by rosbags' own reader (not the tool's)."""
    from rosbags.highlevel import AnyReader

    times: dict[str, list[int]] = {}
    with AnyReader([path]) as reader:
        for conn, t, _raw in reader.messages():
            times.setdefault(conn.topic, []).append(t)
    return {k: np.array(v, dtype=np.int64) for k, v in times.items()}


def test_the_recording_gives_each_replaced_node_its_topics_rate_and_loop(tmp_path: Path) -> None:
    space = load_space(_space(tmp_path, _replay()))
    assert space.replay is not None
    inspected = inspect_recording(space.replay)
    times = _independent(CAMERA_BAG)
    (stand,) = inspected.stands
    assert stand.node == "/camera" and set(stand.topics) == {IMAGE, INFO}  # default: what /camera published
    rates = {t: (len(v) - 1) / ((v[-1] - v[0]) / 1e9) for t, v in times.items()}
    assert stand.rate_hz == pytest.approx(max(rates.values()), rel=1e-12)
    assert inspected.settings(2) == {"camera": float(f"{max(rates.values()) * 2:.4g}")}
    # the loop ends one mean period after the last message (the topic whose period ends last)
    begin = min(int(v[0]) for v in times.values())
    ends = [int(v[-1]) + (int(v[-1]) - int(v[0])) / (len(v) - 1) - (int(v[0]) - begin) for v in times.values()]
    assert abs(stand.loop_end_ns - max(ends)) <= 1
    only = load_space(_space(tmp_path, _replay(topics=[IMAGE])))
    assert only.replay is not None
    (s,) = inspect_recording(only.replay).stands
    v = times[IMAGE]
    assert s.topics == (IMAGE,) and abs(s.loop_end_ns - (int(v[-1]) + (int(v[-1]) - int(v[0])) / (len(v) - 1))) <= 1


def _bad_recording(tmp_path: Path, recording: Path, **kw: Any) -> str:
    space = load_space(_space(tmp_path, _replay(recording=recording, **kw)))
    assert space.replay is not None
    with pytest.raises(InputError) as err:
        inspect_recording(space.replay)
    text = str(err.value)
    assert "\n" not in text
    return text


def _short_bag(path: Path, seconds: float, rate: float = 10.0) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "std_msgs/msg/String"
    with Writer(path) as writer:
        conn = writer.add_connection("/camera/status", msgtype, typestore=store, callerid="/camera")
        for i in range(int(seconds * rate) + 1):
            writer.write(conn, 10**18 + int(i * 1e9 / rate),
                         store.serialize_ros1(store.types[msgtype](f"{i}"), msgtype))
    return path


def test_bad_recordings_are_one_line(tmp_path: Path) -> None:
    assert "replay: the recording does not exist" in _bad_recording(tmp_path, tmp_path / "nope.bag")
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(CAMERA_BAG.read_bytes()[:5000])
    assert str(damaged) in _bad_recording(tmp_path, damaged)
    text = _bad_recording(tmp_path, CAMERA_BAG, topics=["/camera/depth"])
    assert "replay: topic(s) /camera/depth not in the recording" in text and IMAGE in text
    short = _short_bag(tmp_path / "short.bag", 0.5)
    assert "replay: the replayed topics span 0.5 s, shorter than 1 s" in _bad_recording(tmp_path, short)
    assert "replaced node /lidar published no topic" in _bad_recording(
        tmp_path, _short_bag(tmp_path / "ok.bag", 2), replaces=["lidar"])


def test_a_replay_recording_that_is_a_named_pipe_is_refused_at_once(tmp_path: Path) -> None:
    """A FIFO called x.bag blocked forever (opening it waits for a writer): it is no regular
    file, said before it is opened. Run in a child process: its timeout detects a hang."""
    import os
    import subprocess
    import sys

    fifo = tmp_path / "x.bag"
    os.mkfifo(fifo)
    space = _space(tmp_path, _replay(recording=fifo))
    code = ("import sys\nfrom perfros_bag.errors import InputError\nfrom perfros_bag.sweep.replay import "
            "inspect_recording\nfrom perfros_bag.sweep.space import load_space\ntry:\n"
            f"    inspect_recording(load_space({str(space)!r}).replay)\n"
            "except InputError as exc:\n    print(exc)\n    sys.exit(2)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30,
                          cwd=Path(__file__).resolve().parent.parent)
    assert done.returncode == 2, done.stderr
    assert done.stdout.strip() \
        == f"{fifo}: is not a regular file (a named pipe, device or socket), expected a recording"
    info = subprocess.run([sys.executable, "-m", "perfros_bag", "info", str(fifo)], capture_output=True, text=True,
                          timeout=30, cwd=Path(__file__).resolve().parent.parent)
    assert info.returncode == 2 and "is not a regular file" in info.stderr and "Traceback" not in info.stderr
    system = tmp_path / "system.yaml"  # a YAML input that is a pipe: the same, not a hang
    os.mkfifo(system)
    solve = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(system)], capture_output=True,
                           text=True, timeout=30, cwd=Path(__file__).resolve().parent.parent)
    assert solve.returncode == 2 and f"{system}: is not a regular file" in solve.stderr


def _converted(tmp_path: Path, source: Path) -> tuple[Path, Path]:
    space = load_space(_space(tmp_path, _replay(recording=source)))
    assert space.replay is not None
    out = tmp_path / f"runs-{source.name}"
    prepared = prepare(inspect_recording(space.replay), out)
    return prepared.bag, prepared.loops["/camera"]


def _to_rosbag2(tmp_path: Path, storage: str) -> Path:
    from rosbags.convert import convert

    dst = tmp_path / f"camera_{storage}"
    convert([CAMERA_BAG], dst, storage, 8, None, "file", None, None, [], [], [], [])
    return dst


def _messages(path: Path) -> list[tuple[str, int, Any]]:
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def _same(a: Any, b: Any, path: str = "") -> None:
    """Two decoded messages hold the same values (but the Header's ``seq``: a ROS 2 recording
    has none, rosbags' converter gives it 0)."""
    if isinstance(a, np.ndarray):
        assert np.array_equal(a, np.asarray(b)), path
        return
    fields = getattr(a, "__dataclass_fields__", None)
    if fields is None:
        assert a == b, path
        return
    for name in fields:
        if name in ("__msgtype__", "seq"):
            continue
        _same(getattr(a, name), getattr(b, name), f"{path}.{name}")


@pytest.mark.parametrize("kind", ["sqlite3", "mcap", "plain-mcap"])
def test_rosbag2_and_mcap_recordings_convert_to_the_same_messages(tmp_path: Path, kind: str) -> None:
    source = _to_rosbag2(tmp_path, "mcap" if kind != "sqlite3" else "sqlite3")
    if kind == "plain-mcap":
        source = next(source.glob("*.mcap"))
    bag, loop = _converted(tmp_path, source)
    original = _messages(CAMERA_BAG)
    converted = _messages(bag)
    assert [(t, s) for t, s, _ in converted] == [(t, s) for t, s, _ in original]
    for (_t, _s, a), (_u, _v, b) in zip(original, converted, strict=True):
        _same(b, a)
    from rosbags.rosbag1 import Reader

    with Reader(bag) as reader:
        assert {(c.topic, c.ext.callerid) for c in reader.connections} == {(IMAGE, "/camera"), (INFO, "/camera")}
        # Debian's roscpp checks this: the ROS 1 md5 of sensor_msgs/Image
        assert next(c.digest for c in reader.connections if c.topic == IMAGE) == "060021388200f6f0f447d0fcd9c64743"
    with Reader(loop) as reader:
        (conn,) = reader.connections
        assert conn.topic == LOOP_TOPIC
        assert [t for _c, t, _r in reader.messages()] == [inspect_recording(
            load_space(tmp_path / "space.yaml").replay).stands[0].loop_end_ns]  # type: ignore[arg-type]


def test_a_converted_recording_is_cached_and_not_converted_again(tmp_path: Path) -> None:
    source = _to_rosbag2(tmp_path, "mcap")
    bag, loop = _converted(tmp_path, source)
    stamps = (bag.stat().st_mtime_ns, loop.stat().st_mtime_ns)
    again, loop_again = _converted(tmp_path, source)
    assert (again, loop_again) == (bag, loop) and (again.stat().st_mtime_ns, loop_again.stat().st_mtime_ns) == stamps
    assert sorted(p.name for p in bag.parent.iterdir()) == sorted([bag.name, loop.name])  # no temporary left
    # a ROS 1 recording is copied (its replayed topics) the same way, under its own name
    ros1, _ = _converted(tmp_path, CAMERA_BAG)
    assert ros1.name.startswith("camera-") and ros1.suffix == ".bag"
    assert [(t, s) for t, s, _ in _messages(ros1)] == [(t, s) for t, s, _ in _messages(CAMERA_BAG)]


def test_a_type_rosbags_cannot_convert_is_one_line_naming_type_and_topic(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "custom.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema("my_pkg/msg/Blob", "ros2msg", b"this is not a message definition !!")
        channel = writer.register_channel("/camera/blob", "cdr", schema)
        for i in range(21):
            writer.add_message(channel, log_time=10**18 + i * 10**8, data=b"\x00\x01\x00\x00", publish_time=0)
        writer.finish()
    space = load_space(_space(tmp_path, _replay(recording=path)))
    assert space.replay is not None
    with pytest.raises(InputError) as err:
        prepare(inspect_recording(space.replay), tmp_path / "runs")
    text = str(err.value)
    assert "\n" not in text and "cannot convert message type my_pkg/msg/Blob of topic /camera/blob" in text
    assert not list((tmp_path / "runs" / ".replay").iterdir())  # nothing half-written kept


def test_the_player_plays_the_node_topics_and_its_loop_as_that_node(tmp_path: Path) -> None:
    space = load_space(_space(tmp_path, _replay(replaces=["robot1/camera"], topics=[IMAGE])))
    assert space.replay is not None
    shutil.copy(CAMERA_BAG, tmp_path / "camera.bag")
    prepared = prepare(inspect_recording(space.replay), tmp_path / "runs")
    argv = player_argv(prepared, "/robot1/camera", 2.0)
    assert argv[-2:] == ["__name:=camera", "__ns:=/robot1"]
    assert "--loop" in argv and "--rate=2.0" in argv and "--clock" not in argv
    assert argv[argv.index("--topics") + 1:-2] == [IMAGE, LOOP_TOPIC]
    assert str(prepared.bag) in argv and str(prepared.loops["/robot1/camera"]) in argv


def test_graph_yaml_marks_the_player_standing_in_for_a_replaced_node(tmp_path: Path) -> None:
    graph = Graph((GraphNode("/camera", 42, "/usr/lib/rosbag/play", True, Replayed("camera.bag", 2.0)),
                   GraphNode("/detector", 43, "/usr/lib/opencv_apps/hough_circles")),
                  (GraphTopic(IMAGE, "sensor_msgs/Image", ("/camera",), ("/detector",)),), "replay-x2")
    write_graph(tmp_path / "graph.yaml", graph)
    doc = yaml.safe_load((tmp_path / "graph.yaml").read_text())
    assert doc["nodes"][0]["replay"] == {"recording": "camera.bag", "factor": 2.0}
    assert "replay" not in doc["nodes"][1]  # the existing contract, unchanged for other nodes
    assert read_graph(tmp_path / "graph.yaml") == graph
    doc["nodes"][0]["replay"] = {"recording": "camera.bag", "factor": 0}
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match=r"nodes\[0\].replay"):
        read_graph(tmp_path / "graph.yaml")


def test_vary_may_be_left_out_only_with_replay(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="missing 'vary:'"):
        parse_space({"duration_s": 4}, tmp_path / "space.yaml")
    assert parse_space({"replay": _replay()}, tmp_path / "space.yaml").vary == ()


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_a_latched_topic_stays_latched(tmp_path: Path, kind: str) -> None:
    """rosbag play re-publishes a latched topic's last message to late subscribers only when
    the bag says it is latched (ROS 1 ``latching``; rosbag2's transient-local offer)."""
    from rosbags.convert import convert
    from rosbags.rosbag1 import Reader, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "std_msgs/msg/String"
    source = tmp_path / "latched.bag"
    with Writer(source) as writer:
        plain = writer.add_connection("/camera/status", msgtype, typestore=store, callerid="/camera")
        latched = writer.add_connection("/camera/config", msgtype, typestore=store, callerid="/camera", latching=1)
        for i in range(21):
            t = 10**18 + i * 10**8
            writer.write(plain, t, store.serialize_ros1(store.types[msgtype](f"{i}"), msgtype))
            if i % 10 == 0:
                writer.write(latched, t, store.serialize_ros1(store.types[msgtype]("config"), msgtype))
    if kind != "ros1":
        dst = tmp_path / f"latched_{kind}"
        convert([source], dst, kind, 8, None, "file", None, None, [], [], [], [])
        source = dst
    bag, _loop = _converted(tmp_path, source)
    with Reader(bag) as reader:
        assert {c.topic: c.ext.latching for c in reader.connections} == {"/camera/status": 0, "/camera/config": 1}
