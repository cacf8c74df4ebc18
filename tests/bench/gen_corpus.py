"""Generate recordings with known contents, in every format, for tests and benchmarks.

Each recording holds ``std_msgs/UInt8MultiArray`` messages of known sizes at known
(jittered) times on a few topics; :func:`write_recording` returns the ground truth
(per topic: count, payload bytes as stored, every timestamp), computed here and not by
any reader. Payloads are random bytes (incompressible), sliced from one pool so that
gigabytes are written quickly. Formats: ``ros1`` (.bag, chunks none/lz4/bz2),
``rosbag2-sqlite3`` and ``rosbag2-mcap`` (rosbag2 directories) and ``mcap`` (plain
MCAP written with the ``mcap`` package, chunks none/zstd/lz4).

Command line: ``python tests/bench/gen_corpus.py OUTDIR --gb 2 --recordings 20``
writes a mixed-format corpus (not in git: use tests/bench/data/ or a temp dir).
"""

from __future__ import annotations

import argparse
import heapq
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MSGTYPE = "std_msgs/msg/UInt8MultiArray"
FORMATS = ("ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap")
_POOL_BYTES = 32 << 20
_POOL: np.ndarray | None = None


@dataclass(frozen=True)
class TopicSpec:
    name: str
    rate_hz: float
    payload: int  # data bytes per message (the serialised message adds a small header)
    callerid: str = ""


@dataclass
class Truth:
    """What a reader must find for one topic."""

    topic: str
    messages: int = 0
    bytes: int = 0
    times: list[int] = field(default_factory=list)


def default_topics(scale: float = 1.0) -> list[TopicSpec]:
    """A robot-like mix: a camera (130 KB), a scan (2 KB), an IMU and odometry."""
    return [
        TopicSpec("/camera/image_raw", 10.0, int(130_000 * scale), "/camera_driver"),
        TopicSpec("/scan", 40.0, int(2_000 * scale), "/lidar_driver"),
        TopicSpec("/imu/data", 200.0, 300, "/imu_driver"),
        TopicSpec("/odom", 50.0, 700, "/base_controller"),
    ]


def _pool() -> np.ndarray:
    global _POOL
    if _POOL is None:
        _POOL = np.random.default_rng(12345).integers(0, 256, _POOL_BYTES, dtype=np.uint8)
    return _POOL


def _schedule(topics: list[TopicSpec], duration_s: float, start_ns: int,
              seed: int) -> Iterator[tuple[int, int, int]]:
    """(time_ns, topic index, payload size) in time order; jittered periods, unique times."""
    rng = np.random.default_rng(seed)
    streams = []
    for i, spec in enumerate(topics):
        n = max(1, int(duration_s * spec.rate_hz))
        period = 1e9 / spec.rate_hz
        jitter = rng.uniform(-0.2, 0.2, n) * period
        times = (start_ns + i * 1013 + np.arange(n) * period + jitter).astype(np.int64)
        times = np.maximum.accumulate(times)
        sizes = np.full(n, spec.payload, dtype=np.int64)
        if spec.payload > 64:  # vary sizes a little so byte totals are not count * size
            sizes += rng.integers(-32, 33, n)
        streams.append(_stream(times, i, sizes))
    return heapq.merge(*streams)


def _stream(times: np.ndarray, index: int, sizes: np.ndarray) -> Iterator[tuple[int, int, int]]:
    for t, s in zip(times.tolist(), sizes.tolist(), strict=True):
        yield t, index, s


def _payload(size: int, offset: int, ros1: bool) -> bytes:
    pool = _pool()
    start = offset % (_POOL_BYTES - size - 1)
    data = pool[start:start + size].tobytes()
    if ros1:
        return struct.pack("<III", 0, 0, size) + data
    return b"\x00\x01\x00\x00" + struct.pack("<III", 0, 0, size) + data


