"""The case study on Debian's real, unmodified C++ nodes: RQ2 and RQ3 with CPU and links emulated.

    .venv/bin/python pipelines/casestudy_real.py [--out out/casestudy-real] [--duration 15]
        [--sweep-duration 12] [--instances 1,2,3,4,5,6] [--docs docs/casestudy-real.md]

The application (fixtures/casestudy_real): per robot a camera (image_publisher, a 320x240
RGB image the pipeline draws, at 5, 7.5 or 10 Hz: a knob the solver chooses), a HOG people
detector (opencv_apps people_detect, parameter scale0) and a bilateral smoother (opencv_apps
smoothing, parameter kernel_size), both driven by the camera's images (system.yaml
``input:``: their CPU follows its rate). Everything runs through the tool's own verbs:

1. ``sweep`` robot 1's application over the three parameters (one at a time), ``init``
   drafts the system from it (the detectors as driven nodes), ``characterise`` measures
   every setting;
2. per instance (robots, capacities, links below): the instance's system.yaml (the drafted
   nodes, once per robot, with the stated performance levels, residence, coresidence and
   weights), robot 1's measurements copied to every robot, ``fit``, ``solve`` Problem 1
   (greedy, greedy+, exact) and Problem 2 (greedy, exact);
3. ``deploy`` every distinct plan (computers as CPU-capped cgroups, each computer a network
   namespace, links shaped with tc), which records and validates it (eq 10);
4. ``tune`` each instance: Problem 1 with the model's measured headroom, deployed, refitted
   on its recording, up to 3 rounds;
5. RQ3: instance 2's plan with parameters and nodes forced above it on the robot, and
   instance 4's plan with robot 2's detector forced across a link too small for its images,
   with the rates each node keeps predicted and measured.

Results: OUT/results.json, OUT/rq2.png, OUT/rq3.png and the results section of
docs/casestudy-real.md with the commands. A step whose output exists is reused (a run
whose deploy.json exists is not run again, tune resumes its rounds): delete OUT, or one
run's folder, to measure again.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml
from _common import interrupt_on_sigterm, read_rows, run_shown, write_rows, write_section
from rich.console import Console

from perfros_bag.cpu.speed import SPEED_SHARE as SAME_SPEED_SHARE
from perfros_bag.cpu.speed import same_speed, speed_distance

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).with_name("perfros-bag")
FIXTURES = ROOT / "fixtures" / "casestudy_real"
err = Console(stderr=True)
COMMANDS: list[str] = []
FAILED: list[dict[str, Any]] = []  # solves that found no plan
DEPLOYS = {"ran": 0, "reused": 0}
EXCLUDE = "/robot[0-9]+/people/image"  # the detector's debug image: never needed, never recorded
SCALE0 = [1.05, 1.1, 1.2, 1.4]
KERNEL = [3, 7, 11, 15]
# The stated performance levels (the paper's experts did the same in Table I): a finer HOG
# pyramid finds more people; a wider bilateral filter removes more noise.
PERF_PEOPLE = {1.05: 100.0, 1.1: 85.0, 1.2: 60.0, 1.4: 30.0}
PERF_SMOOTH = {3: 25.0, 7: 55.0, 11: 80.0, 15: 100.0}
# The camera's frame rate is a knob the solver chooses (the data-flow contract: the detectors
# are driven by its images, so their CPU follows the rate it picks). Stated performance: a
# tracker downstream loses little at 7.5 Hz and much at 5 Hz.
CAMERA_RATES = [5.0, 7.5, 10.0]
PERF_CAMERA = {5.0: 60.0, 7.5: 85.0, 10.0: 100.0}
WEIGHTS = {"camera": 0.5, "people": 2.0, "smooth": 1.0}
UNITS_PER_CORE = 100.0  # CPU units of one core of this machine (what init drafts)


@dataclass(frozen=True)
class Instance:
    number: int
    robot_capacity: tuple[float, ...]  # per robot, CPU units (100 = one core here)
    server_capacity: float
    link_kBps: tuple[float, ...]  # per robot, its link to the server
    wifi_kBps: float | None = None  # every link on one shared medium of this bandwidth


INSTANCES = {
    1: Instance(1, (25,), 40, (3000,)),
    2: Instance(2, (15,), 15, (3000,)),
    3: Instance(3, (20, 20), 30, (3000, 3000)),
    4: Instance(4, (20, 20), 25, (3000, 2000)),  # robot 2's images cannot cross its link
    5: Instance(5, (15, 15, 15), 45, (3000, 3000, 3000), wifi_kBps=5000),  # two robots' images at most
    6: Instance(6, (25, 25, 25), 20, (2000, 3000, 3000), wifi_kBps=6000),
}


def rel(p: Path | str) -> str:
    return str(p).replace(str(ROOT) + "/", "")


def sh(args: Sequence[object], *, ok: tuple[int, ...] = (0,)) -> subprocess.CompletedProcess[str]:
    return run_shown(args, root=ROOT, program=BIN, commands=COMMANDS, console=err, ok=ok)


# ---------------------------------------------------------------- the application

def draw_scene(path: Path) -> None:
    """A 320x240 RGB test image: coloured discs and mild noise (fixed seed)."""
    import matplotlib.image as mpimg
    import numpy as np

    rng = np.random.default_rng(7)
    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w]
    img = np.full((h, w, 3), 0.5)
    for _ in range(12):
        cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(8, 40)
        img[(x - cx) ** 2 + (y - cy) ** 2 < r * r] = rng.uniform(0, 1, 3)
    img = (img + rng.normal(0, 0.05, img.shape)).clip(0, 1)
    mpimg.imsave(path, img)


def space(robots: int, duration: float) -> dict[str, Any]:
    vary = []
    for k in range(1, robots + 1):
        vary.append({"node": f"/robot{k}/camera", "parameter": {"name": "publish_rate", "unit": "Hz"},
                     "arg": f"robot{k}_rate", "values": CAMERA_RATES, "default": 10.0})
        vary.append({"node": f"/robot{k}/people", "parameter": {"name": "scale0", "unit": ""},
                     "arg": f"robot{k}_scale0", "values": SCALE0, "default": 1.1})
        vary.append({"node": f"/robot{k}/smooth", "parameter": {"name": "kernel_size", "unit": "px"},
                     "arg": f"robot{k}_kernel", "values": KERNEL, "default": 7})
    return {"duration_s": duration, "settle_s": 3, "repeats": 1, "design": "one-at-a-time",
            "startup_timeout_s": 60, "exclude": EXCLUDE, "vary": vary}


def application(out: Path, args: argparse.Namespace) -> Path:
    app = out / "app"
    app.mkdir(parents=True, exist_ok=True)
    for f in FIXTURES.glob("*.launch"):
        shutil.copyfile(f, app / f.name)
    if not (app / "scene.png").exists():
        draw_scene(app / "scene.png")
    for n in (1, 2, 3):
        (app / f"space{n}.yaml").write_text(yaml.safe_dump(space(n, args.duration), sort_keys=False))
    (app / "space-sweep.yaml").write_text(yaml.safe_dump(space(1, args.sweep_duration), sort_keys=False))
    return app


# ---------------------------------------------------------------- 1. sweep, init, characterise

def characterise(out: Path, app: Path) -> tuple[Path, dict[str, Any]]:
    rec = out / "sweep"
    # runs made while the host ran at another speed than the rest are recorded again (up to twice)
    sh([BIN, "sweep", app / "app1.launch", "--space", app / "space-sweep.yaml", "--out", rec,
        "--repeat-off-speed", "2"])
    draft = out / "draft.yaml"
    sh([BIN, "init", rec, "--out", draft])
    csv_path = out / "characterisation.csv"
    sh([BIN, "characterise", rec, "--system", draft, "--out", csv_path])
    return csv_path, yaml.safe_load(draft.read_text())


def cpu_against_rate(char_csv: Path, draft: dict[str, Any]) -> list[dict[str, Any]]:
    """How the detectors' CPU follows the camera's rate, from the sweep: the runs with people
    and smooth at their defaults (scale0 1.1, kernel 7), per camera rate each node's CPU."""
    _fields, rows = read_rows(char_csv)
    values: dict[str, dict[str, float]] = {}
    for r in rows:
        if r["node"].startswith("robot1_") and r["value"]:
            values.setdefault(r["recording"], {})[kind(r["node"])] = float(r["value"])
    rate_of = {rec: v["camera"] for rec, v in values.items()
               if "camera" in v and v.get("people") == 1.1 and v.get("smooth") == 7}
    cpu: dict[float, dict[str, float]] = {}
    out_hz: dict[float, float] = {}
    for r in rows:
        if r["recording"] not in rate_of:
            continue
        if r["node"].startswith("robot1_") and r["cpu_units_mean"]:
            cpu.setdefault(rate_of[r["recording"]], {})[kind(r["node"])] = float(r["cpu_units_mean"])
        if r["topic"] == "/robot1/people/found" and r["frequency_hz"]:
            out_hz[rate_of[r["recording"]]] = float(r["frequency_hz"])
    line: dict[str, tuple[float, float]] = {}  # init's drafted line CPU = cpu + cpu_per_hz x rate
    for n in draft["nodes"]:
        want = {"robot1_people": 1.1, "robot1_smooth": 7}.get(n["name"])
        s = next((s for s in n["settings"] if want is not None and s.get("value") == want and "cpu_per_hz" in s), None)
        if s is not None:
            line[kind(n["name"])] = (float(s["cpu"]), float(s["cpu_per_hz"]))
    return [{"rate_hz": rate, **cpu[rate], "people_hz": out_hz.get(rate),
             **{f"{k}_line": a + b * rate for k, (a, b) in line.items()}} for rate in sorted(cpu)]


def kind(node: str) -> str:
    return node.split("_", 1)[1]


#: Latency budgets (system.yaml chains' ``budget_ms``), per chain kind, on the instances listed:
#: camera -> people within a p95 that the unbudgeted plans' detectors miss. Solved (exact,
#: headroom auto) on the quiet-machine sweep's CPU lines with the latency model's default
#: parameters and a 10 ms CFS period, the unbudgeted plans predict 211 ms p95 (instance 1,
#: scale0 1.05 offloaded), 254-338 ms (3) and 323 ms (6); with 200 ms each plan changes
#: (1: scale0 1.2 on the server, 162 ms; 3: both detectors at 1.4, 140-147 ms; 6: 1.4 on the
#: robots, 112 ms) and a budget of 150 ms was still feasible on all three. camera -> smooth is
#: measured and predicted, unbudgeted.
PEOPLE_BUDGET_MS = {"p95": 200.0}
BUDGET_INSTANCES = (1, 3, 6)


