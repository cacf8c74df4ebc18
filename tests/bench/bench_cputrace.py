"""CPU trace reading: the fast path (pandas' C parser) vs the careful line-by-line parser
and vs a bare ``pandas.read_csv`` of the same file (the floor), plus per-node attribution.

    .venv/bin/python tests/bench/bench_cputrace.py [--rows 500000] [--repeat 3]

The trace is generated in a temporary directory (20 processes, 0.5 s interval, like a
long case-study run); both parsers must return identical arrays.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from _timing import best  # tests/bench/_timing.py (this folder is on sys.path)

from perfros_bag.cpu.trace import node_cpu, read_cpu_trace, write_cpu_trace  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=500_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    procs = 20
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.cpu.csv"
        rows = ((1_700_000_000 + (i // procs) * 0.5, 1000 + i % procs, f"node{i % procs}", "python3",
                 round(float(rng.uniform(0, 200)), 1), 40_000_000 + i % procs) for i in range(args.rows))
        write_cpu_trace(path, rows, host="bench", logical_cpus=4, interval_s=0.5)
        size = path.stat().st_size
        fast = read_cpu_trace(path)
        from perfros_bag.cpu.trace import parse_cpu_trace

        slow = parse_cpu_trace(path.read_text(), path, fast=False)
        assert (fast.time == slow.time).all() and (fast.cpu_percent == slow.cpu_percent).all()
        assert fast.node == slow.node and (fast.pid == slow.pid).all()

        t_fast = best(lambda: read_cpu_trace(path), args.repeat)
        t_slow = best(lambda: parse_cpu_trace(path.read_text(), path, fast=False), args.repeat)
        t_pandas = best(lambda: pd.read_csv(path, comment="#"), args.repeat)
        nodes: dict[str, str | None] = {f"node{k}": None for k in range(procs)}
        t_attr = best(lambda: node_cpu(fast, 100.0, nodes=nodes), args.repeat)

    print(f"trace: {args.rows:,} rows, {size / 1e6:.1f} MB, best of {args.repeat}")
    print("| reader | s | rows/s | vs careful parser | vs bare pandas.read_csv |")
    print("|---|---:|---:|---:|---:|")
    for name, t in (("fast path (read_cpu_trace)", t_fast), ("careful parser (fast=False)", t_slow),
                    ("bare pandas.read_csv", t_pandas)):
        print(f"| {name} | {t:.3f} | {args.rows / t:,.0f} | {t_slow / t:.1f}x | {t_pandas / t:.2f}x |")
    print(f"node_cpu (20 nodes, mean + p95): {t_attr:.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
