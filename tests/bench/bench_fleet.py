"""Fleet-scale benchmark: characterise a ~2 GB corpus in-process vs ``--workers 2``; peers.

One run (``.venv/bin/python tests/bench/bench_fleet.py``, also run by ``make bench``):

1. writes a corpus of 20 recordings, ~2 GB, mixed formats (ROS 1 bag, rosbag2 sqlite3,
   rosbag2 mcap, plain MCAP; tests/bench/gen_corpus.py) under tests/bench/data/ (git-ignored),
   plus one ~2 GB ROS 1 bag and one ~2 GB MCAP file for the memory target;
2. times, each in a subprocess whose whole process tree is sampled with psutil (peak RSS,
   and peak RSS minus file-backed/shared pages = anonymous memory):
   ``cat`` (raw read from the page cache), ``perfros-bag characterise`` in-process and with
   ``--workers 2`` (same CSV bytes after sorting is asserted), and on the same files the
   peers: Debian ``rosbag info`` (/usr/bin/rosbag) and its Python API (/usr/bin/python3:
   ``get_type_and_topic_info`` from the index, and a ``read_messages(raw=True)`` loop), a
   plain rosbags ``AnyReader`` loop over raw messages, the mcap reader's ``iter_messages``;
3. the 2 GB files: ``characterise`` in-process (memory target < 300 MB RSS) and with
   ``--workers 2`` (the file is split into chunk-range tasks), and the chunk split alone
   (``read_split``) in-process vs ``--workers 2``;
4. prints a table with ratios and deletes the data (``--keep`` keeps it).
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import psutil

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path.insert(0, str(ROOT))
from tests.bench.gen_corpus import default_topics, write_corpus, write_recording  # noqa: E402

PY = sys.executable
CLI = str(Path(PY).with_name("perfros-bag"))
DEBIAN_PY = "/usr/bin/python3"
ROSBAG = "/usr/bin/rosbag"


@dataclass
class Run:
    name: str
    files: str
    wall_s: float
    peak_rss: int
    peak_anon: int


def measure(name: str, files: str, cmd: list[str], *, cwd: Path = ROOT) -> Run:
    """Wall time and peak memory of ``cmd`` and all its children (sampled every 10 ms)."""
    with tempfile.TemporaryFile() as errf:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=errf, cwd=cwd)
        peak = [0, 0]
        stop = threading.Event()

        def sample() -> None:
            root = psutil.Process(proc.pid)
            while not stop.is_set():
                rss = anon = 0
                try:
                    tree = [root, *root.children(recursive=True)]
                except psutil.Error:
                    tree = []
                for p in tree:
                    try:
                        mi = p.memory_info()
                    except psutil.Error:
                        continue
                    rss += mi.rss
                    anon += mi.rss - mi.shared
                peak[0], peak[1] = max(peak[0], rss), max(peak[1], anon)
                stop.wait(0.01)

        thread = threading.Thread(target=sample, daemon=True)
        thread.start()
        rc = proc.wait()
        wall = time.perf_counter() - t0
        stop.set()
        thread.join()
        if rc != 0:
            errf.seek(0)
            tail = errf.read().decode(errors="replace")[-2000:]
            raise SystemExit(f"{name} failed (exit {rc}): {' '.join(cmd)}\n{tail}")
    run = Run(name, files, wall, peak[0], peak[1])
    print(f"  {name:<44} {files:<14} {wall:8.2f} s  peak RSS {peak[0] / 1e6:7.0f} MB"
          f"  (anon {peak[1] / 1e6:5.0f} MB)", flush=True)
    return run


def py_loop(code: str, files: list[Path]) -> list[str]:
    return [PY, "-c", code, *map(str, files)]


ANYREADER = """
import sys
from pathlib import Path
from rosbags.highlevel import AnyReader
n = b = 0
for f in sys.argv[1:]:
    with AnyReader([Path(f)]) as r:
        for conn, t, raw in r.messages():
            n += 1; b += len(raw)
print(n, b)
"""

MCAP_ITER = """
import sys
from mcap.reader import make_reader
n = b = 0
for f in sys.argv[1:]:
    with open(f, 'rb') as fh:
        for schema, channel, msg in make_reader(fh).iter_messages():
            n += 1; b += len(msg.data)
print(n, b)
"""

DEBIAN_INFO_API = """
import sys, rosbag
n = 0
for f in sys.argv[1:]:
    with rosbag.Bag(f) as bag:
        n += sum(t.message_count for t in bag.get_type_and_topic_info().topics.values())
print(n)
"""

DEBIAN_READ = """
import sys, rosbag
n = b = 0
for f in sys.argv[1:]:
    with rosbag.Bag(f) as bag:
        for topic, raw, t in bag.read_messages(raw=True):
            n += 1; b += len(raw[1])
