"""The watch loop: attach, then one window after another until told to stop.

Attached to ``ROS_MASTER_URI`` (or ``master_uri``), or to a deploy in progress
(``deployment``: its ``live.json``, see :mod:`perfros_bag.sweep.livestate`): then the
watch runs on a thread of its own that enters the network namespace the deploy's master
runs in (``setns(2)`` on that thread only, as the deploy's own runner does; the process
stays in the host's), every node is local and a node's CPU is in the units of its emulated
computer. The watch starts no process and stops none.
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import InputError, PerfrosError, PerfrosWarning
from perfros_bag.validation import DEFAULT_TOLERANCE

if TYPE_CHECKING:
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.types import System
    from perfros_bag.watch.observe import Observer, Reading
    from perfros_bag.watch.stamps import StampListener

#: Windows a watch waits for a master that does not answer: none (bad input at once).
MASTER_TIMEOUT_S = 3.0
PERSIST_DEFAULT = 2
#: share of a window a reading waits for the publishers' answers
READ_SHARE = 0.4


@dataclass
class WatchResult:
    windows: int = 0
    alarms: list[dict[str, Any]] = field(default_factory=list)  # every alarm raised (when new)
    ended: str | None = None  # why the watch ended by itself (the master or the deploy went away)
    replans: list[dict[str, Any]] = field(default_factory=list)


def check_window(window_s: float) -> float:
    if isinstance(window_s, bool) or not isinstance(window_s, int | float) or not math.isfinite(window_s) \
            or window_s <= 0:
        raise InputError(None, f"--window must be a positive finite number of seconds, got {window_s!r}")
    return float(window_s)


def _master_up(uri: str) -> bool:
    import socket
    from urllib.parse import urlsplit

    from perfros_bag.rosrun.master import master_call

    parts = urlsplit(uri)
    try:
        with socket.create_connection((parts.hostname or "localhost", parts.port or 11311), timeout=MASTER_TIMEOUT_S):
            pass
    except (OSError, ValueError):
        return False
    return master_call(uri, "getPid") is not None


def _only(plan: Plan, nodes: list[str]) -> Plan:
    return replace(plan, nodes={n: pn for n, pn in plan.nodes.items() if n in nodes})


def unsettled_window(doc: dict[str, Any], pinned: dict[str, Any], last_pinned: dict[str, Any]) -> bool:
    """Does a window mix two settings, so that it characterises neither: a node in it was
    restarting or dead, or a value running changed since the last window (``pinned``, the
    operator's values, against ``last_pinned``)? Its rows are then left out of the refit."""
    return (any(n.get("state") == "restarting" or not n.get("alive", True) for n in doc["nodes"].values())
            or pinned != last_pinned)


@dataclass
class OperatorPins:
    """The values an operator set while the watch runs (a running value that differed from
    the plan watched when a window saw it): every later re-plan keeps them, also once a
    re-plan's own plan holds them (so a second re-plan cannot move the operator's camera rate
    again), until the operator changes them again."""

    kept: dict[str, Any] = field(default_factory=dict)  # every node's latest value pinned
    last: dict[str, Any] = field(default_factory=dict)  # the last window's ``pinned``

    def see(self, doc: dict[str, Any], pinned: dict[str, Any]) -> bool:
        """Take a window's ``pinned``; whether the window is unsettled (:func:`unsettled_window`)."""
        unsettled = unsettled_window(doc, pinned, self.last)
        self.last = dict(pinned)
        self.kept.update(pinned)
        return unsettled

    def world(self, world: dict[str, Any]) -> dict[str, Any]:
        """``world`` for a re-plan: its ``pinned`` every value kept."""
        return {**world, "pinned": dict(self.kept)} if self.kept else world


def window_rows(k: int, doc: dict[str, Any], plan: Plan, stats_types: dict[str, str]) -> list[Row]:
    """The window as characterisation rows (one per node and topic, recording ``watch-<k>``):
    what ``fit`` and ``tune --base`` take, with the node's planned value as its setting, or
    the value it runs at when an operator changed it (the window's ``pinned``)."""
    from perfros_bag.characterisation.csvfile import Row

    rows = []
    running = doc.get("pinned") or {}
    for name, n in doc["nodes"].items():
        pn = plan.nodes[name]
        value = running.get(name, pn.value)
        if not n.get("alive", True):
            continue
        input_hz = None
        if pn.input is not None:
            src = next((m for m in doc["nodes"].values() if pn.input in m["topics"]), None)
            input_hz = None if src is None else src["topics"][pn.input]["measured_hz"]
        for topic, tc in (n["topics"].items() or [(None, None)]):
            if tc is not None and tc["measured_hz"] is None:  # unreadable this window: no row
                continue
            rows.append(Row(f"watch-{k:05d}", name, pn.parameter, value, topic,
                            stats_types.get(topic or "") or None,
                            None if tc is None else int(tc["messages"]), float(doc["seconds"]),
                            None if tc is None else float(tc["measured_hz"]), None if tc is None else float(tc["kBps"]),
                            n.get("cpu"), None, 1 if "cpu" in n else 0, input_hz=input_hz))
    return rows


def watch(plan_path: str | Path, *, master_uri: str | None = None, deployment: str | Path | None = None,
          system_path: str | Path | None = None, window_s: float = 5.0, tolerance: float = DEFAULT_TOLERANCE,
          persist: int = PERSIST_DEFAULT, partial: bool = False, windows: int | None = None,
          out: str | Path | None = None, adapt: Any = None, latency_tolerance: float | None = None,
          on_window: Callable[[dict[str, Any], list[dict[str, Any]]], None] | None = None) -> WatchResult:
    """Watch the plan at ``plan_path`` until ``windows`` windows (None: until Ctrl-C, or the
    master or the deploy goes away). ``on_window(doc, new_alarms)`` gets every window's JSON
    object. ``adapt``: an :class:`~perfros_bag.watch.adapt.Adapter`, asked to re-plan
    when a new alarm is raised."""
    import os

    from perfros_bag.system.planfile import load_plan, plan_system

    window_s = check_window(window_s)
    if not math.isfinite(tolerance) or tolerance < 0:
        raise InputError(None, f"--tolerance must be a finite number >= 0, got {tolerance!r}")
    if latency_tolerance is not None and not latency_tolerance >= 0:  # math.inf: chains never alarm
        raise InputError(None, f"--latency-tolerance must be a finite number >= 0, got {latency_tolerance!r}")
    lat_tol = tolerance if latency_tolerance is None else latency_tolerance
    if persist < 1:
        raise InputError(None, f"--persist must be >= 1, got {persist}")
    plan = load_plan(plan_path)
    plan.require_feasible(plan_path, "watch")
    live = None
    if deployment is not None:
        from perfros_bag.sweep.livestate import read_live

        live = read_live(deployment)
        master_uri = live.master_uri
        if system_path is None and live.system is not None:
            system_path = live.system
    master_uri = master_uri or os.environ.get("ROS_MASTER_URI")
    if not master_uri:
        raise InputError(None, "no ROS master to watch: set ROS_MASTER_URI, or give --master or --deployment")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        system = plan_system(plan, plan_path, system_path)
    ns = live.namespaces.get(live.master_computer) if live is not None and live.master_computer else None
    stop = threading.Event()

    def run() -> WatchResult:
        return _watch(plan, plan_path, system, master_uri, live is not None, live, window_s, (tolerance, lat_tol),
                      persist, partial, windows, out, adapt, on_window, stop)

    if ns is None:
        return run()
    return _in_namespace(ns, run, stop, window_s)


def _in_namespace(ns: str, run: Callable[[], WatchResult], stop: threading.Event, window_s: float) -> WatchResult:
    """``run()`` on a thread of its own inside network namespace ``ns``. Only that thread
    enters it: the process stays in the host's namespace, so the deploy, removing its
    namespaces at its end (it ends the processes still inside), does not take the watch with
    them. Ctrl-C in the main thread asks the watch to end after its current reading."""
    from perfros_bag.rosrun.network import enter_namespace

    box: dict[str, Any] = {}

    def work() -> None:
        try:
            with enter_namespace(Path("/run/netns") / ns):
                box["result"] = run()
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            box["error"] = exc

    worker = threading.Thread(target=work, name="perfros-watch", daemon=True)
    worker.start()
    try:
        while worker.is_alive():
            worker.join(0.2)
    except KeyboardInterrupt:
        stop.set()
        worker.join(window_s + 30.0)
    error = box.get("error")
    if isinstance(error, OSError):
        raise PerfrosError(f"cannot reach the deploy's network namespace {ns}: {error}") from None
    if error is not None:
        raise error
    result: WatchResult = box["result"]
    return result


def _watch(plan: Plan, plan_path: str | Path, system: System | None, master_uri: str, attached: bool, live: Any,
           window_s: float, tolerance: tuple[float, float], persist: int, partial: bool, windows: int | None,
           out: str | Path | None, adapt: Any,
           on_window: Callable[[dict[str, Any], list[dict[str, Any]]], None] | None,
           stop: threading.Event) -> WatchResult:
    from perfros_bag.watch.observe import Observer

    if not _master_up(master_uri):
        raise InputError(None, f"no ROS master reachable at {master_uri} (waited {MASTER_TIMEOUT_S:g} s)")
    observer = Observer(master_uri, {n: list(pn.topics) for n, pn in plan.nodes.items()}, all_local=attached,
                        call_budget_s=call_budget(window_s))
    try:
        return _watch_attached(observer, plan, plan_path, system, live, window_s, tolerance, persist, partial,
                               windows, out, adapt, on_window, stop, master_uri)
    finally:
        observer.close()


def call_budget(window_s: float) -> float:
    """Seconds one reading waits for the publishers' ``getBusStats``: :data:`READ_SHARE` of
    the window, at most the XML-RPC timeout (a publisher that answers later is unreadable in
    that reading, and the window keeps its cadence)."""
    from perfros_bag.rosrun.master import CALL_TIMEOUT_S

    return min(CALL_TIMEOUT_S, READ_SHARE * window_s)


def _watch_attached(observer: Observer, plan: Plan, plan_path: str | Path, system: System | None, live: Any,
                    window_s: float, tolerance: tuple[float, float], persist: int, partial: bool,
                    windows: int | None, out: str | Path | None, adapt: Any,
                    on_window: Callable[[dict[str, Any], list[dict[str, Any]]], None] | None,
                    stop: threading.Event, master_uri: str) -> WatchResult:
    from perfros_bag.watch.alarms import Persistence

    missing = observer.attach()
    if missing:
        if not partial or len(missing) == len(plan.nodes):
            raise InputError(plan_path, f"planned node(s) not running: {', '.join(missing)}"
                             + ("" if partial else " (--partial watches the others)"))
        warnings.warn(f"planned node(s) not running, not watched: {', '.join(missing)}", PerfrosWarning, stacklevel=2)
        plan = _only(plan, [n for n in plan.nodes if n not in missing])
    units = live.units_per_core if live is not None else None
    outdir = None if out is None else Path(out)
    if outdir is not None:
        outdir.mkdir(parents=True, exist_ok=True)
    persistence = Persistence(persist)
    result = WatchResult()
    listeners: dict[str, StampListener] = {}  # made by _windows once it has read the topics' sizes
    try:
        _windows(observer, plan, system, live, units, window_s, tolerance, persistence, windows, outdir, adapt,
                 on_window, result, master_uri, listeners, stop)
    except KeyboardInterrupt:
        result.ended = "interrupted (Ctrl-C)"
    finally:
        for listener in listeners.values():
            listener.close()
    return result


def listen_to_chains(observer: Observer, plan: Plan, reading: Reading, listeners: dict[str, StampListener],
                     unlistened: dict[str, str]) -> None:
    """Per chain with a prediction, a subscriber to its last topic (its header stamps), kept
    in ``listeners``, unless the topic's messages are large (:data:`~perfros_bag.watch.stamps.
    STAMP_MAX_BYTES`, by ``reading``'s counters): such a chain goes into ``unlistened`` with
    the reason, and a listener made before its size was known (no message counted yet) is
    closed. Called at every reading; a chain decided stays so."""
    from perfros_bag.watch.stamps import STAMP_MAX_BYTES, StampListener, mean_message_bytes
    from perfros_bag.watch.window import planned_chains

    for c in planned_chains(plan):
        name, topic = str(c["name"]), str(c["topics"][-1])
        if name in unlistened:
            continue
        size = mean_message_bytes(reading.topics, topic)
        if size is not None and size > STAMP_MAX_BYTES:
            unlistened[name] = (f"{topic}: messages of {size / 1000:.1f} kB (over {STAMP_MAX_BYTES / 1000:g}); "
                                "subscribing would copy each one to the watcher, across a link")
            listener = listeners.pop(name, None)
            if listener is not None:
                listener.close()
        elif name not in listeners:
            uris = [u for p in observer.publishers.get(topic, []) if (u := observer._uri(p)) is not None]
            listeners[name] = StampListener(topic, observer.types.get(topic, "*"), uris)


def chain_latency(listeners: dict[str, StampListener]) -> dict[str, dict[str, Any] | None]:
    """Per chain, its window's latency in ms ``{p50, p95, messages}``; None without a message."""
    from perfros_bag.watch.stamps import percentile

    out: dict[str, dict[str, Any] | None] = {}
    for name, listener in listeners.items():
        xs = listener.take()
        out[name] = None if not xs else {"p50": 1000.0 * percentile(xs, 50), "p95": 1000.0 * percentile(xs, 95),
                                         "messages": len(xs)}
    return out


def _windows(observer: Observer, plan: Plan, system: System | None, live: Any, units: float | None, window_s: float,
             tolerances: tuple[float, float], persistence: Any, windows: int | None, outdir: Path | None, adapt: Any,
             on_window: Callable[[dict[str, Any], list[dict[str, Any]]], None] | None, result: WatchResult,
             master_uri: str, listeners: dict[str, StampListener], stop: threading.Event) -> None:
    from perfros_bag.characterisation.csvfile import columns_for, rows_csv, write_characterisation
    from perfros_bag.fileio import append_lines, atomic_write_text, json_text
    from perfros_bag.watch.alarms import foreign_present, rate_drifts, value_drifts
    from perfros_bag.watch.window import (
        cgroup_cpu_s,
        evaluate,
        unreadable_topics,
        window_cpu,
        window_document,
        window_stats,
    )

    tolerance, latency_tolerance = tolerances
    rows: list[Row] = []
    written: tuple[str, ...] | None = None  # characterisation.csv's columns once it is started
    groups = dict(live.cgroups) if live is not None else {}
    replans = _Replans(adapt, live)
    before = observer.read()
    used_before = {c: cgroup_cpu_s(d) for c, d in groups.items()}
    unlistened: dict[str, str] = {}  # chain -> why its last topic is not subscribed to
    listen_to_chains(observer, plan, before, listeners, unlistened)
    for listener in listeners.values():
        listener.take()  # what came before the first window's start is not in it
    k = 0
    pins = OperatorPins()
    in_force = PlanInForce()
    # (window, measured Σ w·P) of the last windows, as many as an alarm takes to be raised
    measured: deque[tuple[int, float] | None] = deque(maxlen=persistence.persist)
    try:
        while windows is None or k < windows:
            end = before.t + window_s
            after = _read_until(observer, end, live, stop, replans.poll, before.t)
            used_after = {c: cgroup_cpu_s(d) for c, d in groups.items()}
            if stop.is_set():
                result.ended = "interrupted (Ctrl-C)"
                break
            listen_to_chains(observer, plan, after, listeners, unlistened)  # a topic found large: not listened
            latency = chain_latency(listeners)  # right after the counters, so both cover the same seconds
            for listener in listeners.values():  # a restarted publisher (a new URI) is listened to again
                listener.follow([u for p in observer.publishers.get(listener.topic, []) if (u := observer._uri(p))])
            k += 1
            replan = replans.take()  # applied since the last window: this window is judged against it
            # a window in which the deploy was restarting nodes for a new plan
            transition = replans.transition()
            if replan is not None:
                persistence = type(persistence)(persistence.persist)  # the new plan's drifts count afresh
                measured.clear()
                result.replans.append(replan)
                if replan.get("sent"):  # the deploy runs it now: watch it against that
                    from perfros_bag.system.planfile import load_plan

                    plan = load_plan(replan["plan"])
            stats = window_stats(before, after, observer.types, f"window-{k}")
            cpu = window_cpu(before, after, plan, units)
            now = _live_now(live)
            world = _world(now, plan, before, after, used_before, used_after, units)
            restarting = restarting_nodes(now, observer, after)
            if world.get("links") and system is not None:
                from perfros_bag.watch.adapt import world_system

                system = world_system(system, {"links": world["links"]})  # judged against the rates in force
            v = evaluate(stats, plan, system, cpu, tolerance)
            unread = unreadable_topics(before, after)
            doc = window_document(k, after.t, after.t - before.t, v, plan, after.alive, set(cpu), [], latency,
                                  restarting, unread, unlistened)
            blind = sorted(n for n, pn in plan.nodes.items() if any(t in unread for t in pn.topics))
            if blind and len(blind) < len(plan.nodes):  # Σ w·P over the nodes that could be read
                seen = evaluate(stats, _only(plan, [n for n in plan.nodes if n not in blind]), system, cpu, tolerance)
                doc["overall"] = {"expected": seen.overall_expected, "measured": seen.overall_measured,
                                  "deviation_pct": seen.deviation_pct, "unreadable": blind}
            for c, x in (world.get("foreign") or {}).items():
                if c in doc["computers"]:
                    doc["computers"][c]["foreign"] = x
            if world.get("pinned"):
                doc["pinned"] = world["pinned"]
            if replan is not None:
                doc["replan"] = replan
            # a transition window, half the old plan and the restarts, is reported but raises no alarm
            alarms = [] if transition else persistence.update(
                rate_drifts(doc, tolerance, latency_tolerance)
                + value_drifts(doc.get("pinned"), {n: pn.value for n, pn in plan.nodes.items()}),
                foreign_present(doc))
            doc["alarms"] = [a.to_dict() for a in alarms]
            new = [a.to_dict() for a in alarms if a.new]
            result.alarms += new
            result.windows = k
            # the window as characterisation rows, made once for the re-plan and --out (a
            # transition window, a mix of two plans, characterises neither and raises nothing;
            # nor does a window in which a node was restarting or dead, or a running value
            # changed: its rates mix two settings, and a driven node's output over an input
            # read while its publisher restarted is no ratio of its own)
            unsettled = pins.see(doc, world.get("pinned") or {})
            added = [] if transition or unsettled or (outdir is None and not new) else window_rows(
                k, doc, plan, observer.types)
            # the running plan's Σ w·P as measured (None where a window cannot say it: blind on a
            # node, or running an operator's values that no plan in force holds). Under an
            # operator's values it is eq 10 against the plan the deploy runs (live.json
            # plan_in_force), as a re-plan that keeps those values predicts it
            running = doc["overall"]["measured"]
            if world.get("pinned"):
                held = in_force.get(now, plan, world["pinned"])
                running = None if held is None else evaluate(stats, held, system, cpu, tolerance).overall_measured
            measured.append(None if transition or blind or running is None else (k, running))
            if new:  # a re-plan still being made takes these alarms' windows in its successor, if they last
                replans.ask(plan, rows + added, new, k, pins.world(world),
                            running_measure(measured))
            if on_window is not None:
                on_window(doc, new)
            if outdir is not None:  # each window appended: a long watch writes each once
                rows += added
                line = json_text(doc, indent=None) + "\n"
                if written is None:
                    atomic_write_text(outdir / "windows.jsonl", line)
                else:
                    append_lines(outdir / "windows.jsonl", line)
                # started, or the new rows fill a column the file lacks: the whole file once
                if written is None or not set(columns_for(added)) <= set(written):
                    write_characterisation(outdir / "characterisation.csv", rows)
                    written = columns_for(rows)
                elif added:
                    append_lines(outdir / "characterisation.csv", rows_csv(added, written, header=False))
            if not after.master_up or (live is not None and not _deploy_running(live)):
                result.ended = "the deploy ended" if live is not None else f"the master at {master_uri} went away"
                break
            before, used_before = after, used_after
        if result.ended is None:  # --windows N reached: the re-plan asked for is finished, logged, applied
            result.replans += replans.drain()
    finally:
        replans.cancel()


class _Replans:
    """``--adapt``'s re-plans as the loop sees them: at most one refit at a time, in a child
    process (:mod:`perfros_bag.watch.refit`); applied as soon as it is done, taken by the
    next window."""

    def __init__(self, adapter: Any, live: Any = None) -> None:
        import subprocess

        from perfros_bag.watch.refit import Pending

        self.adapter = adapter
        self.live = live
        #: a re-plan sent to the deploy: (its plan, until when to wait for the deploy to run it)
        self.awaiting: tuple[Path, float] | None = None
        self.ran = False  # the deploy finished running it since the last window
        self.pending: Pending | None = None
        self.standby: subprocess.Popen[bytes] | None = None  # a refit child waiting, its imports done
        self.done: list[dict[str, Any]] = []
        #: live.json's ``plan_in_force`` when the refit under way was asked for
        self.asked_in_force: str | None = None
        self._warm()

    def _warm(self) -> None:
        from perfros_bag.watch.refit import warm

        if self.adapter is not None and self.standby is None and self.pending is None:
            try:
                self.standby = warm(self.adapter)
            except OSError as exc:  # a refit then starts its own child when asked
                warnings.warn(f"--adapt: no refit process started ahead: {exc}", PerfrosWarning, stacklevel=2)

    def ask(self, plan: Plan, rows: list[Row], alarms: list[dict[str, Any]], k: int, world: dict[str, Any],
            running: dict[str, Any] | None = None) -> None:
        """Start window ``k``'s re-plan (unless one is under way or awaited). ``running``: the
        running plan's measured Σ w·P in the windows that raised ``alarms``; a re-plan
        predicting less is logged, not sent."""
        if self.adapter is None or self.pending is not None or self.awaiting is not None:
            return
        from perfros_bag.watch.refit import start

        standby, self.standby = self.standby, None
        now = _live_now(self.live)
        self.asked_in_force = None if now is None else now.plan_in_force
        try:
            self.pending = start(self.adapter, plan, rows, alarms, k, world, standby, running)
        except (OSError, PerfrosError) as exc:
            warnings.warn(f"--adapt: window {k}: no re-plan: {exc}", PerfrosWarning, stacklevel=2)

    def poll(self) -> bool:
        """Apply the re-plan whose refit has ended (control.json, adapt.jsonl). True when the
        deploy has just finished running the one sent last (live.json ``plan_in_force`` it,
        nothing ``restarting``): a window may end there, so the next is wholly the new plan's."""
        if self.pending is not None and self.pending.poll():
            stale = self._stale()
            entry = self.pending.finish(stale)
            self.pending = None
            if entry is not None and entry.get("held_back"):  # stale, or worse than running
                warnings.warn(f"--adapt: window {entry['window']}: re-plan {entry['applied']}", PerfrosWarning,
                              stacklevel=2)
            elif entry is not None:
                self.done.append(entry)
                if entry.get("sent") and self.live is not None:
                    grace = self.live.restart_timeout_s or RESTART_GRACE_S
                    self.awaiting = (Path(entry["plan"]).resolve(), time.time() + grace + 5.0)
        if self.awaiting is None:
            return False
        now = _live_now(self.live)
        if now is None or time.time() > self.awaiting[1]:
            self.awaiting = None
            return False
        if now.plan_in_force and Path(now.plan_in_force).resolve() == self.awaiting[0] and not now.restarting:
            self.awaiting = None
            self.ran = True
            return True
        return False

    def _stale(self) -> str | None:
        """Why the re-plan just made must not be sent: someone else (an operator's
        control.json) changed the plan in force while it was refitted from the one before,
        which it would undo. None when it may go (or without a deploy)."""
        now = _live_now(self.live)
        if now is None or now.plan_in_force == self.asked_in_force:
            return None
        before = self.asked_in_force or "the deploy's own"
        return (f"the plan in force changed while it was refitted ({before} -> "
                f"{now.plan_in_force}); the windows judge the change, a new re-plan starts from it")

    def transition(self) -> bool:
        """Whether the window just ended saw a new plan sent to the deploy and its restarts
        (from its sending until the deploy ran it); asked once per window, after :meth:`take`."""
        ran, self.ran = self.ran, False
        return ran or self.awaiting is not None

    def take(self) -> dict[str, Any] | None:
        """The last re-plan applied since the previous call (earlier ones are in adapt.jsonl);
        a refit child is warmed again for the next one. It does not poll: a refit that ends
        after the window's counters were read is applied at the next :meth:`poll` and taken by
        the next window, never by one that ended before it."""
        self._warm()
        done, self.done = self.done, []
        return done[-1] if done else None

    def drain(self) -> list[dict[str, Any]]:
        """Wait for the refit under way, apply it; every re-plan not taken yet."""
        if self.pending is not None:
            self.pending.wait()
        self.poll()
        done, self.done = self.done, []
        return done

    def cancel(self) -> None:
        from perfros_bag.watch.refit import end

        if self.pending is not None:
            self.pending.cancel()
            self.pending = None
        if self.standby is not None:
            end(self.standby)
            self.standby = None


@dataclass
class PlanInForce:
    """The plan a deploy runs under an operator's values (live.json ``plan_in_force``), read
    once per path: the one eq 10 judges the running plan against while values are pinned."""

    read: dict[str, Plan | None] = field(default_factory=dict)

    def get(self, now: Any, watched: Plan, pinned: dict[str, Any]) -> Plan | None:
        """That plan when it runs the watched plan's nodes and holds every ``pinned`` value;
        None without one (no deploy, the plan watched itself, unreadable, or another plan)."""
        path = getattr(now, "plan_in_force", None)
        if not path:
            return None
        if path not in self.read:
            from perfros_bag.system.planfile import load_plan

            try:
                self.read[path] = load_plan(path)
            except (PerfrosError, OSError):
                self.read[path] = None
        got = self.read[path]
        if got is None or set(got.nodes) != set(watched.nodes):
            return None
        holds = all(got.nodes[n].value is not None and isinstance(v, int | float)
                    and _runs_as(float(got.nodes[n].value or 0.0), v) for n, v in pinned.items())
        return got if holds else None


def running_measure(measured: Iterable[tuple[int, float] | None]) -> dict[str, Any] | None:
    """The running plan's measured Σ w·P over the windows that raised an alarm (the last
    ``persist`` windows): their mean, and which windows; None when one of them cannot say it."""
    got = list(measured)
    if not got or any(m is None for m in got):
        return None
    pairs = [m for m in got if m is not None]
    return {"measured": sum(x for _, x in pairs) / len(pairs), "windows": [k for k, _ in pairs]}


def _live_now(live: Any) -> Any:
    """The deploy's live.json as it is now (None without a deploy, or once it is gone)."""
    from perfros_bag.sweep.livestate import read_live

    if live is None or live.folder is None:
        return None
    try:
        return read_live(live.folder)
    except PerfrosError:
        return None


#: how long a node the deploy says it is restarting may be away before it is dead, when
#: live.json does not say (``restart_timeout_s``)
RESTART_GRACE_S = 90.0


def restarting_nodes(now: Any, observer: Observer, reading: Reading) -> set[str]:
    """The planned nodes not running in ``reading`` that the deploy (live.json ``now``) is
    restarting for a new plan, since at most its restart timeout, or has just restarted (it
    names a new PID for them that runs): away for a restart, not dead."""
    import psutil

    if now is None:
        return set()
    grace = now.restart_timeout_s or RESTART_GRACE_S
    out = set()
    for name, node in observer.nodes.items():
        if reading.alive.get(name, True):
            continue
        since = now.restarting.get(node.ros_name)
        pid = (now.nodes.get(node.ros_name) or {}).get("pid")
        if since is not None and reading.t - since <= grace:
            out.add(name)
        elif isinstance(pid, int) and pid != node.pid:
            try:
                if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                    out.add(name)
            except psutil.Error:
                pass
    return out


def _world(now: Any, plan: Plan, before: Reading, after: Reading, used_before: dict[str, dict[int, float] | None],
           used_after: dict[str, dict[int, float] | None], units: float | None) -> dict[str, Any]:
    """The world as a deploy in progress (its live.json ``now``) has it (nothing without
    one): its links' rates in force, each computer's CPU beyond its planned nodes
    (``foreign``), and the values it runs that differ from the plan watched (``pinned``: an
    operator's change)."""
    from perfros_bag.system.names import system_node_name
    from perfros_bag.watch.window import foreign_cpu

    if now is None:
        return {}
    # each node where the deploy runs it now (a re-plan another watcher applied moves it),
    # else where the plan watched puts it
    running = {system_node_name(ros): str(x["computer"]) for ros, x in now.nodes.items()
               if isinstance(x, dict) and isinstance(x.get("computer"), str)}
    where = {n: running.get(n, pn.computer) for n, pn in plan.nodes.items()}
    pinned = {n: v for n, v in now.values.items()
              if n in plan.nodes and plan.nodes[n].value is not None and isinstance(v, int | float)
              and not _runs_as(float(plan.nodes[n].value or 0.0), v)}
    return {"links": now.links, "foreign": foreign_cpu(before, after, used_before, used_after, where, units or 100.0),
            "pinned": pinned}


def _runs_as(planned: float, running: float) -> bool:
    """Whether a node running at ``running`` runs its planned value (a whole-number
    parameter runs the planned value rounded, as deploy's ``plan_run`` does)."""
    if isinstance(running, int) and not isinstance(running, bool):
        return int(round(planned)) == running
    return abs(planned - float(running)) <= 1e-9 * max(1.0, abs(planned))


def _deploy_running(live: Any) -> bool:
    return bool(live.running())


#: a window is ended early where a deploy finished running a new plan, if it has lasted this long
MIN_CUT_S = 1.0


def _read_until(observer: Observer, end: float, live: Any, stop: threading.Event,
                tick: Callable[[], bool] | None = None, start: float | None = None) -> Reading:
    """Sleep until ``end`` (seconds since the epoch), in short steps so a deploy that ends is
    noticed, then read. ``tick()`` is called at each (a re-plan applied as soon as it is
    ready); when it says the deploy has just finished running a new plan, the window ends
    there (once it has lasted :data:`MIN_CUT_S` since ``start``), so the next is wholly the new plan's."""
    while True:
        if tick is not None and tick() and (start is None or time.time() - start >= MIN_CUT_S):
            break
        left = end - time.time()
        if left <= 0:
            break
        if stop.wait(min(left, 0.25)) or (live is not None and not _deploy_running(live)):
            break
    return observer.read()
