"""Run a plan on real ROS 1: roscore, the case-study nodes, ``rosbag record``, a CPU trace.

:func:`run_plan` starts, in order: ``roscore`` on a free port (its own ``ROS_HOME`` under
the output folder), one node per plan entry inside its computer's cgroup
(:mod:`perfros_bag.casestudy.cgroups`), ``perfros-bag record-cpu`` on those nodes, and
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

import contextlib
import functools
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
import xmlrpc.client
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import IO, Any

from perfros_bag.casestudy.cgroups import CpuGroups
from perfros_bag.casestudy.profiles import (
    Calibration,
    NodeLaunch,
    NodeProfile,
    launch_for,
)
from perfros_bag.errors import InputError, PerfrosError
from perfros_bag.fileio import atomic_write_json, atomic_write_text
from perfros_bag.system.plan import Plan
from perfros_bag.system.planfile import plan_document, save_plan
from perfros_bag.system.types import System

RUN_ENV = "PERFROS_CASESTUDY_RUN"
ROSCORE = "roscore"
ROSBAG = "rosbag"
# Debian's rosbag C++ recorder: what `rosbag record` (a Python wrapper) runs; starting it
# directly saves the wrapper's ~1 s of imports.
RECORD_BIN = Path("/usr/lib/rosbag/record")

Progress = Callable[[str, float, float], None]  # (stage, done, total)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Started:
    name: str
    popen: subprocess.Popen[bytes]
    log: IO[bytes]


@dataclass
class Processes:
    """The processes of one run, each in its own session/process group."""

    run_id: str
    env: dict[str, str]
    started: list[Started] = field(default_factory=list)
    seen: dict[int, float] = field(default_factory=dict)  # pid -> create_time of every descendant

    def start(self, name: str, argv: list[str], log_path: Path, cwd: Path | None = None) -> Started:
        log = log_path.open("wb")
        try:
            popen = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                     env=self.env, cwd=cwd, start_new_session=True)
        except OSError as exc:
            log.close()
            raise PerfrosError(f"cannot start {name} ({argv[0]}): {exc.strerror or exc}") from None
        st = Started(name, popen, log)
        self.started.append(st)
        self.remember()
        return st

    def remember(self) -> None:
        """Note every current descendant (roscore's rosmaster/rosout live in other groups)."""
        import psutil

        for st in self.started:
            try:
                proc = psutil.Process(st.popen.pid)
                family = [proc, *proc.children(recursive=True)]
            except psutil.Error:
                continue
            for p in family:
                with contextlib.suppress(psutil.Error):
                    self.seen[p.pid] = p.create_time()

    def stop(self, names: list[str] | None = None, timeout: float = 8.0) -> None:
        """SIGINT the groups (of ``names``, or all, in reverse start order), then escalate."""
        self.remember()
        todo = [st for st in reversed(self.started) if names is None or st.name in names]
        for st in todo:
            _signal_group(st.popen, signal.SIGINT)
        deadline = time.monotonic() + timeout
        for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            for st in todo:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    st.popen.wait(max(0.0, deadline - time.monotonic()))
            still = [st for st in todo if st.popen.poll() is None]
            if not still:
                break
            for st in still:
                _signal_group(st.popen, sig)
            deadline = time.monotonic() + wait
        for st in todo:
            with contextlib.suppress(subprocess.TimeoutExpired):
                st.popen.wait(1.0)
            st.log.close()

    def kill_leftovers(self) -> list[int]:
        """SIGKILL every remembered descendant still alive (same pid and start time)."""
        import psutil

        killed = []
        for pid, created in list(self.seen.items()):
            try:
                p = psutil.Process(pid)
                if abs(p.create_time() - created) > 0.01:
                    continue
                p.kill()
                killed.append(pid)
            except psutil.Error:
                continue
        for pid in killed:
            with contextlib.suppress(psutil.Error):
                psutil.Process(pid).wait(2.0)
        return killed


def _signal_group(popen: subprocess.Popen[bytes], sig: int) -> None:
    if popen.poll() is not None:
        return
    try:
        os.killpg(popen.pid, sig)
    except (ProcessLookupError, PermissionError):
        with contextlib.suppress(OSError):
            popen.send_signal(sig)


def leftover_processes(run_id: str | None = None) -> list[int]:
    """PIDs of live processes started by a case-study run (of ``run_id``, or any)."""
    import psutil

    found = []
    for p in psutil.process_iter(["pid"]):
        try:
            env = p.environ()
        except (psutil.Error, OSError):
            continue
        tag = env.get(RUN_ENV)
        if tag is not None and (run_id is None or tag == run_id) and p.status() != psutil.STATUS_ZOMBIE:
            found.append(p.pid)
    return found


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM/SIGHUP raise KeyboardInterrupt, so they take the same cleanup path as Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _master_state(uri: str) -> tuple[list[Any], list[Any]] | None:
    reply = _master_call(uri, "getSystemState")
    if reply is None:
        return None
    return list(reply[0]), list(reply[1])


def _master_call(uri: str, method: str) -> Any:
    """One ROS master XML-RPC call; None on any failure (not up yet, or not a ROS master:
    another program may have taken the port)."""
    try:
        reply: Any = getattr(xmlrpc.client.ServerProxy(uri), method)("/perfros_launcher")
        code, _msg, value = reply
    except Exception:  # noqa: BLE001 - whatever answers on the port, it is not our master
        return None
    return value if code == 1 else None


def _exited(st: Started) -> str | None:
    return st.name if st.popen.poll() is not None else None


def _start_roscore(procs: Processes, out: Path, timeout: float) -> str:
    """roscore on a free port; retried on another port when the port was taken meanwhile.
    The master must be ours: its PID is a descendant of the roscore we started."""
    import psutil

    for attempt in range(3):
        port = free_port()
        uri = f"http://127.0.0.1:{port}"
        procs.env["ROS_MASTER_URI"] = uri
        core = procs.start(f"roscore{attempt or ''}", [ROSCORE, "-p", str(port)],
                           out / f"roscore{attempt or ''}.log", cwd=out)

        def ours(uri: str = uri, core: Started = core) -> bool:
            pid = _master_call(uri, "getPid")
            if pid is None:
                return False
            try:
                return pid in {c.pid for c in psutil.Process(core.popen.pid).children(recursive=True)}
            except psutil.Error:
                return False

        try:
            _wait("roscore", ours, timeout, functools.partial(_exited, core))
            return uri
        except PerfrosError:
            procs.stop([core.name])
            if attempt == 2:
                raise
    raise AssertionError("unreachable")


def _wait(what: str, check: Callable[[], bool], timeout: float, alive: Callable[[], str | None]) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        dead = alive()
        if dead:
            raise PerfrosError(f"{dead} exited while waiting for {what}")
        if time.monotonic() > deadline:
            raise PerfrosError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.2)


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
    """Cores of CPU time per computer used by the plan (capacity / units_per_core)."""
    caps = {c.name: c.capacity for c in system.computers}
    cores: dict[str, float] = {}
    for name in sorted({pn.computer for pn in plan.nodes.values()}):
        cap = plan.computers[name].capacity if name in plan.computers else None
        if cap is None:
            cap = caps.get(name)
        if cap is None or cap <= 0:
            raise InputError(plan.system, f"computer {name!r} has no capacity to emulate")
        cores[name] = cap / units_per_core
    return cores


