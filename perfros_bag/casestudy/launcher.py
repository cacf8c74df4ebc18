"""Run a plan on real ROS 1: roscore, the case-study nodes, ``rosbag record``, a CPU trace.

:func:`run_plan` starts, in order: ``roscore`` on a free port (its own ``ROS_HOME`` under
the output folder), one node per plan entry inside its computer's cgroup
(:mod:`perfros_bag.rosrun.cgroups`), ``perfros-bag record-cpu`` on those nodes, and
``rosbag record`` of every node topic once every node publishes. After ``duration``
seconds it stops everything it started (SIGINT to each process group, then SIGTERM,
then SIGKILL to every remaining process it or its descendants started, by PID), removes
the cgroups, and writes ``run.bag``, ``run.cpu.csv``, ``manifest.yaml``, ``plan.json``
and ``run.json`` (what ran, where, capped or not, measured loads) into ``out``.

Every process carries ``PERFROS_CASESTUDY_RUN=<run id>`` in its environment, so
:func:`leftover_processes` can prove nothing outlived a run. Ctrl-C, SIGTERM and errors
go through the same cleanup.
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from perfros_bag.casestudy.profiles import (
    Calibration,
    NodeLaunch,
    NodeProfile,
    launch_for,
)
from perfros_bag.errors import InputError, PerfrosError
from perfros_bag.fileio import atomic_write_json, atomic_write_text
from perfros_bag.rosrun.cgroups import CpuGroups, emulated_trace
from perfros_bag.rosrun.cgroups import computer_cores as plan_cores
from perfros_bag.rosrun.master import ROSCORE, master_state, start_roscore
from perfros_bag.rosrun.processes import (
    Processes,
    kill_stale,
    ros_env,
    sigterm_as_interrupt,
    wait_for,
)
from perfros_bag.rosrun.recorders import ROSBAG, cpu_ready_path, start_record_cpu, start_rosbag
from perfros_bag.system.plan import Plan
from perfros_bag.system.planfile import plan_document, save_plan
from perfros_bag.system.types import System

Progress = Callable[[str, float, float], None]  # (stage, done, total)



@dataclass
class RunConfig:
    duration: float = 30.0
    units_per_core: float = 400.0
    headroom: float = 0.85
    cap: bool = True
    interval: float = 0.5
    startup_timeout: float = 45.0
    calibration: Calibration | None = None


def node_launches(system: System, plan: Plan, calib: Calibration,
                  overrides: dict[str, float] | None = None) -> list[NodeLaunch]:
    """The node processes for ``plan`` (with parameter ``overrides``: node -> value)."""
    by_name = {n.name: n for n in system.nodes}
    missing = [n for n in plan.nodes if n not in by_name]
    if missing:
        raise InputError(plan.system, f"plan nodes not in the system: {', '.join(missing)}")
    for name in overrides or {}:
        if name not in plan.nodes:
            raise InputError(None, f"--set {name}: no such node in the plan ({', '.join(plan.nodes)})")
        if not NodeProfile.of(by_name[name]).configurable:
            raise InputError(None, f"--set {name}: the node has no parameter to set")
    topics = {n.name: (n.topics or (f"/{n.name}/out",)) for n in system.nodes}
    subs: dict[str, list[str]] = {n: [] for n in plan.nodes}
    for e in system.edges:
        if e.dst in subs and e.src in plan.nodes:
            for t in ([e.topic] if e.topic else list(topics[e.src])):
                if t not in subs[e.dst]:
                    subs[e.dst].append(t)
    out = []
    for name, pn in plan.nodes.items():
        node = by_name[name]
        prof = NodeProfile.of(node)
        value = pn.value
        if overrides and name in overrides:
            value = overrides[name]
        elif value is None and prof.configurable:
            value = prof.value_for_cpu(pn.cpu)
        if value is not None and prof.configurable and node.parameter and node.parameter.type == "int":
            value = float(round(value))
        out.append(launch_for(node, pn.computer, value, calib, tuple(subs[name])))
    return out


def computer_cores(system: System, plan: Plan, units_per_core: float) -> dict[str, float]:
    """Cores of CPU time per computer used by the plan (capacity / units_per_core; the
    system's capacity where the plan states none)."""
    return plan_cores(plan, units_per_core, {c.name: c.capacity for c in system.computers})


def run_plan(system: System, plan: Plan, out: Path, cfg: RunConfig, *,
             overrides: dict[str, float] | None = None, progress: Progress | None = None,
             system_path: Path | None = None) -> dict[str, Any]:
    """Deploy ``plan`` for ``cfg.duration`` seconds of recording; returns run.json's content."""
    for tool in (ROSCORE, ROSBAG):
        if shutil.which(tool) is None:
            raise PerfrosError(f"{tool} not found: install Debian's ROS 1 "
                               "(apt-get install ros-core python3-rospy python3-rosbag)")
    if not Path("/usr/bin/python3").exists():
        raise PerfrosError("/usr/bin/python3 not found (rospy runs under Debian's python3)")
    note = progress or (lambda stage, done, total: None)
    calib = cfg.calibration or Calibration(units_per_core=cfg.units_per_core, headroom=cfg.headroom)
    launches = node_launches(system, plan, calib, overrides)
    cores = computer_cores(system, plan, cfg.units_per_core)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is not a directory, expected the run folder")
    # every input is read and checked above: only now may an earlier run's files go
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("run.bag", "run.bag.active", "run.cpu.csv", "run.host.cpu.csv", "run.json", "manifest.yaml"):
        (out / stale).unlink(missing_ok=True)

    run_id = uuid.uuid4().hex[:10]
    ros_home = out / "ros"
    ros_home.mkdir(exist_ok=True)
    env = ros_env(run_id, ros_home)
    procs = Processes(run_id, env)
    groups = CpuGroups(run_id, cores)
    record: dict[str, Any] = {
        "format": "perfros-bag/casestudy-run@1", "run_id": run_id,
        "plan": plan_document(plan), "overrides": overrides or {},
        "duration_s": cfg.duration, "calibration": calib.to_dict(),
        "nodes": {ln.name: {"computer": ln.computer, "parameter": ln.parameter, "value": ln.value,
                            "rate_hz": ln.rate_hz, "message_bytes": ln.message_bytes,
                            "work_ms": round(ln.work_ms, 4), "target_cpu": round(ln.target_cpu, 3),
                            "publishes": list(ln.publishes), "subscribes": list(ln.subscribes)}
                  for ln in launches},
    }
    bag = out / "run.bag"
    trace = out / "run.host.cpu.csv"
    topics = sorted({t for ln in launches for t in ln.publishes})
    ok = False
    try:
        with sigterm_as_interrupt():
            # the groups also give the nodes CPU priority over unrelated load: create them
            # uncapped runs too, and set the quotas only when capping
            groups.create(capped=False, quiet=not cfg.cap)
            mode, reason = (groups.mode, groups.reason) if cfg.cap else ("uncapped", "disabled (--no-cap)")
            record["cpu_cap"] = {"mode": mode, "reason": reason, "cgroups": groups.mode,
                                 "cores": cores, "units_per_core": cfg.units_per_core, **groups.cap_record()}
            note("roscore", 0, 1)
            uri = start_roscore(procs, out, cfg.startup_timeout)
            record["ros_master_uri"] = uri
            note("nodes", 0, len(launches))
            node_procs = {}
            for ln in launches:
                node_procs[ln.name] = procs.start(ln.name, groups.wrap(ln.computer, ln.argv(run_id)),
                                                  out / "ros" / f"{ln.name}.log", cwd=out)

            def nodes_dead() -> str | None:
                dead = [n for n, st in node_procs.items() if st.popen.poll() is not None]
                return f"node {dead[0]} (see {out / 'ros' / (dead[0] + '.log')})" if dead else None

            def all_publishing() -> bool:
                state = master_state(uri)
                if state is None:
                    return False
                pubs = {t: set(who) for t, who in state[0]}
                return all(f"/{ln.name}" in pubs.get(t, set()) for ln in launches for t in ln.publishes)

            wait_for("every node to publish", all_publishing, cfg.startup_timeout, nodes_dead)
            if cfg.cap:
                groups.apply()
            note("rosbag", 0, 1)
            cpu = start_record_cpu(procs, [f"--run {run_id} "], cfg.interval, trace, out / "record-cpu.log", out)
            wait_for("record-cpu to sample", cpu_ready_path(trace).exists, cfg.startup_timeout,
                     lambda: "record-cpu" if cpu.popen.poll() is not None else nodes_dead())
            cpu_ready_path(trace).unlink()
            rec = start_rosbag(procs, "rosbag", bag, topics, "perfros_record", out / "rosbag.log", out)

            def recording() -> bool:
                state = master_state(uri)
                if state is None:
                    return False
                subs = {t: set(who) for t, who in state[1]}
                return all("/perfros_record" in subs.get(t, set()) for t in topics)

            wait_for("rosbag record to subscribe", recording, cfg.startup_timeout,
                  lambda: "rosbag record" if rec.popen.poll() is not None else nodes_dead())
            throttle0 = {c: groups.throttled(c) for c in cores}
            t0 = time.time()
            record["started"] = datetime.now(UTC).isoformat(timespec="seconds")
            while (el := time.time() - t0) < cfg.duration:
                dead = nodes_dead() or ("rosbag record" if rec.popen.poll() is not None else None)
                if dead:
                    raise PerfrosError(f"{dead} exited during the recording")
                note("recording", el, cfg.duration)
                time.sleep(min(0.5, cfg.duration - el))
            note("recording", cfg.duration, cfg.duration)
            record["throttling"] = {c: _delta(throttle0[c], groups.throttled(c)) for c in cores}
            procs.stop(["rosbag", "record-cpu"], timeout=15.0)
            ok = True
    finally:
        note("stopping", 0, 1)
        procs.stop()
        # remembered descendants, then anything else carrying the run's tag (a process whose
        # Popen returned just as Ctrl-C arrived is not in procs.started yet)
        record["killed"] = procs.kill_leftovers() + kill_stale(procs.run_id)
        left = groups.remove()
        record["leftover_cgroups"] = [str(p) for p in left]
    if not bag.exists():
        raise PerfrosError(f"rosbag record did not write {bag} (see {out / 'rosbag.log'})")
    if ok:
        record["loads"] = measured_loads(trace, launches, cfg.units_per_core, cores)
        if trace.exists():
            emulated_trace(trace, out / "run.cpu.csv", {ln.name: ln.computer for ln in launches},
                           {c: n * cfg.units_per_core for c, n in cores.items()}, cfg.units_per_core)
        _write_outputs(out, record, system, plan, launches, system_path)
    return record


def _delta(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    return {k: round(b[k] - a.get(k, 0.0), 6) for k in b}


def measured_loads(trace: Path, launches: list[NodeLaunch], units_per_core: float,
                   cores: dict[str, float]) -> dict[str, Any]:
    """Mean CPU units per node and per computer from the CPU trace (units_per_core scale)."""
    from perfros_bag.cpu.trace import read_cpu_trace

    if not trace.exists():
        return {}
    tr = read_cpu_trace(trace)
    where = {ln.name: ln.computer for ln in launches}
    per_time: dict[str, dict[float, float]] = {}
    node_time: dict[str, dict[float, float]] = {}
    for t, label, cpu in zip(tr.time.tolist(), tr.node, tr.cpu_percent.tolist(), strict=True):
        comp = where.get(label)
        if comp is None:
            continue
        units = cpu / 100.0 * units_per_core
        per_time.setdefault(comp, {}).setdefault(t, 0.0)
        per_time[comp][t] += units
        node_time.setdefault(label, {}).setdefault(t, 0.0)
        node_time[label][t] += units

    def mean(d: dict[float, float]) -> float:
        vals = sorted(d.items())[1:] or sorted(d.items())  # drop the first round
        return round(sum(v for _, v in vals) / len(vals), 3) if vals else 0.0

    return {"computers": {c: {"cpu": mean(per_time.get(c, {})), "capacity": round(cores[c] * units_per_core, 3)}
                          for c in cores},
            "nodes": {n: mean(d) for n, d in node_time.items()}}


def _write_outputs(out: Path, record: dict[str, Any], system: System, plan: Plan,
                   launches: list[NodeLaunch], system_path: Path | None) -> None:
    import yaml

    save_plan(plan, out / "plan.json")
    entry: dict[str, Any] = {"path": "run.bag", "cpu": "run.cpu.csv",
                             "settings": {ln.name: ln.value for ln in launches if ln.value is not None}}
    manifest: dict[str, Any] = {}
    if system_path is not None:
        manifest["system"] = os.path.relpath(system_path.resolve(), out.resolve())
    manifest["recordings"] = [entry]
    atomic_write_text(out / "manifest.yaml", yaml.safe_dump(manifest, sort_keys=False))
    atomic_write_json(out / "run.json", record)