print(n, b)
"""

OURS_READ = """
import sys
from perfros_bag.ingest import read_recording
n = 0
for f in sys.argv[1:]:
    n += read_recording(f).messages
print(n)
"""

SPLIT = """
import sys
from perfros_bag.characterisation.cluster import read_split
workers = int(sys.argv[1]) or None
for f in sys.argv[2:]:
    print(read_split(f, workers=workers).messages)
"""


def sorted_csv(path: Path) -> bytes:
    head, *rows = path.read_bytes().splitlines(keepends=True)
    return head + b"".join(sorted(rows))


def storage_files(paths: list[Path], suffix: str) -> list[Path]:
    out = []
    for p in paths:
        out += sorted(p.glob(f"*{suffix}")) if p.is_dir() else ([p] if p.name.endswith(suffix) else [])
    return out


def du(paths: list[Path]) -> int:
    total = 0
    for p in paths:
        total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size
    return total


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gb", type=float, default=2.0, help="corpus size (default 2)")
    parser.add_argument("--big-gb", type=float, default=2.0, help="single recordings (default 2)")
    parser.add_argument("--keep", action="store_true", help="keep the generated data")
    parser.add_argument("--out", type=Path, default=None, help="also write the runs as CSV")
    args = parser.parse_args()

    data = HERE / "data" / "fleet"
    shutil.rmtree(data, ignore_errors=True)
    runs: list[Run] = []
    try:
        t0 = time.perf_counter()
        corpus = write_corpus(data / "corpus", int(args.gb * 1e9), 20)
        big_bag, big_mcap = data / "big" / "big.bag", data / "big" / "big.mcap"
        big_bag.parent.mkdir(parents=True)
        rate = sum(s.rate_hz * s.payload for s in default_topics())
        for k, path in enumerate((big_bag, big_mcap)):
            write_recording(path, "ros1" if k == 0 else "mcap", default_topics(),
                            args.big_gb * 1e9 / rate, chunk_bytes=4 << 20, seed=100 + k)
        print(f"generated {du(corpus) / 1e9:.2f} GB in {len(corpus)} recordings + "
              f"{du([big_bag, big_mcap]) / 1e9:.2f} GB in 2 single recordings "
              f"({time.perf_counter() - t0:.0f} s); machine: {os.cpu_count()} cores, "
              f"load {os.getloadavg()[0]:.1f}", flush=True)

        bags = [p for p in corpus if p.suffix == ".bag"]
        mcaps = storage_files(corpus, ".mcap")  # plain MCAP + rosbag2-mcap storage files
        anyreader_ok = [p for p in corpus if p.suffix != ".mcap"]  # AnyReader: no plain MCAP
        every = [f for p in corpus for f in ([*p.iterdir()] if p.is_dir() else [p])]
        sub = {"all": corpus, "bags": bags, "mcap": mcaps, "anyreader": anyreader_ok}

        print("corpus (20 recordings):", flush=True)
        runs.append(measure("LocalCluster(2 workers) start+stop only", "-",
                            [PY, "-c", "from perfros_bag.characterisation.distributed import run_distributed as r; "
                             "r([1], abs, workers=2)"]))
        measure("warm page cache: cat", "all", ["cat", *map(str, every)])
        runs.append(measure("raw read: cat > /dev/null", "all", ["cat", *map(str, every)]))
        out1, out2 = data / "inproc.csv", data / "workers2.csv"
        runs.append(measure("perfros-bag characterise (in-process)", "all",
                            [CLI, "characterise", str(data / "corpus"), "--out", str(out1)]))
        runs.append(measure("perfros-bag characterise --workers 2", "all",
                            [CLI, "characterise", str(data / "corpus"), "--out", str(out2),
                             "--workers", "2"]))
        same = sorted_csv(out1) == sorted_csv(out2)
        print(f"  same CSV bytes after sorting: {same}", flush=True)
        if not same:
            raise SystemExit("in-process and --workers 2 CSVs differ")
        for name, files in (("bags", bags), ("mcap", mcaps), ("anyreader", anyreader_ok)):
            runs.append(measure("perfros-bag read_recording loop", name, py_loop(OURS_READ, files)))
        runs.append(measure("rosbags AnyReader raw loop", "anyreader", py_loop(ANYREADER, anyreader_ok)))
        runs.append(measure("mcap iter_messages", "mcap", py_loop(MCAP_ITER, mcaps)))
        if Path(ROSBAG).exists():
            runs.append(measure("Debian rosbag info (CLI, per file)", "bags",
                                ["sh", "-c", 'for f in "$@"; do /usr/bin/rosbag info "$f"; done', "sh",
                                 *map(str, bags)]))
            runs.append(measure("Debian rosbag API get_type_and_topic_info", "bags",
                                [DEBIAN_PY, "-c", DEBIAN_INFO_API, *map(str, bags)]))
            runs.append(measure("Debian rosbag API read_messages(raw)", "bags",
                                [DEBIAN_PY, "-c", DEBIAN_READ, *map(str, bags)]))
        runs.append(measure("raw read: cat > /dev/null", "bags", ["cat", *map(str, bags)]))
        runs.append(measure("raw read: cat > /dev/null", "mcap", ["cat", *map(str, mcaps)]))

        print("single 2 GB recordings:", flush=True)
        for path, label in ((big_bag, "big.bag"), (big_mcap, "big.mcap")):
            measure("warm page cache: cat", label, ["cat", str(path)])
            runs.append(measure("raw read: cat > /dev/null", label, ["cat", str(path)]))
            out = data / f"{label}.csv"
            runs.append(measure("perfros-bag characterise (in-process)", label,
                                [CLI, "characterise", str(path), "--out", str(out)]))
            runs.append(measure("perfros-bag characterise --workers 2", label,
                                [CLI, "characterise", str(path), "--out", str(out) + "2",
                                 "--workers", "2"]))
            if sorted_csv(out) != sorted_csv(Path(str(out) + "2")):
                raise SystemExit(f"{label}: in-process and --workers 2 (split) CSVs differ")
            runs.append(measure("read_split in-process", label, py_loop(SPLIT, [Path("0"), path])))
            runs.append(measure("read_split --workers 2", label, py_loop(SPLIT, [Path("2"), path])))
        sizes = {"all": du(corpus), "bags": du(bags), "mcap": du(mcaps),
                 "anyreader": du(anyreader_ok), "big.bag": du([big_bag]), "big.mcap": du([big_mcap])}
    finally:
        if not args.keep:
            shutil.rmtree(data, ignore_errors=True)

    report(runs, sizes, sub)
    if args.out is not None:
        with args.out.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["name", "files", "wall_s", "peak_rss_bytes", "peak_anon_bytes"])
            for r in runs:
                w.writerow([r.name, r.files, f"{r.wall_s:.3f}", r.peak_rss, r.peak_anon])
    return 0


def report(runs: list[Run], sizes: dict[str, int], sub: dict[str, list[Path]]) -> None:
    def t(name: str, files: str) -> float:
        return next(r.wall_s for r in runs if r.name == name and r.files == files)

    ours = "perfros-bag read_recording loop"
    print("\nratios (peer time / our time on the same files; > 1 = we are faster):")
    pairs = [("rosbags AnyReader raw loop", "anyreader"), ("mcap iter_messages", "mcap"),
             ("Debian rosbag info (CLI, per file)", "bags"),
             ("Debian rosbag API get_type_and_topic_info", "bags"),
             ("Debian rosbag API read_messages(raw)", "bags")]
    for peer, files in pairs:
        if any(r.name == peer for r in runs):
            print(f"  {peer:<44} {files:<10} {t(peer, files) / t(ours, files):8.1f}x")
    print("throughput vs raw read (our MB/s / cat MB/s):")
    for files in ("bags", "mcap"):
        print(f"  {ours} on {files:<10} {t('raw read: cat > /dev/null', files) / t(ours, files) * 100:6.0f} %"
              f"  ({sizes[files] / t(ours, files) / 1e6:.0f} MB/s)")
    inproc = t("perfros-bag characterise (in-process)", "all")
    dask = t("perfros-bag characterise --workers 2", "all")
    print(f"characterise corpus: in-process {inproc:.2f} s, --workers 2 {dask:.2f} s "
          f"(speed-up {inproc / dask:.2f}x, {sizes['all'] / inproc / 1e6:.0f} MB/s in-process)")
    print(f"LocalCluster(2) start+stop alone: {t('LocalCluster(2 workers) start+stop only', '-'):.2f} s")
    for label in ("big.bag", "big.mcap"):
        a, b = t("read_split in-process", label), t("read_split --workers 2", label)
        print(f"split {label}: in-process {a:.2f} s, --workers 2 {b:.2f} s (speed-up {a / b:.2f}x)")
    print("memory target: a 2 GB recording under 300 MB RSS (peak RSS / anonymous part):")
    for label in ("big.bag", "big.mcap"):
        for name in ("perfros-bag characterise (in-process)", "perfros-bag characterise --workers 2",
                     "read_split in-process"):
            r = next(r for r in runs if r.name == name and r.files == label)
            verdict = "met" if r.peak_rss < 300e6 else "MISSED"
            print(f"  {label:<9} {name:<40} {r.peak_rss / 1e6:6.0f} MB / {r.peak_anon / 1e6:4.0f} MB  {verdict}")


if __name__ == "__main__":
    sys.exit(main())
