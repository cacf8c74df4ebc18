"""Nodelets (issue 34): the README's steps on fixtures/nodelet, deployed, and a plan that
splits the manager across two computers, deployed.

One sweep of fixtures/nodelet (``nodelet.launch``, its space.yaml, ``--duration`` s a run),
``init``, then two systems of two emulated computers (``robot`` holding the camera, a
``server``, one link), each through ``characterise``, ``fit``, ``solve --measured-only`` (the
README's steps, at values the sweep ran), ``deploy`` (``--deploy-s`` s, ``--deploys`` times) and its validation:

* ``kept``: ``membership: keep``, room for the manager and both nodelets at their best on
  either computer (the README's steps as they stand);
* ``split``: ``membership: choose``, the computers sized from the fitted model so that no
  computer holds the manager with both nodelets at their best, and the robot holds the camera
  with the manager and the smoother, the server the detector with its copy: the plan runs
  one nodelet standalone (``nodelet standalone``) on the other computer.

Performance is stated as a user would (init drafts it from the output rate, which these
settings do not move): people_detect 100 / 80 / 50 at scale0 1.1 / 1.2 / 1.4, smoothing
100 / 70 at kernel 13 / 7. Printed: per deployment the plan's Σ w·P, the measured, the
deviation (eq 10; goal: within 2.5 %) and which nodes ran standalone.

    .venv/bin/python tests/bench/bench_nodelet_deploy.py [--duration 20] [--deploy-s 30] [--deploys 2] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
FIX = ROOT / "fixtures" / "nodelet"
BIN = Path(sys.executable).with_name("perfros-bag")
PERFORMANCE = {"people": {1.1: 100.0, 1.2: 80.0, 1.4: 50.0}, "smooth": {13: 100.0, 7: 70.0}}


def cli(*args: str) -> None:
    done = subprocess.run([str(BIN), *args], capture_output=True, text=True)
    if done.returncode not in (0, 1):  # validate/deploy: 1 = above tolerance, still a result
        raise SystemExit(f"{args[0]} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")


def system_doc(drafted: dict[str, Any], robot: float, server: float, membership: str) -> dict[str, Any]:
    import copy

    doc = copy.deepcopy(drafted)
    doc["computers"] = [{"name": "robot", "kind": "robot", "capacity": round(robot, 2)},
                        {"name": "server", "kind": "server", "capacity": round(server, 2)}]
    doc["links"] = [{"between": ["robot", "server"], "bandwidth_kBps": 20000}]
    doc["membership"] = membership
    for n in doc["nodes"]:
        if n["name"] == "camera":
            n["residence"] = ["robot"]
        for s in n.get("settings", []):
            if n["name"] in PERFORMANCE and s.get("value") is not None:
                s["performance"] = PERFORMANCE[n["name"]][s["value"]]
    return doc


def most(model: dict[str, Any], name: str) -> float:
    node = next(n for n in model["system"]["nodes"] if n["name"] == name)
    return max(float(s["cpu"]) for s in node["settings"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=20.0, help="seconds recorded per sweep run")
    ap.add_argument("--deploy-s", type=float, default=30.0, help="seconds each deploy records")
    ap.add_argument("--deploys", type=int, default=2, help="deployments of each plan")
    ap.add_argument("--keep", type=Path, default=None, help="work folder (its sweep reused when there)")
    a = ap.parse_args()
    import yaml

    load0, t0 = os.getloadavg(), time.monotonic()
    work = a.keep or Path(tempfile.mkdtemp(prefix="bench-nodelet-deploy-"))
    work.mkdir(parents=True, exist_ok=True)
    space = yaml.safe_load((FIX / "space.yaml").read_text())
    space["duration_s"] = a.duration
    space["vary"][1]["values"] = [7, 13]
    (work / "space.yaml").write_text(yaml.safe_dump(space, sort_keys=False))
    runs = work / "runs"
    if not (runs / "manifest.yaml").exists():
        cli("sweep", str(FIX / "nodelet.launch"), "--space", str(work / "space.yaml"), "--out", str(runs))
    cli("init", str(runs), "--out", str(work / "drafted.yaml"))
    drafted = yaml.safe_load((work / "drafted.yaml").read_text())
    # the fitted CPU of each node at its most, on a roomy system, sizes the split's computers
    roomy = system_doc(drafted, 400, 400, "keep")
    (work / "roomy.yaml").write_text(yaml.safe_dump(roomy, sort_keys=False))
    cli("characterise", str(runs), "--system", str(work / "roomy.yaml"), "--out", str(work / "roomy.csv"))
    cli("fit", str(work / "roomy.yaml"), str(work / "roomy.csv"), "--out", str(work / "roomy.json"))
    model = json.loads((work / "roomy.json").read_text())
    cam, mgr, people, smooth = (most(model, n) for n in ("camera", "vision_manager", "people", "smooth"))
    frames = next(float(s["bandwidth_kBps"]) for n in model["system"]["nodes"] if n["name"] == "camera"
                  for s in n["settings"])
    price = next(float(n.get("copy_cpu_per_MBps") or 0.0) for n in model["system"]["nodes"]
                 if n["name"] == "vision_manager")
    copy_cpu = price * frames / 1000
    print(f"fitted CPU at most: camera {cam:.2f}, manager {mgr:.2f}, people {people:.2f}, smooth {smooth:.2f}; "
          f"copy price {price:.3f} units per MB/s x {frames / 1000:.2f} MB/s = {copy_cpu:.2f}")
    both = mgr + people + smooth
    sizes = {"kept": (2.0 * (cam + both), 2.0 * both, "keep"),
             "split": (1.3 * (cam + mgr + smooth), 1.15 * (people + copy_cpu), "choose")}
    robot, server, _ = sizes["split"]
    if robot >= cam + both or server >= both:
        print(f"warning: the split's computers (robot {robot:.1f}, server {server:.1f}) could hold the manager with "
              f"both nodelets at their best ({cam + both:.1f} / {both:.1f}): the plan may keep them together")
    print("\n| scenario | robot / server capacity | deploy | standalone | planned Σ w·P | measured | deviation |")
    print("|---|---|---|---|---:|---:|---:|")
    for name, (robot, server, membership) in sizes.items():
        sys_path = work / f"{name}.yaml"
        sys_path.write_text(yaml.safe_dump(system_doc(drafted, robot, server, membership), sort_keys=False))
        cli("characterise", str(runs), "--system", str(sys_path), "--out", str(work / f"{name}.csv"))
        cli("fit", str(sys_path), str(work / f"{name}.csv"), "--out", str(work / f"{name}.json"))
        plan = work / f"{name}-plan.json"
        cli("solve", str(work / f"{name}.json"), "--problem", "1", "--method", "exact", "--measured-only",
            "--out", str(plan))
        planned = json.loads(plan.read_text())
        alone = sorted(n for n, pn in planned["nodes"].items() if pn.get("standalone"))
        where = ", ".join(f"{n}@{pn['computer']}" for n, pn in planned["nodes"].items())
        print(f"<!-- {name}: {where} -->")
        for k in range(a.deploys):
            dep = work / f"{name}-dep{k + 1}"
            cli("deploy", str(plan), str(FIX / "nodelet.launch"), "--space", str(work / "space.yaml"), "--out",
                str(dep), "--duration", f"{a.deploy_s:g}", "--system", str(sys_path))
            overall = json.loads((dep / "validation.json").read_text())["overall"]
            print(f"| {name} | {robot:.1f} / {server:.1f} | {k + 1} | {', '.join(alone) or '-'} | "
                  f"{overall['expected']:.2f} | {overall['measured']:.2f} | {overall['deviation_pct']:.2f} % |")
    print(f"\n(work folder {work}; {time.monotonic() - t0:.0f} s; load average before {load0[0]:.2f}, "
          f"after {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
