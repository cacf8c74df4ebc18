"""``sweep``: run the user's launch file once per setting of ``space.yaml`` and record each run.

Per run (:func:`record_run`), in ``DIR/.sweep/<run>/`` (removed once the run is done): a
roscore of its own (free loopback port, own ``ROS_HOME``), the ROS parameters of the run
set on it, Debian's ``roslaunch -p PORT APP.launch arg:=value ...``; then

1. every node ``roslaunch --nodes`` lists registers with the master;
2. a probe ``rosbag record -a`` subscribes to everything (nodes that publish only when
   someone listens start working), and every topic the launch's nodes advertise must carry
   a message (the publishers' ``getBusStats``);
3. ``settle_s`` later the graph is taken from the master (``graph.yaml``), ``record-cpu``
   starts on the nodes and a second ``rosbag record -a`` replaces the probe for
   ``duration_s`` seconds;
4. everything is stopped (SIGINT, then SIGTERM, SIGKILL; every process carries the run tag,
   see :mod:`perfros_bag.rosrun.processes`); the CPU trace is relabelled with the ROS node
   names by PID; ``<run>.bag`` and ``<run>.cpu.csv`` are moved into ``DIR``.

:func:`sweep` does every run not yet in ``DIR/manifest.yaml`` and rewrites the manifest
(atomically) after each one, so Ctrl-C or an error keeps every finished run. A failing run
raises a :class:`PerfrosError` ``run NAME: cause``.

With ``replay:`` (:mod:`perfros_bag.sweep.replay`) every run of the design is done at every
play-rate factor: the launch file's nodes but the replaced ones start one by one as
``roslaunch --args NODE`` says (roslaunch cannot leave a node out; the path a run across
namespaces takes), after the launch file's parameters; one ``rosbag play`` per replaced node,
named as that node, plays its topics looping at the factor; the manifest gives each replaced
node its replayed rate as its setting.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import statistics
import time
import uuid
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.characterisation.manifest import (
    SWEEP_UNITS_PER_CORE,
    parse_manifest,
    write_manifest,
)
from perfros_bag.errors import InputError, PerfrosError
from perfros_bag.fileio import atomic_write_text, read_yaml
from perfros_bag.rosrun.master import (
    bus_stats,
    master_call,
    master_state,
    parse_bus_stats,
    port_of,
    start_roscore,
)
from perfros_bag.rosrun.processes import (
    Processes,
    Started,
    kill_stale,
    ros_env,
    sigterm_as_interrupt,
    wait_for,
)
from perfros_bag.rosrun.recorders import (
    cpu_ready_path,
    merge_bags,
    require_free_space,
    start_record_cpu,
    start_rosbag,
)
from perfros_bag.sweep.graph import Graph, capture_graph, write_graph
from perfros_bag.sweep.launchfile import (
    ROSLAUNCH,
    LaunchFile,
    NodeCommand,
    check_space,
    launch_argv,
    launch_nodes,
    launch_params,
    node_command,
    read_launch,
)
from perfros_bag.sweep.nodelets import Nodelet, with_membership
from perfros_bag.sweep.space import PLAYER_TOPICS, Run, Space, load_space, plan_runs

if TYPE_CHECKING:
    from perfros_bag.rosrun.network import Network
    from perfros_bag.sweep.replay import Inspected, Prepared

WORK = ".sweep"
PROBE_NODE = "perfros_probe"
RECORD_NODE = "perfros_record"
OWN_NODES = frozenset({f"/{PROBE_NODE}", f"/{RECORD_NODE}"})
#: Seconds the per-computer recorders of a run with emulated links run before the window
#: opens: their subscriptions cross the shaped links, and the first messages of a topic reach
#: the bag in one late burst (measured: 13 camera frames within 1 ms, 1.3 s after their stamps).
RECORDER_WARMUP_S = 2.0
#: Topics that need not carry a message for a run to start (roscore's log topics).
QUIET_TOPICS = frozenset({"/rosout", "/rosout_agg"})
_DIED = re.compile(r"\[([^\]\s]+)-\d+\] process has died \[pid (\d+), exit code (-?\d+)")
_NOT_LAUNCHED = re.compile(r"ERROR: cannot launch node of type \[([^\]]+)\]: ?(.*)")

#: progress(run index, runs, run name, stage, fraction of the run's recording done)
Progress = Callable[[int, int, str, str, float], None]


@dataclass
class SweepResult:
    runs: list[str]  # every run of the space, in order
    recorded: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    repeated: list[str] = field(default_factory=list)  # recorded again nearer the median speed


def computer_name() -> str:
    """This machine's name as a system.yaml computer."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", socket.gethostname()) or "host"


def require_ros_tools() -> None:
    for tool in ("roscore", ROSLAUNCH, "rosbag"):
        if shutil.which(tool) is None:
            raise PerfrosError(f"{tool} not found: install Debian's ROS 1 "
                               "(apt-get install ros-core python3-rospy python3-rosbag)")


def median_speed(entries: Mapping[str, Mapping[str, Any]]) -> float | None:
    """The median ``speed_factor`` of manifest entries (None when none has one)."""
    found = [float(e["speed_factor"]) for e in entries.values() if e.get("speed_factor")]
    return statistics.median(found) if found else None


def off_speed(entries: Mapping[str, Mapping[str, Any]], median: float | None) -> list[str]:
    """The entries (keys) whose ``speed_factor`` is not the ``median``'s speed
    (:func:`perfros_bag.cpu.speed.same_speed`): recorded while the machine ran at another speed
    than the sweep's other runs."""
    from perfros_bag.cpu.speed import same_speed

    if median is None:
        return []
    return [k for k, e in entries.items() if e.get("speed_factor") and not same_speed(float(e["speed_factor"]), median)]


