"""Writers for synthetic recordings with known contents (tests and benchmarks of the readers).

Every writer takes the same list of :class:`Msg` and writes it with a third-party writer
(rosbags for ROS 1 and rosbag2, the ``mcap`` package for plain MCAP), so the reader under test
is checked against the list itself (:func:`expected`), not against another reader; where a
test needs a file no writer makes (damaged, crafted), :func:`mcap_library_decode` and
:func:`anyreader_decode` give the third-party readers' view of it.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perfros_bag.ingest.stats import RecordingStats

# (ROS 2 type, ROS 1 type, ROS 1 md5) of the types the generators use
TYPES = {
    "std_msgs/msg/String": ("std_msgs/String", "992ce8a1687cec8c8bd883ec73ca41d1", "string data"),
    "sensor_msgs/msg/Image": ("sensor_msgs/Image", "060021388200f6f0f447d0fcd9c64743",
                              "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                              "uint8 is_bigendian\nuint32 step\nuint8[] data"),
}


@dataclass(frozen=True)
class Msg:
    topic: str
    msgtype: str  # ROS 2 spelling, e.g. std_msgs/msg/String
    time_ns: int
    payload: bytes
    callerid: str = "/talker"


@dataclass
class Expected:
    msgtype: str
    count: int
    nbytes: int
    times: list[int]
    publishers: set[str]


def expected(msgs: Iterable[Msg], ros1: bool = False) -> dict[str, Expected]:
    out: dict[str, Expected] = {}
    for m in msgs:
        mtype = TYPES[m.msgtype][0] if ros1 else m.msgtype
        e = out.setdefault(m.topic, Expected(mtype, 0, 0, [], set()))
        e.count += 1
        e.nbytes += len(m.payload)
        e.times.append(m.time_ns)
        e.publishers.add(m.callerid)
    for e in out.values():
        e.times.sort()
    return out


def _conn_key(m: Msg, ros1: bool) -> tuple[str, ...]:
    return (m.topic, m.msgtype, m.callerid) if ros1 else (m.topic, m.msgtype)


def write_ros1(path: Path, msgs: Sequence[Msg], compression: str | None = None,
               chunk_threshold: int | None = None) -> Path:
    from rosbags.rosbag1 import Writer

    w = Writer(path)
    if compression:
        w.set_compression(Writer.CompressionFormat[compression.upper()])
    if chunk_threshold:
        w.chunk_threshold = chunk_threshold
    conns = {}
    with w:
        for m in msgs:
            key = _conn_key(m, True)
            if key not in conns:
                _, md5, msgdef = TYPES[m.msgtype]
                conns[key] = w.add_connection(m.topic, m.msgtype, msgdef=msgdef, md5sum=md5,
                                              callerid=m.callerid)
            w.write(conns[key], m.time_ns, m.payload)
    return path


def write_rosbag2(path: Path, msgs: Sequence[Msg], storage: str = "sqlite3",
                  compression: str | None = None, declare: Sequence[tuple[str, str]] = ()) -> Path:
    """``compression``: None, "file" or "message" (zstd). ``declare``: extra (topic, type)
    connections without messages."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    w = Writer(path, version=9, storage_plugin=plugin)
    if compression:
        w.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    conns = {}
    with w:
        for topic, mtype in declare:
            conns[(topic, mtype)] = w.add_connection(topic, mtype, typestore=ts)
        for m in msgs:
            key = _conn_key(m, False)
            if key not in conns:
                conns[key] = w.add_connection(m.topic, m.msgtype, typestore=ts)
            w.write(conns[key], m.time_ns, m.payload)
    return path


