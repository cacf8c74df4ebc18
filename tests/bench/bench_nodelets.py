"""Nodelets (issue 34): how exact the split of a manager's CPU among its nodelets is.

On fixtures/nodelet (Debian's image_publisher -> one nodelet manager with opencv_apps'
people_detect and smoothing), two sweeps of the same space (one nodelet's setting at a time,
``--repeats`` runs per setting):

* ``nodelet.launch``: the nodelets inside their manager (plus the standalone run ``sweep``
  adds); ``characterise`` splits the manager's CPU (perfros_bag/characterisation/containers.py);
* ``standalone.launch``: the same nodelets, each ``nodelet standalone`` in a process of its
  own: each one's CPU measured on its own, at every setting.

Printed: each nodelet's estimate at each value against its standalone CPU at that value
(goal: within 15 %), per in-manager run the sum of the estimates against the manager's
measured CPU (goal: within 5 %), and the copy price (characterisation/containers.copy_price):
the whole-run CPU the standalone run adds over the in-manager runs at the same values, per
MB/s of the copies it adds.

    .venv/bin/python tests/bench/bench_nodelets.py [--repeats 2] [--duration 30] [--keep DIR] [--repeat-off-speed 2]

Each run's host speed (record-cpu's reference) is printed beside the split: a run made while
the host ran slow costs more CPU for the same frames, and one such run moves its setting's
estimate (sixth run, docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FIX = ROOT / "fixtures" / "nodelet"
BIN = Path(sys.executable).with_name("perfros-bag")


def sweep(launch: Path, space: Path, out: Path, duration: float, off_speed: int) -> None:
    if (out / "manifest.yaml").exists():
        return  # --keep: reuse
    again = ["--repeat-off-speed", str(off_speed)] if off_speed else []
    subprocess.run([str(BIN), "sweep", str(launch), "--space", str(space), "--out", str(out), "--duration",
                    f"{duration:g}", *again], check=True, capture_output=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--keep", type=Path, default=None, help="folder for the two sweeps (reused when there)")
    ap.add_argument("--repeat-off-speed", type=int, default=2,
                    help="sweep's --repeat-off-speed (0: off): runs made while the host ran >15 %% off its median "
                         "speed are recorded again, as the case study's sweep does")
    a = ap.parse_args()
    import yaml

    from perfros_bag.characterisation.manifest import load_manifest
    from perfros_bag.characterisation.table import characterise, table_one
    from perfros_bag.sweep.draft import draft_system
    from perfros_bag.system.systemfile import load_system

    load0, t0 = os.getloadavg(), time.monotonic()
    work = a.keep or Path(tempfile.mkdtemp(prefix="bench-nodelets-"))
    work.mkdir(parents=True, exist_ok=True)
    inside, alone = work / "inside", work / "alone"
    if (work / "space.yaml").exists() and (inside / "manifest.yaml").exists():  # --keep: the kept runs' space
        space = yaml.safe_load((work / "space.yaml").read_text())
    else:
        space = yaml.safe_load((FIX / "space.yaml").read_text())
        space.update(repeats=a.repeats, duration_s=a.duration)
        (work / "space.yaml").write_text(yaml.safe_dump(space))
    sweep(FIX / "nodelet.launch", work / "space.yaml", inside, space["duration_s"], a.repeat_off_speed)
    sweep(FIX / "standalone.launch", work / "space.yaml", alone, space["duration_s"], a.repeat_off_speed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        draft_system(inside, work / "inside.yaml")
        draft_system(alone, work / "alone.yaml")
        m_in, m_alone = load_manifest(inside / "manifest.yaml"), load_manifest(alone / "manifest.yaml")
        split = characterise(m_in.recordings, load_system(work / "inside.yaml"))
        measured = characterise(m_alone.recordings, load_system(work / "alone.yaml"))
    truth = {(t.node, repr(t.value)): t.cpu for t in table_one(measured.rows)}
    speeds = {e.name: e.speed_factor for e in [*m_in.recordings, *m_alone.recordings]}
    print("host speed per run (record-cpu's reference): " + ", ".join(
        f"{k.removesuffix('.bag')} {v:.3f}" for k, v in speeds.items() if v is not None))
    print(f"runs: {work}  (repeats {space['repeats']}, {space['duration_s']:g} s each; sweeps done in "
          f"{time.monotonic() - t0:.0f} s, load average before {load0[0]:.2f}, after {os.getloadavg()[0]:.2f})")
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
    repeats_of_a_setting(split.splits)
    print("\n| container | in-manager runs | standalone run | extra CPU (units) | extra copies (kB/s) |")
    print("|---|---|---|---:|---:|")
    for s in split.splits:
        for pair, (cpu, copies) in (s.copy_runs or {}).items():
            ins, alone_run = pair.split("|")
            print(f"| {s.container} | {ins} | {alone_run} | {cpu:+.3f} | {copies:.0f} |")
        price = "not measured" if s.copy_per_MBps is None else f"{s.copy_per_MBps:.4f} CPU units per MB/s"
        print(f"copy price of {s.container} (apart from lambda = {s.factor:.3f}): {price}")
    copy_at_every_setting(work, m_in.recordings, m_alone.recordings, measured.rows)


def setting_of(recording: str) -> str:
    """A run's setting: its recording's name without the repeat (``_r2``) and the extension."""
    return re.sub(r"_r\d+$", "", recording.removesuffix(".bag"))


def repeats_of_a_setting(splits: list) -> None:
    """Per setting, its repeats' manager CPU and their spread, (max - min) / mean: one
    estimate per setting cannot be nearer to every repeat than half that spread, so half of it
    is the floor of the largest per-run error of the sum. (Against the repeats' mean the sum
    says nothing here: one setting moving at a time has as many settings as unknowns, so the
    fit matches every setting's mean by construction.)"""
    print("\n| setting | manager measured, per repeat | spread of the repeats | half of it |")
    print("|---|---|---:|---:|")
    for s in splits:
        by: dict[str, list[float]] = {}
        for rec, (meas, _fit) in s.runs.items():
            by.setdefault(setting_of(rec), []).append(meas)
        for name, meas in by.items():
            spread = 100 * (max(meas) - min(meas)) / statistics.mean(meas)
            print(f"| {name} | {' / '.join(f'{m:.2f}' for m in meas)} | {spread:.1f} % | {spread / 2:.1f} % |")


def copy_at_every_setting(work: Path, inside: list, alone: list, alone_rows: list) -> None:
    """The same price at every setting the two sweeps share: standalone.launch's runs against
    nodelet.launch's at the same values (repeats averaged), whole-run CPU of every node."""
    import yaml

    from perfros_bag.characterisation.containers import extra_copies
    from perfros_bag.characterisation.table import characterise
    from perfros_bag.system.systemfile import load_system, parse_system

    system = load_system(work / "inside.yaml")
    doc = yaml.safe_load((work / "inside.yaml").read_text())
    for n in doc["nodes"]:
        n.pop("container", None)
        n.pop("copy_cpu_per_MBps", None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = characterise([e for e in inside if not e.standalone], parse_system(doc, "unsplit")).rows
    names = [n.name for n in system.nodes]

    def totals(rs: list, recs: list) -> dict[tuple, list[float]]:
        out: dict[tuple, list[float]] = {}
        for e in recs:
            cpu = {r.node: r.cpu_units_mean for r in rs if r.recording == e.name and r.cpu_units_mean is not None}
            key = tuple(sorted((k, repr(v)) for k, v in e.settings.items()))
            out.setdefault(key, []).append(sum(cpu.get(n, 0.0) for n in names))
        return out

    t_in, t_alone = totals(rows, [e for e in inside if not e.standalone]), totals(alone_rows, alone)
    print("\n| setting | in-manager total | standalone total (standalone.launch) | extra copies (kB/s) | price |")
    print("|---|---:|---:|---:|---:|")
    prices = []
    for host, members in system.containers.items():
        for key in sorted(set(t_in) & set(t_alone)):
            rec = next(e.name for e in alone if tuple(sorted((k, repr(v)) for k, v in e.settings.items())) == key)
            x = extra_copies(system, host, members, alone_rows, rec)
            a, b = statistics.mean(t_in[key]), statistics.mean(t_alone[key])
            price = (b - a) / (x / 1000) if x else float("nan")
            prices.append(price)
            print(f"| {dict(key)} | {a:.2f} | {b:.2f} | {x or 0:.0f} | {price:+.3f} |")
    if prices:
        print(f"copy price over the settings: mean {statistics.mean(prices):+.3f}, "
              f"from {min(prices):+.3f} to {max(prices):+.3f} CPU units per MB/s")


if __name__ == "__main__":
    main()
