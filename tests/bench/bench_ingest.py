"""Benchmark of the recording readers (``perfros_bag.ingest.read_recording``).

Generates, once, into tests/bench/data/ingest/ (git-ignored):
  (a) "big":   ~500 MB: /camera/image 130 KB messages at 10 Hz + /scan 2 KB at 100 Hz
  (b) "small": ~1M small messages (8-120 bytes) on 4 topics
each as a ROS 1 bag (uncompressed chunks), a rosbag2 sqlite3 directory, a rosbag2 mcap
directory (rosbags writers) and a plain zstd-chunked MCAP (mcap writer).

Measured in the same run, page cache warm (every file read once before timing):
  raw     `cat files > /dev/null` (best of 3)
  ours    read_recording(path) in-process (best of 3, imports warmed)
  numpy   rosbag2 sqlite3 only: the same with the numpy page decoder instead of the C one
  cli     `perfros-bag info --json PATH` wall time (one run, includes interpreter start)
  any     rosbags AnyReader, loop over every raw message summing len(raw) (one run)
  rosbag  Debian python3-rosbag (ROS 1 only, /usr/bin/python3 subprocess): Bag(path) +
          get_type_and_topic_info(), and a read_messages(raw=True) loop (one run each)
Each is timed in wall-clock seconds and in CPU seconds (process_time, plus RUSAGE_CHILDREN for
subprocesses): on a shared machine the CPU figures are the steadier ones.
Ratios: any/ours (target >= 20x on "small"), raw/ours = fraction of the raw read speed
(target >= 30 % on "big"), rosbag/ours. Counts and bytes of ours and AnyReader are compared.

    .venv/bin/python tests/bench/bench_ingest.py [--scale 0.1] [--data DIR] [--skip-baselines]
        [--only big:mcap-zstd ...]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path.insert(0, str(ROOT))

from _timing import recording_once  # noqa: E402 - tests/bench/_timing.py (this folder is on sys.path)

from tests.ingest_gen import Msg, write_mcap, write_ros1, write_rosbag2  # noqa: E402

T0 = 1_700_000_000_000_000_000
FORMATS = ["ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap-zstd"]

ROSBAG_SCRIPT = r"""
import json, sys, time
import rosbag
path = sys.argv[1]
t, c = time.perf_counter(), time.process_time()
with rosbag.Bag(path) as bag:
    info = bag.get_type_and_topic_info()
    n_info = sum(v.message_count for v in info.topics.values())
t_info, c_info = time.perf_counter() - t, time.process_time() - c
t, c = time.perf_counter(), time.process_time()
n = size = 0
with rosbag.Bag(path) as bag:
    for topic, raw, ts in bag.read_messages(raw=True):
        n += 1
        size += len(raw[1])
t_loop, c_loop = time.perf_counter() - t, time.process_time() - c
print(json.dumps({"info_s": t_info, "loop_s": t_loop, "info_cpu": c_info, "loop_cpu": c_loop,
                  "messages": n, "info_messages": n_info, "bytes": size}))
