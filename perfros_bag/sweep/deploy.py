"""``deploy``: run a plan on this machine, with the user's launch file, before it goes to the robots.

Each computer of the plan becomes a cgroup of ``capacity / units_per_core`` cores
(:mod:`perfros_bag.rosrun.cgroups`: v1 or v2; ``uncapped``, stated, where cgroups cannot be
made). The launch file runs once with the plan's parameter values (through the ``arg`` or
``param`` of space.yaml that reaches each node), exactly as a ``sweep`` run
(:func:`perfros_bag.sweep.runner.record_run`); once every node is up, each one's process is
moved into its computer's group and the caps are set. The run is recorded (``run.bag``, a
CPU trace rescaled to the emulated computers, ``manifest.yaml``) and validated against
the plan (eq 10, ``validation.json``); ``deploy.json`` says what ran, where, capped or not.
While the nodes run, ``live.json`` (:mod:`perfros_bag.sweep.livestate`) says how to reach
them, for ``watch --deployment``; it is removed when the run ends.
"""

from __future__ import annotations

import math
import os
import shutil
import time
import uuid
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fileio import atomic_write_json
from perfros_bag.sweep.control import CONTROL_FILE, Control
from perfros_bag.sweep.graph import Graph, write_graph
from perfros_bag.sweep.launchfile import check_space, read_launch
from perfros_bag.sweep.livestate import LIVE_FILE, LiveState, write_live
from perfros_bag.sweep.space import Run, Space, Value, arg_text, default_value, load_space

if TYPE_CHECKING:
    from perfros_bag.rosrun.network import Network
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.types import System
    from perfros_bag.validation.eq10 import Validation

DEPLOY_FORMAT = "perfros-bag/deploy-run@1"
#: a node's restart for a new plan resolves the launch file's parameters and the node's command
#: (each within space.yaml's startup_timeout_s), then waits as long for the node to answer:
#: live.json ``restart_timeout_s`` is this many startup timeouts
RESTART_BOUND = 3


@dataclass
class DeployResult:
    record: dict[str, Any]  # deploy.json
    validation: Validation


def plan_run(plan: Plan, space: Space, arg_defaults: dict[str, str | None]) -> Run:
    """The run that sets every varied node to its plan value (its default when the plan
    does not set it); a parameter whose values are all whole numbers gets a whole number."""
    values: dict[str, Value] = {}
    for v in space.vary:
        planned = plan.nodes.get(v.system_name)
        value: Value
        if planned is not None and planned.value is not None:
            value = planned.value
            if all(isinstance(x, int) for x in v.values):
                value = int(round(value))
        else:
            value = default_value(v, arg_defaults)
        values[v.node] = value
    return Run("run", {v.system_name: values[v.node] for v in space.vary},
               {v.arg: arg_text(values[v.node]) for v in space.vary if v.arg is not None},
               {v.param: values[v.node] for v in space.vary if v.param is not None}, 1)