def sweep(launch_path: str | Path, space_path: str | Path, out: str | Path, *, duration: float | None = None,
          interval: float = 0.5, progress: Progress | None = None, repeat_off_speed: int = 0) -> SweepResult:
    """Record every run of ``space_path`` not yet recorded in ``out``. ``repeat_off_speed``:
    then record again, up to that many times each, every run whose machine speed reference
    is off the sweep's median (:func:`off_speed`), keeping the recording nearer the median."""
    from perfros_bag.cpu.trace import trace_speed

    space = load_space(space_path).with_duration(duration)
    launch = read_launch(launch_path)
    check_space(launch, space)
    require_ros_tools()
    runs = plan_runs(space, launch.args)
    outdir = Path(out).absolute()
    if outdir.exists() and not outdir.is_dir():
        raise InputError(outdir, "is not a directory, expected the folder to record into")
    inspected = _inspect_replay(launch, space, runs[0])
    runs += _standalone_runs(launch, space, runs)
    outdir.mkdir(parents=True, exist_ok=True)
    require_free_space(outdir)
    manifest_path = outdir / "manifest.yaml"
    system_ref, entries = _finished_runs(manifest_path)
    copy = outdir / "space.yaml"  # what was varied, for init (parameter names and units)
    if not copy.exists() or not copy.samefile(space.path):
        atomic_write_text(copy, space.path.read_text(encoding="utf-8"))
    result = SweepResult([r.name for r in runs])
    note = progress or (lambda i, n, name, stage, frac: None)
    prepared: Prepared | None = None
    warned = False
    for i, run in enumerate(runs):
        if f"{run.name}.bag" in entries:
            result.skipped.append(run.name)
            note(i, len(runs), run.name, "skipped", 1.0)
            continue
        for stale in (f"{run.name}.bag", f"{run.name}.cpu.csv"):
            (outdir / stale).unlink(missing_ok=True)

        def stage(name: str, frac: float, i: int = i, run: Run = run) -> None:
            note(i, len(runs), run.name, name, frac)

        settings: dict[str, Any] = dict(run.values)
        if inspected is not None and run.factor is not None:
            if prepared is None:  # converted once, when a run needs it (cached in DIR/.replay)
                from perfros_bag.sweep.replay import prepare

                note(i, len(runs), run.name, "converting the recording", 0.0)
                prepared = prepare(inspected, outdir)
            settings.update(inspected.settings(run.factor))
        graph = record_run(launch, space, run, outdir, interval=interval, progress=stage, replay=prepared)
        if inspected is not None and not warned:
            warned = True
            _warn_unsubscribed(graph, inspected)
        entries[f"{run.name}.bag"] = {"path": f"{run.name}.bag", "cpu": f"{run.name}.cpu.csv",
                                      "computer": computer_name(), "units_per_core": SWEEP_UNITS_PER_CORE,
                                      "settings": settings}
        if run.standalone:
            from perfros_bag.system.names import system_node_name

            entries[f"{run.name}.bag"]["standalone"] = [system_node_name(n) for n in run.standalone]
        speed = trace_speed(outdir / f"{run.name}.cpu.csv")  # measured by record-cpu as the run began
        if speed is not None:
            entries[f"{run.name}.bag"]["speed_factor"] = round(speed, 4)
        write_manifest(manifest_path, list(entries.values()), system_ref)
        if not run.standalone or not (outdir / "graph.yaml").exists():  # the graph with the managers
            write_graph(outdir / "graph.yaml", graph)
        result.recorded.append(run.name)
        note(i, len(runs), run.name, "done", 1.0)
    if repeat_off_speed > 0:
        _repeat_off_speed(launch, space, runs, outdir, entries, system_ref, repeat_off_speed, interval, prepared,
                          inspected, result, note)
    with contextlib.suppress(OSError):
        (outdir / WORK).rmdir()  # only when empty: a failed run's logs stay
    return result


def _repeat_off_speed(launch: LaunchFile, space: Space, runs: list[Run], outdir: Path,
                      entries: dict[str, dict[str, Any]], system_ref: str | None, times: int, interval: float,
                      prepared: Prepared | None, inspected: Inspected | None, result: SweepResult,
                      note: Progress) -> None:
    """Record each off-speed run again (up to ``times``) into ``DIR/.respeed``; a repeat nearer
    the median replaces the run's bag and trace (each moved in whole, then the manifest
    rewritten), a farther one is deleted. Ctrl-C or an error keeps the recordings so far."""
    from perfros_bag.cpu.speed import speed_distance
    from perfros_bag.cpu.trace import trace_speed

    by_name = {f"{r.name}.bag": r for r in runs}
    median = median_speed(entries)
    spare = outdir / ".respeed"
    for _ in range(times):
        todo = [k for k in off_speed(entries, median) if k in by_name]
        if not todo:
            break
        for k in todo:
            run = by_name[k]
            i = runs.index(run)
            note(i, len(runs), run.name, f"again: speed {entries[k]['speed_factor']:g} vs the sweep's {median:g}", 0.0)
            spare.mkdir(exist_ok=True)
            if inspected is not None and run.factor is not None and prepared is None:
                from perfros_bag.sweep.replay import prepare

                prepared = prepare(inspected, outdir)
            record_run(launch, space, run, spare, interval=interval, replay=prepared)
            speed = trace_speed(spare / f"{run.name}.cpu.csv")
            old = float(entries[k]["speed_factor"])
            if speed is not None and median is not None and speed_distance(speed, median) < speed_distance(old, median):
                for suffix in (".bag", ".cpu.csv"):
                    os.replace(spare / f"{run.name}{suffix}", outdir / f"{run.name}{suffix}")
                entries[k]["speed_factor"] = round(speed, 4)
                write_manifest(outdir / "manifest.yaml", list(entries.values()), system_ref)
                result.repeated.append(run.name)
            for suffix in (".bag", ".cpu.csv"):
                (spare / f"{run.name}{suffix}").unlink(missing_ok=True)
            note(i, len(runs), run.name, "done", 1.0)
    for empty in (spare / WORK, spare):  # only when empty: a failed run's logs stay
        with contextlib.suppress(OSError):
            empty.rmdir()