"""


def dataset(kind: str, scale: float) -> Iterator[Msg]:
    """Messages in time order; payload objects are reused (content does not matter here)."""
    if kind == "big":
        import numpy as np

        rng = np.random.default_rng(1)
        duration_s = 330 * scale
        n_img, n_scan = int(duration_s * 10), int(duration_s * 100)
        # distinct random payloads: compression (zstd MCAP) cannot shrink them, as with real images
        blob = rng.bytes(130_000 * n_img + 2_000 * n_scan)
        images = [blob[i * 130_000:(i + 1) * 130_000] for i in range(n_img)]
        o = 130_000 * n_img
        scans = [blob[o + i * 2_000:o + (i + 1) * 2_000] for i in range(n_scan)]
        events = [(T0 + i * 100_000_000 + 1234, "/camera/image", "std_msgs/msg/String", images[i])
                  for i in range(n_img)]
        events += [(T0 + i * 10_000_000, "/scan", "std_msgs/msg/String", scans[i]) for i in range(n_scan)]
        events.sort(key=lambda e: e[0])
        for t, topic, mtype, data in events:
            yield Msg(topic, mtype, t, data, "/driver")
    else:
        n = int(1_000_000 * scale)
        payloads = [bytes(range(8 + 16 * k)) for k in range(8)]
        topics = ["/imu", "/odom", "/tf", "/status"]
        for i in range(n):
            yield Msg(topics[i % 4], "std_msgs/msg/String", T0 + i * 250_000, payloads[i % 8], "/node")


def generate(data: Path, kind: str, fmt: str, scale: float) -> Path:
    def write(target: Path) -> None:
        msgs = list(dataset(kind, scale))
        if fmt == "ros1":
            write_ros1(target, msgs)
        elif fmt == "rosbag2-sqlite3":
            write_rosbag2(target, msgs, "sqlite3")
        elif fmt == "rosbag2-mcap":
            write_rosbag2(target, msgs, "mcap")
        else:
            write_mcap(target, msgs, compression="zstd", chunk_size=1 << 20)

    return recording_once(data, f"{kind}-{scale:g}-{fmt}", fmt, write)


def files_of(path: Path) -> list[Path]:
    return sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def best_of(n: int, fn: Callable[[], object]) -> tuple[float, float]:
    """Best wall time and best CPU time (this process + waited-for children) of ``n`` runs."""
    best_wall = best_cpu = float("inf")
    for _ in range(n):
        t, c, cc = time.perf_counter(), time.process_time(), _children_cpu()
        fn()
        best_wall = min(best_wall, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c + _children_cpu() - cc)
    return best_wall, best_cpu


def cat(path: Path) -> None:
    subprocess.run(["cat", *map(str, files_of(path))], stdout=subprocess.DEVNULL, check=True)


def timed(fn: Callable[[], tuple[int, int]]) -> tuple[tuple[int, int], float, float]:
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def anyreader(path: Path) -> tuple[int, int]:
    from rosbags.highlevel import AnyReader

    n = size = 0
    with AnyReader([path]) as reader:
        for _conn, _ts, raw in reader.messages():
            n += 1
            size += len(raw)
    return n, size


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0, help="dataset size factor (1 = 500 MB / 1M msgs)")
    ap.add_argument("--data", type=Path, default=HERE / "data" / "ingest")
    ap.add_argument("--skip-baselines", action="store_true", help="no AnyReader / python3-rosbag runs")
    ap.add_argument("--only", action="append", default=[], metavar="KIND:FORMAT",
                    help="run only these rows, e.g. big:mcap-zstd (repeatable; KIND or FORMAT alone matches all)")
    args, _ = ap.parse_known_args()
    args.data.mkdir(parents=True, exist_ok=True)

    from perfros_bag.ingest import read_recording

    cli = ROOT / ".venv" / "bin" / "perfros-bag"
    rows = []
    for kind in ("big", "small"):
        for fmt in FORMATS:
            if args.only and not any(_selected(sel, kind, fmt) for sel in args.only):
                continue
            path = generate(args.data, kind, fmt, args.scale)
            size = sum(p.stat().st_size for p in files_of(path))
            cat(path)  # warm the page cache
            read_recording(path)  # warm imports
            t_raw, c_raw = best_of(3, lambda p=path: cat(p))  # type: ignore[misc]
            rec = read_recording(path)
            t_ours, c_ours = best_of(3, lambda p=path: read_recording(p))  # type: ignore[misc]
            t = time.perf_counter()
            subprocess.run([str(cli), "info", "--json", str(path)], stdout=subprocess.DEVNULL, check=True)
            t_cli = time.perf_counter() - t
            row = {"kind": kind, "format": fmt, "MB": size / 1e6, "messages": rec.messages,
                   "method": rec.method, "raw_s": t_raw, "ours_s": t_ours, "cli_s": t_cli,
                   "raw_cpu": c_raw, "ours_cpu": c_ours}
            if fmt == "rosbag2-sqlite3":  # the numpy page decoder (the fallback) in the same run
                row["numpy_s"], row["numpy_cpu"] = _numpy_decoder(path)
            if not args.skip_baselines:
                (n, nbytes), row["any_s"], row["any_cpu"] = timed(lambda p=path: anyreader(p))  # type: ignore[misc]
                ours_bytes = sum(tp.bytes for tp in rec.topics.values())
                row["agree"] = (n, nbytes) == (rec.messages, ours_bytes)
                if fmt == "ros1" and Path("/usr/bin/python3").exists():
                    res = subprocess.run(["/usr/bin/python3", "-c", ROSBAG_SCRIPT, str(path)],
                                         capture_output=True, text=True)
                    if res.returncode == 0:
                        rb = json.loads(res.stdout)
                        row["rosbag_info_s"], row["rosbag_loop_s"] = rb["info_s"], rb["loop_s"]
                        row["rosbag_info_cpu"], row["rosbag_loop_cpu"] = rb["info_cpu"], rb["loop_cpu"]
                        row["agree"] = row["agree"] and rb["messages"] == rec.messages
                    else:
                        print(f"  python3-rosbag failed: {res.stderr.strip().splitlines()[-1:]}")
            rows.append(row)
            print(_line(row), flush=True)
    print()
    print(_table(rows, "s"))
    print()
    print(_table(rows, "cpu"))
    print()
    for r in rows:
        if "numpy_s" in r:
            print(f"{r['kind']:5s} {r['format']:16s} C page decoder vs numpy page decoder: "
                  f"{float(r['numpy_s']) / float(r['ours_s']):.1f}x wall, "  # type: ignore[arg-type]
                  f"{float(r['numpy_cpu']) / float(r['ours_cpu']):.1f}x CPU "  # type: ignore[arg-type]
                  f"(numpy {float(r['numpy_s']):.3f} s wall, {float(r['numpy_cpu']):.3f} s CPU)")  # type: ignore[arg-type]
    print()
    for r in rows:
        for unit in ("s", "cpu"):
            ours = float(r[f"ours_{unit}"])  # type: ignore[arg-type]
            what = "wall" if unit == "s" else "cpu "
            if r["kind"] == "small" and f"any_{unit}" in r:
                x = float(r[f"any_{unit}"]) / ours  # type: ignore[arg-type]
                print(f"target small {r['format']:16s} {what} >= 20x AnyReader: {x:7.1f}x  "
                      f"{'met' if x >= 20 else 'MISSED'}")
            if r["kind"] == "big":
                f = float(r[f"raw_{unit}"]) / ours  # type: ignore[arg-type]
                print(f"target big   {r['format']:16s} {what} >= 30% raw read:   {100 * f:7.1f}%  "
                      f"{'met' if f >= 0.3 else 'MISSED'}")
    if any(r.get("agree") is False for r in rows):
        print("DISAGREEMENT between perfros-bag and a baseline reader")
        sys.exit(1)


def _numpy_decoder(path: Path) -> tuple[float, float]:
    """Best-of-3 wall and CPU time of read_recording with the numpy page decoder (what runs
    where the C extension is not built); its numbers must equal the C decoder's."""
    from perfros_bag.ingest import read_recording, sqlitepages

    saved = sqlitepages.DECODER
    sqlitepages.DECODER = "numpy"
    try:
        by_numpy = read_recording(path)
        t = best_of(3, lambda: read_recording(path))
    finally:
        sqlitepages.DECODER = saved
    by_c = read_recording(path)
    if any(x.messages != y.messages or x.bytes != y.bytes or not (x.times_ns == y.times_ns).all()
           for x, y in zip(by_numpy.topics.values(), by_c.topics.values(), strict=True)):
        print("DISAGREEMENT between the numpy and the C sqlite page decoders")
        sys.exit(1)
    return t