def deploy(plan_path: str | Path, launch_path: str | Path, space_path: str | Path, out: str | Path, *,
           duration: float | None = None, units_per_core: float = 100.0, cap: bool = True,
           tolerance: float | None = None, interval: float = 0.5, net: bool = True,
           system_path: str | Path | None = None,
           progress: Callable[[str, float], None] | None = None) -> DeployResult:
    from perfros_bag.characterisation.manifest import write_manifest
    from perfros_bag.cpu.trace import trace_speed
    from perfros_bag.rosrun.cgroups import CpuGroups, computer_cores, emulated_trace
    from perfros_bag.rosrun.network import Network
    from perfros_bag.rosrun.recorders import require_free_space
    from perfros_bag.sweep.nodelets import check_plan_membership, standalone_nodelets
    from perfros_bag.sweep.runner import checked_nodelets, record_run, require_ros_tools
    from perfros_bag.system.names import system_node_name
    from perfros_bag.system.planfile import is_forced, load_plan, plan_system
    from perfros_bag.validation.eq10 import DEFAULT_TOLERANCE, validate_files

    plan = load_plan(plan_path)
    plan.require_feasible(plan_path, "deploy")
    if not math.isfinite(units_per_core) or units_per_core <= 0:
        raise InputError(None, f"CPU units per core must be a finite number > 0, got {units_per_core:g}")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance >= 0):
        raise InputError(None, f"the tolerance must be a finite number >= 0 (%), got {tolerance:g}")
    space = load_space(space_path).with_duration(duration)
    launch = read_launch(launch_path)
    check_space(launch, space)
    unknown = sorted(v.system_name for v in space.vary if v.system_name not in plan.nodes)
    if unknown:
        warnings.warn(f"{space.path}: node(s) {', '.join(unknown)} not in the plan: run at their default",
                      PerfrosWarning, stacklevel=2)
    system = plan_system(plan, plan_path, system_path)
    require_ros_tools()
    run = plan_run(plan, space, dict(launch.args))
    # the launch file's nodelets: each into a manager it starts, of a class its package
    # exports, on its manager's plan computer (the launch file fixes the membership) unless
    # the plan runs it standalone (membership: choose): then as `nodelet standalone` on its own
    nodelets = checked_nodelets(launch, run.args, space.startup_timeout_s)
    alone = plan.standalone
    check_plan_membership(nodelets, {name: pn.computer for name, pn in plan.nodes.items()}, plan_path, alone)
    run = replace(run, standalone=standalone_nodelets(nodelets, alone, launch.path), keep_managers=True)
    cores = computer_cores(plan, units_per_core)
    outdir = Path(out).absolute()
    if outdir.exists() and not outdir.is_dir():
        raise InputError(outdir, "is not a directory, expected the folder to deploy into")
    # every input is read and checked above: only now may an earlier deployment's files go
    outdir.mkdir(parents=True, exist_ok=True)
    require_free_space(outdir)
    for stale in ("run.bag", "run.cpu.csv", "run.host.cpu.csv", "manifest.yaml", "graph.yaml", "deploy.json",
                  "validation.json", LIVE_FILE, CONTROL_FILE):
        (outdir / stale).unlink(missing_ok=True)
    run_id = uuid.uuid4().hex[:10]
    groups = CpuGroups(run_id, cores)
    where = {name: pn.computer for name, pn in plan.nodes.items()}  # system.yaml's node names
    placed: dict[str, str] = {}
    restarted: dict[str, int] = {}  # ROS node -> its PID since a new plan restarted it (control.json)
    links_before: list[dict[str, Any]] = []
    links_after: list[dict[str, Any]] = []
    throttle: dict[str, dict[str, dict[str, float]]] = {}  # "start"/"end" -> computer -> CFS counters
    end_speed: list[float] = []  # the machine's speed as the recording ended (perfros_bag.cpu.speed)
    media_before: list[dict[str, Any]] = []
    media_after: list[dict[str, Any]] = []
    master: list[str] = []  # the run's master URI, once roscore answers
    live: list[LiveState] = []

    def place(graph: Graph) -> None:
        """Move every planned node into its computer's group, then cap the groups."""
        for node in graph.nodes:
            computer = where.get(system_node_name(node.name), "")
            procs_file = groups.procs_file(computer)
            if procs_file is None or node.pid is None:
                continue
            try:
                procs_file.write_text(str(node.pid))
            except OSError as exc:
                raise InputError(None, f"cannot move node {node.name} into {procs_file.parent}: {exc}") from None
            placed[node.name] = computer
        if cap:
            groups.apply()
        live[:] = [LiveState(
            run_id, os.getpid(), master[0] if master else "", network.master_computer() if network.emulated else None,
            str(Path(plan_path).absolute()),
            None if system is None or system.source is None else str(Path(system.source).absolute()),
            units_per_core, dict(network.namespaces), {c: str(d) for c, d in groups.dirs.items()}, dict(cores),
            cap and groups.capped,
            {n.name: {"pid": n.pid, "computer": where.get(system_node_name(n.name))} for n in graph.nodes
             if n.launched}, links=_links_in_force(network), values=dict(run.values),
            restart_timeout_s=RESTART_BOUND * space.startup_timeout_s)]
        write_live(outdir / LIVE_FILE, live[0])

    def restarting(nodes: list[str]) -> None:
        """A new plan about to restart ``nodes`` (control.json): live.json says so first, so a
        watch takes their absence for a restart, not a death."""
        if live:
            now = time.time()
            live[0].restarting = {n: now for n in nodes}
            write_live(outdir / LIVE_FILE, live[0])

    def applied(pids: dict[str, int]) -> None:
        """A new plan applied (control.json): the restarted nodes' PIDs and computers in live.json."""
        if live:
            live[0].restarting = {}
        for name, pid in pids.items():
            placed[name] = control.where.get(system_node_name(name), placed.get(name, ""))
            restarted[name] = pid
            if live:
                live[0].nodes[name] = {"pid": pid, "computer": placed[name]}
        if live:
            live[0].links = _links_in_force(network)
            live[0].values = dict(control.run.values)
            live[0].plan_in_force = control.plan_path
            write_live(outdir / LIVE_FILE, live[0])

    def window(edge: str) -> None:
        """The links', the shared media's and the groups' counters as the recording starts and
        ends; as it ends, the machine's speed again (record-cpu measured it as the run began)."""
        stats = [{**s, "t": time.monotonic()} for s in network.link_stats()]
        media = [{**s, "t": time.monotonic()} for s in network.media_stats()]
        (links_before if edge == "start" else links_after)[:] = stats
        (media_before if edge == "start" else media_after)[:] = media
        throttle[edge] = {c: groups.throttled(c) for c in cores}
        if edge == "end":
            from perfros_bag.cpu.speed import measure_speed

            end_speed.append(measure_speed().factor)

    network = Network(f"d{run_id}", system if system is not None and net else _no_links(plan))
    control = Control(outdir, space, dict(launch.args), run, dict(where), groups, units_per_core, cap, applied,
                      network if network.emulated or net else None, on_restarting=restarting,
                      nodelets=nodelets, standalone=set(alone))
    groups.create(capped=False, quiet=not cap)
    mode, reason = (groups.mode, groups.reason) if cap else ("uncapped", "capping not asked for")
    try:
        network.create()
        if not net:
            network.reason = "link emulation not asked for"
        elif system is None:
            network.reason = "the plan's system was not found: its links are unknown"
        described = network.describe()
        graph = record_run(launch, space, run, outdir, interval=interval, progress=progress, run_id=run_id,
                           on_graph=place, network=network, where=where, on_window=window, on_master=master.append,
                           on_tick=control.tick)
    finally:
        (outdir / LIVE_FILE).unlink(missing_ok=True)
        (outdir / CONTROL_FILE).unlink(missing_ok=True)
        left = groups.remove()
        net_left = network.remove()
    host_trace = outdir / "run.host.cpu.csv"
    shutil.move(outdir / "run.cpu.csv", host_trace)
    by_ros_name = {n.name: where[system_node_name(n.name)] for n in graph.nodes
                   if system_node_name(n.name) in where}
    emulated_trace(host_trace, outdir / "run.cpu.csv", by_ros_name,
                   {c: n * units_per_core for c, n in cores.items()}, units_per_core)
    write_graph(outdir / "graph.yaml", graph)
    speed = trace_speed(host_trace)  # measured by record-cpu as the run began
    entry: dict[str, Any] = {"path": "run.bag", "cpu": "run.cpu.csv", "settings": dict(run.values)}
    if speed is not None:
        entry["speed_factor"] = round(speed, 4)
    write_manifest(outdir / "manifest.yaml", [entry])
    # after a re-plan (control.json), the plan in force at the end is the one the run is judged against
    in_force = control.plan_path
    validation = validate_files(outdir / "run.bag", in_force or plan_path, cpu=[outdir / "run.cpu.csv"],
                                tolerance=DEFAULT_TOLERANCE if tolerance is None else tolerance,
                                plan=None if in_force else plan)
    atomic_write_json(outdir / "validation.json", validation.to_dict())
    record: dict[str, Any] = {
        "format": DEPLOY_FORMAT, "run_id": run_id, "plan": str(plan_path), "forced": is_forced(plan),
        "launch": str(launch.path), "speed_factor": None if speed is None else round(speed, 4),
        "speed_factor_end": round(end_speed[-1], 4) if end_speed else None,
        "duration_s": space.duration_s, "values": dict(run.values), "args": dict(run.args),
        "params": dict(run.params),
        "cpu_cap": {"mode": mode, "reason": reason, "cgroups": groups.mode, "cores": cores,
                    "units_per_core": units_per_core, **groups.cap_record()},
        "throttling": {c: {k: v - throttle.get("start", {}).get(c, {}).get(k, 0.0) for k, v in end.items()}
                       for c, end in throttle.get("end", {}).items()},
        "network": {**described, "links_measured": _link_use(links_before, links_after, network),
                    "media_measured": _medium_use(media_before, media_after, network)},
        "nodes": {n.name: {"pid": restarted.get(n.name, n.pid),
                           "computer": placed.get(n.name, where.get(system_node_name(n.name))),
                           **({"standalone": True} if system_node_name(n.name) in control.standalone else {})}
                  for n in graph.nodes if n.launched},
        "replans": control.applied,
        "validated_against": str(in_force or plan_path),
        "leftover_cgroups": [str(p) for p in left],
        "leftover_namespaces": net_left,
    }
    atomic_write_json(outdir / "deploy.json", record)
    return DeployResult(record, validation)


