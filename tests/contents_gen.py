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
    header = ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=s.stamp_ns // 1_000_000_000,
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
