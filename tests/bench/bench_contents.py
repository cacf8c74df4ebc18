"""Benchmark: latency of every stamped topic (perfros_bag/ingest/contents.py) against the
index-only read and against rosbags deserialising every header.

Data (written once into tests/bench/data/contents/, git-ignored): 1 000 000 messages
(``--scale`` times that) on 4 topics, three of them ``geometry_msgs/PointStamped`` (header +
point) and one ``std_msgs/String``, in four formats: ROS 1 bag (rosbags writer, Noetic
types: the Header has ``seq``), rosbag2 sqlite3, rosbag2 mcap (rosbags writer, Humble types)
and plain MCAP with 1 MiB zstd chunks (the ``mcap`` writer, ``ros2msg`` schemas). Payloads are
serialised once by rosbags and only the stamp bytes are rewritten per message.

Measured in one run, page cache warm, best of 3 (wall and CPU seconds):
**index** = ``read_recording`` (today's ``info``/``characterise`` reader); **index+latency** =
``read_with_latency`` (what ``--latency`` runs: the statistics and the stamps from one index
pass); **latency alone** = ``read_latency`` (only the chunks holding stamped messages);
**AnyReader** = rosbags' AnyReader looping over the stamped topics' messages and
deserialising each one (``header.stamp``). The run checks that our stamps (both ways) equal
AnyReader's on every stamped message, and that ``read_with_latency`` equals
``read_recording`` + ``read_latency``.
Goals (issue 12): index+latency <= 2x index; >= 10x faster than AnyReader.

Metric (second table): a ~500 MB recording (``/camera/image`` 130 KB images at 10 Hz,
380 s, distinct random payloads, plus ``/detector/count`` ``std_msgs/Int32`` at ~26 Hz:
10 000 messages) in ROS 1, rosbag2 sqlite3, rosbag2 mcap and plain MCAP (zstd); **metric**
= ``read_metric`` of ``mean`` of ``data`` over ``/detector/count`` (decoded by the
libraries), checked against the mean of the values written; ``rchar`` = bytes this
process read through read() during it (/proc/self/io; mmap reads are not counted), against
the file size. Goal: < 1 s, reading only that topic's chunks.

Command: ``.venv/bin/python tests/bench/bench_contents.py`` (``--scale 0.05 --data /tmp/x``
for a quick smoke run).
"""

from __future__ import annotations

import argparse
import struct
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent.parent))

from _timing import recording_once  # noqa: E402 - tests/bench/_timing.py (this folder is on sys.path)

FORMATS = ("ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap-zstd")
STAMPED = ("/a/points", "/b/points", "/c/points")
T0 = 1_700_000_000_000_000_000


def _templates(ros1: bool) -> dict[str, tuple[str, bytes, str]]:
    """topic -> (type, payload with a zero stamp, definition) from rosbags."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    time_t = ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    header = (ts.types["std_msgs/msg/Header"](seq=0, stamp=time_t, frame_id="map") if ros1
              else ts.types["std_msgs/msg/Header"](stamp=time_t, frame_id="map"))
    point = ts.types["geometry_msgs/msg/PointStamped"](
        header=header, point=ts.types["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0))
    text = ts.types["std_msgs/msg/String"](data="status ok")
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    out = {}
    for topic in STAMPED:
        out[topic] = ("geometry_msgs/msg/PointStamped", bytes(ser(point, "geometry_msgs/msg/PointStamped")),
                      ts.generate_msgdef("geometry_msgs/msg/PointStamped", ros_version=1 if ros1 else 2)[0])
    out["/status"] = ("std_msgs/msg/String", bytes(ser(text, "std_msgs/msg/String")),
                      ts.generate_msgdef("std_msgs/msg/String", ros_version=1 if ros1 else 2)[0])
    return out


def messages(n: int, ros1: bool) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, log time, payload): stamps 1-50 ms before the log time."""
    tpl = _templates(ros1)
    topics = [*STAMPED, "/status"]
    delays = np.random.default_rng(3).integers(1_000_000, 50_000_000, size=n).tolist()
    at = 4  # ROS 1: after seq; CDR: after the encapsulation
    for i in range(n):
        topic = topics[i % 4]
        t = T0 + i * 250_000
        payload = tpl[topic][1]
        if topic != "/status":
            stamp = t - delays[i]
            buf = bytearray(payload)
            struct.pack_into("<II", buf, at, stamp // 1_000_000_000, stamp % 1_000_000_000)
            payload = bytes(buf)
        yield topic, tpl[topic][0], t, payload


Messages = Callable[[bool], Iterator[tuple[str, str, int, bytes]]]


def write_once(data: Path, name: str, fmt: str, msgs: Messages) -> Path:
    """``data/name-fmt/rec...`` written by the third-party writers from ``msgs(ros1)``
    (ROS 1: Noetic types, else Humble), unless a complete one is there."""
    return recording_once(data, f"{name}-{fmt}", fmt, lambda target: _write(target, fmt, msgs))


def _write(target: Path, fmt: str, msgs: Messages) -> None:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    if fmt == "mcap-zstd":
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter

        with target.open("wb") as f:
            w3 = McapWriter(f, chunk_size=1 << 20, compression=CompressionType.ZSTD)
            w3.start(profile="ros2", library="perfros-bag bench")
            chans: dict[str, int] = {}
            for topic, mtype, stamp, payload in msgs(False):
                if topic not in chans:
                    text = ts.generate_msgdef(mtype, ros_version=2)[0]
                    sid = w3.register_schema(name=mtype, encoding="ros2msg", data=text.encode())
                    chans[topic] = w3.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
                w3.add_message(chans[topic], log_time=stamp, data=payload, publish_time=stamp)
            w3.finish()
    else:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if fmt == "rosbag2-mcap" else StoragePlugin.SQLITE3
        writer: Any = Writer1(target) if fmt == "ros1" else Writer(target, version=9, storage_plugin=plugin)
        extra = {"callerid": "/pub"} if fmt == "ros1" else {}
        with writer as w:
            conns: dict[str, Any] = {}
            for topic, mtype, stamp, payload in msgs(fmt == "ros1"):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, mtype, typestore=ts, **extra)
                w.write(conns[topic], stamp, payload)


