"""Simulate a run of a plan: an MCAP recording at the planned rates and its CPU trace.

Used by the demo (pipelines/validate.mk) in place of a real deployment: every planned
topic is published at ``--rate`` x its planned frequency for ``--seconds`` with messages
sized to its planned bandwidth (std_msgs/msg/String in CDR), and ``<stem>.cpu.csv`` holds
each node at its planned CPU (``--cpu-scale`` x) on a ``--cores``-core computer.

    python pipelines/simulate_run.py out/demo/plan.json out/demo/run.mcap
"""

from __future__ import annotations

import argparse
import struct
import sys
from pathlib import Path

from mcap.writer import Writer

from perfros_bag.cpu.trace import write_cpu_trace
from perfros_bag.errors import PerfrosError
from perfros_bag.fileio import atomic_open
from perfros_bag.system.plan import Plan
from perfros_bag.system.planfile import load_plan

T0_NS = 1_700_000_000_000_000_000


def string_cdr(length: int) -> bytes:
    """A std_msgs/msg/String of ``length`` characters, CDR little-endian."""
    return b"\x00\x01\x00\x00" + struct.pack("<I", length + 1) + b"x" * length + b"\x00"


def write_recording(plan: Plan, path: Path, seconds: float, rate: float) -> int:
    count = 0
    with atomic_open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="perfros-bag simulate_run")
        sid = w.register_schema(name="std_msgs/msg/String", encoding="ros2msg", data=b"string data")
        for pn in plan.nodes.values():
            for topic, pt in pn.topics.items():
                if not pt.frequency_hz:
                    continue
                hz = pt.frequency_hz * rate
                size = max(0, round((pt.bandwidth_kBps or 0.064) * 1000 / hz) - 9)
                payload = string_cdr(size)
                cid = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
                n = int(seconds * hz) + 1
                for i in range(n):
                    t = T0_NS + round(i * 1e9 / hz)
                    w.add_message(channel_id=cid, log_time=t, publish_time=t, data=payload, sequence=i)
                count += n
        w.finish()
    return count


def write_trace(plan: Plan, path: Path, seconds: float, cores: int, cpu_scale: float) -> None:
    rows = []
    for k in range(1, int(seconds) + 1):
        for pid, (name, pn) in enumerate(plan.nodes.items(), start=1000):
            cap = plan.computers[pn.computer].capacity if pn.computer in plan.computers else None
            if not cap:
                continue
            pct = pn.cpu * cpu_scale / cap * 100.0 * cores
            rows.append((T0_NS / 1e9 + k, pid, name, "simulated", pct, 50_000_000))
    write_cpu_trace(path, rows, host="simulated", logical_cpus=cores, interval_s=1.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("plan", type=Path)
    ap.add_argument("out", type=Path, help="the .mcap to write; the trace goes to <stem>.cpu.csv")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=1.0, help="fraction of the planned frequencies")
    ap.add_argument("--cores", type=int, default=4)
    ap.add_argument("--cpu-scale", type=float, default=1.0, help="fraction of the planned CPU")
    args = ap.parse_args(argv)
    try:
        plan = load_plan(args.plan)
        plan.require_feasible(args.plan, "simulate")
        n = write_recording(plan, args.out, args.seconds, args.rate)
        write_trace(plan, args.out.with_name(f"{args.out.stem}.cpu.csv"), args.seconds, args.cores, args.cpu_scale)
    except PerfrosError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({n} messages) and its CPU trace", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
