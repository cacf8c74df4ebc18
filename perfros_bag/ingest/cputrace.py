"""psutil CPU traces: the ``<stem>.cpu.csv`` reader and the recorder behind ``record-cpu``.

File format (design.md contract)::

    # host=NAME
    # logical_cpus=N
    # interval_s=X
    time,pid,node,process,cpu_percent,rss_bytes
    1700000000.500,4242,tracker1,python3,81.2,52428800

``time`` is Unix seconds, ``cpu_percent`` is psutil's per-process figure (100 = one core
busy over the previous interval). One sampling round writes one ``time`` for all the
processes it saw, so a node's CPU at a sample time is the sum over its processes.
CPU units on a computer of capacity R with N logical cores: ``cpu_percent / (100 N) * R``.
"""

from __future__ import annotations

import csv
import io
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

import numpy as np
import numpy.typing as npt

from perfros_bag.errors import InputError

TRACE_COLUMNS: tuple[str, ...] = ("time", "pid", "node", "process", "cpu_percent", "rss_bytes")


# --------------------------------------------------------------------------- reading


@dataclass
class CpuTrace:
    """A parsed CPU trace; one entry per (sample time, process) row."""

    path: Path
    logical_cpus: int
    host: str | None = None
    interval_s: float | None = None
    time: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    pid: npt.NDArray[np.int64] = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    node: list[str] = field(default_factory=list)
    process: list[str] = field(default_factory=list)
    cpu_percent: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    rss_bytes: npt.NDArray[np.int64] = field(default_factory=lambda: np.empty(0, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.time.size)

    @property
    def labels(self) -> list[str]:
        """The distinct trace node labels, in order of first appearance."""
        return list(dict.fromkeys(self.node))


@dataclass(frozen=True)
class NodeCpu:
    """A node's CPU over the samples inside a recording's window, in CPU units."""

    node: str
    mean: float
    p95: float
    samples: int


def read_cpu_trace(path: str | Path) -> CpuTrace:
    """Parse a CPU trace; any malformed line is an :class:`InputError` naming file and line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(p, "CPU trace not found") from None
    except IsADirectoryError:
        raise InputError(p, "is a directory, expected a CPU trace CSV") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read CPU trace: {exc}") from None
    return parse_cpu_trace(text, p)


def parse_cpu_trace(text: str, path: str | Path = "<cpu trace>", *, fast: bool = True) -> CpuTrace:
    """Parse a trace's text. ``fast`` reads the rows with pandas' C parser; anything it
    does not accept cleanly is re-read line by line, which names the first bad line."""
    p = Path(path)
    meta: dict[str, str] = {}
    pos, lineno, header_line = 0, 0, None
    while pos < len(text):  # comment lines, then the header: only the top of the file
        nl = text.find("\n", pos)
        end = len(text) if nl < 0 else nl
        line = text[pos:end].rstrip("\r")
        lineno += 1
        pos = end + 1
        if line.startswith("#") or not line.strip():
            body = line.lstrip("#").strip()
            if "=" in body:
                key, _, value = body.partition("=")
                meta[key.strip()] = value.strip()
            continue
        header_line = line
        break
    if header_line is None:
        raise InputError(p, f"no header line (expected '{','.join(TRACE_COLUMNS)}')")
    header = [h.strip() for h in header_line.split(",")]
    if tuple(header[: len(TRACE_COLUMNS)]) != TRACE_COLUMNS:
        raise InputError(p, f"line {lineno}: bad header {header_line!r} (expected '{','.join(TRACE_COLUMNS)}')")
    ncpu, interval = _meta(p, meta)
    rest = text[pos:]
    parsed = _rows_fast(rest) if fast and len(header) == len(TRACE_COLUMNS) else None
    if parsed is None:
        parsed = _rows_slow(p, rest.splitlines(), len(header), lineno + 1)
    times, pids, nodes, procs, cpus, rsss = parsed
    return CpuTrace(p, ncpu, meta.get("host"), interval, times, pids, nodes, procs, cpus, rsss)


def _meta(p: Path, meta: Mapping[str, str]) -> tuple[int, float | None]:
    if "logical_cpus" not in meta:
        raise InputError(p, "missing the '# logical_cpus=N' comment line (needed to normalise CPU)")
    try:
        ncpu = int(meta["logical_cpus"])
    except ValueError:
        raise InputError(p, f"logical_cpus={meta['logical_cpus']!r} is not an integer") from None
    if ncpu <= 0:
        raise InputError(p, f"logical_cpus must be > 0, got {ncpu}")
    interval: float | None = None
    if meta.get("interval_s"):
        try:
            interval = float(meta["interval_s"])
        except ValueError:
            raise InputError(p, f"interval_s={meta['interval_s']!r} is not a number") from None
        if not (math.isfinite(interval) and interval > 0):
            raise InputError(p, f"interval_s must be > 0, got {meta['interval_s']!r}")
    return ncpu, interval


_Rows = tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], list[str], list[str],
              npt.NDArray[np.float64], npt.NDArray[np.int64]]


def _rows_fast(body: str) -> _Rows | None:
    """pandas' C parser on the rows; None when they need the careful parser (a comment or
    an empty field inside, a bad value, a short or long line: pandas cannot fill a missing
    int64 ``rss_bytes`` and rejects extra fields)."""
    import pandas as pd

    if not body.strip() or body.startswith("#") or "\n#" in body or "\r#" in body:
        return None
    names = [f"c{k}" for k in range(len(TRACE_COLUMNS))]
    dtypes: dict[str, Any] = {"c0": "float64", "c1": "int64", "c2": object, "c3": object,
                              "c4": "float64", "c5": "int64"}
    try:
        df = pd.read_csv(io.StringIO(body), header=None, names=names, engine="c", na_filter=False,
                         dtype=dtypes, skip_blank_lines=True)
    except (ValueError, TypeError, OverflowError, pd.errors.ParserError):
        return None
    times = df["c0"].to_numpy(dtype=np.float64)
    cpus = df["c4"].to_numpy(dtype=np.float64)
    if not (np.isfinite(times).all() and np.isfinite(cpus).all() and (cpus >= 0).all()):
        return None
    return (times, df["c1"].to_numpy(dtype=np.int64), [str(x) for x in df["c2"].tolist()],
            [str(x) for x in df["c3"].tolist()], cpus, df["c5"].to_numpy(dtype=np.int64))


def _rows_slow(p: Path, rows: list[str], ncol: int, first_lineno: int) -> _Rows:
    times: list[float] = []
    pids: list[int] = []
    nodes: list[str] = []
    procs: list[str] = []
    cpus: list[float] = []
    rsss: list[int] = []
    reader = csv.reader(io.StringIO("\n".join(rows)))
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:
            raise InputError(p, f"line {first_lineno + reader.line_num - 1}: not CSV: {exc}") from None
        lineno = first_lineno + reader.line_num - 1  # the row's last physical line
        if not row or (len(row) == 1 and not row[0].strip()) or row[0].startswith("#"):
            continue
        if len(row) != ncol:
            raise InputError(p, f"line {lineno}: expected {ncol} fields, got {len(row)}")
        t = _num(p, lineno, "time", row[0], float)
        pid = _num(p, lineno, "pid", row[1], int)
        cpu = _num(p, lineno, "cpu_percent", row[4], float)
        rss = _num(p, lineno, "rss_bytes", row[5], int) if row[5].strip() else 0
        if cpu < 0:
            raise InputError(p, f"line {lineno}: cpu_percent must be >= 0, got {row[4]!r}")
        times.append(t)
        pids.append(pid)
        nodes.append(row[2])
        procs.append(row[3])
        cpus.append(cpu)
        rsss.append(rss)
    return (np.asarray(times, dtype=np.float64), np.asarray(pids, dtype=np.int64), nodes, procs,
            np.asarray(cpus, dtype=np.float64), np.asarray(rsss, dtype=np.int64))


def _num(p: Path, lineno: int, name: str, raw: str, kind: Callable[[str], Any]) -> Any:
    try:
        value = kind(raw.strip())
    except ValueError:
        raise InputError(p, f"line {lineno}: {name} {raw!r} is not a{'n integer' if kind is int else ' number'}") from None
    if kind is float and not math.isfinite(value):
        raise InputError(p, f"line {lineno}: {name} {raw!r} is not a finite number")
    return value


def match_label(label: str, process: str, node: str, pattern: str | None) -> bool:
    """Does a trace row (its node label and process name) belong to system node ``node``?

    With a ``process`` regex: it is searched in the label and the process name. Without:
    the label equals the node's name (a leading namespace ``/a/b/`` is ignored)."""
    if pattern is not None:
        rx = re.compile(pattern)
        return bool(rx.search(label) or rx.search(process))
    return label == node or label.rsplit("/", 1)[-1] == node