def write_mcap(path: Path, msgs: Sequence[Msg], *, chunked: bool = True, compression: str = "zstd",
               index: bool = True, summary: bool = True, encoding: str = "cdr",
               chunk_size: int = 1 << 20, schemaless: bool = False, callerid: bool = False) -> Path:
    """``callerid``: one channel per (topic, callerid) with the ROS 1 profile's ``callerid``
    channel metadata."""
    from mcap.writer import CompressionType, IndexType, Writer

    with path.open("wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=CompressionType[compression.upper() or "NONE"],
                   index_types=IndexType.ALL if index else IndexType.NONE, use_chunking=chunked,
                   use_statistics=summary, use_summary_offsets=summary,
                   repeat_channels=summary, repeat_schemas=summary)
        w.start(profile="ros2" if encoding == "cdr" else "", library="perfros-bag tests")
        channels: dict[tuple[str, ...], int] = {}
        for m in msgs:
            key = _conn_key(m, callerid)
            if key not in channels:
                sid = 0 if schemaless else w.register_schema(
                    name=m.msgtype, encoding="ros2msg" if encoding == "cdr" else "jsonschema",
                    data=TYPES[m.msgtype][2].encode())
                channels[key] = w.register_channel(topic=m.topic, message_encoding=encoding, schema_id=sid,
                                                   metadata={"callerid": m.callerid} if callerid else {})
            w.add_message(channels[key], log_time=m.time_ns, data=m.payload, publish_time=m.time_ns)
        w.finish()
    return path


def random_msgs(rng: np.random.Generator, n: int, topics: int = 3, max_size: int = 300,
                t0: int = 1_700_000_000_000_000_000) -> list[Msg]:
    """``n`` messages on ``topics`` topics (two callerids on topic 0), random sizes and times."""
    names = [f"/t{i}" for i in range(topics)]
    times = t0 + np.cumsum(rng.integers(1, 50_000_000, size=n))
    out = []
    for i, t in enumerate(times.tolist()):
        k = int(rng.integers(0, topics))
        size = int(rng.integers(0, max_size))
        caller = "/pub_b" if (k == 0 and i % 2) else "/pub_a"
        mtype = "sensor_msgs/msg/Image" if k == 1 else "std_msgs/msg/String"
        out.append(Msg(names[k], mtype, int(t), rng.bytes(size), caller))
    return out


def by_topic(stats: RecordingStats) -> dict[str, tuple[int, int, list[int]]]:
    """(messages, payload bytes, sorted times) per topic, as a reader reported them."""
    return {t: (s.messages, s.bytes, s.times_ns.tolist()) for t, s in stats.topics.items()}


def mcap_library_decode(path: Path) -> dict[str, tuple[int, int, list[int]]]:
    """Counts, payload bytes and log times per topic, by the ``mcap`` package's linear reader
    (no summary, no message index)."""
    from mcap.reader import NonSeekingReader

    out: dict[str, tuple[int, int, list[int]]] = {}
    with path.open("rb") as f:
        for _schema, channel, message in NonSeekingReader(f).iter_messages():
            n, nbytes, times = out.get(channel.topic, (0, 0, []))
            out[channel.topic] = (n + 1, nbytes + len(message.data), [*times, message.log_time])
    return {t: (n, b, sorted(ts)) for t, (n, b, ts) in out.items()}


def anyreader_decode(path: Path) -> dict[str, tuple[int, int, list[int]]]:
    """The same by rosbags' AnyReader (rosbag2 message compression undone)."""
    from rosbags.highlevel import AnyReader

    out: dict[str, tuple[int, int, list[int]]] = {}
    with AnyReader([path]) as reader:
        for conn, ts, raw in reader.messages():
            n, nbytes, times = out.get(conn.topic, (0, 0, []))
            out[conn.topic] = (n + 1, nbytes + len(raw), [*times, ts])
    return {t: (n, b, sorted(tt)) for t, (n, b, tt) in out.items()}


def copy_tree(src: Path, dst: Path) -> Path:
    if src.is_dir():
        shutil.copytree(src, dst)
        for p in dst.rglob("*"):
            p.chmod(0o644 if p.is_file() else 0o755)
        dst.chmod(0o755)
    else:
        shutil.copy(src, dst)
        dst.chmod(0o644)
    return dst
