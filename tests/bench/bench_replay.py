"""Replay (space.yaml ``replay:``): the goals of issue 23.

* ``convert``: a rosbag2 MCAP recording of ``sensor_msgs/msg/Image`` (230 kB frames at 10 Hz,
  2.3 MB/s, distinct random pixels), written by rosbags' rosbag2 writer (MCAP storage), is
  converted to a ROS 1 bag the way ``sweep`` does (:func:`perfros_bag.sweep.replay.prepare`,
  cache emptied each time), against reading it with rosbags: ``AnyReader`` looping over every
  raw message ("read raw") and the same loop deserialising each message ("read +
  deserialise"), and against copying the recording's files (``shutil.copyfile``: the floor of
  anything that writes the bytes once more). Goal: convert <= 2x read.
* ``rates`` (Debian's ROS 1): ``sweep`` of fixtures/app with the camera replaced by
  fixtures/app/camera.bag (2.3 MB/s of images) at factors 0.5, 1, 2, 4, ``--repeats``
  runs each; each run's ``/camera/image_raw`` rate (the tool's reader: (n-1)/span) against
  the recorded rate x the factor. Goal: within 3 %.

    .venv/bin/python tests/bench/bench_replay.py [--part convert|rates|all] [--mb 500] [--repeats 2]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _timing import recording_once, timings

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "bench" / "data"
FRAME = 320 * 240 * 3  # bytes of one bgr8 frame, as the example camera's


def write_images(target: Path, mb: float) -> None:
    import numpy as np
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    image, header, stamp = (store.types[t] for t in ("sensor_msgs/msg/Image", "std_msgs/msg/Header",
                                                     "builtin_interfaces/msg/Time"))
    rng = np.random.default_rng(23)
    n = int(mb * 1e6 / FRAME)
    pool = [rng.integers(0, 256, FRAME, dtype=np.uint8) for _ in range(16)]
    with Writer(target, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/camera/image_raw", "sensor_msgs/msg/Image", typestore=store)
        t0 = 1_700_000_000 * 10**9
        for i in range(n):
            t = t0 + i * 100_000_000
            pixels = pool[i % 16].copy()
            pixels[:8] = np.frombuffer(i.to_bytes(8, "little"), dtype=np.uint8)  # every frame distinct
            msg = image(header(stamp(t // 10**9, t % 10**9), "camera"), 240, 320, "bgr8", 0, 960, pixels)
            writer.write(conn, t, store.serialize_cdr(msg, "sensor_msgs/msg/Image"))


def bench_convert(mb: float, repeats: int) -> None:
    from rosbags.highlevel import AnyReader

    from perfros_bag.sweep.replay import inspect_recording, prepare
    from perfros_bag.sweep.space import parse_space

    rec = recording_once(DATA, f"replay-{mb:g}mb", "rosbag2-mcap", lambda t: write_images(t, mb))
    size = sum(f.stat().st_size for f in rec.iterdir())
    space = parse_space({"replay": {"recording": str(rec), "replaces": ["camera"]}}, DATA / "space.yaml")
    assert space.replay is not None

    def read_raw() -> None:
        with AnyReader([rec]) as reader:
            n = sum(len(raw) for _c, _t, raw in reader.messages())
        assert n > 0

    def read_deserialise() -> None:
        with AnyReader([rec]) as reader:
            for conn, _t, raw in reader.messages():
                reader.deserialize(raw, conn.msgtype)

    out = Path(tempfile.mkdtemp(prefix="bench-replay-", dir=DATA))

    def copy() -> None:  # the floor of any conversion: writing the same bytes once more
        for f in rec.iterdir():
            shutil.copyfile(f, out / f"copy-{f.name}")
        for f in out.glob("copy-*"):
            f.unlink()

    def convert() -> None:
        shutil.rmtree(out / ".replay", ignore_errors=True)
        prepare(inspect_recording(space.replay), out)  # type: ignore[arg-type]

    try:
        rows = {name: timings(fn, repeats) for name, fn in
                (("read raw", read_raw), ("read + deserialise", read_deserialise), ("copy the files", copy),
                 ("convert", convert))}
        bag = next(p for p in (out / ".replay").iterdir() if not p.name.endswith(".loop.bag"))
        print(f"recording: {rec} ({size / 1e6:.0f} MB, rosbag2 MCAP); "
              f"ROS 1 bag written: {bag.stat().st_size / 1e6:.0f} MB")
    finally:
        shutil.rmtree(out, ignore_errors=True)
    conv = statistics.median(rows["convert"])
    for name, ts in rows.items():
        med = statistics.median(ts)
        print(f"  {name:20s} wall s: {', '.join(f'{t:.2f}' for t in ts)}  median {med:.2f}"
              + ("" if name == "convert" else f"  convert / this = {conv / med:.2f}x"))


def bench_rates(repeats: int) -> None:
    from perfros_bag.ingest import read_recording

    camera = ROOT / "fixtures" / "app" / "camera.bag"
    recorded = read_recording(camera).topics["/camera/image_raw"].frequency_hz
    factors = [0.5, 1, 2, 4]
    with tempfile.TemporaryDirectory() as tmp:
        space = Path(tmp) / "space.yaml"
        space.write_text(f"duration_s: 10\nsettle_s: 2\nrepeats: {repeats}\nreplay:\n  recording: {camera}\n"
                         f"  replaces: [camera]\n  topics: [/camera/image_raw]\n  rates: {factors}\n")
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "perfros_bag", "sweep", str(ROOT / "fixtures" / "app" / "app.launch"),
                        "--space", str(space), "--out", f"{tmp}/runs"], check=True)
        print(f"sweep: {len(factors) * repeats} runs in {time.perf_counter() - t:.0f} s; "
              f"recorded rate {recorded:.4f} Hz")
        for f in factors:
            errs = []
            for r in range(1, repeats + 1):
                name = f"replay-x{f:g}" + (f"_r{r}" if repeats > 1 else "")
                stats = read_recording(Path(tmp) / "runs" / f"{name}.bag").topics["/camera/image_raw"]
                errs.append(100 * (stats.frequency_hz / (recorded * f) - 1))
                print(f"  x{f:g} run {r}: {stats.frequency_hz:.3f} Hz, {stats.bandwidth_kBps / 1000:.2f} MB/s, "
                      f"error {errs[-1]:+.2f} %")
            print(f"  x{f:g}: error {min(errs):+.2f} .. {max(errs):+.2f} %")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=["convert", "rates", "all"], default="all")
    ap.add_argument("--mb", type=float, default=500.0)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    if args.part in ("convert", "all"):
        bench_convert(args.mb, args.repeats)
    if args.part in ("rates", "all"):
        bench_rates(args.repeats)


if __name__ == "__main__":
    main()
