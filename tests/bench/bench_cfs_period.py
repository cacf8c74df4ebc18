"""The CFS period of an emulated computer against the delay it adds (issue 29 item 4).

One emulated robot as ``deploy`` makes it (:class:`perfros_bag.rosrun.cgroups.CpuGroups`): the
case study's camera (image_publisher, 320x240 at 10 Hz), people detector (opencv_apps
people_detect, scale0 1.05) and smoother (opencv_apps smoothing, bilateral, kernel 15) in one
CPU-capped group, on a ROS master of our own. Their summed CPU need is measured uncapped
(psutil, over a window), then the group is capped at ``--cap`` x that need (a plan with
headroom: its rates should hold) and, per CFS period (``--periods``, in ms; each ``--repeats``
times, the periods interleaved so a change in the machine's load falls on all of them),
``rosbag record`` (Debian's, outside the group) records the camera's and both nodes' outputs
for a window; the tool's own ``info --latency`` reading of that bag
(:func:`perfros_bag.ingest.contents.read_with_latency`: receipt time - header.stamp, which the
nodes copy from the camera's frame) gives each node's latency p50/p95, and its kept rate is
its output messages over the camera's in the bag. An uncapped window first is the reference.

    .venv/bin/python tests/bench/bench_cfs_period.py [--out FILE.json] [--window 10]
        [--periods 100,10,5] [--repeats 2] [--cap 1.5] [--scale0 1.05] [--kernel 15]
        [--robot people,smooth] [--burst 1.0] [--pin]

Prints a table and the load average; ``--out`` writes the JSON. Everything it starts carries
a run tag and is stopped, and its cgroup removed, on exit, Ctrl-C, SIGTERM or an error (the
JSON lists what was left: empty lists). Needs root and a cgroup cpu controller (exit 1
without). ~2 min with the defaults. :func:`measure` is the same as a function.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cgroup_fairness import INPUT, NODES, RATE_HZ, _cpu_s, bench_run, finish  # noqa: E402  (the same nodes)

ROBOT = "robot"
MEASURED = ("people", "smooth")  # the nodes on the robot by default: their latency and kept rate are measured


def _window(procs: Any, tmp: Path, tag: str, seconds: float, groups: Any, measured: tuple[str, ...]) -> dict[str, Any]:
    """One window: rosbag record of the camera and the nodes' outputs; their rates and latency."""
    from perfros_bag.ingest.contents import read_with_latency
    from perfros_bag.rosrun.recorders import start_rosbag

    bag = tmp / f"{tag}.bag"
    topics = [INPUT, *(NODES[k][3] for k in measured)]
    thr0 = groups.throttled(ROBOT)
    start_rosbag(procs, f"rosbag-{tag}", bag, topics, f"bench_period_{tag}", tmp / f"rosbag-{tag}.log", tmp)
    time.sleep(seconds)
    procs.stop([f"rosbag-{tag}"])
    thr1 = groups.throttled(ROBOT)
    stats, delays = read_with_latency(bag)
    cam = stats.topics.get(INPUT)
    n_in = cam.messages if cam is not None else 0
    out: dict[str, Any] = {"frames_in": n_in, "camera_hz": None if cam is None else cam.frequency_hz,
                           "nr_throttled": thr1.get("nr_throttled", 0.0) - thr0.get("nr_throttled", 0.0),
                           "nr_periods": thr1.get("nr_periods", 0.0) - thr0.get("nr_periods", 0.0),
                           "nodes": {}}
    for key in measured:
        topic = NODES[key][3]
        ts = stats.topics.get(topic)
        d = delays.get(topic)
        n_out = ts.messages if ts is not None else 0
        out["nodes"][key] = {"frames_out": n_out, "kept": round(n_out / n_in, 4) if n_in else None,
                             "p50_ms": None if d is None else round(1e3 * d.p50_s, 2),
                             "p95_ms": None if d is None else round(1e3 * d.p95_s, 2),
                             "max_ms": None if d is None else round(1e3 * d.max_s, 2)}
    bag.unlink(missing_ok=True)
    return out


def _pin(pids: list[int], cpus: list[int]) -> None:
    """Every thread of ``pids`` (and their children) onto ``cpus``."""
    import psutil

    for pid in pids:
        try:
            procs = [psutil.Process(pid), *psutil.Process(pid).children(recursive=True)]
        except psutil.Error:
            continue
        for proc in procs:
            try:
                tids = os.listdir(f"/proc/{proc.pid}/task")
            except OSError:
                continue
            for tid in tids:
                try:
                    os.sched_setaffinity(int(tid), cpus)
                except OSError:
                    pass