def _inspect_replay(launch: LaunchFile, space: Space, run: Run) -> Inspected | None:
    """The replay's recording, read before anything starts (:func:`inspect_recording`), and
    its replaced nodes checked against the launch file's (``roslaunch --nodes``)."""
    if space.replay is None:
        return None
    import tempfile

    from perfros_bag.rosrun.processes import ros_env
    from perfros_bag.sweep.replay import inspect_recording

    inspected = inspect_recording(space.replay)
    with tempfile.TemporaryDirectory(prefix="perfros-nodes-") as home:
        env = ros_env("nodes-" + uuid.uuid4().hex[:10], Path(home))
        nodes = launch_nodes(launch, run.args, env, space.startup_timeout_s)
    missing = [n for n in space.replay.replaces if n not in nodes]
    if missing:
        raise InputError(space.path, f"replay.replaces: node(s) {', '.join(missing)} not in {launch.path} "
                         f"(its nodes: {', '.join(nodes)})")
    return inspected


def _standalone_runs(launch: LaunchFile, space: Space, runs: list[Run]) -> list[Run]:
    """The launch file's nodelets checked before anything starts (each loaded into a manager
    it starts, of a type its package exports: :func:`~perfros_bag.sweep.nodelets.check_nodelets`)
    and, when it loads any, one more run with every nodelet standalone at the defaults: what
    splits the managers' CPU among their nodelets (:mod:`perfros_bag.characterisation.containers`)."""
    from dataclasses import replace

    from perfros_bag.sweep.space import arg_text, default_value

    values = {v.system_name: default_value(v, launch.args) for v in space.vary}
    args = {v.arg: arg_text(values[v.system_name]) for v in space.vary if v.arg is not None}
    nodelets = checked_nodelets(launch, {**runs[0].args, **args}, space.startup_timeout_s)
    if not nodelets or space.replay is not None:
        return []
    base = next((r for r in runs if dict(r.values) == values), None)
    return [replace(runs[0], name=f"{base.name if base is not None else 'defaults'}__standalone", values=values,
                    args=args, params={v.param: values[v.system_name] for v in space.vary if v.param is not None},
                    repeat=1, standalone=tuple(sorted(nodelets)))]


def checked_nodelets(launch: LaunchFile, args: Mapping[str, str], timeout: float) -> dict[str, Nodelet]:
    """The launch file's nodelets with ``args``, as roslaunch resolves it, each loaded into a
    manager the file starts and of a class its package exports
    (:func:`~perfros_bag.sweep.nodelets.check_nodelets`): one :class:`InputError` otherwise.
    Starts nothing (roslaunch's loader only, in a throwaway ROS home)."""
    import tempfile

    from perfros_bag.rosrun.processes import ros_env
    from perfros_bag.sweep.launchfile import resolve_launch
    from perfros_bag.sweep.nodelets import check_nodelets

    with tempfile.TemporaryDirectory(prefix="perfros-nodelets-") as home:
        env = ros_env("nodelets-" + uuid.uuid4().hex[:10], Path(home))
        resolved = resolve_launch(launch, [dict(args)], env, timeout)[0]
    if resolved.error is not None:
        raise InputError(launch.path, f"roslaunch cannot load it: {resolved.error}")
    return check_nodelets(resolved, launch.path)


def _warn_unsubscribed(graph: Graph, inspected: Inspected) -> None:
    """A warning per replayed topic no launched node subscribes to (in the run's graph)."""
    import warnings

    from perfros_bag.errors import PerfrosWarning

    stands = {s.node for s in inspected.stands}
    launched = {n.name for n in graph.nodes if n.launched} - stands
    for t in graph.topics:
        if t.name in inspected.topics and not set(t.subscribers) & launched:
            warnings.warn(PerfrosWarning(f"replay: topic {t.name} is replayed but no launched node subscribes to it"),
                          stacklevel=2)


def _finished_runs(manifest_path: Path) -> tuple[str | None, dict[str, dict[str, Any]]]:
    """What a manifest already in the folder holds, read once: the ``system:`` it names
    (kept when sweep rewrites it) and its entries whose recording is still there (by path,
    in order). A damaged manifest is an error, never overwritten."""
    if not manifest_path.exists():
        return None, {}
    data = read_yaml(manifest_path)
    parse_manifest(data, manifest_path)
    system = data.get("system")
    kept: dict[str, dict[str, Any]] = {}
    for item in data.get("recordings") or []:
        entry = {"path": item} if isinstance(item, str) else dict(item)
        if (manifest_path.parent / entry["path"]).exists():
            kept[entry["path"]] = entry
    return (system if isinstance(system, str) else None), kept


@dataclass
class _Watch:
    """What must stay alive during a run, and how to say what died."""

    launcher: Started | None  # roslaunch; None when the nodes were started one by one
    log: Path
    others: list[Started] = field(default_factory=list)
    pids: dict[str, tuple[int, float]] = field(default_factory=dict)  # node -> (pid, create_time)

    def failure(self) -> str | None:
        import psutil

        died = _died_line(self.log)
        if died:
            return died
        if self.launcher is not None and self.launcher.popen.poll() is not None:
            cause = _last_error(self.log)
            return (f"roslaunch ({cause + '; ' if cause else ''}"
                    f"exit code {self.launcher.popen.returncode}; see {self.log})")
        for st in self.others:
            if st.popen.poll() is not None:
                cause = _last_error(Path(st.log.name))
                return f"{st.name} ({cause + '; ' if cause else ''}exit code {st.popen.returncode}; see {st.log.name})"
        for node, (pid, created) in self.pids.items():
            try:
                p = psutil.Process(pid)
                alive = abs(p.create_time() - created) < 0.01 and p.status() != psutil.STATUS_ZOMBIE
            except psutil.Error:
                alive = False
            if not alive:
                return f"node {node} (pid {pid}; see {self.log})"
        return None