def assign_nodes(trace: CpuTrace, nodes: Mapping[str, str | None] | None) -> list[str]:
    """The system node of each trace row ('' when none).

    ``nodes`` maps system node name -> its ``process`` regex (or None: match by name).
    An exact name match wins over a regex; among regexes the first node (in order) wins.
    Without ``nodes`` the trace's own labels are the nodes.
    """
    if nodes is None:
        return list(trace.node)
    return _owners(trace, nodes).tolist()


def _owners(trace: CpuTrace, nodes: Mapping[str, str | None] | None) -> npt.NDArray[np.object_]:
    """:func:`assign_nodes` as an object array, matching each distinct (label, process) once."""
    import pandas as pd

    if not len(trace):
        return np.empty(0, dtype=object)
    c_node, u_node = pd.factorize(np.asarray(trace.node, dtype=object))
    c_proc, u_proc = pd.factorize(np.asarray(trace.process, dtype=object))
    pair_codes, codes = np.unique(c_node.astype(np.int64) * max(1, len(u_proc)) + c_proc, return_inverse=True)
    owner = []
    for pc in pair_codes.tolist():
        label, proc = str(u_node[pc // max(1, len(u_proc))]), str(u_proc[pc % max(1, len(u_proc))])
        if nodes is None:
            owner.append(label)
            continue
        found = next((n for n in nodes if match_label(label, proc, n, None)), None)
        if found is None:
            found = next((n for n, pat in nodes.items() if pat is not None and match_label(label, proc, n, pat)), "")
        owner.append(found)
    return np.asarray(owner, dtype=object)[codes]


def in_window(trace: CpuTrace, start_ns: int | None, end_ns: int | None) -> npt.NDArray[np.bool_]:
    """Rows whose sample time lies in the recording's window [start, end] (inclusive).

    (A sample at t measures (t - interval_s, t]: the first sample inside may cover up to one
    interval before the recording; over a recording of many intervals that edge is noise.)
    Without a window, every row is kept."""
    if start_ns is None or end_ns is None:
        return np.ones(len(trace), dtype=bool)
    return (trace.time >= start_ns / 1e9) & (trace.time <= end_ns / 1e9)


def node_cpu(trace: CpuTrace, capacity: float, *, start_ns: int | None = None,
             end_ns: int | None = None, nodes: Mapping[str, str | None] | None = None) -> dict[str, NodeCpu]:
    """Mean and p95 CPU units per node inside [start_ns, end_ns].

    A node's value at a sample time is the sum over its processes; samples are the sample
    times at which the node had at least one process. Units: ``cpu_percent / (100 N) * R``.
    """
    import pandas as pd

    owner = _owners(trace, nodes)
    keep = in_window(trace, start_ns, end_ns) & (owner != "")
    scale = capacity / (100.0 * trace.logical_cpus)
    result: dict[str, NodeCpu] = {}
    if not keep.any():
        return result
    df = pd.DataFrame({"node": owner[keep], "time": trace.time[keep], "units": trace.cpu_percent[keep] * scale})
    sums = df.groupby(["node", "time"], sort=False).units.sum()  # a node's processes, per sample
    order = list(dict.fromkeys(df["node"].tolist()))
    for name, per_time in sums.groupby(level=0, sort=False):
        values = per_time.to_numpy(dtype=np.float64)
        result[str(name)] = NodeCpu(str(name), float(values.mean()), float(np.percentile(values, 95)), int(values.size))
    return {n: result[n] for n in order}


# --------------------------------------------------------------------------- writing


def trace_header(host: str, logical_cpus: int, interval_s: float) -> str:
    return (f"# host={host}\n# logical_cpus={logical_cpus}\n# interval_s={interval_s:g}\n"
            + ",".join(TRACE_COLUMNS) + "\n")


def write_cpu_trace(path: str | Path, rows: Iterable[Sequence[Any]], *, host: str,
                    logical_cpus: int, interval_s: float) -> None:
    """Write a whole trace atomically (rows in :data:`TRACE_COLUMNS` order)."""
    from perfros_bag.fileio import atomic_open

    with atomic_open(path, "w") as handle:
        handle.write(trace_header(host, logical_cpus, interval_s))
        writer = csv.writer(handle, lineterminator="\n")
        for row in rows:
            writer.writerow(_fmt_row(row))


def _fmt_row(row: Sequence[Any]) -> list[str]:
    t, pid, node, proc, cpu, rss = row
    return [f"{float(t):.3f}", str(int(pid)), str(node), str(proc), f"{float(cpu):g}", str(int(rss))]


# --------------------------------------------------------------------------- recording

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


class CpuRecorder:
    """Samples matching processes every ``interval`` seconds (psutil), writing trace rows.

    A process is tracked when one of ``patterns`` is found (``re.search``) in its node label,
    its name or its command line, or when it descends from ``root_pid`` (COMMAND and its
    children). New processes are picked up at every round; a process's first round only
    primes psutil's counter (psutil's first ``cpu_percent`` is meaningless), so every
    written row measures one full interval.
    """

    def __init__(self, patterns: Sequence[str], interval: float, *, root_pid: int | None = None,
                 exclude_pids: Iterable[int] = ()) -> None:
        if interval <= 0:
            raise ValueError("interval must be > 0")
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

    def sample(self, now: float | None = None) -> list[tuple[float, int, str, str, float, int]]:
        """One round: scan for new processes, read every tracked one. Returns the rows."""
        import psutil

        self._scan()
        stamp = _time.time() if now is None else now
        rows: list[tuple[float, int, str, str, float, int]] = []
        for key, tr in list(self.tracked.items()):
            try:
                with tr.proc.oneshot():
                    cpu = tr.proc.cpu_percent(None)
                    rss = tr.proc.memory_info().rss
            except psutil.Error:
                del self.tracked[key]
                continue
            if tr.primed:
                rows.append((stamp, key[0], tr.label, tr.name, cpu, rss))
            tr.primed = True
        return rows


def record_cpu(out: str | Path, patterns: Sequence[str], interval: float = 0.5, *,
               duration: float | None = None, command: Sequence[str] | None = None,
               stop: threading.Event | None = None, handle_signals: bool = True,
               on_round: Callable[[int, int], None] | None = None) -> int:
    """Record a CPU trace to ``out`` (written atomically when the recording ends).

    Stops when ``duration`` seconds have passed, ``stop`` is set, SIGINT/SIGTERM arrive
    (with ``handle_signals``; they are forwarded to COMMAND), or ``command`` exits.
    Returns COMMAND's exit code (0 without a command). ``on_round(round, rows)`` is called
    after every sampling round.
    """
    import psutil

    from perfros_bag.fileio import atomic_open

    if not patterns and not command:
        raise InputError(None, "record-cpu needs --match REGEX or a COMMAND to watch")
    for pat in patterns:
        try:
            re.compile(pat)
        except re.error as exc:
            raise InputError(None, f"--match {pat!r} is not a valid regular expression: {exc}") from None
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
    try:
        if command:
            try:
                child = subprocess.Popen(list(command))
            except OSError as exc:
                raise InputError(None, f"cannot run {command[0]!r}: {exc.strerror or exc}") from None
        recorder = CpuRecorder(patterns, interval, root_pid=child.pid if child else None)
        try:
            with atomic_open(out, "w") as handle:
                handle.write(trace_header(socket.gethostname(), psutil.cpu_count(logical=True) or 1, interval))
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
            writer.writerow(_fmt_row(row))
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
