"""Does normalising a node's CPU by the machine's speed factor make it steadier?

perfros_bag/cpu/speed.py measures ``speed_factor = REFERENCE_S / (best CPU seconds of a fixed
workload)``. If the machine's speed drifts (background load on a shared host, a neighbour on
the same physical core, frequency), a node doing fixed work would use more CPU when the
factor is low, and ``cpu x factor`` would be steadier than ``cpu``. This bench checks that on
a real node: the case study's people_detect (scale0 1.05) on the camera's 320x240 images at
10 Hz, uncapped; for each background load (0, 1, 2 busy-looping Python processes, in turn,
``--rounds`` times), the factor is measured as ``record-cpu`` measures it (at the start of the
window) and the node's CPU over ``--window`` seconds (psutil). Printed: each window, then the
coefficient of variation (sd / mean) of ``cpu`` and of ``cpu x factor`` over all windows.

    .venv/bin/python tests/bench/bench_speed_reference.py [--out FILE.json] [--window 6] [--rounds 2]

Everything it starts carries a run tag and is stopped on exit, Ctrl-C or an error (~1 min).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench_cgroup_fairness import COUNTER, INPUT, NODES, RATE_HZ, ROOT, ROS_PY, _Counter, _cpu_s

sys.path.insert(0, str(ROOT))


def _spin(stop: Any) -> None:
    import signal

    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):  # not the parent's cleanup handlers
        signal.signal(sig, signal.SIG_DFL)
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x = (x * 31 + 7) & 0xFFFF


def _cv(values: list[float]) -> float:
    return statistics.pstdev(values) / statistics.mean(values) if values and statistics.mean(values) else 0.0


def measure(window: float, rounds: int, loads: list[int], log: Any = print) -> dict[str, Any]:
    from perfros_bag.cpu.speed import REFERENCE_S, measure_speed
    from perfros_bag.rosrun.master import start_roscore
    from perfros_bag.rosrun.processes import (
        Processes,
        leftover_processes,
        ros_env,
        sigterm_as_interrupt,
    )

    run_id = f"speed{uuid.uuid4().hex[:8]}"
    tmp = Path(tempfile.mkdtemp(prefix="bench-speed-"))
    sys.path.insert(0, str(ROOT / "pipelines"))
    from casestudy_real import draw_scene

    draw_scene(tmp / "scene.png")
    (tmp / "ros").mkdir()
    procs = Processes(run_id, ros_env(run_id, tmp / "ros"))
    windows: list[dict[str, Any]] = []
    spinners: list[multiprocessing.Process] = []
    stop = multiprocessing.Event()
    try:
        with sigterm_as_interrupt():
            start_roscore(procs, tmp, 30.0)
            _n, cam, _a, _t = NODES["camera"]
            procs.start("camera", [cam, str(tmp / "scene.png"), f"_publish_rate:={RATE_HZ:g}", "__name:=camera"],
                        tmp / "camera.log")
            _n, exe, extra, out_topic = NODES["people"]
            node = procs.start("people", [exe, *(a % {"scale0": "1.05", "kernel": "15"} for a in extra),
                                          "__name:=people"], tmp / "people.log")
            cpop = subprocess.Popen([ROS_PY, "-c", COUNTER, INPUT, out_topic], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=procs.env,
                                    start_new_session=True)
            procs.started.append(type(node)("counter", cpop, open(os.devnull, "wb")))
            counter = _Counter(cpop)
            time.sleep(5.0)
            for rnd in range(rounds):
                for load in loads:
                    while len(spinners) < load:
                        p = multiprocessing.Process(target=_spin, args=(stop,), daemon=True)
                        p.start()
                        spinners.append(p)
                    while len(spinners) > load:
                        p = spinners.pop()
                        p.terminate()
                        p.join()
                    time.sleep(1.0)
                    sp = measure_speed()
                    t0, c0 = counter.mark()
                    cpu0 = _cpu_s(node.popen.pid)
                    time.sleep(window)
                    t1, c1 = counter.mark()
                    cpu1 = _cpu_s(node.popen.pid)
                    sp_end = measure_speed()
                    frames = c1[out_topic] - c0[out_topic]
                    cores = (cpu1 - cpu0) / (t1 - t0)
                    w = {"round": rnd + 1, "background_spinners": load, "speed_factor": round(sp.factor, 4),
                         "speed_factor_end": round(sp_end.factor, 4), "cpu_cores": round(cores, 4),
                         "frames_out": frames, "frames_in": c1[INPUT] - c0[INPUT],
                         "cpu_s_per_frame": round((cpu1 - cpu0) / frames, 5) if frames else None,
                         "normalised_cores": round(cores * sp.factor, 4), "load_average_1m": os.getloadavg()[0]}
                    windows.append(w)
                    log(f"round {rnd + 1}, {load} spinner(s): factor {sp.factor:.3f} (end {sp_end.factor:.3f}), "
                        f"people {100 * cores:.1f} % of a core ({frames} frames), "
                        f"x factor {100 * cores * sp.factor:.1f} %")
    finally:
        stop.set()
        for p in spinners:
            p.terminate()
            p.join()
        procs.stop()
        procs.kill_leftovers()
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    per_frame = [w["cpu_s_per_frame"] for w in windows if w["cpu_s_per_frame"]]
    per_frame_norm = [w["cpu_s_per_frame"] * w["speed_factor"] for w in windows if w["cpu_s_per_frame"]]
    factors = [w["speed_factor"] for w in windows]
    return {"format": "perfros-bag/bench-speed-reference@1", "reference_s": REFERENCE_S, "window_s": window,
            "windows": windows,
            "cv_cpu": round(_cv([w["cpu_cores"] for w in windows]), 4),
            "cv_cpu_x_factor": round(_cv([w["normalised_cores"] for w in windows]), 4),
            # the factor as well as it is known: the mean of the window's start and end
            "cv_cpu_x_mean_factor": round(_cv([w["cpu_cores"] * (w["speed_factor"] + w["speed_factor_end"]) / 2
                                               for w in windows]), 4),
            "cv_cpu_per_frame": round(_cv(per_frame), 4),
            "cv_cpu_per_frame_x_factor": round(_cv(per_frame_norm), 4),
            "cv_factor": round(_cv(factors), 4),
            "factor_range": [min(factors), max(factors)] if factors else None,
            "leftover_processes": leftover_processes(run_id)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--window", type=float, default=6.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--loads", default="0,1,2", help="background busy-loop processes per step")
    args, _unknown = ap.parse_known_args(argv)
    try:
        doc = measure(args.window, args.rounds, [int(x) for x in args.loads.split(",")],
                      log=lambda s: print(s, flush=True))
    except KeyboardInterrupt:
        print("interrupted: everything the bench started is stopped", file=sys.stderr)
        return 130
    print(f"coefficient of variation over {len(doc['windows'])} windows: CPU {100 * doc['cv_cpu']:.1f} %, "
          f"CPU x factor {100 * doc['cv_cpu_x_factor']:.1f} % (x the mean of the start and end factors "
          f"{100 * doc['cv_cpu_x_mean_factor']:.1f} %); CPU per frame {100 * doc['cv_cpu_per_frame']:.1f} %, "
          f"x factor {100 * doc['cv_cpu_per_frame_x_factor']:.1f} %; factor {doc['factor_range']}")
    if args.out:
        from perfros_bag.fileio import atomic_write_json

        atomic_write_json(args.out, doc)
    print(json.dumps({k: v for k, v in doc.items() if k != "windows"}))
    return 0 if not doc["leftover_processes"] else 1


if __name__ == "__main__":
    sys.exit(main())
