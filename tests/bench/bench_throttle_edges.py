"""Issue 31's layout (fixtures/throttle_edges: image_publisher at 15 Hz; topic_tools' throttle,
rate 3 / 6 / 12, in front of opencv_apps' fback_flow; opencv_apps' edge_detection, apertureSize
3 / 5 / 7, on the raw stream): the README's steps as a new user runs them, with no file
written by hand except the computer's capacity:

    sweep -> init -> characterise -> fit -> solve (Problem 1, exact) -> deploy

once per capacity of the one computer (the machine's 200 units, and smaller ones where the
plan must lower the throttle). Printed per capacity: what init drafted for the flow node, the
plan's throttle value and flow input rate, whether the value was measured, the deployment's
deviation (goal: within 2.5 %) and the machine's load (1-minute average) before each step.

    .venv/bin/python tests/bench/bench_throttle_edges.py [--capacities 200,40,30] [--duration 10] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
FIX = ROOT / "fixtures" / "throttle_edges"
LAUNCH, SPACE = FIX / "throttle_edges.launch", FIX / "space.yaml"
BIN = Path(sys.executable).with_name("perfros-bag")


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([str(BIN), *args], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "200"})
    if done.returncode not in (0, 1):  # deploy exits 1 when the deviation is over its tolerance
        sys.exit(f"{args[0]} failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return done


def load() -> float:
    return os.getloadavg()[0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capacities", default="200,40,30", help="the computer's capacities to plan and deploy at")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds each deployment records")
    ap.add_argument("--keep", type=Path, default=None, help="work here (the runs a sweep there finished are kept)")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="throttle_edges-"))
    work.mkdir(parents=True, exist_ok=True)
    started = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    sweep_load = load()
    cli("sweep", str(LAUNCH), "--space", str(SPACE), "--out", "runs/", cwd=work)  # runs already there are kept
    cli("init", "runs/", "--out", "system.yaml", cwd=work)
    draft = yaml.safe_load((work / "system.yaml").read_text())
    flow = next(n for n in draft["nodes"] if n["name"] == "flow")
    drafted = f"driven by {flow['input']}" if "input" in flow else "NOT driven (an ordinary node)"
    cli("characterise", "runs/", "--system", "system.yaml", "--out", "characterisation.csv", cwd=work)
    print(f"{started}: sweep at load {sweep_load:.1f}; init drafted flow {drafted}")
    print(f"{'capacity':>8} {'throttle':>8} {'measured':>8} {'flow in Hz':>10} {'deviation %':>11} {'load':>5}")
    worst = 0.0
    for cap in (float(c) for c in args.capacities.split(",")):
        sys_doc = dict(draft, computers=[dict(c, capacity=cap) for c in draft["computers"]])
        name = f"{cap:g}"
        (work / f"system-{name}.yaml").write_text(yaml.safe_dump(sys_doc, sort_keys=False))
        cli("fit", f"system-{name}.yaml", "characterisation.csv", "--out", f"model-{name}.json", cwd=work)
        solved = cli("solve", f"model-{name}.json", "--problem", "1", "--method", "exact", "--out",
                     f"plan-{name}.json", cwd=work)
        if solved.returncode != 0:
            print(f"{name:>8} no plan fits: {solved.stderr.strip()[-200:]}")
            continue
        plan = json.loads((work / f"plan-{name}.json").read_text())["nodes"]
        at = load()
        cli("deploy", f"plan-{name}.json", str(LAUNCH), "--space", str(SPACE), "--system", f"system-{name}.yaml",
            "--out", f"deployed-{name}/", "--duration", f"{args.duration:g}", cwd=work)
        deviation = json.loads((work / f"deployed-{name}" / "validation.json").read_text())["overall"]["deviation_pct"]
        worst = max(worst, deviation)
        print(f"{name:>8} {plan['throttle']['value']:>8.3g} {str(plan['throttle'].get('measured', '-')):>8} "
              f"{plan['flow'].get('input_hz') or 0:>10.3g} {deviation:>11.2f} {at:>5.1f}", flush=True)
    print(f"worst deviation {worst:.2f} % (goal 2.5 %); work in {work}")
    return 0 if worst <= 2.5 else 1


if __name__ == "__main__":
    sys.exit(main())