def best_of(n: int, fn: Callable[[], object]) -> tuple[float, float]:
    wall = cpu = float("inf")
    for _ in range(n):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return wall, cpu


def anyreader_stamps(path: Path) -> dict[str, list[tuple[int, int]]]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list[tuple[int, int]]] = {t: [] for t in STAMPED}
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic in STAMPED]
        for conn, log_ns, raw in reader.messages(connections=conns):
            stamp = reader.deserialize(raw, conn.msgtype).header.stamp
            out[conn.topic].append((log_ns, stamp.sec * 1_000_000_000 + stamp.nanosec))
    return out


IMAGE_BYTES, METRIC_MSGS = 130_000, 10_000


def metric_messages(ros1: bool, scale: float) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, log time, payload) of the metric recording, in time order."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    time_t = ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    header = (ts.types["std_msgs/msg/Header"](seq=0, stamp=time_t, frame_id="cam") if ros1
              else ts.types["std_msgs/msg/Header"](stamp=time_t, frame_id="cam"))
    image = ts.types["sensor_msgs/msg/Image"](header=header, height=1, width=IMAGE_BYTES, encoding="mono8",
                                              is_bigendian=0, step=IMAGE_BYTES,
                                              data=np.zeros(IMAGE_BYTES, dtype=np.uint8))
    template = bytes(ser(image, "sensor_msgs/msg/Image"))
    pool = np.random.default_rng(5).bytes(64 << 20)
    n_img, n_metric = int(3800 * scale), int(METRIC_MSGS * scale)
    duration = 380 * scale
    events: list[tuple[int, str]] = [(T0 + int(i * 1e8), "img") for i in range(n_img)]
    events += [(T0 + int(k * duration * 1e9 / n_metric) + 1, "count") for k in range(n_metric)]
    events.sort()
    k = 0
    for i, (t, kind) in enumerate(events):
        if kind == "img":
            off = (i * 7919 * 64) % (len(pool) - IMAGE_BYTES)
            yield "/camera/image", "sensor_msgs/msg/Image", t, template[:-IMAGE_BYTES] + pool[off:off + IMAGE_BYTES]
        else:
            yield "/detector/count", "std_msgs/msg/Int32", t, bytes(ser(ts.types["std_msgs/msg/Int32"](data=k % 97),
                                                                        "std_msgs/msg/Int32"))
            k += 1


def _rchar() -> int:
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("rchar:"):
            return int(line.split()[1])
    return 0


