"""Cgroup fairness per case-study node (issue 21 item 3, "emulated computers, measured").

For each node of the real-node case study (fixtures/casestudy_real/robot.launch: the camera
is Debian's image_publisher, 320x240 at 10 Hz; people = opencv_apps people_detect at scale0
1.05; smooth = opencv_apps smoothing, bilateral, kernel_size 15): the camera and that node run
on a ROS master of our own (a free loopback port); the node's mean CPU need is measured
uncapped (psutil: its CPU seconds over the window), then ONLY that node's process is capped in
a cgroup (the tool's own :class:`perfros_bag.rosrun.cgroups.CpuGroups`, as ``deploy`` uses it)
at 1.0x, 1.1x and 1.25x of that need, and at each point the share of frames it keeps is
counted: frames out / frames in (a rospy subscriber counts both topics, ``rospy.AnyMsg``: no
deserialisation). For the camera, kept = its output rate / its uncapped output rate.
Prediction: kept = min(1, quota / need).

    .venv/bin/python tests/bench/bench_cgroup_fairness.py [--out FILE.json] [--window 8]
        [--factors 1.0,1.1,1.25] [--nodes people,smooth,camera] [--scale0 1.05] [--kernel 15]

Prints a table; ``--out`` writes the JSON (``kept_at_1x``: node -> kept share at 1.0x,
``kept_at_1x_min``: the smallest; the headroom rule of docs/solvers.md cites it). Everything
it starts carries a run tag (:data:`perfros_bag.rosrun.processes.RUN_ENV`) and is stopped, and
its cgroup removed, on exit, Ctrl-C, SIGTERM or an error; the JSON states what was left
(``leftover_processes``, ``leftover_cgroups``: empty lists). Without root / cgroups the bench
says so and exits 1. ~3 min with the defaults (150-186 s measured). :func:`measure` is the same as a function.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

ROS_PY = "/usr/bin/python3"  # Debian's interpreter, with rospy
RATE_HZ = 10.0
# Per node: (ROS node name, executable, extra args (private params; %(k)s from the options),
# its output topic). The camera's image is the input of the other two.
NODES: dict[str, tuple[str, str, list[str], str]] = {
    "camera": ("camera", "/usr/lib/image_publisher/image_publisher", [], "/camera/image_raw"),
    "people": ("people", "/usr/lib/opencv_apps/people_detect",
               ["image:=/camera/image_raw", "_debug_view:=false", "_scale0:=%(scale0)s"], "/people/found"),
    "smooth": ("smooth", "/usr/lib/opencv_apps/smoothing",
               ["image:=/camera/image_raw", "_debug_view:=false", "_filter_type:=3", "_kernel_size:=%(kernel)s"],
               "/smooth/image"),
}
INPUT = "/camera/image_raw"

# Counts messages of the topics in argv[1:] (rospy.AnyMsg: nothing deserialised); every line
# on stdin is answered with one JSON line {"t": time, "counts": {topic: n}}.
COUNTER = r"""
import json, sys, time, threading, rospy
rospy.init_node("perfros_fairness_counter", anonymous=True, disable_signals=True)
counts = {t: 0 for t in sys.argv[1:]}
lock = threading.Lock()
def make(topic):
    def cb(_msg):
        with lock:
            counts[topic] += 1
    return cb
subs = [rospy.Subscriber(t, rospy.AnyMsg, make(t), queue_size=100) for t in counts]
print(json.dumps({"ready": True}), flush=True)
for _line in sys.stdin:
    with lock:
        print(json.dumps({"t": time.monotonic(), "counts": dict(counts)}), flush=True)