def instance_chains(robots: int, draft: dict[str, Any], budgeted: bool,
                    budget: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """Per robot the chains camera -> people and camera -> smooth (the drafted nodes' input
    topic, then their first output topic), camera -> people with ``budget`` (default
    :data:`PEOPLE_BUDGET_MS`) when ``budgeted``."""
    base = {kind(n["name"]): n for n in draft["nodes"] if n["name"].startswith("robot1_")}
    chains = []
    for k in range(1, robots + 1):
        for what in ("people", "smooth"):
            node = base.get(what)
            if node is None or not node.get("input") or not node.get("topics"):
                if k == 1:  # said once: a node init did not draft as driven has no stamp to follow
                    err.print(f"[yellow]warning[/]: no chain camera -> {what}: the draft's robot1_{what} is not "
                              "driven by the camera (init did not see its rate follow the camera's)")
                continue
            topics = [str(t).replace("/robot1/", f"/robot{k}/") for t in (node["input"], node["topics"][0])]
            chain: dict[str, Any] = {"name": f"robot{k}_{what}", "topics": topics}
            if what == "people" and budgeted:
                chain["budget_ms"] = dict(budget if budget is not None else PEOPLE_BUDGET_MS)
            chains.append(chain)
    return chains


def instance_system(inst: Instance, draft: dict[str, Any], budget: dict[str, float] | None = None,
                    budgeted: tuple[int, ...] = BUDGET_INSTANCES) -> dict[str, Any]:
    """The drafted robot-1 nodes once per robot, with the instance's computers, links and
    chains (:func:`instance_chains`; budgeted on the instances ``budgeted``)."""
    robots = len(inst.robot_capacity)
    base = {kind(n["name"]): n for n in draft["nodes"] if n["name"].startswith("robot1_")}
    nodes, edges = [], []
    for k in range(1, robots + 1):
        for what, src in base.items():
            node = json.loads(json.dumps(src).replace("/robot1/", f"/robot{k}/").replace("robot1_", f"robot{k}_"))
            node["weight"] = round(WEIGHTS[what] / (robots * sum(WEIGHTS.values())), 6)
            levels: dict[str, dict[Any, float]] = {"camera": PERF_CAMERA, "people": PERF_PEOPLE,
                                                   "smooth": PERF_SMOOTH}
            perf = levels.get(what)
            for s in node["settings"]:
                s["performance"] = 100.0 if perf is None else perf[s["value"]]
            node["residence"] = {"camera": [f"robot{k}"], "people": [f"robot{k}", "server"],
                                 "smooth": [f"robot{k}", "server"]}[what]
            if what == "smooth":
                node["coresidence"] = [f"robot{k}_camera"]
            nodes.append(node)
        for e in draft.get("edges", []):
            edges.append({key: str(v).replace("/robot1/", f"/robot{k}/").replace("robot1_", f"robot{k}_")
                          for key, v in e.items()})
    return {"cpu_unit": f"100 = one core of this machine ({UNITS_PER_CORE:g} units per core)",
            "computers": [{"name": f"robot{k}", "kind": "robot", "capacity": c}
                          for k, c in enumerate(inst.robot_capacity, 1)]
            + [{"name": "server", "kind": "server", "capacity": inst.server_capacity,
                "max_capacity": 150}],
            "links": [{"between": [f"robot{k}", "server"], "bandwidth_kBps": b,
                       **({"medium": "wifi"} if inst.wifi_kBps else {})}
                      for k, b in enumerate(inst.link_kBps, 1)],
            **({"media": [{"name": "wifi", "bandwidth_kBps": inst.wifi_kBps}]} if inst.wifi_kBps else {}),
            "nodes": nodes, "edges": edges,
            "chains": instance_chains(robots, draft, inst.number in budgeted, budget),
            # deploy's computers are CFS-capped cgroups of this period: the latency model's
            # head start of a node that finds its cgroup idle (docs/solvers.md, "Latency");
            # its links are tc tbf shapers whose bucket lets a message's first part at once
            "latency": {"cfs_period_ms": cfs_period_ms(),
                        "link_burst_ms": link_burst_ms([*inst.link_kBps, *filter(None, [inst.wifi_kBps])])}}


def cfs_period_ms() -> float:
    """The CFS bandwidth period deploy's cgroups use here (PERFROS_CFS_PERIOD_US or 10 ms), in ms."""
    from perfros_bag.rosrun.cgroups import default_period_us

    return default_period_us() / 1000.0


def link_burst_ms(bandwidths_kBps: list[float]) -> float:
    """What deploy's ``tbf`` bucket lets through at once, in ms at the link's rate
    (rosrun/network.py: 10 ms at the rate, at least four full frames), the least over the
    instance's links and medium (one figure for the model)."""
    from perfros_bag.rosrun.network import tbf_burst_bytes, tbf_rate_bit

    return min(1000.0 * tbf_burst_bytes(tbf_rate_bit(bw)) * 8 / tbf_rate_bit(bw) for bw in bandwidths_kBps)


def instance_csv(rows: list[dict[str, str]], robots: int) -> list[dict[str, str]]:
    """Robot 1's measured rows copied to every robot (the robots run the same nodes)."""
    out = []
    for row in rows:
        if not row["node"].startswith("robot1_"):
            continue
        for k in range(1, robots + 1):
            new = dict(row)
            new["node"] = row["node"].replace("robot1_", f"robot{k}_", 1)
            new["topic"] = row["topic"].replace("/robot1/", f"/robot{k}/", 1)
            out.append(new)
    return out


# ---------------------------------------------------------------- 2. fit + solve

METHODS = (("p1-greedy", 1, "greedy"), ("p1-greedy+", 1, "greedy+"), ("p1-exact", 1, "exact"),
           ("p2-greedy", 2, "greedy"), ("p2-exact", 2, "exact"), ("p1-exact-nomargin", 1, "exact"))
# Every plan keeps the model's measured headroom (`solve --headroom auto`, docs/solvers.md)
# except *-nomargin: the paper's model as fitted, solved to the computers' full capacity,
# deployed on instances 2, 4 and 6 to show what the headroom buys (stated apart, not an RQ2
# plan of the tool).
# Problem 2: the smallest server for the settings of Problem 1's exact plan. tune's first
# round solves what p1-exact solves, so the two share one deployment.
NO_MARGIN = "-nomargin"
NO_MARGIN_INSTANCES = (2, 4, 6)  # one robot; a link too small; the shared wifi (time: each is one more deployment)


#: the budget each budgeted instance was given (:func:`binding_budget`; None: none could bind)
BUDGETS: dict[int, dict[str, float] | None] = {}
#: a budget is tried at these fractions of the unbudgeted plan's predicted p95 (the first
#: feasible one is kept): below 1 it must change the plan; the floor a fixed budget such as
#: ``--people-budget-p95`` may also give is tried first
BUDGET_FRACTIONS = (0.8, 0.9, 0.97)


def write_system(path: Path, number: int, system: dict[str, Any]) -> None:
    path.write_text(f"# instance {number} of the real-node case study, written by pipelines/casestudy_real.py\n"
                    + yaml.safe_dump(system, sort_keys=False))


def with_budget(model: Path, dest: Path, budget: dict[str, float] | None) -> None:
    """``model`` (a fitted model.json) written to ``dest`` with every camera -> people chain
    carrying ``budget`` (none: no budget). A budget changes no fit (the latency fit reads the
    chains only to warn about unmeasured hops), so the instance is fitted once and each budget
    is written into the fitted model's system instead of fitting again."""
    from perfros_bag.fileio import atomic_write_json

    doc = json.loads(model.read_text())
    for chain in (doc.get("system") or {}).get("chains") or []:
        if str(chain.get("name", "")).endswith("_people"):
            if budget:
                chain["budget_ms"] = dict(budget)
            else:
                chain.pop("budget_ms", None)
    atomic_write_json(dest, doc)


def binding_budget(d: Path, inst: Instance, model: Path, given: dict[str, float] | None) -> dict[str, float] | None:
    """A camera -> people p95 budget that binds on this instance's fitted ``model`` (fitted
    without a budget) and that a plan can keep: the unbudgeted exact plan (``--headroom
    auto``) predicts p95 ``U`` for its slowest people chain; ``given`` (when below ``U``) is
    tried, then each of :data:`BUDGET_FRACTIONS` x ``U``; the first that exact can keep is the
    instance's budget. A budget fixed before the sweep cannot do this: the sweep's own latency
    sets the scale. Each try is the same fitted model with the budget written in (:func:`with_budget`)."""
    work = d / "budget-search"
    work.mkdir(parents=True, exist_ok=True)
    plan = work / "plan.json"

    def solve_with(budget: dict[str, float] | None) -> dict[str, Any] | None:
        tried = work / ("model.json" if budget is None else f"model-p95-{budget['p95']:g}.json")
        with_budget(model, tried, budget)
        plan.unlink(missing_ok=True)
        done = sh([BIN, "solve", tried, "--problem", "1", "--method", "exact", "--headroom", "auto",
                   "--out", plan], ok=(0, 2))
        return json.loads(plan.read_text()) if done.returncode == 0 else None

    free = solve_with(None)
    if free is None:
        return given
    p95s = [c["predicted_ms"]["p95"] for c in free.get("chains", [])
            if c["name"].endswith("_people") and (c.get("predicted_ms") or {}).get("p95") is not None]
    if not p95s:
        return given
    top = max(p95s)
    tries = ([given["p95"]] if given and given.get("p95") and given["p95"] < top else [])
    tries += [round(f * top, 1) for f in BUDGET_FRACTIONS]
    for b in tries:
        if solve_with({"p95": b}) is not None:
            err.print(f"instance {inst.number}: camera -> people budget p95 {b:g} ms (unbudgeted plan: {top:.1f} ms)")
            return {"p95": b}
    FAILED.append({"instance": inst.number, "plan": "budget",
                   "why": f"no p95 budget below the unbudgeted plan's {top:.1f} ms could be kept: left unbudgeted"})
    return None


def fit_and_solve(out: Path, char_csv: Path, draft: dict[str, Any], numbers: list[int],
                  budget: dict[str, float] | None = None,
                  budgeted: tuple[int, ...] = BUDGET_INSTANCES) -> dict[int, dict[str, Path]]:
    fields, rows = read_rows(char_csv)
    plans: dict[int, dict[str, Path]] = {}
    for i in numbers:
        inst = INSTANCES[i]
        d = out / f"instance{i}"
        d.mkdir(parents=True, exist_ok=True)
        sys_path = d / "system.yaml"
        inst_csv = d / "characterisation.csv"
        write_rows(inst_csv, fields, instance_csv(rows, len(inst.robot_capacity)))
        model = d / "model.json"
        # one fit per instance: a budget changes no fit, it is written into the fitted model
        write_system(sys_path, i, instance_system(inst, draft, None, ()))
        sh([BIN, "fit", sys_path, inst_csv, "--out", model] + (["--plots", d / "fit-plots"] if i == 1 else []))
        if i in budgeted:
            chosen = BUDGETS[i] = binding_budget(d, inst, model, budget)
            if chosen is not None:
                write_system(sys_path, i, instance_system(inst, draft, chosen, budgeted))
                with_budget(model, model, chosen)
                COMMANDS.append(f"# {rel(model)}: the budget p95 {chosen['p95']:g} ms written into its chains "
                                f"(as {rel(sys_path)} states it)")
        plans[i] = {}
        for key, problem, method in METHODS:
            if key.endswith(NO_MARGIN) and i not in NO_MARGIN_INSTANCES:
                continue
            p = d / f"plan-{key}.json"
            # Problem 2: the smallest server for the settings of Problem 1's optimal plan
            if problem == 2 and "p1-exact" not in plans[i]:
                FAILED.append({"instance": i, "plan": key, "why": "no Problem 1 exact plan to take the settings from"})
                continue
            given = ["--settings", plans[i]["p1-exact"]] if problem == 2 else []
            p.unlink(missing_ok=True)
            headroom = [] if key.endswith(NO_MARGIN) else ["--headroom", "auto"]
            done = sh([BIN, "solve", model, "--problem", str(problem), "--method", method, *given, *headroom,
                       "--out", p], ok=(0, 2))
            if done.returncode == 0:
                plans[i][key] = p
            else:  # e.g. the paper's greedy stuck where exact finds a plan: said in the results
                FAILED.append({"instance": i, "plan": key, "why": rel(done.stderr.strip().splitlines()[-1])})
    return plans


# ---------------------------------------------------------------- 3. deploy + validate

def signature(plan: dict[str, Any]) -> str:
    """What a deployment runs: placement, values and capacities (plans equal in these run once)."""
    nodes = {n: (v["computer"], v.get("value") if not isinstance(v.get("value"), float) else float(f"{v['value']:.6g}"))
             for n, v in sorted(plan["nodes"].items())}
    caps = {c: round(v.get("capacity") or 0.0, 3) for c, v in sorted(plan["computers"].items())}
    return json.dumps([nodes, caps])


# ---------------------------------------------------------------- the host's speed, before each deployment

#: The host's speed moves under a run (docs/casestudy-real.md, the 01:32-04:45 runs): record-cpu's
#: speed reference (perfros_bag/cpu/speed.py) is bimodal here, ~0.75 or ~0.40-0.55, switching
#: within minutes, and a deployment run in the slow state needs 1.4-1.6x the CPU per message the
#: sweep measured, so every prediction made from the sweep (CPU, latency) is off by that much.
#: Before each deployment (and each instance's tune) the pipeline measures the speed and, while
#: it is not within SPEED_SHARE of the sweep's median (either way), waits (SPEED_STEP_S at a time) up to
#: SPEED_WAIT_S, and at most SPEED_BUDGET_S over the whole run; then it deploys whatever the
#: speed. Every wait is stated (results.json ``speed_gate``, results.md). Environment:
#: CASESTUDY_SPEED_WAIT_S (0: no waiting), CASESTUDY_SPEED_BUDGET_S.
SPEED_SHARE = SAME_SPEED_SHARE
SPEED_STEP_S = 5.0
#: Off by default since the two runs made with it (2026-11-28 06:19, 07:02) did not gain from
#: it (docs/casestudy-real.md): CASESTUDY_SPEED_WAIT_S=120 CASESTUDY_SPEED_REPEATS=2 turn it on.
SPEED_WAIT_S = float(os.environ.get("CASESTUDY_SPEED_WAIT_S", "0"))
SPEED_BUDGET_S = float(os.environ.get("CASESTUDY_SPEED_BUDGET_S", "900"))
SPEED_GATE: dict[str, Any] = {"reference": None, "waits": []}
#: ... and a deployment whose own speed reference (deploy.json, measured as its recording
#: began) is still off the sweep's is deployed again, up to SPEED_REPEATS times; the attempt
#: nearest the sweep's speed is kept as the run, the others stay beside it as
#: ``run-*.off-speed-K`` and every attempt's speed is stated (results.json ``redeployed``).
#: Environment: CASESTUDY_SPEED_REPEATS (0: never again). tune's own rounds are not repeated.
SPEED_REPEATS = int(os.environ.get("CASESTUDY_SPEED_REPEATS", "0"))
REDEPLOYS: list[dict[str, Any]] = []


def at_speed(speed: float | None, reference: float | None, share: float = SPEED_SHARE) -> bool:
    """``speed`` within ``share`` of ``reference`` either way (True without either: nothing to hold)."""
    if speed is None or reference is None or reference <= 0:
        return True
    return same_speed(speed, reference, share)


def run_speed(record: dict[str, Any], reference: float | None) -> float | None:
    """A deployment's speed as this pipeline judges it: of its two readings (deploy.json
    ``speed_factor`` as the recording began, ``speed_factor_end`` as it ended), the one
    farther from ``reference`` (the machine may slow down mid-run); either alone when the
    other is unknown."""
    got = [s for s in (record.get("speed_factor"), record.get("speed_factor_end"))
           if isinstance(s, int | float) and s > 0]
    if not got or reference is None or reference <= 0:
        return got[0] if got else None
    return max(got, key=lambda s: speed_distance(s, reference))


def nearest_speed(attempts: Sequence[tuple[float | None, Path]], reference: float | None) -> Path:
    """The attempt whose speed is nearest ``reference`` (by ratio); the last one when none
    can be compared."""
    known = [(speed_distance(s, reference), k) for k, (s, _) in enumerate(attempts)
             if s is not None and s > 0 and reference is not None and reference > 0]
    return attempts[min(known)[1]][1] if known else attempts[-1][1]


def sweep_speed(manifest: Path) -> float | None:
    """The median ``speed_factor`` of the sweep's runs (its manifest.yaml), None without one."""
    from perfros_bag.characterisation.manifest import load_manifest

    found = [e.speed_factor for e in load_manifest(manifest).recordings if e.speed_factor]
    return statistics.median(found) if found else None


def speed_gate(reference: float | None, measure: Any, sleep: Any, clock: Any, *, wait_s: float,
               budget_s: float, share: float = SPEED_SHARE, step_s: float = SPEED_STEP_S) -> dict[str, Any]:
    """Wait while the host's speed (``measure()``: a speed factor) is not within ``share`` of
    ``reference`` (below ``share`` x it, or above it / ``share``: the two states this host
    switches between are 1.6x apart, and a deployment faster than its sweep is mispredicted
    as much as a slower one), up to ``wait_s`` and ``budget_s``: {speed, waited_s, held}
    (``held``: the last speed is within; True without a reference, nothing to hold to)."""
    if reference is None or reference <= 0:
        return {"speed": None, "waited_s": 0.0, "held": True}

    def within(x: float) -> bool:
        return at_speed(x, reference, share)

    start = clock()
    speed = measure()
    limit = max(0.0, min(wait_s, budget_s))
    while not within(speed) and clock() - start + step_s <= limit:
        sleep(step_s)
        speed = measure()
    return {"speed": speed, "waited_s": clock() - start, "held": within(speed)}


def wait_for_speed(label: str) -> None:
    """:func:`speed_gate` before ``label``'s deployment, against the sweep's median speed
    (SPEED_GATE["reference"], set once the sweep ran); the wait goes into SPEED_GATE."""
    ref = SPEED_GATE["reference"]
    if ref is None or SPEED_WAIT_S <= 0:
        return
    from perfros_bag.cpu.speed import measure_speed

    spent = sum(w["waited_s"] for w in SPEED_GATE["waits"])
    got = speed_gate(ref, lambda: measure_speed().factor, time.sleep, time.monotonic, wait_s=SPEED_WAIT_S,
                     budget_s=SPEED_BUDGET_S - spent)
    SPEED_GATE["waits"].append({"deployment": label, **got})
    if got["waited_s"] >= SPEED_STEP_S or not got["held"]:
        err.print(f"{label}: waited {got['waited_s']:.0f} s for the host's speed "
                  f"({got['speed']:.2f}, the sweep's {ref:.2f}){'' if got['held'] else ': still slow, deploying'}")


def speed_gate_summary() -> dict[str, Any]:
    """The gate over the run: the reference, how many deployments waited, for how long, how
    many ran below the threshold anyway."""
    waits = SPEED_GATE["waits"]
    return {"reference": SPEED_GATE["reference"], "share": SPEED_SHARE, "checked": len(waits),
            "waited": sum(1 for w in waits if w["waited_s"] >= SPEED_STEP_S),
            "waited_s": sum(w["waited_s"] for w in waits), "slow": sum(1 for w in waits if not w["held"]),
            "waits": waits}


def deploy(plan: Path, robots: int, system: Path, run_dir: Path, app: Path, args: argparse.Namespace,
           label: str) -> dict[str, Any]:
    sig = signature(json.loads(plan.read_text()))
    stamp = run_dir / "plan.signature"
    if (run_dir / "deploy.json").exists() and (run_dir / "validation.json").exists() \
            and stamp.exists() and stamp.read_text() == sig:
        err.print(f"reusing {rel(run_dir)}")
        DEPLOYS["reused"] += 1
        COMMANDS.append(f"perfros-bag deploy {rel(plan)} {rel(app / f'app{robots}.launch')} --space "
                        f"{rel(app / f'space{robots}.yaml')} --out {rel(run_dir)} --system {rel(system)}   # reused")
    else:
        attempts: list[tuple[float | None, Path]] = []  # (deploy.json's speed, where that attempt is now)
        for attempt in range(1 + SPEED_REPEATS):
            wait_for_speed(label)
            err.print(f"[bold]{label}[/]: deploying -> {rel(run_dir)}")
            if run_dir.exists():
                shutil.rmtree(run_dir)
            sh([BIN, "deploy", plan, app / f"app{robots}.launch", "--space", app / f"space{robots}.yaml", "--out",
                run_dir, "--system", system, "--units-per-core", f"{UNITS_PER_CORE:g}"], ok=(0, 1))
            DEPLOYS["ran"] += 1
            speed = run_speed(json.loads((run_dir / "deploy.json").read_text()), SPEED_GATE["reference"])
            if at_speed(speed, SPEED_GATE["reference"]) or attempt == SPEED_REPEATS:
                attempts.append((speed, run_dir))
                break
            aside = run_dir.with_name(f"{run_dir.name}.off-speed-{attempt + 1}")  # kept, and stated
            if aside.exists():
                shutil.rmtree(aside)
            run_dir.rename(aside)
            attempts.append((speed, aside))
            err.print(f"{label}: the host ran at speed {speed} (the sweep's {SPEED_GATE['reference']:.2f}): "
                      f"deploying again ({rel(aside)} kept)")
        keep = nearest_speed(attempts, SPEED_GATE["reference"])
        if keep != run_dir:
            if run_dir.exists():
                run_dir.rename(run_dir.with_name(f"{run_dir.name}.off-speed-{len(attempts)}"))
            keep.rename(run_dir)
        if len(attempts) > 1:
            planned = json.loads(plan.read_text())
            aside_now = sorted(run_dir.parent.glob(f"{run_dir.name}.off-speed-*"))
            REDEPLOYS.append({"deployment": label, "speeds": [s for s, _ in attempts],
                              "kept": [d for _, d in attempts].index(keep),
                              # the attempts set aside, measured against the same plan: stated, not dropped
                              "set_aside_chains": [c for d in aside_now if (d / "validation.json").exists()
                                                   for c in chain_rows(json.loads((d / "validation.json").read_text()),
                                                                       planned)]})
        stamp.write_text(sig)
    record = json.loads((run_dir / "deploy.json").read_text())
    validation = json.loads((run_dir / "validation.json").read_text())
    return {"record": record, "validation": validation}


def chain_rows(validation: dict[str, Any], plan: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Per chain of a validation.json: measured p50/p95 (ms), predicted (its ``predicted_ms``,
    else the plan's ``chains[].predicted_ms``) and the budget (the chain's ``budget_ms`` in the
    validation, else in the plan); None where a number is missing."""
    planned = {c.get("name"): c for c in (plan or {}).get("chains") or [] if isinstance(c, dict)}

    def ms(x: Any) -> float | None:
        return None if x is None else 1e3 * float(x)

    rows = []
    for c in validation.get("chains") or []:
        pc = planned.get(c.get("name")) or {}
        pred = c.get("predicted_ms") or pc.get("predicted_ms") or {}
        budget = c.get("budget_ms") or pc.get("budget_ms") or {}
        rows.append({"chain": c.get("name"), "matched": c.get("matched"),
                     "p50_ms": ms(c.get("p50_s")), "p95_ms": ms(c.get("p95_s")),
                     "pred_p50_ms": pred.get("p50"), "pred_p95_ms": pred.get("p95"),
                     "budget_p50_ms": budget.get("p50"), "budget_p95_ms": budget.get("p95")})
    return rows


def summarise(res: dict[str, Any], plan: dict[str, Any] | None = None) -> dict[str, Any]:
    val, rec = res["validation"], res["record"]
    ratios = [abs(t["ratio"] - 1) * 100 for n in val["nodes"] for t in n["topics"] if t.get("ratio") is not None]
    links = rec["network"].get("links_measured", [])
    return {"expected": val["overall"]["expected"], "measured": val["overall"]["measured"],
            "deviation_pct": val["overall"]["deviation_pct"],
            "speed_factor": run_speed(rec, SPEED_GATE["reference"]), "speed_factor_start": rec.get("speed_factor"),
            "speed_factor_end": rec.get("speed_factor_end"),
            "freq_dev_mean_pct": sum(ratios) / len(ratios) if ratios else None,
            "cpu_cap": rec["cpu_cap"]["mode"], "net": rec["network"]["mode"],
            "computers": {c["computer"]: {"capacity": c["capacity"], "expected": c["cpu_expected"],
                                          "measured": c["cpu_measured"], "overloaded": c["overloaded"]}
                          for c in val["computers"]},
            "links": [{"between": x["between"], "capacity": x["capacity_kBps"], "expected": x["expected_kBps"],
                       "measured": x["measured_kBps"], "overloaded": x["overloaded"]} for x in val.get("links", [])],
            "link_use": links,
            "nodes": {n["node"]: {"computer": n["computer"], "value": n["value"], "cpu_expected": n["cpu_expected"],
                                  "cpu_measured": n["cpu_measured"], "p_expected": n["p_expected"],
                                  "p_measured": n["p_measured"], "f_ratio": n["ratio"]} for n in val["nodes"]},
            "chains": chain_rows(val, plan)}


RUN_OF: dict[tuple[int, str], Path] = {}  # (instance, plan key) -> the run that deployed it


def deploy_all(out: Path, app: Path, plans: dict[int, dict[str, Path]], args: argparse.Namespace,
               bar: Any) -> list[dict[str, Any]]:
    results = []
    for i, ps in plans.items():
        robots = len(INSTANCES[i].robot_capacity)
        system = out / f"instance{i}" / "model.json"  # the fitted model: validate knows every setting a plan may pick
        done: dict[str, dict[str, Any]] = {}
        for r in ROUNDS.get(i, []):  # tune's rounds: a plan equal to one shares its run
            done.setdefault(signature(r["plan"]), {"run": r["run"], "record": r["record"],
                                                   "validation": r["validation"]})
        for key in ps:
            plan = json.loads(ps[key].read_text())
            sig = signature(plan)
            if sig not in done:
                run_dir = out / f"instance{i}" / f"run-{key}"
                done[sig] = {"run": rel(run_dir), **deploy(ps[key], robots, system, run_dir, app, args,
                                                           f"instance {i} {key}")}
            else:
                COMMANDS.append(f"# instance {i} {key}: same deployment as {done[sig]['run']}")
            res = done[sig]
            RUN_OF[(i, key)] = ROOT / res["run"] if not Path(res["run"]).is_absolute() else Path(res["run"])
            row = {"instance": i, "plan": key, "problem": plan["problem"], "method": plan["method"],
                   "objective": plan["objective"], "status": plan["status"], "run": res["run"], **summarise(res, plan)}
            # eq 10 against this plan (a deployment shared by two plans is validated against each)
            if res["validation"]["plan"] != str(ps[key]):
                v = sh([BIN, "validate", ROOT / res["run"] / "run.bag", ps[key], "--system", system,
                        "--cpu", ROOT / res["run"] / "run.cpu.csv", "--json"], ok=(0, 1))
                row.update(summarise({"validation": json.loads(v.stdout), "record": res["record"]}, plan))
            results.append(row)
            err.print(f"instance {i} {key}: expected {row['expected']:.2f} measured {row['measured']:.2f} "
                      f"({row['deviation_pct']:.2f} %), freq. dev. {row['freq_dev_mean_pct'] or 0:.2f} %")
            bar[0].advance(bar[1])
    return results


# ---------------------------------------------------------------- 0. the emulated computers, measured

FAIRNESS_FACTORS = "1.0,1.1,1.25"


def fairness(out: Path) -> dict[str, Any]:
    """Is a capped cgroup a fair small computer for each detector? tests/bench/bench_cgroup_fairness.py
    caps one node at 1.0x, 1.1x and 1.25x of its measured need and counts the frames it keeps
    (the floor of the measured headroom, docs/solvers.md, rests on it). Reused when done."""
    path = out / "fairness.json"
    if not path.exists():
        err.print("[bold]cgroup fairness[/]: each detector capped at 1.0x, 1.1x, 1.25x of its need")
        sh([sys.executable, ROOT / "tests" / "bench" / "bench_cgroup_fairness.py", "--nodes", "people,smooth",
            "--factors", FAIRNESS_FACTORS, "--out", path])
    doc: dict[str, Any] = json.loads(path.read_text())
    return doc


def fairness_lines(doc: dict[str, Any]) -> list[str]:
    factors = [float(x) for x in doc["factors"]]
    lines = ["### The emulated computers, measured (`tests/bench/bench_cgroup_fairness.py`)", "",
             "Each detector with the camera at 10 Hz, its CPU need measured uncapped, then only its process "
             "capped at a multiple of that need; the share of the camera's frames it kept (the floor of "
             "`--headroom auto`, docs/solvers.md, rests on this):", "",
             "| node | need before / after (% of a core) | " + " | ".join(f"kept at {x:g}x" for x in factors) + " |",
             "|---|---|" + "---|" * len(factors)]
    for key, r in doc["nodes"].items():
        kept = {float(c["factor"]): c["kept"] for c in r["capped"]}
        after = r.get("need_after_cores")
        lines.append(f"| {key} ({r['executable']}) | {100 * r['need_cores']:.1f} / "
                     f"{'-' if after is None else f'{100 * after:.1f}'} | "
                     + " | ".join("-" if kept.get(x) is None else f"{100 * kept[x]:.1f} %" for x in factors) + " |")
    lines += ["", f"Leftover processes: {len(doc.get('leftover_processes') or [])}, leftover cgroups: "
              f"{len(doc.get('leftover_cgroups') or [])}; {doc.get('wall_s')} s.", ""]
    return lines


# ---------------------------------------------------------------- 3b. the loop (tune)

TUNE_ROUNDS = 3  # issue 21: the loop converges in at most 3 rounds
TUNE_TOLERANCE = 2.5  # % (eq 10): a round within it ends the loop
TUNED: dict[int, dict[str, Any]] = {}  # instance -> tune.json
# instance -> per round (tune.json's order): its run folder, plan.json and deploy/validation, read once
ROUNDS: dict[int, list[dict[str, Any]]] = {}


def tune_all(out: Path, app: Path, numbers: list[int], args: argparse.Namespace, bar: Any) -> list[dict[str, Any]]:
    """Per instance, ``tune`` from the instance's characterisation (``--base``: robot 1's
    sweep copied to each robot), with the model's measured headroom (``--headroom auto``):
    each round solves Problem 1 exactly, deploys, validates and refits on the recording.
    Each round is one RQ2 row (plan ``p1-tuned-rK``). tune resumes its finished rounds."""
    results = []
    for i in numbers:
        robots = len(INSTANCES[i].robot_capacity)
        d = out / f"instance{i}"
        cmd: list[object] = [BIN, "tune", app / f"app{robots}.launch", "--space", app / f"space{robots}.yaml",
                             "--system", d / "system.yaml", "--base", d / "characterisation.csv", "--out", d / "tune",
                             "--rounds", TUNE_ROUNDS, "--tolerance", TUNE_TOLERANCE, "--headroom", "auto",
                             "--duration", f"{args.duration:g}", "--units-per-core", f"{UNITS_PER_CORE:g}"]
        if not (d / "tune" / "tune.json").exists():
            wait_for_speed(f"instance {i} tune")
        err.print(f"[bold]instance {i}[/]: tune (up to {TUNE_ROUNDS} rounds) -> {rel(d / 'tune')}")
        # 1: stopped without a round that holds (plan unchanged, or the last round); 2: a round's
        # refit has no plan (e.g. a budget its model can no longer keep): its finished rounds count
        done = sh(cmd, ok=(0, 1, 2))
        if done.returncode == 2:
            FAILED.append({"instance": i, "plan": "tune", "why": rel(done.stderr.strip().splitlines()[-1])})
        if not (d / "tune" / "tune.json").exists():
            bar[0].advance(bar[1])
            continue
        doc = json.loads((d / "tune" / "tune.json").read_text())
        TUNED[i] = doc
        ROUNDS[i] = []
        for r in doc["rounds"]:
            run_dir = d / "tune" / r["dir"]
            plan = json.loads((run_dir / "plan.json").read_text())
            res = {"record": json.loads((run_dir / "deploy.json").read_text()),
                   "validation": json.loads((run_dir / "validation.json").read_text())}
            ROUNDS[i].append({"run": rel(run_dir), "plan": plan, **res})
            row = {"instance": i, "plan": f"p1-tuned-r{r['round']}", "problem": 1, "method": plan["method"],
                   "objective": plan["objective"], "status": plan["status"], "run": rel(run_dir),
                   "round": r["round"], "last_round": r is doc["rounds"][-1], **summarise(res, plan)}
            results.append(row)
            err.print(f"instance {i} tune round {r['round']}: expected {row['expected']:.2f} measured "
                      f"{row['measured']:.2f} ({row['deviation_pct']:.2f} %)")
        bar[0].advance(bar[1])
    return results


def confirm_all(out: Path, app: Path, numbers: list[int], args: argparse.Namespace,
                bar: Any) -> list[dict[str, Any]]:
    """After the loop, a fresh run: Problem 1 solved exactly (``--headroom auto``) on the
    model tune refitted after its last round, deployed once more in a run of its own (plan
    ``p1-tuned-final``), even when it equals the last round's plan. Its CPU error per node is
    the model's error after the loop, measured out of sample."""
    results = []
    for i in numbers:
        doc = TUNED.get(i)
        if not doc or not doc["rounds"]:
            continue
        d = out / f"instance{i}"
        model = d / "tune" / doc["rounds"][-1]["refit_model"]
        plan = d / "plan-p1-tuned-final.json"
        plan.unlink(missing_ok=True)
        done = sh([BIN, "solve", model, "--problem", "1", "--method", "exact", "--headroom", "auto", "--out", plan],
                  ok=(0, 2))
        if done.returncode != 0:
            FAILED.append({"instance": i, "plan": "p1-tuned-final", "why": rel(done.stderr.strip().splitlines()[-1])})
            bar[0].advance(bar[1])
            continue
        robots = len(INSTANCES[i].robot_capacity)
        run_dir = d / "run-p1-tuned-final"
        res = deploy(plan, robots, model, run_dir, app, args, f"instance {i} p1-tuned-final")
        body = json.loads(plan.read_text())
        row = {"instance": i, "plan": "p1-tuned-final", "problem": 1, "method": body["method"],
               "objective": body["objective"], "status": body["status"], "run": rel(run_dir), "final": True,
               **summarise(res, body)}
        results.append(row)
        err.print(f"instance {i} p1-tuned-final: expected {row['expected']:.2f} measured {row['measured']:.2f} "
                  f"({row['deviation_pct']:.2f} %)")
        bar[0].advance(bar[1])
    return results


# ---------------------------------------------------------------- 4. RQ3

def forced(out: Path, name: str, source: Path, change: dict[str, tuple[str | None, float | None]]) -> Path:
    """``source`` with some nodes moved and/or set to another value, the model's predictions
    rebuilt for them (``build_plan`` with the fitted model), status ``feasible`` and marked
    ``"forced": true`` (whatever this run's fit says a node needs, it is deployed)."""
    from perfros_bag.system.plan import Assignment, Status
    from perfros_bag.system.planfile import load_plan, save_plan
    from perfros_bag.system.rules import build_plan
    from perfros_bag.system.systemfile import load_system

    plan = load_plan(source)
    model = source.parent / "model.json"
    system = load_system(model)
    placement = {n: pn.computer for n, pn in plan.nodes.items()}
    setting = {}
    for node in system.nodes:
        pn = plan.nodes[node.name]
        computer, value = change.get(node.name, (None, None))
        if computer is not None:
            placement[node.name] = computer
        want = pn.value if value is None else value
        setting[node.name] = min(range(len(node.settings)), key=lambda k: abs((node.settings[k].value or 0.0)
                                                                                - (want or 0.0)))
    from perfros_bag.system.types import Choice, Problem

    choices: dict[str, Choice] = {}
    for node in system.nodes:  # sources first: a driven node's CPU and rate follow its input's
        if not node.driven:
            s = node.settings[setting[node.name]]
            choices[node.name] = Choice(0, s.cpu, s.performance, s.value, s.frequency_hz, s.bandwidth_kBps, s.topics)
    for driven in system.flow_order:
        input_hz = system.input_hz(driven, choices[system.flow_parent[driven]])
        choices[driven] = system.driven_choice(system.node[driven], setting[driven], input_hz)
    new = build_plan(system, Assignment(placement, choices), problem=Problem.PERFORMANCE, method=f"forced ({name})",
                     status=Status.FEASIBLE)
    new.extra["forced"] = True  # beyond its computers on purpose: plan.json's reader and deploy accept it
    path = out / f"plan-{name}.json"
    save_plan(new, path)
    return path


def rq3(out: Path, app: Path, plans: dict[int, dict[str, Path]], args: argparse.Namespace,
        bar: Any) -> list[dict[str, Any]]:
    d = out / "rq3"
    d.mkdir(parents=True, exist_ok=True)
    rows = []
    configs: list[tuple[str, int, Path, str, str]] = []
    for i in (2, 4):  # the forced plans start from these instances' Problem 1 optimum
        if i in plans and "p1-exact" not in plans[i]:
            FAILED.append({"instance": i, "plan": "rq3",
                           "why": "no Problem 1 exact plan to force from: RQ3 left it out"})
    if "p1-exact" in plans.get(2, {}):
        base = plans[2]["p1-exact"]
        configs.append(("instance 2 plan (baseline)", 2, base, "cpu", "robot1"))
        for people, smooth in ((1.2, 15.0), (1.1, 11.0), (1.1, 15.0)):
            name = f"robot-people{people:g}-smooth{smooth:g}"
            configs.append((f"robot: camera 10 Hz, people {people:g} on the robot, smooth {smooth:g}", 2,
                            forced(d, name, base, {"robot1_camera": (None, 10.0), "robot1_people": ("robot1", people),
                                                   "robot1_smooth": ("robot1", smooth)}), "cpu", "robot1"))
    if "p1-exact" in plans.get(4, {}):
        base = plans[4]["p1-exact"]
        configs.append(("instance 4 plan (baseline)", 4, base, "link", "robot2"))
        configs.append(("link: robot 2's camera at 10 Hz, its people detector on the server (2,000 kB/s link)", 4,
                        forced(d, "link-over", base,
                               {"robot2_camera": (None, 10.0), "robot2_people": ("server", None)}),
                        "link", "robot2"))
    for label, i, plan_path, what, where in configs:
        robots = len(INSTANCES[i].robot_capacity)
        system = out / f"instance{i}" / "model.json"  # the fitted model: validate knows every setting a plan may pick
        if plan_path.parent == d:
            res = deploy(plan_path, robots, system, d / f"run-{plan_path.stem}", app, args, f"RQ3 {label}")
        else:  # the instance's own plan: its RQ2 run
            run_dir = RUN_OF[(i, "p1-exact")]
            res = {"record": json.loads((run_dir / "deploy.json").read_text()),
                   "validation": json.loads((run_dir / "validation.json").read_text())}
        plan = json.loads(plan_path.read_text())
        s = summarise(res, plan)
        row: dict[str, Any] = {"config": label, "instance": i, "what": what, "where": where, **s}
        if what == "cpu":
            comp = plan["computers"][where]
            row["predicted_load"], row["capacity"] = comp["cpu"], comp["capacity"]
            row["predicted_overload"] = comp["cpu"] > comp["capacity"] + 1e-9
            thr = res["record"].get("throttling", {}).get(where) or {}
            row["observed_load"] = s["computers"][where]["measured"]
            row["throttled"] = thr["nr_throttled"] / thr["nr_periods"] if thr.get("nr_periods") else None
            # observed overloaded: a node on it fell behind its planned rate (missed frames)
            behind = [n["f_ratio"] for n in s["nodes"].values() if n["computer"] == where and n["f_ratio"] is not None]
            row["slowest_ratio"] = min(behind) if behind else None
            row["observed_overload"] = bool(behind and min(behind) < 0.95)
            # beyond the paper: the rates each node on it keeps, predicted (validate's kept
            # rates: CFS's max-min fair share per busy thread, propagated down the data flow) vs measured
            kept = (res["validation"].get("kept") or {}).get("nodes") or []
            row["kept"] = [{"node": k["node"], "predicted": k["f_predicted"] / k["f_planned"],
                            "measured": k["f_measured"] / k["f_planned"]}
                           for k in kept if k["computer"] == where and k.get("f_planned")
                           and k.get("f_predicted") is not None and k.get("f_measured") is not None]
        else:
            link = next(x for x in s["links"] if where in x["between"])
            use = next((x for x in s["link_use"] if x["from"] == where), None)
            row["predicted_load"], row["capacity"] = link["expected"], link["capacity"]
            row["predicted_overload"] = link["expected"] > link["capacity"] + 1e-9
            row["observed_load"] = use["sent_kBps"] if use else None
            row["utilisation"] = use["utilisation"] if use else None
            row["overlimits"] = use["overlimits"] if use else None
            row["observed_overload"] = bool(use and use["utilisation"] is not None and use["utilisation"] >= 0.95)
        rows.append(row)
        bar[0].advance(bar[1])
    return rows


# ---------------------------------------------------------------- report

def computer_errors(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Is CPU additive when nodes share a computer? Per computer kind, the sum the model
    predicts against the group's measured CPU, over every deployment (each run once); and
    the camera's CPU with its detector on the robot vs on the server (the cost of sending
    its images to one more subscriber across a link)."""
    seen: set[str] = set()
    comp: dict[str, list[tuple[float, float]]] = {"robot": [], "server": []}
    camera: dict[str, list[float]] = {"robot": [], "server": []}
    for r in results:
        if r["run"] in seen:
            continue
        seen.add(r["run"])
        for name, c in r["computers"].items():
            if c["measured"] is not None and c["expected"]:
                comp["server" if name == "server" else "robot"].append((c["expected"], c["measured"]))
        for name, n in r["nodes"].items():
            if kind(name) == "camera" and n["cpu_measured"] is not None:
                people = r["nodes"].get(name.replace("_camera", "_people"), {})
                camera["server" if people.get("computer") == "server" else "robot"].append(n["cpu_measured"])

    def summary(pairs: list[tuple[float, float]]) -> dict[str, Any]:
        if not pairs:
            return {"n": 0}
        errs = [(m - e) / e * 100 for e, m in pairs]
        return {"n": len(pairs), "predicted_mean": sum(e for e, _ in pairs) / len(pairs),
                "measured_mean": sum(m for _, m in pairs) / len(pairs), "error_mean_pct": sum(errs) / len(errs)}

    return {"computers": {k: summary(v) for k, v in comp.items()},
            "camera_cpu": {k: (sum(v) / len(v) if v else None, len(v)) for k, v in camera.items()}}


def distinct_deployments(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per deployment (``run``): plans that share a deployment count once, with the
    row of the first plan that deployed it (its own validation.json)."""
    seen: dict[str, dict[str, Any]] = {}
    for r in rows:
        seen.setdefault(r["run"], r)
    return list(seen.values())


def rq2_distinct(results: list[dict[str, Any]]) -> dict[str, Any]:
    """RQ2 over distinct deployments: K and the mean |deviation| (eq 10) over them (the
    tool's plans: the no-headroom contrast plans are not counted, they are stated apart)."""
    plans = [r for r in results if not r["plan"].endswith(NO_MARGIN)]
    rows = distinct_deployments(plans)
    dev = sum(abs(r["deviation_pct"]) for r in rows) / len(rows) if rows else None
    return {"deployments": len(rows), "plans": len(plans), "mean_abs_deviation_pct": dev}


def full_run_line(date: str, summary: dict[str, Any]) -> str:
    """The line docs/casestudy-real.md keeps for each full run from an empty out/ (issue 21)."""
    x = summary["mean_abs_deviation_pct"]
    return (f"full run {date}: RQ2 mean |deviation| {'-' if x is None else f'{x:.2f}'} % over "
            f"{summary['deployments']} distinct deployments")


#: Under this measured latency a chain's error is counted in ms, not % (issue 29's goal: within 5 ms).
SMALL_MS = 20.0
#: A budget holds when the measured latency is within this factor of it (issue 29's goal: 1.05).
BUDGET_SLACK = 1.05


def latency_rows(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """RQ2-L: per distinct deployment of the RQ2 plans (as :func:`rq2_distinct` counts them)
    and chain, measured and predicted p50/p95 and the budget."""
    plans = [r for r in results if not r["plan"].endswith(NO_MARGIN)]
    return [{"instance": r["instance"], "plan": r["plan"], "run": r["run"], "speed_factor": r.get("speed_factor"), **c}
            for r in distinct_deployments(plans) for c in r.get("chains") or []]


def latency_by_speed(rows: list[dict[str, Any]], reference: float | None) -> dict[str, Any] | None:
    """:func:`latency_summary` apart for the chain-deployments that ran at the sweep's speed
    (their deployment's ``speed_factor`` within SPEED_SHARE of ``reference``, as
    :func:`speed_gate` holds it) and the others (or with no speed known); None without a
    reference."""
    if reference is None:
        return None
    floor, ceiling = SPEED_SHARE * reference, reference / SPEED_SHARE

    def at(r: dict[str, Any]) -> bool:
        return r.get("speed_factor") is not None and at_speed(r["speed_factor"], reference)

    return {"reference": reference, "floor": floor, "ceiling": ceiling,
            "at_speed": latency_summary([r for r in rows if at(r)]),
            "off_speed": latency_summary([r for r in rows if not at(r)])}


def speed_split_line(split: dict[str, Any] | None) -> str | None:
    """One line: the latency error of the chain-deployments at the sweep's speed and off it."""
    if split is None:
        return None

    def part(s: dict[str, Any]) -> str:
        x50, x95 = s["p50"]["error_pct"], s["p95"]["error_pct"]
        return (f"p50 {'-' if x50 is None else f'{x50:.1f}'} %, p95 {'-' if x95 is None else f'{x95:.1f}'} % "
                f"over {s['chain_deployments']}")

    return (f"By the host's speed (record-cpu's speed reference at each deployment against the sweep's median "
            f"{split['reference']:.2f}; at speed: {split['floor']:.2f}-{split['ceiling']:.2f}): at speed "
            f"{part(split['at_speed'])}; off speed {part(split['off_speed'])}.")


def latency_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The prediction's error and the budgets over ``rows`` (:func:`latency_rows`): per
    quantile, over the chain-deployments with both a measured and a predicted value, the mean
    |predicted - measured| / measured in % where measured >= :data:`SMALL_MS`, and in ms where
    below (``*_small``); budgets: of the chain-deployments with a budget and a measurement, how
    many measured within :data:`BUDGET_SLACK` x every budgeted quantile."""
    out: dict[str, Any] = {}
    counted: set[int] = set()
    for q in ("p50", "p95"):
        pct, small = [], []
        for k, r in enumerate(rows):
            meas, pred = r.get(f"{q}_ms"), r.get(f"pred_{q}_ms")
            if meas is None or pred is None:
                continue
            counted.add(k)
            if meas >= SMALL_MS:
                pct.append(abs(pred - meas) / meas * 100)
            else:
                small.append(abs(pred - meas))
        out[q] = {"error_pct": sum(pct) / len(pct) if pct else None, "n_pct": len(pct),
                  "error_ms_small": sum(small) / len(small) if small else None, "n_small": len(small)}
    held = total = 0
    for r in rows:
        pairs = [(r.get(f"{q}_ms"), r.get(f"budget_{q}_ms")) for q in ("p50", "p95")]
        budgets = [(m, float(b)) for m, b in pairs if b is not None]
        measured = [(float(m), b) for m, b in budgets if m is not None]
        if not budgets or len(measured) < len(budgets):
            continue
        total += 1
        held += all(m <= BUDGET_SLACK * b for m, b in measured)
    return {**out, "chain_deployments": len(counted), "budgets_held": held, "budgets": total}


def latency_line(date: str, summary: dict[str, Any]) -> str:
    """The latency line docs/casestudy-real.md keeps for each full run (issue 29); the errors
    of chains measured under :data:`SMALL_MS` ms follow in ms."""
    def pct(q: str) -> str:
        x = summary[q]["error_pct"]
        return "-" if x is None else f"{x:.1f}"

    small = [f"{q} {summary[q]['error_ms_small']:.1f} ms" for q in ("p50", "p95") if summary[q]["n_small"]]
    tail = (f" (under {SMALL_MS:g} ms measured, counted in ms: {', '.join(small)} over "
            f"{max(summary[q]['n_small'] for q in ('p50', 'p95'))})") if small else ""
    return (f"full run {date}: latency p50 |error| {pct('p50')} % p95 |error| {pct('p95')} % over "
            f"{summary['chain_deployments']} chain-deployments; budgets held {summary['budgets_held']} of "
            f"{summary['budgets']}{tail}")


def kept_errors(rq3_rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """RQ3: per node kind, the mean |predicted - measured| kept share in points (goal: <= 10)."""
    acc: dict[str, list[float]] = {}
    for r in rq3_rows:
        for k in r.get("kept") or []:
            acc.setdefault(kind(k["node"]), []).append(100 * abs(k["predicted"] - k["measured"]))
    return {n: {"n": len(v), "mean_abs_points": sum(v) / len(v)} for n, v in sorted(acc.items())}


FULL_RUNS_BEGIN, FULL_RUNS_END = "<!-- casestudy-real-full-runs:begin -->", "<!-- casestudy-real-full-runs:end -->"


def append_full_run(docs: Path, line: str) -> None:
    """Add ``line`` to the page's list of full runs (kept across runs; made when missing): on a
    line of its own that starts with it, exactly as issue 21 asks (a blank line between two
    runs so that Markdown keeps them apart)."""
    from perfros_bag.fileio import atomic_write_text

    text = docs.read_text() if docs.exists() else "# Case study on real nodes\n"
    if FULL_RUNS_BEGIN not in text:
        text += (f"\n## Full runs from an empty out/\n\nEach full run of `make casestudy-real` from an empty "
                 f"`out/`, as the pipeline wrote it (failures too):\n\n{FULL_RUNS_BEGIN}\n{FULL_RUNS_END}\n")
    head, rest = text.split(FULL_RUNS_BEGIN, 1)
    body, tail = rest.split(FULL_RUNS_END, 1)
    atomic_write_text(docs, f"{head}{FULL_RUNS_BEGIN}{body.rstrip()}\n\n{line}\n{FULL_RUNS_END}{tail}")


def model_errors(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per node kind: CPU predicted by the fit vs measured, frequency ratio, over the given
    deployments (each run once)."""
    seen: set[str] = set()
    acc: dict[str, dict[str, list[float]]] = {}
    for r in results:
        if r["run"] in seen:
            continue
        seen.add(r["run"])
        for name, n in r["nodes"].items():
            k = kind(name)
            a = acc.setdefault(k, {"cpu_err": [], "cpu_pred": [], "cpu_meas": [], "f": []})
            if n["cpu_expected"] is not None and n["cpu_measured"] is not None:
                a["cpu_pred"].append(n["cpu_expected"])
                a["cpu_meas"].append(n["cpu_measured"])
                if n["cpu_expected"] > 0:
                    a["cpu_err"].append((n["cpu_measured"] - n["cpu_expected"]) / n["cpu_expected"] * 100)
            if n["f_ratio"] is not None:
                a["f"].append((n["f_ratio"] - 1) * 100)
    rows = []
    for k, a in sorted(acc.items()):
        def mean(xs: list[float]) -> float | None:
            return sum(xs) / len(xs) if xs else None
        rows.append({"node": k, "runs": len(a["cpu_pred"]), "cpu_predicted_mean": mean(a["cpu_pred"]),
                     "cpu_measured_mean": mean(a["cpu_meas"]), "cpu_error_mean_pct": mean(a["cpu_err"]),
                     "cpu_abs_error_mean_pct": mean([abs(x) for x in a["cpu_err"]]),
                     "freq_dev_mean_pct": mean(a["f"])})
    return rows


def plots(out: Path, results: list[dict[str, Any]], rq3_rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, problem in zip(axes, (1, 2), strict=True):
        rows = [r for r in results if r["problem"] == problem]
        xs = list(range(len(rows)))
        ax.bar(xs, [r["measured"] / r["expected"] for r in rows], 0.6,
               color=["tab:orange" if "tuned" in r["plan"] else "tab:blue" for r in rows])
        ax.axhline(1.0, color="grey", lw=0.8)
        for y in (0.975, 1.025):
            ax.axhline(y, color="grey", lw=0.6, ls=":")
        ax.set_ylim(0.85, 1.05)
        ax.set_xticks(xs, [f"{r['instance']} {r['plan'].split('-', 1)[1]}" for r in rows], fontsize=7, rotation=90)
        ax.set_title(f"Problem {problem}: measured / expected Σ w·P (eq 10)", fontsize=10)
    axes[0].set_ylabel("measured / expected (dotted: ±2.5 %)")
    axes[0].text(0.01, 0.02, "blue: the paper's plans; orange: tune's rounds (measured headroom)",
                 transform=axes[0].transAxes, fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rq2.png", dpi=110)
    plt.close(fig)
    if rq3_rows:
        fig, ax = plt.subplots(figsize=(11, 3.8))
        xs = list(range(len(rq3_rows)))
        ax.bar([x - 0.2 for x in xs], [r["predicted_load"] / r["capacity"] for r in rq3_rows], 0.4,
               label="predicted load / capacity")
        ax.bar([x + 0.2 for x in xs], [(r["observed_load"] or 0) / r["capacity"] for r in rq3_rows], 0.4,
               label="observed load / capacity")
        ax.axhline(1.0, color="red", lw=1)
        ax.set_xticks(xs, [r["config"].split(":")[0].replace(" (baseline)", "\nbaseline") for r in rq3_rows],
                      fontsize=7)
        ax.set_title("RQ3: robot CPU and link load against capacity")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "rq3.png", dpi=110)
        plt.close(fig)


def f(x: Any, nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def kept_cell(r: dict[str, Any]) -> str:
    """RQ3: each node's kept share of its planned rate, predicted (validate's kept rates) / measured."""
    kept = r.get("kept") or []
    return "; ".join(f"{kind(k['node'])} {100 * k['predicted']:.0f} / {100 * k['measured']:.0f} %" for k in kept) or "-"


def rq2l_lines(results: list[dict[str, Any]], started: str) -> list[str]:
    """The RQ2-L section: per distinct deployment and chain, predicted and measured p50/p95
    (ms) and the budget, then the summary line (:func:`latency_line`)."""
    rows = latency_rows(results)
    if not rows:
        return []
    lines = ["### RQ2-L: chain latency, predicted vs measured", "",
             "Each chain's latency: from the camera frame's `header.stamp` to the recorder's receipt of the "
             "node's output carrying it (validate's chains); predicted by the plan's latency model "
             "(`chains[].predicted_ms`). The camera -> people budgets this run chose on its fitted model "
             "(the first of the given p95 and 0.8/0.9/0.97 x the unbudgeted plan's predicted p95 that exact "
             "can keep): " + ("; ".join(f"instance {i}: " + ("none could bind" if b is None else f"p95 {b['p95']:g} ms")
                                       for i, b in sorted(BUDGETS.items())) or "none") + ".", "",
             "| instance | plan | chain | predicted p50 ms | measured p50 ms | predicted p95 ms | measured p95 ms "
             "| budget p95 ms | held | host speed | run |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        budget = r.get("budget_p95_ms")
        held = "-" if budget is None or r.get("p95_ms") is None else (
            "yes" if r["p95_ms"] <= BUDGET_SLACK * budget else "**no**")
        lines.append(f"| {r['instance']} | {r['plan']} | {r['chain']} | {f(r.get('pred_p50_ms'), 1)} | "
                     f"{f(r.get('p50_ms'), 1)} | {f(r.get('pred_p95_ms'), 1)} | {f(r.get('p95_ms'), 1)} | "
                     f"{f(budget, 0)} | {held} | {f(r.get('speed_factor'), 2)} | {r['run'].rsplit('/', 1)[-1]} |")
    lines += ["", latency_line(f"{started} UTC", latency_summary(rows)).replace("full run", "This run", 1)
              + f" (goals: p50 <= 15 %, p95 <= 25 %, under {SMALL_MS:g} ms within 5 ms; budgets held in >= 95 %).", ""]
    split = speed_split_line(latency_by_speed(rows, SPEED_GATE["reference"]))
    gate = speed_gate_summary()
    if split is not None:
        lines += [split, ""]
    if gate["checked"]:
        lines += [f"The host's speed before each deployment (pipelines/casestudy_real.py, SPEED_SHARE "
                  f"{SPEED_SHARE:g} of the sweep's, waits of up to {SPEED_WAIT_S:g} s, {SPEED_BUDGET_S:g} s in all): "
                  f"checked {gate['checked']}, waited {gate['waited']} times ({gate['waited_s']:.0f} s in all), "
                  f"deployed still off speed {gate['slow']} times. Deployed again because the deployment's own "
                  f"reading was off speed: {len(REDEPLOYS)} deployment(s)"
                  + (": " + "; ".join(f"{r['deployment']} at " + ", ".join("-" if s is None else f"{s:.2f}"
                                                                         for s in r["speeds"])
                                      + f" (kept attempt {r['kept'] + 1})" for r in REDEPLOYS) if REDEPLOYS else "")
                  + ".", ""]
        aside = latency_summary([c for r in REDEPLOYS for c in r.get("set_aside_chains", [])])
        if aside["chain_deployments"]:
            lines += [f"The attempts set aside, against their plans: latency p50 |error| "
                      f"{f(aside['p50']['error_pct'], 1)} %, p95 {f(aside['p95']['error_pct'], 1)} % over "
                      f"{aside['chain_deployments']} chain-deployments (not in the line above).", ""]
    return lines


def markdown(results: list[dict[str, Any]], rq3_rows: list[dict[str, Any]], errors: dict[str, list[dict[str, Any]]],
             computers: dict[str, Any], rates: list[dict[str, Any]], args: argparse.Namespace, argv: list[str],
             started: str, seconds: float, fair: dict[str, Any] | None = None) -> str:
    lines = [f"Pipeline run {started} (UTC), {seconds / 60:.1f} min wall on this 2-core machine, "
             f"{DEPLOYS['ran']} deployment(s) run and {DEPLOYS['reused']} reused from an earlier start "
             f"({UNITS_PER_CORE:g} CPU units = one core; {args.duration:g} s recorded per deployment, "
             f"{args.sweep_duration:g} s per sweep run).", "",
             "### The instances", "",
             "| instance | robots | robot capacity | server capacity | links (kB/s) | shared wifi (kB/s) |",
             "|---|---|---|---|---|---|"]
    for i in sorted({r["instance"] for r in results}):
        inst = INSTANCES[i]
        lines.append(f"| {i} | {len(inst.robot_capacity)} | {', '.join(f'{c:g}' for c in inst.robot_capacity)} | "
                     f"{inst.server_capacity:g} | {', '.join(f'{b:g}' for b in inst.link_kBps)} | "
                     f"{f(inst.wifi_kBps, 0) if inst.wifi_kBps else '-'} |")
    lines += ["", "### RQ2: expected vs measured performance (eq 10)", "",
              "| instance | plan | objective | status | expected Σ w·P | measured Σ w·P | deviation % "
              "| mean freq. dev. % | CPU cap | links | run |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['instance']} | {r['plan']} | {f(r['objective'])} | {r['status']} | {f(r['expected'])} | "
                     f"{f(r['measured'])} | {f(r['deviation_pct'])} | {f(r['freq_dev_mean_pct'])} | {r['cpu_cap']} | "
                     f"{r['net']} | {r['run'].rsplit('/', 1)[-1]} |")
    groups = (("Problem 1 (greedy, greedy+, exact; measured headroom)",
               lambda r: r["problem"] == 1 and "tuned" not in r["plan"] and not r["plan"].endswith(NO_MARGIN)),
              ("Problem 1, tune's rounds (measured headroom, refitted after each round)",
               lambda r: "tuned-r" in r["plan"]),
              ("Problem 1, tune's last round per instance", lambda r: r.get("last_round", False)),
              ("Problem 1 after the loop: the final model's plan, deployed afresh", lambda r: r.get("final", False)),
              ("Problem 2 (greedy, exact; the server sized with measured headroom)", lambda r: r["problem"] == 2),
              ("Not an RQ2 plan: Problem 1 exact on the model as fitted, no headroom (the paper's way)",
               lambda r: r["plan"].endswith(NO_MARGIN)))
    for label, member in groups:
        plans_in = [r for r in results if member(r)]
        rows = distinct_deployments(plans_in)
        if rows:
            dev = sum(abs(r["deviation_pct"]) for r in rows) / len(rows)
            fr = [r["freq_dev_mean_pct"] for r in rows if r["freq_dev_mean_pct"] is not None]
            lines.append(f"\n{label}: mean |deviation| **{dev:.2f} %** over {len(rows)} distinct deployments "
                         f"of {len(plans_in)} plans ({len({r['instance'] for r in rows})} instances); mean topic "
                         f"frequency deviation **{sum(fr) / len(fr):.2f} %** (goals: 2.5 % and 3 %).")
    summary = rq2_distinct(results)
    if summary["deployments"]:
        lines.append(f"\nAll RQ2 plans (every plan above but the no-headroom contrast): mean |deviation| "
                     f"**{summary['mean_abs_deviation_pct']:.2f} %** over {summary['deployments']} distinct "
                     f"deployments of {summary['plans']} plans (each deployment once, against the plan that "
                     f"deployed it).")
    for fail in FAILED:
        lines.append(f"\nInstance {fail['instance']} {fail['plan']}: no plan ({fail['why'].removeprefix('error: ')}).")
    lines += ["", "![RQ2](casestudy-real/rq2.png)", ""]
    lines += rq2l_lines(results, started)
    if rq3_rows:
        lines += ["### RQ3: settings and placements forced above the plan", "",
                  "| configuration | resource | predicted load | capacity | overload predicted | observed load "
                  "| observed overload | evidence | kept rate per node, predicted / measured "
                  "| expected Σ w·P | measured Σ w·P | mean freq. dev. % |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rq3_rows:
            if r["what"] == "cpu":
                evidence = (f"CFS throttled {f(None if r.get('throttled') is None else 100 * r['throttled'], 0)} % "
                            "of periods; slowest node at "
                            f"{f(None if r.get('slowest_ratio') is None else 100 * r['slowest_ratio'], 0)} "
                            "% of its planned rate")
                resource = f"{r['where']} CPU (units)"
            else:
                evidence = (f"link at {f(None if r.get('utilisation') is None else 100 * r['utilisation'], 0)} "
                            f"% of its rate, {r.get('overlimits')} overlimits")
                resource = f"link {r['where']}-server (kB/s)"
            lines.append(f"| {r['config']} | {resource} | {f(r['predicted_load'], 1)} | {f(r['capacity'], 0)} | "
                         f"{'yes' if r['predicted_overload'] else 'no'} | {f(r['observed_load'], 1)} | "
                         f"{'yes' if r['observed_overload'] else 'no'} | {evidence} | {kept_cell(r)} | "
                         f"{f(r['expected'])} | "
                         f"{f(r['measured'])} | {f(r['freq_dev_mean_pct'])} |")
        kerr = kept_errors(rq3_rows)
        if kerr:
            lines += ["", "Kept rates, predicted (CFS's share: small needs met first, one slice per node) "
                      "against measured, mean |difference| per node (goal: at most 10 points): "
                      + ", ".join(f"{n} **{e['mean_abs_points']:.1f}** points over {e['n']}" for n, e in kerr.items())
                      + "."]
        agree = all(r["predicted_overload"] == r["observed_overload"] for r in rq3_rows)
        lines += ["", f"Every prediction matched the observation: **{'yes' if agree else 'no'}**.", "",
                  "![RQ3](casestudy-real/rq3.png)", ""]
    if fair:
        lines += fairness_lines(fair)
    if TUNED:
        lines += ["### The loop (`tune`): each instance's rounds", "",
                  f"`tune --base instance/characterisation.csv --headroom auto --rounds {TUNE_ROUNDS} --tolerance "
                  f"{TUNE_TOLERANCE:g}`: each round solves Problem 1 exactly with the model's measured headroom, "
                  "deploys, validates, and refits on the recording.", "",
                  "| instance | round | values deployed | objective | margin kept (units) | expected Σ w·P "
                  "| measured Σ w·P | deviation % | starved | refit: CPU the model gives the deployed settings, "
                  "before -> after |", "|---|---|---|---|---|---|---|---|---|---|"]
        for i, doc in sorted(TUNED.items()):
            for r, ran in zip(doc["rounds"], ROUNDS[i], strict=True):
                margin = sum(c.get("margin") or 0.0 for c in ran["plan"]["computers"].values())
                before = sum(n["model_cpu_before"] or 0.0 for n in r["nodes"].values())
                after = sum(n["model_cpu_after"] or 0.0 for n in r["nodes"].values())
                starved = [c for c, v in r["computers"].items() if v["starved"]]
                values = ", ".join(f"{n.split('_', 1)[1] if n.startswith('robot1_') else n}={v:g}"
                                   if isinstance(v, int | float) else f"{n}={v}" for n, v in r["values"].items())
                lines.append(f"| {i} | {r['round']} | {values} | {f(r['objective'])} | {f(margin, 1)} | "
                             f"{f(r['expected'])} | {f(r['measured'])} | {f(r['deviation_pct'])} | "
                             f"{', '.join(starved) or '-'} | {f(before, 1)} -> {f(after, 1)} |")
            stop = doc.get("stopped") or {}
            lines.append(f"| {i} | stopped | {stop.get('reason', '-')} after round {stop.get('after_round', '-')} "
                         "| | | | | | | |")
        worst = max(len(doc["rounds"]) for doc in TUNED.values())
        per = ", ".join(f"{i}: {len(d['rounds'])}" for i, d in sorted(TUNED.items()))
        lines += ["", f"Rounds per instance: {per} "
                  f"(at most {worst}; goal: at most {TUNE_ROUNDS}).", ""]
    for key, title in (("after_loop", "after the loop: the final model's plan (`p1-tuned-final`), deployed afresh"),
                       ("last_round", "in the loop: each instance's last `tune` round, predicted by the model "
                                      "before it"),
                       ("plans", "every deployment of the solved plans (tune's rounds apart), once")):
        rows = errors.get(key) or []
        if not rows:
            continue
        lines += [f"### The model's CPU error per node, {title}", "",
                  "| node | runs | CPU predicted (mean units) | CPU measured (mean units) | mean CPU error % "
                  "| mean abs. CPU error % | mean freq. deviation % |", "|---|---|---|---|---|---|---|"]
        for e in rows:
            lines.append(f"| {e['node']} | {e['runs']} | {f(e['cpu_predicted_mean'])} | {f(e['cpu_measured_mean'])} | "
                         f"{f(e['cpu_error_mean_pct'], 1)} | {f(e['cpu_abs_error_mean_pct'], 1)} | "
                         f"{f(e['freq_dev_mean_pct'], 2)} |")
        lines.append("")
    if computers:
        lines += ["", "Per computer, the model's sum of its nodes' CPU against the capped group's measured CPU "
                  "(is CPU additive when nodes share a computer?):", "",
                  "| computer | deployments | predicted (mean units) | measured (mean units) | mean error % |",
                  "|---|---|---|---|---|"]
        for k, c in computers["computers"].items():
            if c["n"]:
                lines.append(f"| {k} | {c['n']} | {f(c['predicted_mean'])} | {f(c['measured_mean'])} | "
                             f"{f(c['error_mean_pct'], 1)} |")
        on_robot, on_server = computers["camera_cpu"]["robot"], computers["camera_cpu"]["server"]
        lines += ["", f"The camera's measured CPU with its people detector on the robot: {f(on_robot[0], 3)} units "
                  f"({on_robot[1]} runs); on the server (its images sent across the link): {f(on_server[0], 3)} units "
                  f"({on_server[1]} runs). The model gives the camera one CPU figure wherever its subscribers run."]
    if rates:
        lines += ["", "CPU against the camera's rate (robot 1's sweep runs with people at scale0 1.1 and smooth at "
                  "kernel 7): measured, and the line `init` drafted for each driven node (CPU = cpu + cpu_per_hz x "
                  "input rate, least squares over these runs):", "",
                  "| camera Hz | people output Hz | camera CPU | people CPU | people, drafted line | smooth CPU "
                  "| smooth, drafted line |", "|---|---|---|---|---|---|---|"]
        for r in rates:
            lines.append(f"| {r['rate_hz']:g} | {f(r.get('people_hz'))} | {f(r.get('camera'), 3)} | "
                         f"{f(r.get('people'))} | "
                         f"{f(r.get('people_line'))} | {f(r.get('smooth'))} | {f(r.get('smooth_line'))} |")
    lines += ["", "### Commands", "", "```",
              f"make casestudy-real   # = .venv/bin/python pipelines/casestudy_real.py {' '.join(argv)}",
              *dict.fromkeys(COMMANDS), "```", ""]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "casestudy-real")
    ap.add_argument("--duration", type=float, default=15.0, help="seconds recorded per deployment")
    ap.add_argument("--sweep-duration", type=float, default=12.0, help="seconds recorded per sweep run")
    ap.add_argument("--instances", default="1,2,3,4,5,6")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs" / "casestudy-real.md")
    ap.add_argument("--no-docs", action="store_true", help="leave the docs page alone")
    ap.add_argument("--skip-rq3", action="store_true")
    ap.add_argument("--skip-tune", action="store_true", help="no tune loop (not a full run)")
    ap.add_argument("--skip-fairness", action="store_true", help="no cgroup fairness bench (not a full run)")
    ap.add_argument("--people-budget-p95", type=float, default=PEOPLE_BUDGET_MS["p95"],
                    help="ms: the camera -> people chain's p95 budget on the budgeted instances")
    ap.add_argument("--budget-instances", default=",".join(map(str, BUDGET_INSTANCES)),
                    help="the instances whose camera -> people chains carry the budget ('' for none)")
    args = ap.parse_args(argv)
    interrupt_on_sigterm()
    numbers = [int(x) for x in args.instances.split(",") if x.strip()]
    unknown = [n for n in numbers if n not in INSTANCES]
    if unknown:
        raise SystemExit(f"error: no instance {unknown[0]} (there are {', '.join(map(str, INSTANCES))})")
    out: Path = args.out.resolve()
    # a full run: every instance and RQ3 from an empty out/; its line goes into the docs page
    full = (not out.exists() or not any(out.iterdir())) and set(numbers) == set(INSTANCES) and not args.skip_rq3 \
        and not args.skip_tune and not args.skip_fairness
    out.mkdir(parents=True, exist_ok=True)
    started, t0 = datetime.now(UTC).strftime("%Y-%m-%d %H:%M"), time.monotonic()
    try:
        return run(out, numbers, args, argv, started, t0, full)
    except (SystemExit, Exception) as exc:
        if full and not args.no_docs:  # a failed full run is stated too
            append_full_run(args.docs, f"full run {started} UTC: failed after {(time.monotonic() - t0) / 60:.1f} min: "
                                       f"{str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__}")
        raise


def run(out: Path, numbers: list[int], args: argparse.Namespace, argv: list[str], started: str, t0: float,
        full: bool) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    app = application(out, args)
    fair = None if args.skip_fairness else fairness(out)
    char_csv, draft = characterise(out, app)
    SPEED_GATE["reference"] = sweep_speed(out / "sweep" / "manifest.yaml")
    rates = cpu_against_rate(char_csv, draft)
    plans = fit_and_solve(out, char_csv, draft, numbers, {"p95": args.people_budget_p95},
                          tuple(int(x) for x in args.budget_instances.split(",") if x.strip()))
    with Progress(TextColumn("deployments"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=err) as progress:
        bar = (progress, progress.add_task("", total=sum(map(len, plans.values())) + 2 * len(numbers)
                                           + (0 if args.skip_rq3 else 6)))
        tuned = [] if args.skip_tune else tune_all(out, app, numbers, args, bar)
        results = deploy_all(out, app, plans, args, bar) + tuned
        results += [] if args.skip_tune else confirm_all(out, app, numbers, args, bar)
        rq3_rows = [] if args.skip_rq3 else rq3(out, app, plans, args, bar)
    errors = {"plans": model_errors([r for r in results
                                     if "tuned" not in r["plan"] and not r["plan"].endswith(NO_MARGIN)]),
              "after_loop": model_errors([r for r in results if r.get("final")]),
              "last_round": model_errors([r for r in results if r.get("last_round")])}
    computers = computer_errors(results)
    seconds = time.monotonic() - t0
    distinct = rq2_distinct(results)
    line = full_run_line(f"{started} UTC", distinct)
    chains = latency_rows(results)
    latency = latency_summary(chains)
    lat_line = latency_line(f"{started} UTC", latency)
    by_speed = latency_by_speed(chains, SPEED_GATE["reference"])
    (out / "results.json").write_text(json.dumps({"rq2": results, "rq2_distinct": distinct, "rq3": rq3_rows,
                                                  "model_errors": errors,
                                                  "computer_errors": computers, "cpu_against_rate": rates,
                                                  "fairness": fair, "rq2_latency": chains,
                                                  "rq2_latency_summary": latency, "latency_line": lat_line,
                                                  "rq2_latency_by_speed": by_speed,
                                                  "speed_gate": speed_gate_summary(), "redeployed": REDEPLOYS,
                                                  "rq3_kept_errors": kept_errors(rq3_rows),
                                                  "no_plan": FAILED, "full_run": full, "full_run_line": line,
                                                  "seconds": seconds}, indent=1, default=str))
    plots(out, results, rq3_rows)
    section = markdown(results, rq3_rows, errors, computers, rates, args, argv, started, seconds, fair)
    (out / "results.md").write_text(section)
    if not args.no_docs:
        write_section(args.docs, "casestudy-real", section, out, ("rq2.png", "rq3.png"), "Case study on real nodes")
        if full:
            append_full_run(args.docs, line)
            append_full_run(args.docs, lat_line)
    err.print(section)
    for text in (line, lat_line):
        err.print(text if full else f"{text} (not a full run from an empty out/: not written to the docs)",
                  highlight=False)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
