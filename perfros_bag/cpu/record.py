"""The psutil recorder behind ``perfros-bag record-cpu``: samples the CPU %, RSS and busy
threads of matching processes (and of COMMAND's process tree) into a ``<stem>.cpu.csv`` trace
(format: :mod:`perfros_bag.cpu.trace`)."""

from __future__ import annotations

import csv
import math
import os
import re
import signal
import socket
import subprocess
import threading
import time as _time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

from perfros_bag.cpu.trace import format_row, trace_header
from perfros_bag.errors import InputError

_NAME_ARG = re.compile(r"^(?:__name|__node):=(.+)$")
_INTERPRETERS = re.compile(r"^(python[0-9.]*|pypy[0-9.]*|ruby|node|perl|bash|sh)$")


def ros_node_label(name: str, cmdline: Sequence[str]) -> str:
    """A process's node label: its ROS ``__name:=`` / ``__node:=`` argument, else the
    script an interpreter runs (basename), else the process name."""
    for arg in cmdline:
        m = _NAME_ARG.match(arg)
        if m:
            return m.group(1)
    if _INTERPRETERS.match(name or ""):
        args = list(cmdline[1:])
        for k, arg in enumerate(args):
            if arg == "-m" and k + 1 < len(args):
                return args[k + 1]
            if arg == "-c":
                break
            if arg and not arg.startswith("-"):
                return os.path.basename(arg)
    return name or (os.path.basename(cmdline[0]) if cmdline else "")


@dataclass
class _Tracked:
    proc: Any  # psutil.Process
    label: str
    name: str
    primed: bool = False
    thread_s: dict[int, float] = field(default_factory=dict)  # thread id -> CPU seconds at the last round


def busy_threads(before: Mapping[int, float], after: Mapping[int, float]) -> float:
    """The busy threads of a process over one interval: ``(Σ t_k)² / Σ t_k²`` of the CPU
    seconds ``t_k`` each thread used in it (``after`` - ``before``; a thread not in ``before``
    started inside the interval: all its seconds count). n threads equally busy: n; one busy
    thread beside idle ones: 1; no CPU used: 0."""
    used = [max(0.0, t - before.get(k, 0.0)) for k, t in after.items()]
    total, squares = sum(used), sum(u * u for u in used)
    return total * total / squares if squares > 0 else 0.0


def _thread_seconds(proc: Any) -> dict[int, float]:
    """CPU seconds per thread of a psutil process (``Process.threads``)."""
    return {int(t.id): float(t.user_time + t.system_time) for t in proc.threads()}


class CpuRecorder:
    """Samples matching processes every ``interval`` seconds (psutil), writing trace rows.

    A process is tracked when one of ``patterns`` is found (``re.search``) in its node label,
    its name or its command line, or when it descends from ``root_pid`` (COMMAND and its
    children). New processes are picked up at every round; a process's first round only
    primes psutil's counter (psutil's first ``cpu_percent`` is meaningless), so every
    written row measures one full interval, but the last: the round taken when recording
    stops measures the time since the one before (trace.node_cpu weighs it by those seconds).
    """

    def __init__(self, patterns: Sequence[str], interval: float, *, root_pid: int | None = None,
                 exclude_pids: Iterable[int] = ()) -> None:
        if not math.isfinite(interval) or interval <= 0:
            raise ValueError("interval must be a finite number > 0")
        self.patterns = [re.compile(p) for p in patterns]
        self.interval = interval
        self.root_pid = root_pid
        self.exclude = {os.getpid(), *exclude_pids}
        self.tracked: dict[tuple[int, float], _Tracked] = {}

    def _wanted(self, label: str, name: str, cmdline: Sequence[str]) -> bool:
        joined = " ".join(cmdline)
        return any(rx.search(label) or rx.search(name) or rx.search(joined) for rx in self.patterns)

    def _scan(self) -> None:
        import psutil

        family: set[int] = set()
        if self.root_pid is not None:
            try:
                root = psutil.Process(self.root_pid)
                family = {self.root_pid, *(c.pid for c in root.children(recursive=True))}
            except psutil.Error:
                family = set()
        for proc in psutil.process_iter(["pid", "name", "cmdline", "create_time"]):
            info = proc.info
            pid = info["pid"]
            if pid in self.exclude:
                continue
            key = (pid, info.get("create_time") or 0.0)
            name = info.get("name") or ""
            cmdline = info.get("cmdline") or []
            label = ros_node_label(name, cmdline)
            if key in self.tracked:  # refresh: an exec keeps the pid but changes the program
                self.tracked[key].label, self.tracked[key].name = label, name
                continue
            if pid in family or self._wanted(label, name, cmdline):
                self.tracked[key] = _Tracked(proc, label, name)

    def sample(self, now: float | None = None) -> list[tuple[float, int, str, str, float, int, float]]:
        """One round: scan for new processes, read every tracked one. Returns the rows
        (:data:`~perfros_bag.cpu.trace.TRACE_COLUMNS`, then the busy threads)."""
        import psutil

        self._scan()
        stamp = _time.time() if now is None else now
        rows: list[tuple[float, int, str, str, float, int, float]] = []
        for key, tr in list(self.tracked.items()):
            try:
                with tr.proc.oneshot():
                    cpu = tr.proc.cpu_percent(None)
                    rss = tr.proc.memory_info().rss
                    threads = _thread_seconds(tr.proc)
            except psutil.Error:
                del self.tracked[key]
                continue
            if tr.primed:
                rows.append((stamp, key[0], tr.label, tr.name, cpu, rss, busy_threads(tr.thread_s, threads)))
            tr.primed, tr.thread_s = True, threads
        return rows