"""


@dataclass
class BenchRun:
    """What :func:`bench_run` gives a bench: its run tag, a temp folder with the case study's
    scene, its processes and its (uncapped) cgroups; ``left`` after the run."""

    run_id: str
    tmp: Path
    scene: Path
    procs: Any
    groups: Any
    left_groups: list[Path] = field(default_factory=list)

    def leftovers(self) -> dict[str, list[Any]]:
        from perfros_bag.rosrun.cgroups import leftover_groups
        from perfros_bag.rosrun.processes import leftover_processes

        return {"leftover_processes": leftover_processes(self.run_id),
                "leftover_cgroups": [str(p) for p in self.left_groups + leftover_groups(run_id=self.run_id)]}


@contextmanager
def bench_run(bench: str, tag: str, cores: dict[str, float]) -> Iterator[BenchRun]:
    """Root and cgroups checked (SystemExit naming ``bench`` without), a run tag ``tag`` +
    8 hex digits, the scene drawn, the groups ``cores`` created uncapped, everything started
    stopped and removed on exit, Ctrl-C, SIGTERM or an error (then its processes waited for up
    to 5 s). Start roscore with ``start_roscore(run.procs, run.tmp, 30.0)``."""
    import shutil

    from perfros_bag.rosrun.cgroups import CpuGroups, cgroup_version
    from perfros_bag.rosrun.processes import (
        Processes,
        leftover_processes,
        ros_env,
        sigterm_as_interrupt,
    )

    if os.geteuid() != 0 or cgroup_version() == "none":
        raise SystemExit(f"{bench}: needs root and a cgroup cpu controller (v1 or v2)")
    run_id = f"{tag}{uuid.uuid4().hex[:8]}"
    tmp = Path(tempfile.mkdtemp(prefix=f"bench-{tag}-"))
    sys.path.insert(0, str(ROOT / "pipelines"))
    from casestudy_real import draw_scene  # the case study's own 320x240 scene

    scene = tmp / "scene.png"
    draw_scene(scene)
    (tmp / "ros").mkdir()
    run = BenchRun(run_id, tmp, scene, Processes(run_id, ros_env(run_id, tmp / "ros")), CpuGroups(run_id, cores))
    try:
        with sigterm_as_interrupt():
            run.groups.create(capped=False)
            if not run.groups.capped:
                raise SystemExit(f"{bench}: no cgroups ({run.groups.reason})")
            yield run
    finally:
        run.procs.stop()
        run.procs.kill_leftovers()
        run.left_groups = run.groups.remove()
        shutil.rmtree(tmp, ignore_errors=True)
        deadline = time.monotonic() + 5
        while leftover_processes(run_id) and time.monotonic() < deadline:
            time.sleep(0.2)


def _cpu_s(pid: int) -> float:
    import psutil

    t = psutil.Process(pid).cpu_times()
    return float(t.user + t.system)


class _Counter:
    def __init__(self, popen: subprocess.Popen[bytes]) -> None:
        self.popen = popen
        line = popen.stdout.readline() if popen.stdout else b""
        if not line:
            raise RuntimeError("the rospy counter did not start")

    def mark(self) -> tuple[float, dict[str, int]]:
        assert self.popen.stdin is not None and self.popen.stdout is not None
        self.popen.stdin.write(b"\n")
        self.popen.stdin.flush()
        doc = json.loads(self.popen.stdout.readline())
        return float(doc["t"]), {k: int(v) for k, v in doc["counts"].items()}


def _window(counter: _Counter, pid: int, seconds: float, out_topic: str, groups: Any, comp: str) -> dict[str, Any]:
    """Count, CPU seconds and throttling of the node over one window."""
    thr0 = groups.throttled(comp)
    t0, c0 = counter.mark()
    cpu0 = _cpu_s(pid)
    time.sleep(seconds)
    t1, c1 = counter.mark()
    cpu1 = _cpu_s(pid)
    thr1 = groups.throttled(comp)
    span = t1 - t0
    n_in, n_out = c1[INPUT] - c0[INPUT], c1[out_topic] - c0[out_topic]
    return {"seconds": round(span, 3), "frames_in": n_in, "frames_out": n_out,
            "in_hz": round(n_in / span, 3), "out_hz": round(n_out / span, 3),
            "cpu_cores": round((cpu1 - cpu0) / span, 4),
            "nr_throttled": thr1.get("nr_throttled", 0.0) - thr0.get("nr_throttled", 0.0),
            "nr_periods": thr1.get("nr_periods", 0.0) - thr0.get("nr_periods", 0.0)}


def measure(nodes: list[str], factors: list[float], window: float = 8.0, settle: float = 2.0,
            scale0: float = 1.05, kernel: int = 15, log: Any = print, warmup: float = 5.0) -> dict[str, Any]:
    """Run the bench; the result document (see the module's docstring)."""
    from perfros_bag.cpu.speed import measure_speed
    from perfros_bag.rosrun.master import start_roscore

    results: dict[str, Any] = {}
    speed_before = measure_speed()
    started = time.monotonic()
    with bench_run("bench_cgroup_fairness", "fair", {n: 1.0 for n in nodes}) as run:
        procs, groups, tmp, scene, run_id = run.procs, run.groups, run.tmp, run.scene, run.run_id
        uri = start_roscore(procs, tmp, 30.0)
        log(f"roscore at {uri}; run tag {run_id}")
        cam_name, cam_exe, _a, _t = NODES["camera"]
        camera_args = [str(scene), f"_publish_rate:={RATE_HZ:g}", f"__name:={cam_name}"]
        for key in nodes:
            name, exe, extra, out_topic = NODES[key]
            opts = {"scale0": f"{scale0:g}", "kernel": str(kernel)}
            argv = [exe, *(a % opts for a in extra), f"__name:={name}"]
            if key == "camera":  # the camera itself is the node under test: started in the group
                node = procs.start(key, groups.wrap(key, [cam_exe, *camera_args]), tmp / f"{key}.log")
            else:
                procs.start(f"camera-{key}", [cam_exe, *camera_args], tmp / f"camera-{key}.log")
                node = procs.start(key, groups.wrap(key, argv), tmp / f"{key}.log")
            topics = [INPUT] if key == "camera" else [INPUT, out_topic]
            cpop = subprocess.Popen([ROS_PY, "-c", COUNTER, *topics], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=open(tmp / f"counter-{key}.log", "wb"),
                                    env=procs.env, start_new_session=True)
            procs.started.append(type(node)(f"counter-{key}", cpop, open(os.devnull, "wb")))
            counter = _Counter(cpop)
            pid = node.popen.pid  # the wrapper execs the node: same pid
            time.sleep(warmup)  # connections made, the node's first frames done
            base = _window(counter, pid, window, out_topic, groups, key)
            need = base["cpu_cores"]
            base_kept = base["frames_out"] / base["frames_in"] if key != "camera" else 1.0
            row: dict[str, Any] = {"node": key, "executable": Path(exe).name, "need_cores": need,
                                   "uncapped": {**base, "kept": round(base_kept, 4)}, "capped": []}
            log(f"{key}: need {100 * need:.1f} % of a core uncapped, kept {100 * base_kept:.1f} % "
                f"({base['frames_out']}/{base['frames_in']})")
            for f in factors:
                groups.cores[key] = max(need * f, 0.01)
                groups.apply()
                time.sleep(settle)
                w = _window(counter, pid, window, out_topic, groups, key)
                if key == "camera":
                    kept = w["out_hz"] / base["out_hz"] if base["out_hz"] else 0.0
                else:
                    kept = w["frames_out"] / w["frames_in"] if w["frames_in"] else 0.0
                row["capped"].append({"factor": f, "quota_cores": round(groups.cores[key], 4),
                                      "predicted_kept": round(min(1.0, f), 4), **w, "kept": round(kept, 4)})
                log(f"  x{f:g}: quota {100 * groups.cores[key]:.1f} %, used {100 * w['cpu_cores']:.1f} %, "
                    f"kept {100 * kept:.1f} % ({w['frames_out']}/{w['frames_in']}), "
                    f"throttled {w['nr_throttled']:.0f}/{w['nr_periods']:.0f} periods")
            groups.cores[key] = 64.0  # uncapped again: has the need moved meanwhile?
            groups.apply()
            time.sleep(settle)
            after = _window(counter, pid, window, out_topic, groups, key)
            row["need_after_cores"] = after["cpu_cores"]
            row["uncapped_after"] = after
            both = (need + after["cpu_cores"]) / 2  # the need as best known afterwards
            for c in row["capped"]:
                c["predicted_kept_mean_need"] = round(min(1.0, c["quota_cores"] / both), 4) if both else None
            log(f"  uncapped again: {100 * after['cpu_cores']:.1f} % of a core")
            results[key] = row
            procs.stop([key, f"camera-{key}", f"counter-{key}"])
    speed_after = measure_speed()
    kept1 = {k: next((c["kept"] for c in r["capped"] if c["factor"] == 1.0), None) for k, r in results.items()}
    return {"format": "perfros-bag/bench-cgroup-fairness@1", "run_id": run_id, "cgroups": groups.mode,
            "window_s": window, "factors": factors, "scale0": scale0, "kernel": kernel, "rate_hz": RATE_HZ,
            "wall_s": round(time.monotonic() - started, 1),
            "speed_factor": {"before": round(speed_before.factor, 3), "after": round(speed_after.factor, 3)},
            "load_average": os.getloadavg(), "nodes": results,
            "kept_at_1x": kept1,
            "kept_at_1x_min": min((v for v in kept1.values() if v is not None), default=None),
            **run.leftovers()}


def table(doc: dict[str, Any]) -> str:
    lines = ["| node | need (% core) | cap | quota (% core) | used (% core) | frames out/in | kept | predicted "
             "| throttled periods |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for key, r in doc["nodes"].items():
        u = r["uncapped"]
        lines.append(f"| {key} | {100 * r['need_cores']:.1f} | none | - | {100 * u['cpu_cores']:.1f} | "
                     f"{u['frames_out']}/{u['frames_in']} | {100 * u['kept']:.1f} % | - | - |")
        for c in r["capped"]:
            lines.append(f"| {key} | | {c['factor']:g}x | {100 * c['quota_cores']:.1f} | {100 * c['cpu_cores']:.1f} | "
                         f"{c['frames_out']}/{c['frames_in']} | {100 * c['kept']:.1f} % | "
                         f"{100 * c['predicted_kept']:.0f} % | {c['nr_throttled']:.0f}/{c['nr_periods']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the JSON here")
    ap.add_argument("--window", type=float, default=8.0, help="seconds per measurement point")
    ap.add_argument("--settle", type=float, default=2.0, help="seconds after each change, before counting")
    ap.add_argument("--factors", default="1.0,1.1,1.25", help="caps, as multiples of the node's need")
    ap.add_argument("--nodes", default="people,smooth,camera")
    ap.add_argument("--scale0", type=float, default=1.05)
    ap.add_argument("--kernel", type=int, default=15)
    args, _unknown = ap.parse_known_args(argv)  # tests/bench/run.py passes its own arguments to all
    nodes = [n.strip() for n in args.nodes.split(",") if n.strip()]
    bad = [n for n in nodes if n not in NODES]
    if bad:
        ap.error(f"unknown node(s) {', '.join(bad)}; known: {', '.join(NODES)}")
    factors = [float(f) for f in args.factors.split(",")]
    try:
        doc = measure(nodes, factors, args.window, args.settle, args.scale0, args.kernel,
                      log=lambda s: print(s, flush=True))
    except KeyboardInterrupt:
        print("interrupted: everything the bench started is stopped", file=sys.stderr)
        return 130
    return finish(doc, table(doc),
                  "kept share at 1.0x of need: "
                  f"{', '.join(f'{k} {100 * v:.1f} %' for k, v in doc['kept_at_1x'].items() if v is not None)}"
                  f"; smallest {100 * (doc['kept_at_1x_min'] or 0):.1f} %; wall {doc['wall_s']} s; "
                  f"speed factor {doc['speed_factor']['before']} -> {doc['speed_factor']['after']}", args.out)


def finish(doc: dict[str, Any], table_text: str, summary: str, out: Path | None) -> int:
    """Print a bench's table and summary with what it left, write its JSON to ``out``; the
    exit code: 1 when a process or cgroup was left."""
    print(table_text)
    print(f"{summary}; left: {len(doc['leftover_processes'])} processes, {len(doc['leftover_cgroups'])} cgroups")
    if out:
        from perfros_bag.fileio import atomic_write_json

        atomic_write_json(out, doc)
    return 0 if not doc["leftover_processes"] and not doc["leftover_cgroups"] else 1


if __name__ == "__main__":
    sys.exit(main())
