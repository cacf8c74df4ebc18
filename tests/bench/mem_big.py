"""Memory of ``characterise`` on single 2 GB recordings (issue 7: under 300 MB RSS).

The memory part of ``bench_fleet.py`` alone (not a ``bench_*`` file, so ``make bench`` does
not run it twice): writes one ~2 GB ROS 1 bag, one ~2 GB MCAP file and one ~2 GB rosbag2
sqlite3 recording (``--formats`` picks some) under
``tests/bench/data/mem_big/`` (deleted at the end), warms the page cache, then measures
``perfros-bag characterise FILE`` in-process with ``bench_fleet.measure`` (peak RSS and its
anonymous part of the whole process tree, sampled every 10 ms).

    .venv/bin/python tests/bench/mem_big.py [--gb 2.0] [--formats ros1,mcap,rosbag2-sqlite3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent.parent))

from tests.bench.bench_fleet import CLI, measure  # noqa: E402
from tests.bench.gen_corpus import default_topics, write_recording  # noqa: E402

#: recording per format (rosbag2: a directory)
TARGETS = {"ros1": "big.bag", "mcap": "big.mcap", "rosbag2-sqlite3": "big_sqlite3"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gb", type=float, default=2.0, help="size of each recording (default 2)")
    parser.add_argument("--formats", default=",".join(TARGETS),
                        help="comma-separated subset of " + ", ".join(TARGETS))
    args = parser.parse_args()
    formats = [f for f in args.formats.split(",") if f]
    if not formats or set(formats) - set(TARGETS):
        parser.error(f"--formats takes a subset of {', '.join(TARGETS)}")
    data = HERE / "data" / "mem_big"
    shutil.rmtree(data, ignore_errors=True)
    data.mkdir(parents=True)
    try:
        rate = sum(s.rate_hz * s.payload for s in default_topics())
        files = []
        for k, fmt in enumerate(formats):
            path = data / TARGETS[fmt]
            write_recording(path, fmt, default_topics(), args.gb * 1e9 / rate,
                            chunk_bytes=4 << 20, seed=100 + k)
            files.append(path)
        print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}", flush=True)
        over = []
        for path in files:
            parts = sorted(path.glob("*.db3")) if path.is_dir() else [path]
            size = sum(p.stat().st_size for p in parts)
            print(f"{path.name}: {size / 1e9:.2f} GB", flush=True)
            measure("warm page cache: cat", path.name, ["cat", *map(str, parts)])
            measure("raw read: cat > /dev/null", path.name, ["cat", *map(str, parts)])
            run = measure("perfros-bag characterise (in-process)", path.name,
                          [CLI, "characterise", str(path), "--out", str(data / f"{path.name}.csv")])
            if run.peak_rss >= 300e6:
                over.append(path.name)
        print("target < 300 MB RSS:", "missed for " + ", ".join(over) if over else "met", flush=True)
    finally:
        shutil.rmtree(data, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