def write_recording(path: Path, fmt: str, topics: list[TopicSpec], duration_s: float, *,
                    chunk_bytes: int = 1 << 20, compression: str = "none", seed: int = 0,
                    start_ns: int = 1_700_000_000_000_000_000) -> dict[str, Truth]:
    """Write one recording at ``path`` (a file, or a directory for rosbag2); return the truth."""
    truth = {spec.name: Truth(spec.name) for spec in topics}
    events = _schedule(topics, duration_s, start_ns, seed)
    writers = {"ros1": _write_ros1, "rosbag2-sqlite3": _write_rosbag2,
               "rosbag2-mcap": _write_rosbag2, "mcap": _write_mcap}
    if fmt not in writers:
        raise ValueError(f"unknown format {fmt!r}; expected one of {FORMATS}")

    def record(events: Iterator[tuple[int, int, int]], ros1: bool) -> Iterator[tuple[int, int, bytes]]:
        offset = seed * 7919
        for t, i, size in events:
            data = _payload(size, offset, ros1)
            offset += size * 31 + 17
            entry = truth[topics[i].name]
            entry.messages += 1
            entry.bytes += len(data)
            entry.times.append(t)
            yield t, i, data

    writers[fmt](path, fmt, topics, record(events, fmt == "ros1"), chunk_bytes, compression)
    return truth


def _write_ros1(path: Path, fmt: str, topics: list[TopicSpec],
                messages: Iterator[tuple[int, int, bytes]], chunk_bytes: int,
                compression: str) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    writer = Writer(path)
    writer.chunk_threshold = chunk_bytes
    if compression != "none":
        writer.set_compression(Writer.CompressionFormat[compression.upper()])
    with writer:
        conns = [writer.add_connection(spec.name, MSGTYPE, typestore=store,
                                       callerid=spec.callerid or None) for spec in topics]
        for t, i, data in messages:
            writer.write(conns[i], t, data)


def _write_rosbag2(path: Path, fmt: str, topics: list[TopicSpec],
                   messages: Iterator[tuple[int, int, bytes]], chunk_bytes: int,
                   compression: str) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if fmt == "rosbag2-mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=8, storage_plugin=plugin) as writer:
        conns = [writer.add_connection(spec.name, MSGTYPE, typestore=store) for spec in topics]
        for t, i, data in messages:
            writer.write(conns[i], t, data)


def _write_mcap(path: Path, fmt: str, topics: list[TopicSpec],
                messages: Iterator[tuple[int, int, bytes]], chunk_bytes: int,
                compression: str) -> None:
    from mcap.writer import CompressionType, Writer
    from rosbags.typesys import Stores, get_typestore

    msgdef, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(MSGTYPE, ros_version=2)
    with path.open("wb") as stream:
        writer = Writer(stream, chunk_size=chunk_bytes,
                        compression=CompressionType[compression.upper()])
        writer.start(profile="ros2", library="perfros-bag gen_corpus")
        schema = writer.register_schema(MSGTYPE, "ros2msg", msgdef.encode())
        chans = [writer.register_channel(spec.name, "cdr", schema) for spec in topics]
        seq = 0
        for t, i, data in messages:
            writer.add_message(chans[i], log_time=t, data=data, publish_time=t, sequence=seq)
            seq += 1
        writer.finish()


def corpus_plan(total_bytes: int, recordings: int) -> list[tuple[str, str, float]]:
    """(name, format, duration_s) for a mixed corpus of about ``total_bytes``."""
    rate = sum(s.rate_hz * s.payload for s in default_topics())  # bytes per second
    duration = total_bytes / recordings / rate
    plan = []
    for k in range(recordings):
        fmt = FORMATS[k % len(FORMATS)]
        suffix = {"ros1": ".bag", "mcap": ".mcap"}.get(fmt, "")
        plan.append((f"robot{k:02d}_{fmt}{suffix}", fmt, duration))
    return plan


def write_corpus(outdir: Path, total_bytes: int, recordings: int) -> list[Path]:
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (name, fmt, duration) in enumerate(corpus_plan(total_bytes, recordings)):
        target = outdir / name
        write_recording(target, fmt, default_topics(), duration, chunk_bytes=4 << 20, seed=k)
        paths.append(target)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outdir", type=Path)
    parser.add_argument("--gb", type=float, default=2.0)
    parser.add_argument("--recordings", type=int, default=20)
    args = parser.parse_args(argv)
    for path in write_corpus(args.outdir, int(args.gb * 1e9), args.recordings):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