def bench_metric(data: Path, scale: float) -> list[str]:
    from perfros_bag.ingest.contents import read_metric
    from perfros_bag.ingest.document import file_bytes
    from perfros_bag.system.types import Aggregate, Metric

    metric = Metric("/detector/count", "data", Aggregate.MEAN)
    expected = float(np.mean([k % 97 for k in range(int(METRIC_MSGS * scale))]))
    print("\n| format | MB | metric msgs | metric wall s | metric cpu s | rchar MB | value ok |")
    print("|---|---|---|---|---|---|---|")
    verdicts = []
    for fmt in FORMATS:
        path = write_once(data, f"metric-{scale:g}", fmt, lambda ros1: metric_messages(ros1, scale))
        value = read_metric(path, metric)
        before = _rchar()
        wall, cpu = best_of(3, lambda path=path: read_metric(path, metric))
        read_mb = (_rchar() - before) / 3 / 1e6
        ok = value is not None and abs(value - expected) < 1e-9
        print(f"| {fmt} | {file_bytes(path) / 1e6:.0f} | {int(METRIC_MSGS * scale)} | {wall:.3f} | {cpu:.3f} "
              f"| {read_mb:.1f} | {'yes' if ok else 'NO'} |", flush=True)
        if not ok:
            raise SystemExit(f"{fmt}: metric {value} != {expected}")
        verdicts.append(f"target {fmt:16s} metric < 1 s: {wall:.3f} s  {'met' if wall < 1 else 'MISSED'}")
    return verdicts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0, help="1 = 1 000 000 messages")
    ap.add_argument("--data", type=Path, default=HERE / "data" / "contents")
    ap.add_argument("--skip-baselines", action="store_true", help="no AnyReader runs")
    ap.add_argument("--skip-latency", action="store_true", help="only the metric table")
    args, _ = ap.parse_known_args()
    args.data.mkdir(parents=True, exist_ok=True)
    n = int(1_000_000 * args.scale)
    verdicts = [] if args.skip_latency else latency_table(args, n)
    verdicts += bench_metric(args.data, args.scale)
    print("\n".join(verdicts))


def latency_table(args: argparse.Namespace, n: int) -> list[str]:
    from perfros_bag.ingest import read_recording
    from perfros_bag.ingest.contents import read_latency, read_stamps, read_with_latency
    from perfros_bag.ingest.stamps import read_with_stamps

    print("| format | msgs | index wall s | index+latency wall s | ratio | index cpu s | index+latency cpu s "
          "| ratio | latency alone wall s | AnyReader wall s | x faster |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    verdicts: list[str] = []
    for fmt in FORMATS:
        path = write_once(args.data, str(n), fmt, lambda ros1: messages(n, ros1))
        stamps, _ = read_stamps(path)
        acc, _fmt, finder = read_with_stamps(path)
        in_pass = finder.stamps(acc)
        stats, latency = read_with_latency(path)
        whole = read_recording(path)
        if latency != read_latency(path) or [(t.messages, t.bytes) for t in stats.topics.values()] != \
                [(t.messages, t.bytes) for t in whole.topics.values()]:
            raise SystemExit(f"{fmt}: read_with_latency differs from read_recording + read_latency")
        if not args.skip_baselines:
            t = time.perf_counter()
            ref = anyreader_stamps(path)
            any_wall = time.perf_counter() - t
            for topic in STAMPED:  # equal to rosbags' deserialisation on every stamped message
                for way in (stamps, in_pass):
                    ours = sorted(zip(*(a.tolist() for a in way[topic]), strict=True))
                    if ours != sorted(ref[topic]):
                        raise SystemExit(f"{fmt} {topic}: stamps differ from AnyReader's")
        idx = best_of(3, lambda path=path: read_recording(path))
        both = best_of(3, lambda path=path: read_with_latency(path))
        lat = best_of(3, lambda path=path: read_latency(path))
        ratio_w, ratio_c = both[0] / idx[0], both[1] / idx[1]
        faster = "-" if args.skip_baselines else f"{any_wall / lat[0]:.1f}x"
        any_txt = "-" if args.skip_baselines else f"{any_wall:.3f}"
        print(f"| {fmt} | {n} | {idx[0]:.3f} | {both[0]:.3f} | {ratio_w:.2f}x | {idx[1]:.3f} | {both[1]:.3f} "
              f"| {ratio_c:.2f}x | {lat[0]:.3f} | {any_txt} | {faster} |", flush=True)
        verdicts.append(f"target {fmt:16s} index+latency <= 2x index (cpu): {ratio_c:5.2f}x  "
                        f"{'met' if ratio_c <= 2 else 'MISSED'}")
        if not args.skip_baselines:
            x = any_wall / lat[0]
            verdicts.append(f"target {fmt:16s} latency >= 10x faster than AnyReader: {x:6.1f}x  "
                            f"{'met' if x >= 10 else 'MISSED'}")
    return verdicts


if __name__ == "__main__":
    main()
