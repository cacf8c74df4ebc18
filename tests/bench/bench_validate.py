"""validate's cost over reading the recording: eq 10, CPU trace and link checks on top of
``read_recording`` (the baseline, measured in the same run on the same file).

    .venv/bin/python tests/bench/bench_validate.py [--nodes 200] [--seconds 60] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from _timing import best  # tests/bench/_timing.py (this folder is on sys.path)

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "pipelines"))


def make_plan(nodes: int, path: Path) -> None:
    plan = {
        "format": "perfros-bag/plan@1", "problem": 1, "method": "bench", "status": "optimal",
        "computers": {f"c{k}": {"kind": "server", "capacity": 400, "cpu": 0} for k in range(4)},
        "links": [],
        "nodes": {
            f"n{i}": {"computer": f"c{i % 4}", "cpu": 1, "performance": 50 + i % 50, "weight": 1 / nodes,
                      "topics": {f"/n{i}/out": {"frequency_hz": float(5 + i % 20), "bandwidth_kBps": 1.0}}}
            for i in range(nodes)
        },
    }
    path.write_text(json.dumps(plan))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--nodes", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import simulate_run

    from perfros_bag.ingest import read_recording
    from perfros_bag.system.planfile import load_plan
    from perfros_bag.validation.eq10 import check_run, node_cpu_from_trace, validate_files

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        make_plan(args.nodes, d / "plan.json")
        plan = load_plan(d / "plan.json")
        n = simulate_run.write_recording(plan, d / "run.mcap", args.seconds, 1.0)
        simulate_run.write_trace(plan, d / "run.cpu.csv", args.seconds, 4, 1.0)
        base = best(lambda: read_recording(d / "run.mcap"), args.repeat)
        stats = read_recording(d / "run.mcap")
        eq10 = best(lambda: check_run(stats, plan), args.repeat)
        trace = best(lambda: node_cpu_from_trace(d / "run.cpu.csv", plan, None, stats.start_ns, stats.end_ns),
                     args.repeat)
        full = best(lambda: validate_files(d / "run.mcap", d / "plan.json"), args.repeat)
        v = validate_files(d / "run.mcap", d / "plan.json")
        assert abs(v.deviation_pct) < 0.5, v.deviation_pct
        print(f"{args.nodes} nodes, {n} messages, {args.seconds:g} s, "
              f"CPU trace {len(plan.nodes) * int(args.seconds)} rows")
        print(f"| step | best of {args.repeat} (s) | ratio to reading |")
        print("|---|---:|---:|")
        print(f"| read_recording (baseline) | {base:.3f} | 1.00 |")
        print(f"| eq 10 on the statistics (check_run) | {eq10:.4f} | {eq10 / base:.3f} |")
        print(f"| CPU trace: read_cpu_trace + node_cpu | {trace:.3f} | {trace / base:.2f} |")
        print(f"| validate (read + eq 10 + CPU trace) | {full:.3f} | {full / base:.2f} |")


if __name__ == "__main__":
    main()