def _selected(sel: str, kind: str, fmt: str) -> bool:
    """``--only`` value ``KIND:FORMAT``, ``KIND`` or ``FORMAT`` matches this row."""
    k, _, f = sel.partition(":")
    return (k == kind and f in ("", fmt)) or (not f and k == fmt)


def _line(r: dict[str, object]) -> str:
    return " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items())


def _table(rows: list[dict[str, object]], unit: str) -> str:
    """Markdown table of wall-clock seconds (unit "s") or CPU seconds (unit "cpu")."""
    label = "wall s" if unit == "s" else "CPU s"
    head = (f"| data | format | MB | msgs | path | raw {label} | ours {label} | ours vs raw "
            f"| AnyReader {label} | ours × faster | rosbag info {label} | × | rosbag loop {label} | × |"
            + ("| cli wall s |" if unit == "s" else "") + "\n|" + "---|" * (15 if unit == "s" else 14))
    out = [head.replace("||", "|")]
    for r in rows:
        ours = float(r[f"ours_{unit}"])  # type: ignore[arg-type]

        def val(key: str, r: dict[str, object] = r) -> str:
            return f"{float(r[key]):.3f}" if key in r else "-"  # type: ignore[arg-type]

        def ratio(key: str, r: dict[str, object] = r, ours: float = ours) -> str:
            return f"{float(r[key]) / ours:.1f}×" if key in r else "-"  # type: ignore[arg-type]

        line = (f"| {r['kind']} | {r['format']} | {float(r['MB']):.0f} | {r['messages']} | {r['method']} "  # type: ignore[arg-type]
                f"| {val(f'raw_{unit}')} | {ours:.3f} | {100 * float(r[f'raw_{unit}']) / ours:.0f} % "  # type: ignore[arg-type]
                f"| {val(f'any_{unit}')} | {ratio(f'any_{unit}')} | {val(f'rosbag_info_{unit}')} "
                f"| {ratio(f'rosbag_info_{unit}')} | {val(f'rosbag_loop_{unit}')} | {ratio(f'rosbag_loop_{unit}')} |")
        if unit == "s":
            line += f" {val('cli_s')} |"
        out.append(line)
    return "\n".join(out)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