def run_plan(system: System, plan: Plan, out: Path, cfg: RunConfig, *,
             overrides: dict[str, float] | None = None, progress: Progress | None = None,
             system_path: Path | None = None) -> dict[str, Any]:
    """Deploy ``plan`` for ``cfg.duration`` seconds of recording; returns run.json's content."""
    for tool in (ROSCORE, ROSBAG):
        if shutil.which(tool) is None:
            raise PerfrosError(f"{tool} not found: install Debian's ROS 1 (apt-get install ros-core python3-rospy python3-rosbag)")
    if not Path("/usr/bin/python3").exists():
        raise PerfrosError("/usr/bin/python3 not found (rospy runs under Debian's python3)")
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("run.bag", "run.bag.active", "run.cpu.csv", "run.host.cpu.csv", "run.json", "manifest.yaml"):
        (out / stale).unlink(missing_ok=True)
    note = progress or (lambda stage, done, total: None)
    calib = cfg.calibration or Calibration(units_per_core=cfg.units_per_core, headroom=cfg.headroom)
    launches = node_launches(system, plan, calib, overrides)
    cores = computer_cores(system, plan, cfg.units_per_core)

    run_id = uuid.uuid4().hex[:10]
    ros_home = out / "ros"
    ros_home.mkdir(exist_ok=True)
    env = dict(os.environ)
    for k in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "ROS_NAMESPACE"):
        env.pop(k, None)
    env["PATH"] = ":".join(p for p in env.get("PATH", "").split(":")
                           if p and not p.startswith(str(Path(sys.prefix)))) or "/usr/bin:/bin"
    env.update({"ROS_IP": "127.0.0.1", "ROS_HOME": str(ros_home),
                "ROS_LOG_DIR": str(ros_home / "log"), RUN_ENV: run_id, "PYTHONUNBUFFERED": "1"})
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
        with _sigterm_as_interrupt():
            # the groups also give the nodes CPU priority over unrelated load: create them
            # uncapped runs too, and set the quotas only when capping
            groups.create(capped=False, quiet=not cfg.cap)
            mode, reason = (groups.mode, groups.reason) if cfg.cap else ("uncapped", "disabled (--no-cap)")
            record["cpu_cap"] = {"mode": mode, "reason": reason, "cgroups": groups.mode,
                                 "cores": cores, "units_per_core": cfg.units_per_core}
            note("roscore", 0, 1)
            uri = _start_roscore(procs, out, cfg.startup_timeout)
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
                state = _master_state(uri)
                if state is None:
                    return False
                pubs = {t: set(who) for t, who in state[0]}
                return all(f"/{ln.name}" in pubs.get(t, set()) for ln in launches for t in ln.publishes)

            _wait("every node to publish", all_publishing, cfg.startup_timeout, nodes_dead)
            if cfg.cap:
                groups.apply()
            note("rosbag", 0, 1)
            procs.start("record-cpu", [sys.executable, "-m", "perfros_bag", "record-cpu", "--quiet",
                                       "--match", f"--run {run_id} ", "--interval", f"{cfg.interval:g}",
                                       "--out", str(trace)], out / "record-cpu.log", cwd=out)
            recorder = [str(RECORD_BIN)] if RECORD_BIN.exists() else [ROSBAG, "record"]
            rec = procs.start("rosbag", [*recorder, "-O", str(bag), *topics, "__name:=perfros_record"],
                              out / "rosbag.log", cwd=out)

            def recording() -> bool:
                state = _master_state(uri)
                if state is None:
                    return False
                subs = {t: set(who) for t, who in state[1]}
                return all("/perfros_record" in subs.get(t, set()) for t in topics)

            _wait("rosbag record to subscribe", recording, cfg.startup_timeout,
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
        record["killed"] = procs.kill_leftovers()
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


def emulated_trace(raw: Path, dest: Path, where: dict[str, str], capacity: dict[str, float],
                   units_per_core: float) -> None:
    """Rewrite the host's psutil trace for the emulated computers.

    The contract normalises a trace as ``cpu_percent / (100 N) * R`` (N = the host's logical
    CPUs, R = the computer's capacity). An emulated computer of capacity R is
    ``R / units_per_core`` cores, so each row of a node on it is scaled by
    ``N * units_per_core / R``: then the contract's formula gives
    ``cpu_percent / 100 * units_per_core`` CPU units, as it should. Rows of processes that
    are not plan nodes are dropped. The raw trace stays beside it (``run.host.cpu.csv``).
    """
    from perfros_bag.cpu.trace import read_cpu_trace, write_cpu_trace

    tr = read_cpu_trace(raw)
    rows = []
    for t, pid, label, proc, cpu, rss in zip(tr.time.tolist(), tr.pid.tolist(), tr.node, tr.process,
                                             tr.cpu_percent.tolist(), tr.rss_bytes.tolist(), strict=True):
        comp = where.get(label)
        if comp is None:
            continue
        rows.append((t, pid, label, proc, cpu * tr.logical_cpus * units_per_core / capacity[comp], rss))
    write_cpu_trace(dest, rows, host=f"{tr.host or 'host'} (emulated computers: cpu_percent scaled by "
                    f"N*{units_per_core:g}/capacity; raw psutil trace: {raw.name})",
                    logical_cpus=tr.logical_cpus, interval_s=tr.interval_s or 0.5)


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


def kill_stale(run_id: str | None = None) -> list[int]:
    """SIGKILL every live process of a case-study run (for ``casestudy cleanup``)."""
    import psutil

    pids = leftover_processes(run_id)
    for pid in pids:
        with contextlib.suppress(psutil.Error):
            psutil.Process(pid).kill()
    for pid in pids:
        with contextlib.suppress(psutil.Error):
            psutil.Process(pid).wait(2.0)
    return pids