def _links_in_force(network: Network) -> list[dict[str, Any]]:
    """Every link of the run with the bandwidth it is shaped to now (live.json ``links``)."""
    return [{"between": list(link.between), "bandwidth_kBps": link.bandwidth_kBps} for link in network.system.links]


def _no_links(plan: Plan) -> System:
    """A system of the plan's computers without links: a network with nothing to emulate."""
    from perfros_bag.system.types import Computer, System

    return System(tuple(Computer(name, "robot", c.capacity) for name, c in plan.computers.items()), ())


def _link_use(before: list[dict[str, Any]], after: list[dict[str, Any]], network: Network) -> list[dict[str, Any]]:
    """Per link direction, what its qdisc passed during the recording: kB/s sent against the
    shaped rate, packets dropped, times the rate held a packet back."""
    from perfros_bag.rosrun.network import tbf_rate_bit

    first = {(s["link"], s["from"]): s for s in before}
    rows = []
    for s in after:
        b = first.get((s["link"], s["from"]))
        if b is None:
            continue
        rate = tbf_rate_bit(network.system.links[s["link"]].bandwidth_kBps) / 8000.0
        rows.append({"link": s["link"], "from": s["from"], "to": s["to"], **_qdisc_use(b, s, rate)})
    return rows


def _qdisc_use(before: dict[str, Any], after: dict[str, Any], rate_kBps: float) -> dict[str, Any]:
    """What a qdisc passed between two readings of its counters: kB/s sent against its shaped
    rate, packets dropped, times the rate held a packet back."""
    seconds = after["t"] - before["t"]
    kbps = (after["bytes"] - before["bytes"]) / 1000.0 / seconds if seconds > 0 else 0.0
    return {"sent_kBps": round(kbps, 3), "shaped_kBps": rate_kBps,
            "utilisation": round(kbps / rate_kBps, 4) if rate_kBps else None,
            "drops": after["drops"] - before["drops"], "overlimits": after["overlimits"] - before["overlimits"]}


def _medium_use(before: list[dict[str, Any]], after: list[dict[str, Any]], network: Network) -> list[dict[str, Any]]:
    """Per emulated shared medium, what its IFB's qdisc passed during the recording (both
    directions of all its links): kB/s against the medium's shaped rate, drops, overlimits."""
    from perfros_bag.rosrun.network import tbf_rate_bit

    first = {s["medium"]: s for s in before}
    rows = []
    for s in after:
        b = first.get(s["medium"])
        if b is None:
            continue
        rate = tbf_rate_bit(network.system.medium[s["medium"]].bandwidth_kBps) / 8000.0
        rows.append({"medium": s["medium"], "hub": s["hub"], **_qdisc_use(b, s, rate)})
    return rows