def _log_text(log: Path) -> str:
    """A log's text without terminal colour codes ('' when unreadable)."""
    try:
        return re.sub(r"\x1b\[[0-9;]*m", "", log.read_text(errors="replace"))
    except OSError:
        return ""


def _last_error(log: Path) -> str | None:
    """A log's last error line, without ROS's ``[ERROR] [stamp]:`` prefix."""
    lines = [x.strip() for x in _log_text(log).splitlines()]
    last = next((x for x in reversed(lines) if re.search(r"error|exception", x, re.IGNORECASE)), None)
    return None if last is None else re.sub(r"^\[ERROR\] \[[0-9.]+\]:\s*", "", last)


def _died_line(log: Path) -> str | None:
    text = _log_text(log)
    m = _DIED.search(text)
    if m is not None:
        return f"node {m.group(1)} (pid {m.group(2)}, exit code {m.group(3)}; see {log})"
    m = _NOT_LAUNCHED.search(text)
    if m is not None:  # roslaunch goes on without it: it never ran, so it did not "exit"
        cause = m.group(2).strip().rstrip(".")
        hint = missing_package(m.group(1))
        raise PerfrosError(f"roslaunch cannot launch node of type [{m.group(1)}]"
                           f"{': ' + cause if cause else ''}{'; ' + hint if hint else ''} (see {log})")
    return None


#: where Debian's ROS 1 packages put a package's package.xml and its node executables
DEBIAN_SHARE, DEBIAN_LIB = Path("/usr/share"), Path("/usr/lib")


def missing_package(node_type: str, share: Path | None = None, lib: Path | None = None) -> str | None:
    """Why roslaunch may not find ``pkg/type``, as far as Debian's layout tells: the node's
    executable installed (``/usr/lib/<pkg>/<type>``) but not the package's ``package.xml``
    (``/usr/share/<pkg>``, which Debian ships in ``lib<pkg>-dev`` for C++ packages, e.g.
    topic_tools' in libtopic-tools-dev), or no trace of the package at all; None when both are there."""
    pkg, _, exe = node_type.partition("/")
    if not pkg or not exe or "/" in exe or pkg in (".", ".."):
        return None
    share, lib = share or DEBIAN_SHARE, lib or DEBIAN_LIB
    has_xml = (share / pkg / "package.xml").is_file()
    has_exe = (lib / pkg / exe).is_file()
    if has_xml and has_exe:
        return None
    dev = f"lib{pkg.replace('_', '-')}-dev"
    known = debian_package_known(dev)
    if has_exe:
        where = f"Debian ships it in {dev} (apt-get install {dev})" if known else "not installed"
        return (f"{lib / pkg / exe} is installed but not {share / pkg / 'package.xml'}, which roslaunch needs to "
                f"find the package: {where}")
    if has_xml:
        return f"the package {pkg} has no executable {exe} in {lib / pkg}"
    return f"the ROS package {pkg} is not installed" + (f" (Debian: apt-get install {dev})" if known else "")