def record_cpu(out: str | Path, patterns: Sequence[str], interval: float = 0.5, *,
               duration: float | None = None, command: Sequence[str] | None = None,
               stop: threading.Event | None = None, handle_signals: bool = True,
               on_round: Callable[[int, int], None] | None = None, speed: bool = True) -> int:
    """Record a CPU trace to ``out`` (written atomically when the recording ends).

    With ``speed`` the machine's speed is measured first (~0.2 s of CPU, before COMMAND
    starts: :func:`perfros_bag.cpu.speed.measure_speed`) and written as ``# speed_factor=``
    and ``# reference_s=`` comment lines.

    Stops when ``duration`` seconds have passed, ``stop`` is set, SIGINT/SIGTERM arrive
    (with ``handle_signals``; they are forwarded to COMMAND), or ``command`` exits.
    Returns COMMAND's exit code (0 without a command). ``on_round(round, rows)`` is called
    after every sampling round.
    """
    import psutil

    from perfros_bag.fileio import atomic_open

    if not patterns and not command:
        raise InputError(None, "nothing to watch: no process pattern and no command")
    for pat in patterns:
        try:
            re.compile(pat)
        except re.error as exc:
            raise InputError(None, f"process pattern {pat!r} is not a valid regular expression: {exc}") from None
    if Path(out).is_dir():
        raise InputError(out, "is a directory, expected the CPU trace file to write")
    stop = stop or threading.Event()
    child: subprocess.Popen[bytes] | None = None
    old_handlers: dict[int, Any] = {}

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()
        if child is not None and child.poll() is None:
            try:
                child.send_signal(signum)
            except OSError:
                pass

    if handle_signals and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old_handlers[sig] = signal.signal(sig, on_signal)
    rc = 0
    measured = None
    if speed:
        from perfros_bag.cpu.speed import measure_speed

        measured = measure_speed()
    try:
        if command:
            try:
                child = subprocess.Popen(list(command))
            except OSError as exc:
                raise InputError(None, f"cannot run {command[0]!r}: {exc.strerror or exc}") from None
        recorder = CpuRecorder(patterns, interval, root_pid=child.pid if child else None)
        try:
            with atomic_open(out, "w") as handle:
                handle.write(trace_header(socket.gethostname(), psutil.cpu_count(logical=True) or 1, interval,
                                          speed_factor=None if measured is None else measured.factor,
                                          reference_s=None if measured is None else measured.reference_s,
                                          threads=True))
                rc = _loop(recorder, handle, interval, duration, child, stop, on_round)
        except OSError as exc:
            raise InputError(out, f"cannot write the CPU trace: {exc.strerror or exc}") from None
    finally:
        for signum, old in old_handlers.items():
            signal.signal(signum, old)
        if child is not None and child.poll() is None:
            child.terminate()
            try:
                child.wait(5)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
    return rc


def _loop(recorder: CpuRecorder, handle: IO[str], interval: float, duration: float | None,
          child: subprocess.Popen[bytes] | None, stop: threading.Event,
          on_round: Callable[[int, int], None] | None) -> int:
    writer = csv.writer(handle, lineterminator="\n")
    start = _time.monotonic()
    deadline = None if duration is None else start + duration
    rnd = 0
    rc = 0
    while True:
        rows = recorder.sample()
        for row in rows:
            writer.writerow(format_row(row))
        handle.flush()
        if on_round is not None:
            on_round(rnd, len(rows))
        if child is not None and child.poll() is not None:
            rc = int(child.returncode)
            if rc < 0:  # killed by a signal: the shell's convention
                rc = 128 - rc
            break
        if stop.is_set():
            break
        now = _time.monotonic()
        if deadline is not None and now >= deadline - 1e-3:
            break
        rnd += 1
        wake = start + rnd * interval
        if deadline is not None:
            wake = min(wake, deadline)
        if child is not None:
            # wake early when the command exits, but sample once more at that moment
            while not stop.is_set() and _time.monotonic() < wake and child.poll() is None:
                stop.wait(min(0.05, max(0.0, wake - _time.monotonic())))
        else:
            stop.wait(max(0.0, wake - _time.monotonic()))
    return rc
