"""Recordings with known message contents, written by the third-party writers (rosbags for
ROS 1 and rosbag2, the ``mcap`` package for plain MCAP): a custom stamped type, a standard
one, a type without header; out-of-order and zero stamps. The expected values are the list
itself (:class:`Sent`), not any reader's view."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SCORED = "perfros_test/msg/Scored"
PLAIN = "perfros_test/msg/Plain"
IMU = "sensor_msgs/msg/Imu"
CUSTOM_MSGS = {SCORED: "std_msgs/Header header\nfloat64 score\nint32 count\n",
               PLAIN: "float64 score\n"}
TOPICS = {"/detector/scored": SCORED, "/detector/plain": PLAIN, "/imu": IMU}


@dataclass(frozen=True)
class Sent:
    """One message as written: topic, log time, header stamp (0 = unset), score."""

    topic: str
    time_ns: int
    stamp_ns: int
    score: float


def typestore() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in CUSTOM_MSGS.items():
        ts.register(get_types_from_msg(text, name))
    return ts


def sent_messages(n: int, seed: int = 7, t0: int = 1_700_000_000_000_000_000) -> list[Sent]:
    """``n`` messages over the three topics; stamps 1-80 ms before the log time, every 13th
    one later than the next (out of order), every 17th stamped 0; scores random."""
    rng = np.random.default_rng(seed)
    out = []
    names = list(TOPICS)
    for i in range(n):
        t = t0 + i * 10_000_000
        delay = int(rng.integers(1_000_000, 80_000_000)) + (30_000_000 if i % 13 == 0 else 0)
        stamp = 0 if i % 17 == 0 else t - delay
        out.append(Sent(names[i % 3], t, stamp, float(rng.normal(5.0, 2.0))))
    return out


def _message(ts: Any, s: Sent) -> Any:
    seq = {"seq": 7} if ts.fielddefs["std_msgs/msg/Header"][1][0][0] == "seq" else {}  # ROS 1 Header
    header = ts.types["std_msgs/msg/Header"](
        **seq, stamp=ts.types["builtin_interfaces/msg/Time"](sec=s.stamp_ns // 1_000_000_000,
                                                             nanosec=s.stamp_ns % 1_000_000_000),
        frame_id="base")
    kind = TOPICS[s.topic]
    if kind == SCORED:
        return ts.types[SCORED](header=header, score=s.score, count=int(abs(s.score)))
    if kind == PLAIN:
        return ts.types[PLAIN](score=s.score)
    vec = ts.types["geometry_msgs/msg/Vector3"](x=s.score, y=0.0, z=0.0)
    quat = ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    cov = np.zeros(9, dtype=np.float64)
    return ts.types[IMU](header=header, orientation=quat, orientation_covariance=cov,
                         angular_velocity=vec, angular_velocity_covariance=cov,
                         linear_acceleration=vec, linear_acceleration_covariance=cov)


def write_ros1(path: Path, sent: list[Sent], compression: str | None = None) -> Path:
    from rosbags.rosbag1 import Writer

    ts = typestore()
    w = Writer(path)
    if compression:
        w.set_compression(Writer.CompressionFormat[compression.upper()])
    w.chunk_threshold = 4096
    with w:
        conns = {t: w.add_connection(t, m, typestore=ts, callerid="/detector") for t, m in TOPICS.items()}
        for s in sent:
            w.write(conns[s.topic], s.time_ns, ts.serialize_ros1(_message(ts, s), TOPICS[s.topic]))
    return path


def write_rosbag2(path: Path, sent: list[Sent], storage: str = "sqlite3",
                  compression: str | None = None) -> Path:
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    ts = typestore()
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    if compression:
        w.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with w:
        conns = {t: w.add_connection(t, m, typestore=ts) for t, m in TOPICS.items()}
        for s in sent:
            w.write(conns[s.topic], s.time_ns, ts.serialize_cdr(_message(ts, s), TOPICS[s.topic]))
    return path


def write_mcap(path: Path, sent: list[Sent], *, big_endian_every: int = 0, compression: str = "zstd") -> Path:
    """Plain MCAP, ``cdr`` payloads, ``ros2msg`` schemas (rosbags' ROS 2 definition text);
    every ``big_endian_every``-th message serialised big-endian."""
    from mcap.writer import CompressionType, Writer

    ts = typestore()
    with path.open("wb") as f:
        w = Writer(f, chunk_size=4096, compression=CompressionType[compression.upper()])
        w.start(profile="ros2", library="perfros-bag tests")
        chans = {}
        for topic, mtype in TOPICS.items():
            text, _ = ts.generate_msgdef(mtype, ros_version=2)
            sid = w.register_schema(name=mtype, encoding="ros2msg", data=text.encode())
            chans[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
        for i, s in enumerate(sent):
            little = not (big_endian_every and i % big_endian_every == 0)
            data = ts.serialize_cdr(_message(ts, s), TOPICS[s.topic], little_endian=little)
            w.add_message(chans[s.topic], log_time=s.time_ns, data=bytes(data), publish_time=s.time_ns)
        w.finish()
    return path


# --------------------------------------------------------------------------- node names, parameters

#: (log time offset s, node, parameter, value): what /parameter_events says, in order
PARAMETER_EVENTS = [
    (0.0, "/detector", "rate", 2), (0.0, "/detector", "mode", "fast"), (0.0, "/tracker", "gain", 1.0),
    (8.0, "/tracker", "gain", 2.5),  # changed at 80 % of the recording: 1.0 is held longest
]
ROSOUT_NAMES = ["detector", "tracker", "lonely"]  # ROS 2 /rosout spells names without a slash
GRAPH_SPAN_NS = 10_000_000_000


def _parameter_value(ts: Any, value: Any) -> Any:
    kind = {bool: 1, int: 2, float: 3, str: 4}[type(value)]
    fields = {"bool_value": False, "integer_value": 0, "double_value": 0.0, "string_value": ""}
    fields[{1: "bool_value", 2: "integer_value", 3: "double_value", 4: "string_value"}[kind]] = value
    empty = np.array([], dtype=np.int64)
    return ts.types["rcl_interfaces/msg/ParameterValue"](
        type=kind, **fields, byte_array_value=np.array([], dtype=np.uint8),
        bool_array_value=np.array([], dtype=np.bool_),
        integer_array_value=empty, double_array_value=np.array([], dtype=np.float64), string_array_value=[])


def graph_messages(ts: Any, t0: int = 1_700_000_000_000_000_000) -> list[tuple[str, str, int, Any]]:
    """(topic, type, log time, message): /parameter_events, /rosout and a data topic that
    spans the whole recording."""
    time_t = ts.types["builtin_interfaces/msg/Time"]
    out: list[tuple[str, str, int, Any]] = []
    new_seen: set[tuple[str, str]] = set()
    for offset, node, name, value in PARAMETER_EVENTS:
        t = t0 + int(offset * 1e9)
        param = ts.types["rcl_interfaces/msg/Parameter"](name=name, value=_parameter_value(ts, value))
        is_new = (node, name) not in new_seen
        new_seen.add((node, name))
        out.append(("/parameter_events", "rcl_interfaces/msg/ParameterEvent", t,
                    ts.types["rcl_interfaces/msg/ParameterEvent"](
            stamp=time_t(sec=t // 10**9, nanosec=t % 10**9), node=node,
            new_parameters=[param] if is_new else [], changed_parameters=[] if is_new else [param],
            deleted_parameters=[])))
    for i, name in enumerate(ROSOUT_NAMES):
        t = t0 + (i + 1) * 1_000_000_000
        out.append(("/rosout", "rcl_interfaces/msg/Log", t, ts.types["rcl_interfaces/msg/Log"](
            stamp=time_t(sec=t // 10**9, nanosec=t % 10**9), level=20, name=name, msg="hello",
            file="x.cpp", function="f", line=1)))
    for k in range(11):
        t = t0 + k * GRAPH_SPAN_NS // 10
        out.append(("/detector/plain", PLAIN, t, ts.types[PLAIN](score=float(k))))
    return sorted(out, key=lambda m: m[2])


def write_graph_rosbag2(path: Path, storage: str = "sqlite3") -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    with w:
        conns: dict[str, Any] = {}
        for topic, mtype, t, msg in graph_messages(ts):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, mtype, typestore=ts)
            w.write(conns[topic], t, ts.serialize_cdr(msg, mtype))
    return path


def write_graph_ros1(path: Path) -> Path:
    """A ROS 1 bag: /rosout (rosgraph_msgs/Log, names with a slash) from /logger and a data
    topic published by /detector and /helper (their callerids)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    t0 = 1_700_000_000_000_000_000
    header = ts.types["std_msgs/msg/Header"](seq=0, stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                             frame_id="")
    with Writer(path) as w:
        rosout = w.add_connection("/rosout", "rosgraph_msgs/msg/Log", typestore=ts, callerid="/logger")
        data = {c: w.add_connection("/data", "std_msgs/msg/String", typestore=ts, callerid=c)
                for c in ("/detector", "/helper")}
        for i, name in enumerate(["/detector", "/planner"]):
            log = ts.types["rosgraph_msgs/msg/Log"](header=header, level=2, name=name, msg="hi", file="a.py",
                                                    function="f", line=1, topics=["/data"])
            w.write(rosout, t0 + i, ts.serialize_ros1(log, "rosgraph_msgs/msg/Log"))
        for i, conn in enumerate(data.values()):
            w.write(conn, t0 + 10 + i,
                    ts.serialize_ros1(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    return path


def write_mcap_ros1(path: Path, sent: list[Sent]) -> Path:
    """Plain MCAP of the ROS 1 profile: ``ros1msg`` schemas (ROS 1 definitions with Noetic's
    Header, which has ``seq``), ``ros1`` payloads."""
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    for name, text in CUSTOM_MSGS.items():
        ts.register(get_types_from_msg(text, name))
    with path.open("wb") as f:
        w = Writer(f, chunk_size=4096)
        w.start(profile="ros1", library="perfros-bag tests")
        chans = {}
        for topic, mtype in TOPICS.items():
            text, _ = ts.generate_msgdef(mtype, ros_version=1)
            sid = w.register_schema(name=mtype.replace("/msg/", "/"), encoding="ros1msg", data=text.encode())
            chans[topic] = w.register_channel(topic=topic, message_encoding="ros1", schema_id=sid)
        for s in sent:
            data = ts.serialize_ros1(_message(ts, s), TOPICS[s.topic])
            w.add_message(chans[s.topic], log_time=s.time_ns, data=bytes(data), publish_time=s.time_ns)
        w.finish()
    return path


def write_mcap_json(path: Path, sent: list[Sent]) -> Path:
    """Plain MCAP with ``json`` payloads (``jsonschema`` schemas): {"score": ..., "header": ...}."""
    import json

    from mcap.writer import Writer

    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="", library="perfros-bag tests")
        sid = w.register_schema(name="Scored", encoding="jsonschema", data=b'{"type": "object"}')
        chan = w.register_channel(topic="/detector/scored", message_encoding="json", schema_id=sid)
        for s in sent:
            if s.topic == "/detector/scored":
                doc = {"header": {"stamp": {"sec": s.stamp_ns // 10**9, "nsec": s.stamp_ns % 10**9}},
                       "score": s.score, "boxes": [1] * int(abs(s.score))}
                w.add_message(chan, log_time=s.time_ns, data=json.dumps(doc).encode(), publish_time=s.time_ns)
        w.finish()
    return path


# --------------------------------------------------------------------------- chains of topics

#: a vision chain: camera -> detector -> tracker, each copying its input's header; /detector/plain
#: has no header
CHAIN_TOPICS = {"/camera/image_raw": SCORED, "/detector/circles": SCORED, "/tracker/tracks": SCORED,
                "/detector/plain": PLAIN}


def chain_messages(n: int = 120, seed: int = 3, t0: int = 1_700_000_000_000_000_000) -> list[tuple[str, int, int]]:
    """(topic, log time, stamp) of a chain with known delays: a camera frame every 33 ms,
    stamped 2-6 ms before it is logged; the detector handles 2 frames in 3 (20-60 ms later,
    the frame's stamp copied), plus every 10th output of its own with a fresh stamp (matches
    nothing); the tracker handles every detection (5-15 ms later, stamp copied); every 25th
    frame is stamped 0; /detector/plain mirrors the detector without a header."""
    rng = np.random.default_rng(seed)
    out: list[tuple[str, int, int]] = []
    for i in range(n):
        t = t0 + i * 33_000_000
        stamp = 0 if i % 25 == 0 else t - int(rng.integers(2_000_000, 6_000_000))
        out.append(("/camera/image_raw", t, stamp))
        if i % 3 == 2:
            continue
        td = t + int(rng.integers(20_000_000, 60_000_000))
        own = i % 10 == 1
        ds = td - 1_000_000 if own else stamp
        out.append(("/detector/circles", td, ds))
        out.append(("/detector/plain", td, 0))
        out.append(("/tracker/tracks", td + int(rng.integers(5_000_000, 15_000_000)), ds))
    return sorted(out, key=lambda m: m[1])


def _chain_message(ts: Any, topic: str, stamp: int) -> Any:
    if CHAIN_TOPICS[topic] == PLAIN:
        return ts.types[PLAIN](score=1.0)
    seq = {"seq": 0} if ts.fielddefs["std_msgs/msg/Header"][1][0][0] == "seq" else {}
    header = ts.types["std_msgs/msg/Header"](
        **seq, stamp=ts.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="cam")
    return ts.types[SCORED](header=header, score=1.0, count=1)


def write_chain(path: Path, kind: str = "ros1", messages: list[tuple[str, int, int]] | None = None) -> Path:
    """The chain as a ROS 1 bag (``ros1``) or a rosbag2 directory (``sqlite3``, ``mcap``)."""
    msgs = chain_messages() if messages is None else messages
    if kind == "ros1":
        from rosbags.rosbag1 import Writer as W1
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        ts = get_typestore(Stores.ROS1_NOETIC)
        for name, text in CUSTOM_MSGS.items():
            ts.register(get_types_from_msg(text, name))
        with W1(path) as w1:
            c1 = {t: w1.add_connection(t, m, typestore=ts, callerid="/" + t.split("/")[1])
                  for t, m in CHAIN_TOPICS.items()}
            for topic, t, stamp in msgs:
                w1.write(c1[topic], t, ts.serialize_ros1(_chain_message(ts, topic, stamp), CHAIN_TOPICS[topic]))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3)
    with w:
        c2 = {t: w.add_connection(t, m, typestore=ts) for t, m in CHAIN_TOPICS.items()}
        for topic, t, stamp in msgs:
            w.write(c2[topic], t, ts.serialize_cdr(_chain_message(ts, topic, stamp), CHAIN_TOPICS[topic]))
    return path


def solve_and_validate(system: Path, run: Path, tmp_path: Path) -> tuple[Any, Path]:
    """``solve`` the system (Problem 1, exact) then ``validate --json --out`` the run against
    the plan through the CLI: (the validate result, the saved validation.json)."""
    from typer.testing import CliRunner

    from perfros_bag.cli import app

    plan = tmp_path / "plan.json"
    runner = CliRunner()
    res = runner.invoke(app, ["solve", str(system), "--problem", "1", "--method", "exact", "--out", str(plan)])
    assert res.exit_code == 0, res.output
    saved = tmp_path / "validation.json"
    res = runner.invoke(app, ["validate", str(run), str(plan), "--json", "--tolerance", "100", "--out", str(saved)])
    assert res.exit_code == 0, res.output
    return res, saved