def debian_package_known(name: str) -> bool:
    """Does apt know a package ``name`` (installed or installable)? False without apt."""
    import subprocess

    apt = shutil.which("apt-cache")
    if apt is None:
        return False
    try:
        done = subprocess.run([apt, "show", "--no-all-versions", name], capture_output=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return False
    return done.returncode == 0 and bool(done.stdout.strip())


def record_run(launch: LaunchFile, space: Space, run: Run, out: Path, *, interval: float = 0.5,
               progress: Callable[[str, float], None] | None = None, run_id: str | None = None,
               on_graph: Callable[[Graph], None] | None = None, network: Network | None = None,
               where: Mapping[str, str] | None = None, on_window: Callable[[str], None] | None = None,
               replay: Prepared | None = None, on_master: Callable[[str], None] | None = None,
               on_tick: Callable[[Restarter], None] | None = None) -> Graph:
    """Record one run into ``out/<run>.bag`` and ``out/<run>.cpu.csv``; returns its graph.
    ``on_graph`` is called with the graph (every node up, with its PID) before recording
    starts; ``on_window`` with ``"start"`` and ``"end"`` as the recording's ``duration_s``
    begins and ends; ``on_master`` with the master's URI once roscore answers; ``on_tick``
    about four times a second while recording, with a :class:`Restarter` (runs across
    emulated computers only); ``run_id`` tags the run's processes (default: a new one).

    With an emulated ``network`` (:class:`~perfros_bag.rosrun.network.Network`, made by the
    caller) the run happens across its namespaces: roscore in the namespace of
    :meth:`Network.master_computer`, each node started as ``roslaunch --args`` says, in the
    namespace of its computer (``where``: node as system.yaml names it -> computer; others
    go with the master), and one ``rosbag record`` per computer of the topics published there, so that
    recording adds no traffic to a link; their bags are merged into one.

    With ``replay`` (:func:`perfros_bag.sweep.replay.prepare`) and a run with a ``factor``,
    the replaced nodes are not started: a ``rosbag play`` per replaced node stands in for it."""
    note = progress or (lambda stage, frac: None)
    work = out / WORK / run.name
    if work.exists():
        shutil.rmtree(work)
    ros_home = work / "ros"
    ros_home.mkdir(parents=True)
    run_id = run_id or uuid.uuid4().hex[:10]
    procs = Processes(run_id, ros_env(run_id, ros_home))
    timeout = space.startup_timeout_s
    interrupted = False
    try:
        with sigterm_as_interrupt():
            try:
                if network is not None and network.emulated:
                    spread = _Spread(network, dict(where or {}))
                    with network.inside(spread.master):
                        graph = _record(launch, space, run, work, procs, timeout, interval, note, on_graph,
                                        spread, on_window, on_master=on_master, on_tick=on_tick)
                else:
                    graph = _record(launch, space, run, work, procs, timeout, interval, note, on_graph,
                                    on_window=on_window, replay=replay if run.factor is not None else None,
                                    on_master=on_master)
            except PerfrosError as exc:
                raise PerfrosError(f"run {run.name}: {exc}") from None
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        note("stopping", 1.0)
        procs.stop()
        procs.kill_leftovers()
        kill_stale(run_id)
        if interrupted:  # an error keeps the logs the message points to
            shutil.rmtree(work, ignore_errors=True)
    try:
        trace = _node_trace(work / "host.cpu.csv", graph)
        shutil.move(work / "run.bag", out / f"{run.name}.bag")
        shutil.move(trace, out / f"{run.name}.cpu.csv")
    except OSError as exc:
        (out / f"{run.name}.bag").unlink(missing_ok=True)
        raise PerfrosError(f"run {run.name}: cannot keep the recording in {out}: {exc.strerror or exc}") from None
    shutil.rmtree(work, ignore_errors=True)
    return graph


@dataclass
class _Spread:
    """A run across emulated computers (see :func:`record_run`)."""

    network: Network
    where: dict[str, str]  # node as system.yaml names it -> computer
    master: str = field(init=False)  # where roscore runs (Network.master_computer)

    def __post_init__(self) -> None:
        self.master = self.network.master_computer()

    def computer(self, node: str) -> str:
        """The computer of ROS node ``node`` (``where`` names nodes as system.yaml does)."""
        from perfros_bag.system.names import system_node_name

        return self.where.get(system_node_name(node), self.master)

    def env(self, computer: str, uri: str) -> list[str]:
        """``env`` assignments for a process on ``computer`` (its ROS_IP, the run's master)."""
        addresses = self.network.ros_addresses(computer, self.master, port_of(uri))
        return [f"{k}={v}" for k, v in addresses.items()]


def _nodelets(launch: LaunchFile, args: Mapping[str, str], env: Mapping[str, str],
              timeout: float) -> tuple[dict[str, Nodelet], set[str]]:
    """The launch file's nodelets and nodelet managers with ``args`` (roslaunch's resolution)."""
    from perfros_bag.sweep.launchfile import resolve_launch
    from perfros_bag.sweep.nodelets import managers_of, nodelets_of

    resolved = resolve_launch(launch, [args], env, timeout)[0]
    return nodelets_of(resolved), managers_of(resolved)


def _start_nodes(launch: LaunchFile, run: Run, nodes: list[str], spread: _Spread | None, uri: str, work: Path,
                 procs: Processes, timeout: float, standalone: frozenset[str] = frozenset()) -> list[Started]:
    """Each node (in its computer's namespace with a ``spread``), as ``roslaunch --args``
    would start it, after the launch file's parameters (``roslaunch --dump-params``) are set
    on the master; a nodelet named in ``standalone`` as ``nodelet standalone``."""
    with ThreadPoolExecutor(max_workers=4) as pool:
        params = pool.submit(launch_params, launch, run.args, dict(procs.env), timeout)
        commands = list(pool.map(lambda n: node_command(launch, n, run.args, dict(procs.env), timeout), nodes))
        for name, value in params.result().items():
            if master_call(uri, "setParam", name, value) is None:
                raise PerfrosError(f"the master did not take the launch file's parameter {name}")
    return [procs.start(cmd.node, _node_argv(cmd, spread, uri, standalone), work / f"node{i}.log",
                        cwd=Path(procs.env["ROS_HOME"])) for i, cmd in enumerate(commands)]


def _node_argv(cmd: NodeCommand, spread: _Spread | None, uri: str,
               standalone: frozenset[str] = frozenset()) -> list[str]:
    """A node's command line as ``roslaunch --args`` gave it (a nodelet named in
    ``standalone`` as ``nodelet standalone``), in its computer's namespace."""
    from perfros_bag.sweep.nodelets import standalone_argv

    argv = ["env", *(f"{k}={v}" for k, v in cmd.env.items())]
    words = standalone_argv(cmd.argv) if cmd.node in standalone else list(cmd.argv)
    if spread is None:
        return argv + words
    comp = spread.computer(cmd.node)
    return spread.network.wrap(comp, [*argv, *spread.env(comp, uri), *words])


@dataclass
class Restarter:
    """Restarts launched nodes of a run across emulated computers while it records
    (``deploy``'s control file): those of one plan together, the others and the master untouched."""

    launch: LaunchFile
    spread: _Spread
    uri: str
    work: Path
    procs: Processes
    watch: _Watch
    timeout: float
    restarts: int = 0

    def restart(self, node: str, args: Mapping[str, str], params: Mapping[str, Any], computer: str) -> int:
        """Stop ROS node ``node``, set the launch file's parameters for ``args`` (and
        ``params``) on the master, start it again with ``args`` on ``computer``; its new PID
        once it answers. The run's failure check follows the new process."""
        return self.restart_many([(node, args, params, computer)])[node]

    def restart_many(self, batch: list[tuple[str, Mapping[str, str], Mapping[str, Any], str]],
                     standalone: frozenset[str] = frozenset()) -> dict[str, int]:
        """:meth:`restart` of several nodes ``(node, args, params, computer)`` together (a
        nodelet named in ``standalone`` as ``nodelet standalone``, the others as the launch
        file starts them: a loader loads its nodelet into its manager again): what
        roslaunch says of each is asked at once before any stops (two ``roslaunch`` runs a
        node, a second or more each on a loaded machine), then every node is stopped, started
        again and only then waited for. A re-plan that moves four nodes took 12 to 18 s one
        node after the other in RQ4 (2026-11-28); together it takes about one restart's time.
        Per node its new PID."""
        from perfros_bag.rosrun.master import node_call
        from perfros_bag.system.names import system_node_name

        if not batch:
            return {}
        env = dict(self.procs.env)
        def key(args: Mapping[str, str]) -> tuple[tuple[str, str], ...]:
            return tuple(sorted(args.items()))

        with ThreadPoolExecutor(max_workers=4) as pool:  # the launch file's parameters once per set of args
            distinct = {key(args): args for _n, args, _p, _c in batch}
            dumped = {k: pool.submit(launch_params, self.launch, args, env, self.timeout)
                      for k, args in distinct.items()}
            commands = [pool.submit(node_command, self.launch, node, args, env, self.timeout)
                        for node, args, _p, _c in batch]
            values = [{**dumped[key(args)].result(), **params} for _n, args, params, _c in batch]
            cmds = [c.result() for c in commands]
        names = [node for node, _a, _p, _c in batch]
        old = {node: self.watch.pids.pop(node, (None, 0.0))[0] for node in names}
        self.watch.others = [st for st in self.watch.others if st.name not in names]
        self.procs.stop(names)
        for node, node_values in zip(names, values, strict=True):
            for name, value in node_values.items():
                if master_call(self.uri, "setParam", name, value) is None:
                    raise PerfrosError(f"the master did not take the parameter {name} for node {node}'s restart")
        for (node, _a, _p, computer), cmd in zip(batch, cmds, strict=True):
            self.spread.where[system_node_name(node)] = computer
            self.restarts += 1
            st = self.procs.start(node, _node_argv(cmd, self.spread, self.uri, standalone),
                                  self.work / f"restart{self.restarts}.log", cwd=Path(self.procs.env["ROS_HOME"]))
            self.watch.others.append(st)
        pids: dict[str, int] = {}
        for node in names:
            def up(node: str = node) -> bool:
                node_uri = master_call(self.uri, "lookupNode", node)
                answer = node_call(node_uri, "getPid") if isinstance(node_uri, str) else None
                if isinstance(answer, int) and answer != old[node]:
                    pids[node] = answer
                return node in pids

            wait_for(f"node {node} to start again", up, self.timeout, self.watch.failure)
            self.watch.pids[node] = (pids[node], _create_time(pids[node]))
        self.procs.remember()
        return pids


def _start_players(replay: Prepared, factor: float, work: Path, procs: Processes) -> list[Started]:
    """One ``rosbag play`` per replaced node, named as that node (:func:`replay.player_argv`)."""
    from perfros_bag.sweep.replay import player_argv

    return [procs.start(f"rosbag play {s.node}", player_argv(replay, s.node, factor), work / f"play{i}.log",
                        cwd=work) for i, s in enumerate(replay.inspected.stands)]


def _record(launch: LaunchFile, space: Space, run: Run, work: Path, procs: Processes, timeout: float,
            interval: float, note: Callable[[str, float], None],
            on_graph: Callable[[Graph], None] | None = None, spread: _Spread | None = None,
            on_window: Callable[[str], None] | None = None, replay: Prepared | None = None,
            on_master: Callable[[str], None] | None = None,
            on_tick: Callable[[Restarter], None] | None = None) -> Graph:
    note("roscore", 0.0)
    if spread is not None:
        procs.env["ROS_IP"] = spread.network.address(spread.master)
    with ThreadPoolExecutor(max_workers=2) as pool:  # roslaunch --nodes while roscore starts
        listing = pool.submit(launch_nodes, launch, run.args, dict(procs.env), timeout)
        members = pool.submit(_nodelets, launch, run.args, dict(procs.env), timeout)
        uri = start_roscore(procs, work, timeout, host=procs.env["ROS_IP"])
        nodes = listing.result()
        nodelets, managers = members.result()
    if run.keep_managers:  # deploy: a standalone nodelet is in no container (the sweep's graph keeps them)
        nodelets = {k: v for k, v in nodelets.items() if k not in run.standalone}
    if on_master is not None:
        on_master(uri)
    for name, value in run.params.items():
        if master_call(uri, "setParam", name, value) is None:
            raise PerfrosError(f"the master did not take the parameter {name}={value!r}")
    log = work / "roslaunch.log"
    if run.standalone:  # those nodelets in a process of their own; the sweep's run starts no manager
        if not run.keep_managers:
            nodes = [n for n in nodes if n not in managers]
        watch = _Watch(None, log, _start_nodes(launch, run, nodes, spread, uri, work, procs, timeout,
                                               frozenset(run.standalone)))
    elif replay is not None and run.factor is not None:  # the replaced nodes: a player each, under their names
        replaced = {s.node for s in replay.inspected.stands}
        started = _start_nodes(launch, run, [n for n in nodes if n not in replaced], spread, uri, work, procs,
                               timeout)
        watch = _Watch(None, log, [*started, *_start_players(replay, run.factor, work, procs)])
    elif spread is None:
        launcher = procs.start("roslaunch", [ROSLAUNCH, "-p", str(port_of(uri)), *launch_argv(launch, run.args)],
                               log, cwd=work)
        watch = _Watch(launcher, log)
    else:
        watch = _Watch(None, log, _start_nodes(launch, run, nodes, spread, uri, work, procs, timeout))

    def registered() -> bool:
        return all(isinstance(master_call(uri, "lookupNode", n), str) for n in nodes)

    note("nodes", 0.0)
    wait_for(f"the nodes {', '.join(nodes)} to register", registered, timeout, watch.failure)
    procs.remember()
    probe = start_rosbag(procs, "rosbag probe", work / "probe.bag", None, PROBE_NODE, work / "probe.log", work,
                         space.record_exclude)
    watch.others.append(probe)
    waiting: list[str] = []
    players_own = PLAYER_TOPICS if replay is not None else frozenset()

    def publishing() -> bool:
        graph = capture_graph(uri, nodes, OWN_NODES)
        quiet = [t for t in _silent_topics(uri, graph, nodes) if space.recorded(t) and t not in players_own]
        waiting[:] = quiet
        if quiet:
            return False
        # and the probe listens to every one (rosbag record -a looks for new topics once a
        # second): a node that works only when someone listens has started working
        state = master_state(uri)
        probed = {t for t, who in state[1] if f"/{PROBE_NODE}" in who} if state is not None else set()
        return all(t.name in probed for t in graph.topics if t.name not in QUIET_TOPICS and t.name not in players_own
                   and set(t.publishers) & set(nodes) and space.recorded(t.name))

    note("topics", 0.0)
    try:
        wait_for("every topic to publish", publishing, timeout, watch.failure)
    except PerfrosError as exc:
        if waiting and "timed out" in str(exc):
            raise PerfrosError(f"topic(s) {', '.join(waiting)} never published within {timeout:g} s") from None
        raise
    procs.remember()
    deadline = time.monotonic() + space.settle_s
    while time.monotonic() < deadline:
        _check(watch, "settling")
        note("settling", 0.0)
        time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
    graph = with_membership(capture_graph(uri, nodes, OWN_NODES, run.name), nodelets)
    if replay is not None and run.factor is not None:
        graph = _replayed_graph(graph, space, replay, run.factor)
    for n in graph.nodes:
        if n.launched and n.pid is not None:
            watch.pids[n.name] = (n.pid, _create_time(n.pid))
    missing = [n.name for n in graph.nodes if n.launched and n.pid is None]
    if missing:
        raise PerfrosError(f"node(s) {', '.join(missing)} did not answer getPid")
    if on_graph is not None:
        on_graph(graph)
    labels = sorted({n.rsplit("/", 1)[-1] for n in nodes})
    pattern = "(^| )__name:=(" + "|".join(re.escape(x) for x in labels) + ")( |$)"
    cpu = start_record_cpu(procs, [pattern], interval, work / "host.cpu.csv", work / "record-cpu.log", work)
    advertised = [t.name for t in graph.topics
                  if t.name not in QUIET_TOPICS and set(t.publishers) & set(nodes) and space.recorded(t.name)]
    if spread is None:
        recorders = [start_rosbag(procs, "rosbag record", work / "run.bag", None, RECORD_NODE, work / "rosbag.log",
                                  work, space.record_exclude)]
        bags: dict[str, Path] = {}
        expected = {t: f"/{RECORD_NODE}" for t in advertised}
    else:
        recorders, expected, bags = _start_recorders(graph, nodes, space, spread, uri, work, procs)
    watch.others += [cpu, *recorders]

    def recording() -> bool:
        state = master_state(uri)
        if state is None:
            return False
        subs = {t: set(who) for t, who in state[1]}
        return all(who in subs.get(t, set()) for t, who in expected.items() if t in advertised)

    wait_for("rosbag record to subscribe", recording, timeout, watch.failure)
    ready = cpu_ready_path(work / "host.cpu.csv")
    wait_for("record-cpu to sample", ready.exists, timeout, watch.failure)
    ready.unlink()
    procs.stop(["rosbag probe"])
    watch.others.remove(probe)
    if spread is not None:  # the recorders' first messages come in a burst, late: left out of the window
        deadline = time.monotonic() + RECORDER_WARMUP_S
        while time.monotonic() < deadline:
            _check(watch, "the recorders' start")
            time.sleep(0.1)
    window = on_window or (lambda edge: None)
    window("start")
    started_ns = time.time_ns()
    t0 = time.monotonic()
    restarter = None if spread is None else Restarter(launch, spread, uri, work, procs, watch, timeout)
    while (elapsed := time.monotonic() - t0) < space.duration_s:
        _check(watch, "the recording")
        if on_tick is not None and restarter is not None:
            on_tick(restarter)
        note("recording", elapsed / space.duration_s)
        time.sleep(min(0.25, space.duration_s - elapsed))
    _check(watch, "the recording")
    window("end")
    ended_ns = time.time_ns()
    graph = _with_later_edges(graph, with_membership(capture_graph(uri, nodes, OWN_NODES, run.name), nodelets))
    if replay is not None and run.factor is not None:
        graph = _replayed_graph(graph, space, replay, run.factor)
    note("recording", 1.0)
    procs.stop([*(r.name for r in recorders), "record-cpu"], timeout=15.0)
    if spread is not None:
        _merge_recordings(bags, work, started_ns, ended_ns)
    if not (work / "run.bag").exists():
        raise PerfrosError(f"rosbag record did not write its bag (see {work / 'rosbag.log'})")
    if not (work / "host.cpu.csv").exists():
        raise PerfrosError(f"record-cpu did not write its trace (see {work / 'record-cpu.log'})")
    return graph


def _with_later_edges(graph: Graph, later: Graph) -> Graph:
    """``graph`` (taken before the recording) with the publishers and subscribers the master
    knew at its end added: a node that subscribes to its input only once its outputs have a
    listener (opencv_apps' lazy nodelets) may have done so after the first look."""
    from dataclasses import replace

    more = {t.name: t for t in later.topics}
    topics = []
    for t in graph.topics:
        m = more.get(t.name)
        if m is not None:
            t = replace(t, publishers=tuple(sorted(set(t.publishers) | set(m.publishers))),
                        subscribers=tuple(sorted(set(t.subscribers) | set(m.subscribers))))
        topics.append(t)
    return replace(graph, topics=tuple(topics))


def _replayed_graph(graph: Graph, space: Space, replay: Prepared, factor: float) -> Graph:
    """The graph with each player marked as the replaced node it stands for (``replay:``),
    without the players' own topics (:data:`PLAYER_TOPICS`)."""
    from dataclasses import replace

    from perfros_bag.sweep.graph import Replayed

    assert space.replay is not None
    stands = {s.node for s in replay.inspected.stands}
    shown = str(space.replay.recording)
    with contextlib.suppress(ValueError):
        shown = str(space.replay.recording.relative_to(space.path.parent.absolute()))
    nodes = tuple(replace(n, replay=Replayed(shown, factor)) if n.name in stands else n for n in graph.nodes)
    topics = []
    for t in graph.topics:  # the players' own topics are not the replaced nodes'
        if t.name in PLAYER_TOPICS:
            t = replace(t, publishers=tuple(p for p in t.publishers if p not in stands))
            if not t.publishers and not t.subscribers:
                continue
        topics.append(t)
    return replace(graph, nodes=nodes, topics=tuple(topics))


def _start_recorders(graph: Graph, nodes: list[str], space: Space, spread: _Spread, uri: str, work: Path,
                     procs: Processes) -> tuple[list[Started], dict[str, str], dict[str, Path]]:
    """One ``rosbag record`` per computer, of the topics published there (a topic with
    several publishers: where its first launched publisher runs; the rest with the master);
    returns them, per topic the recorder that must subscribe to it, and per recorder its bag."""
    from perfros_bag.rosrun.recorders import rosbag_argv

    launched = set(nodes)
    by_computer: dict[str, list[str]] = {}
    for t in graph.topics:
        if not t.publishers or not space.recorded(t.name):
            continue
        owner = next((p for p in t.publishers if p in launched), None)
        comp = spread.computer(owner) if owner else spread.master
        by_computer.setdefault(comp, []).append(t.name)
    recorders, expected, bags = [], {}, {}
    for comp, topics in sorted(by_computer.items()):
        node = f"{RECORD_NODE}_{comp}".replace("-", "_")
        name, bag = f"rosbag record {comp}", work / f"run.{comp}.bag"
        argv = spread.network.wrap(comp, ["env", *spread.env(comp, uri), *rosbag_argv(bag, topics, node)])
        recorders.append(procs.start(name, argv, work / f"rosbag.{comp}.log", cwd=work))
        expected.update(dict.fromkeys(topics, f"/{node}"))
        bags[name] = bag
    return recorders, expected, bags


def _merge_recordings(bags: Mapping[str, Path], work: Path, start_ns: int, end_ns: int) -> None:
    """The per-computer bags (recorder -> its bag) merged into ``run.bag``, cut to the
    recording's window."""
    missing = [name for name, bag in bags.items() if not bag.exists()]
    if missing:
        raise PerfrosError(f"{', '.join(missing)} did not write its bag (see {work})")
    try:
        merge_bags(list(bags.values()), work / "run.bag", start_ns, end_ns)
    except Exception as exc:  # noqa: BLE001 - rosbags' own errors: name the run's folder
        raise PerfrosError(f"cannot merge the computers' bags in {work}: {exc}") from None


def _check(watch: _Watch, during: str) -> None:
    dead = watch.failure()
    if dead:
        raise PerfrosError(f"{dead} exited during {during}")


def _create_time(pid: int) -> float:
    import psutil

    try:
        return float(psutil.Process(pid).create_time())
    except psutil.Error:
        return 0.0


def _silent_topics(uri: str, graph: Graph, nodes: list[str]) -> list[str]:
    """Topics the launch's nodes advertise on which no message was sent yet."""
    sent: dict[str, bool] = {}
    for node in nodes:
        node_uri = master_call(uri, "lookupNode", node)
        stats = bus_stats(node_uri) if isinstance(node_uri, str) else None
        for topic, bytes_sent in _published_bytes(stats).items():
            sent[topic] = sent.get(topic, False) or bytes_sent > 0
    return sorted(t.name for t in graph.topics
                  if t.name not in QUIET_TOPICS and set(t.publishers) & set(nodes) and not sent.get(t.name, False))


def _published_bytes(stats: Any) -> dict[str, int]:
    """Message bytes sent per published topic, from a node's ``getBusStats`` (handshake
    headers not counted): roscpp's per connection summed, rospy's own total
    (:func:`~perfros_bag.rosrun.master.parse_bus_stats`)."""
    return {topic: c.total_bytes if c.total_bytes is not None else sum(b for _, b in c.connections.values())
            for topic, c in parse_bus_stats(stats).items()}


def _node_trace(raw: Path, graph: Graph) -> Path:
    """The CPU trace with each row labelled with its ROS node (matched by PID); rows of
    other processes are dropped. Written beside ``raw`` as ``node.cpu.csv``."""
    from perfros_bag.cpu.trace import has_threads, read_cpu_trace, trace_rows, write_cpu_trace

    by_pid: Mapping[int, str] = {n.pid: n.name for n in graph.nodes if n.launched and n.pid is not None}
    tr = read_cpu_trace(raw)
    rows: list[tuple[Any, ...]] = []
    for row in trace_rows(tr):
        node = by_pid.get(int(row[1]))
        if node is not None:
            rows.append((row[0], int(row[1]), node, *row[3:]))
    dest = raw.with_name("node.cpu.csv")
    write_cpu_trace(dest, rows, host=tr.host or socket.gethostname(), logical_cpus=tr.logical_cpus,
                    interval_s=tr.interval_s or 0.5, speed_factor=tr.speed_factor, reference_s=tr.reference_s,
                    threads=has_threads(tr))
    return dest