def measure(periods_ms: list[float], repeats: int = 2, window: float = 10.0, cap: float = 1.5,
            scale0: float = 1.05, kernel: int = 15, settle: float = 2.0, warmup: float = 6.0,
            log: Any = print, measured: tuple[str, ...] = MEASURED, burst: float = 0.0,
            pin: bool = False) -> dict[str, Any]:
    """Run the bench; the result document (see the module's docstring)."""
    from perfros_bag.rosrun.master import start_roscore

    rows: list[dict[str, Any]] = []
    started = time.monotonic()
    load_before = os.getloadavg()
    need = 0.0
    with bench_run("bench_cfs_period", "period", {ROBOT: 1.0}) as run:
        procs, groups, tmp, scene, run_id = run.procs, run.groups, run.tmp, run.scene, run.run_id
        uri = start_roscore(procs, tmp, 30.0)
        log(f"roscore at {uri}; run tag {run_id}")
        opts = {"scale0": f"{scale0:g}", "kernel": str(kernel)}
        pids = []
        for key in ("camera", *measured):
            name, exe, extra, _topic = NODES[key]
            argv = ([exe, str(scene), f"_publish_rate:={RATE_HZ:g}", f"__name:={name}"] if key == "camera"
                    else [exe, *(a % opts for a in extra), f"__name:={name}"])
            pids.append(procs.start(key, groups.wrap(ROBOT, argv), tmp / f"{key}.log").popen.pid)
        time.sleep(warmup)
        cpu0, t0 = sum(_cpu_s(p) for p in pids), time.monotonic()
        base = _window(procs, tmp, "uncapped", window, groups, measured)
        need = (sum(_cpu_s(p) for p in pids) - cpu0) / (time.monotonic() - t0)
        rows.append({"option": "uncapped", "period_ms": None, "repeat": 1, "quota_cores": None, **base})
        log(f"uncapped: need {100 * need:.1f} % of a core; " + _line(base))
        groups.cores[ROBOT] = cap * need
        options = [(p, 0.0, False) for p in periods_ms]
        options += [(p, burst, False) for p in periods_ms if burst > 0 and p < 100]
        options += [(p, 0.0, True) for p in periods_ms if pin and p < 100]
        every = sorted(os.sched_getaffinity(0))
        for r in range(1, repeats + 1):
            for p, b, pinned in options:
                groups.period_us, groups.burst = int(round(p * 1000)), b
                groups.apply()
                _pin(pids, every[-1:] if pinned else every)
                time.sleep(settle)
                name = (f"CFS period {p:g} ms" + (f" + burst {b:g}x quota" if b else "")
                        + (" + pinned to 1 CPU" if pinned else ""))
                w = _window(procs, tmp, f"p{p:g}b{b:g}r{r}", window, groups, measured)
                rows.append({"option": name, "period_ms": p, "burst": b, "pinned": pinned, "repeat": r,
                             "quota_cores": round(groups.cores[ROBOT], 4),
                             "period_us": groups.group_period_us(ROBOT), **w})
                log(f"{name} (repeat {r}): " + _line(w))
    return {"format": "perfros-bag/bench-cfs-period@1", "run_id": run_id, "cgroups": groups.mode,
            "window_s": window, "cap": cap, "robot": ["camera", *measured], "need_cores": round(need, 4),
            "scale0": scale0, "kernel": kernel,
            "rate_hz": RATE_HZ, "wall_s": round(time.monotonic() - started, 1),
            "load_average": {"before": load_before, "after": os.getloadavg()}, "rows": rows,
            **run.leftovers()}


def _line(w: dict[str, Any]) -> str:
    return "; ".join(f"{k} kept {_pct(n['kept'])} p50 {n['p50_ms']} ms p95 {n['p95_ms']} ms"
                     for k, n in w["nodes"].items()) + f"; throttled {w['nr_throttled']:.0f}/{w['nr_periods']:.0f}"


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def table(doc: dict[str, Any]) -> str:
    measured = doc["robot"][1:]
    lines = ["| option | repeat | quota (% core) | camera Hz | "
             + " | ".join(f"{k} kept | {k} p50 ms | {k} p95 ms" for k in measured) + " | throttled periods |",
             "|---|---:|---:|---:|" + "---:|" * (3 * len(measured)) + "---:|"]
    for r in doc["rows"]:
        q = "-" if r["quota_cores"] is None else f"{100 * r['quota_cores']:.1f}"
        cam = "-" if r["camera_hz"] is None else f"{r['camera_hz']:.2f}"
        cells = " | ".join(f"{_pct(n['kept'])} | {n['p50_ms']} | {n['p95_ms']}" for n in r["nodes"].values())
        lines.append(f"| {r['option']} | {r['repeat']} | {q} | {cam} | {cells} | "
                     f"{r['nr_throttled']:.0f}/{r['nr_periods']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the JSON here")
    ap.add_argument("--window", type=float, default=10.0, help="seconds recorded per option and repeat")
    ap.add_argument("--periods", default="100,10,5", help="CFS periods to compare, ms")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cap", type=float, default=1.5, help="the robot's cap, as a multiple of its nodes' need")
    ap.add_argument("--scale0", type=float, default=1.05)
    ap.add_argument("--kernel", type=int, default=15)
    ap.add_argument("--robot", default=",".join(MEASURED), help="the nodes on the robot beside the camera")
    ap.add_argument("--pin", action="store_true", help="also each period under 100 ms with the robot pinned to one CPU")
    ap.add_argument("--burst", type=float, default=0.0,
                    help="also each period under 100 ms with this CFS burst (share of the quota, 0-1)")
    args, _unknown = ap.parse_known_args(argv)  # tests/bench/run.py passes its own arguments to all
    periods = [float(p) for p in args.periods.split(",") if p.strip()]
    if not periods or any(not (1 <= p <= 1000) for p in periods) or args.repeats < 1:
        ap.error("periods must be 1-1000 ms and repeats >= 1")
    robot = tuple(n.strip() for n in args.robot.split(",") if n.strip())
    if not robot or any(n not in MEASURED for n in robot):
        ap.error(f"--robot: some of {', '.join(MEASURED)}")
    try:
        doc = measure(periods, args.repeats, args.window, args.cap, args.scale0, args.kernel,
                      log=lambda s: print(s, flush=True), measured=robot, burst=args.burst,
                      pin=args.pin)
    except KeyboardInterrupt:
        print("interrupted: everything the bench started is stopped", file=sys.stderr)
        return 130
    la = doc["load_average"]
    return finish(doc, table(doc),
                  f"robot: {', '.join(doc['robot'])}; need {100 * doc['need_cores']:.1f} % of a core, "
                  f"cap {doc['cap']:g}x; wall {doc['wall_s']} s; load average before {la['before'][0]:.2f} "
                  f"after {la['after'][0]:.2f} (2 cores)", args.out)


if __name__ == "__main__":
    sys.exit(main())
