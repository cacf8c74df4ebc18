"""Nodelets (issue 34): how exact the split of a manager's CPU among its nodelets is.

On fixtures/nodelet (Debian's image_publisher -> one nodelet manager with opencv_apps'
people_detect and smoothing), two sweeps of the same space (one nodelet's setting at a time,
``--repeats`` runs per setting):

* ``nodelet.launch``: the nodelets inside their manager (plus the standalone run ``sweep``
  adds); ``characterise`` splits the manager's CPU (perfros_bag/characterisation/containers.py);
* ``standalone.launch``: the same nodelets, each ``nodelet standalone`` in a process of its
  own: each one's CPU measured on its own, at every setting.

Printed: each nodelet's estimate at each value against its standalone CPU at that value
(goal: within 15 %), and per in-manager run the sum of the estimates against the manager's
measured CPU (goal: within 5 %).

    .venv/bin/python tests/bench/bench_nodelets.py [--repeats 2] [--duration 8] [--keep DIR]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FIX = ROOT / "fixtures" / "nodelet"
BIN = Path(sys.executable).with_name("perfros-bag")


def sweep(launch: Path, space: Path, out: Path, duration: float) -> None:
    if (out / "manifest.yaml").exists():
        return  # --keep: reuse
    subprocess.run([str(BIN), "sweep", str(launch), "--space", str(space), "--out", str(out), "--duration",
                    f"{duration:g}"], check=True, capture_output=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--keep", type=Path, default=None, help="folder for the two sweeps (reused when there)")
    a = ap.parse_args()
    import yaml

    from perfros_bag.characterisation.manifest import load_manifest
    from perfros_bag.characterisation.table import characterise, table_one
    from perfros_bag.sweep.draft import draft_system
    from perfros_bag.system.systemfile import load_system

    work = a.keep or Path(tempfile.mkdtemp(prefix="bench-nodelets-"))
    work.mkdir(parents=True, exist_ok=True)
    space = yaml.safe_load((FIX / "space.yaml").read_text())
    space["repeats"] = a.repeats
    (work / "space.yaml").write_text(yaml.safe_dump(space))
    inside, alone = work / "inside", work / "alone"
    sweep(FIX / "nodelet.launch", work / "space.yaml", inside, a.duration)
    sweep(FIX / "standalone.launch", work / "space.yaml", alone, a.duration)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        draft_system(inside, work / "inside.yaml")
        draft_system(alone, work / "alone.yaml")
        m_in, m_alone = load_manifest(inside / "manifest.yaml"), load_manifest(alone / "manifest.yaml")
        split = characterise(m_in.recordings, load_system(work / "inside.yaml"))
        measured = characterise(m_alone.recordings, load_system(work / "alone.yaml"))
    truth = {(t.node, repr(t.value)): t.cpu for t in table_one(measured.rows)}
    print(f"runs: {work}  (repeats {a.repeats}, {a.duration:g} s each)")
    print("| nodelet | value | estimate inside the manager | standalone, measured | error |")
    print("|---|---|---:|---:|---:|")
    errors = []
    for s in split.splits:
        for node, by_value in s.cpu.items():
            for value, est in sorted(by_value.items(), key=lambda kv: float(kv[0])):
                true = truth.get((node, value))
                if true is None or not true:
                    continue
                err = 100 * (est - true) / true
                errors.append(abs(err))
                print(f"| {node} | {value} | {est:.2f} | {true:.2f} | {err:+.1f} % |")
    print(f"\nlargest |error| per nodelet and value: {max(errors):.1f} %" if errors else "")
    print("\n| run (inside the manager) | manager measured | sum of the estimates | error |")
    print("|---|---:|---:|---:|")
    sums = []
    for s in split.splits:
        print(f"(container {s.container}: lambda = {s.factor:.3f})")
        for rec, (meas, fit) in s.runs.items():
            sums.append(abs(100 * (fit - meas) / meas))
            print(f"| {rec} | {meas:.2f} | {fit:.2f} | {100 * (fit - meas) / meas:+.1f} % |")
    if sums:
        print(f"\nlargest |error| of a run's sum: {max(sums):.1f} %; mean {statistics.mean(sums):.1f} %")


if __name__ == "__main__":
    main()
