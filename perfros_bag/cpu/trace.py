"""psutil CPU traces, ``<stem>.cpu.csv``: reading, attribution to nodes, writing.

The recorder behind ``record-cpu`` is :mod:`perfros_bag.cpu.record`.

File format (design.md contract)::

    # host=NAME
    # logical_cpus=N
    # interval_s=X
    # speed_factor=F           (optional: the machine's speed, perfros_bag.cpu.speed)
    # reference_s=S            (optional: the reference workload's CPU seconds behind F)
    time,pid,node,process,cpu_percent,rss_bytes[,threads]
    1700000000.500,4242,tracker1,python3,81.2,52428800,1.97

``time`` is Unix seconds, ``cpu_percent`` is psutil's per-process figure (100 = one core
busy over the previous interval). One sampling round writes one ``time`` for all the
processes it saw, so a node's CPU at a sample time is the sum over its processes.
CPU units on a computer of capacity R with N logical cores: ``cpu_percent / (100 N) * R``.
``threads`` (optional trailing column, :data:`OPTIONAL_TRACE_COLUMNS`; ``record-cpu`` writes it)
is the process's busy threads over the interval: ``(Σ t_k)² / Σ t_k²`` of the CPU seconds
``t_k`` each of its threads used (two threads equally busy: 2; one busy thread beside idle
ones: ~1; no CPU used: 0). It is what the CFS share of a capped computer counts
(:mod:`perfros_bag.system.cpushare`). Traces without it stay valid (``threads`` all NaN).
``record-cpu`` measures the machine's speed as it starts (:func:`perfros_bag.cpu.speed.measure_speed`)
and writes it as ``# speed_factor=`` (and ``# reference_s=``); traces without it stay valid
(``speed_factor`` None). It is recorded, not applied: CPU figures are never rescaled by it.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from perfros_bag.errors import InputError
from perfros_bag.fileio import read_text
from perfros_bag.limits import MAX_MAGNITUDE, number_problem

TRACE_COLUMNS: tuple[str, ...] = ("time", "pid", "node", "process", "cpu_percent", "rss_bytes")
#: Optional columns after :data:`TRACE_COLUMNS` (in this order; readers accept traces without them).
OPTIONAL_TRACE_COLUMNS: tuple[str, ...] = ("threads",)


# --------------------------------------------------------------------------- reading


@dataclass
class CpuTrace:
    """A parsed CPU trace; one entry per (sample time, process) row."""

    path: Path
    logical_cpus: int  # ``# logical_cpus=``: the cores its CPU percentages are out of (100 each)
    host: str | None = None  # ``# host=``: the computer it was recorded on
    interval_s: float | None = None  # ``# interval_s=``: the sampling interval it was recorded at
    speed_factor: float | None = None  # ``# speed_factor=``: REFERENCE_S / the reference workload's seconds
    reference_s: float | None = None  # ``# reference_s=``: the reference workload's best CPU seconds
    time: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    pid: npt.NDArray[np.int64] = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    node: list[str] = field(default_factory=list)
    process: list[str] = field(default_factory=list)
    cpu_percent: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    rss_bytes: npt.NDArray[np.int64] = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    #: busy threads per row (``threads`` column); NaN where the trace does not give it
    threads: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty(0))

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
    #: mean busy threads over the samples where it used CPU (its processes' summed); None
    #: when the trace has no ``threads`` column or the node never used CPU
    threads: float | None = None


def read_cpu_trace(path: str | Path) -> CpuTrace:
    """Parse a CPU trace; any malformed line is an :class:`InputError` naming file and line."""
    p = Path(path)
    return parse_cpu_trace(read_text(p, "CPU trace CSV"), p)


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
    speed, reference = (_positive(p, meta, key) for key in ("speed_factor", "reference_s"))
    with_threads = len(header) > len(TRACE_COLUMNS) and header[len(TRACE_COLUMNS)] == "threads"
    rest = text[pos:]
    parsed = (_rows_fast(rest, with_threads)
              if fast and len(header) == len(TRACE_COLUMNS) + int(with_threads) else None)
    if parsed is None:
        parsed = _rows_slow(p, rest.splitlines(), len(header), lineno + 1, with_threads)
    times, pids, nodes, procs, cpus, rsss, threads = parsed
    return CpuTrace(p, ncpu, meta.get("host"), interval, speed, reference, times, pids, nodes, procs, cpus, rsss,
                    threads)


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


def _positive(p: Path, meta: Mapping[str, str], key: str) -> float | None:
    """An optional comment value that must be a finite number > 0 (None when absent)."""
    raw = meta.get(key)
    if raw is None or not raw.strip():
        return None
    from perfros_bag.cpu.speed import speed_problem

    try:
        value = float(raw)
    except ValueError:
        raise InputError(p, f"{key}={raw!r} is not a number") from None
    problem = speed_problem(value)
    if problem is not None:
        raise InputError(p, f"{key} {problem.replace(repr(value), repr(raw))}")
    return value


_Rows = tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], list[str], list[str],
              npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float64]]


def _rows_fast(body: str, with_threads: bool = False) -> _Rows | None:
    """pandas' C parser on the rows; None when they need the careful parser (a comment or
    an empty field inside, a bad value, a short or long line: pandas cannot fill a missing
    int64 ``rss_bytes`` and rejects extra fields)."""
    import pandas as pd

    if not body.strip() or body.startswith("#") or "\n#" in body or "\r#" in body:
        return None
    names = [f"c{k}" for k in range(len(TRACE_COLUMNS) + int(with_threads))]
    dtypes: dict[str, Any] = {"c0": "float64", "c1": "int64", "c2": object, "c3": object,
                              "c4": "float64", "c5": "int64", "c6": "float64"}
    dtypes = {k: v for k, v in dtypes.items() if k in names}
    try:
        df = pd.read_csv(io.StringIO(body), header=None, names=names, engine="c", na_filter=False,
                         dtype=dtypes, skip_blank_lines=True)
    except (ValueError, TypeError, OverflowError, pd.errors.ParserError):
        return None
    times = df["c0"].to_numpy(dtype=np.float64)
    cpus = df["c4"].to_numpy(dtype=np.float64)
    if not (np.isfinite(times).all() and np.isfinite(cpus).all() and (cpus >= 0).all()
            and (np.abs(times) <= MAX_MAGNITUDE).all() and (cpus <= MAX_MAGNITUDE).all()):
        return None  # the careful parser names the line and the problem
    threads = df["c6"].to_numpy(dtype=np.float64) if with_threads else np.full(times.size, np.nan)
    if with_threads and not (np.isfinite(threads).all() and (threads >= 0).all() and (threads <= MAX_MAGNITUDE).all()):
        return None
    return (times, df["c1"].to_numpy(dtype=np.int64), [str(x) for x in df["c2"].tolist()],
            [str(x) for x in df["c3"].tolist()], cpus, df["c5"].to_numpy(dtype=np.int64), threads)


def _rows_slow(p: Path, rows: list[str], ncol: int, first_lineno: int, with_threads: bool = False) -> _Rows:
    times: list[float] = []
    pids: list[int] = []
    nodes: list[str] = []
    procs: list[str] = []
    cpus: list[float] = []
    rsss: list[int] = []
    threads: list[float] = []
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
        busy = _num(p, lineno, "threads", row[6], float) if with_threads and row[6].strip() else math.nan
        if busy < 0:
            raise InputError(p, f"line {lineno}: threads must be >= 0, got {row[6]!r}")
        threads.append(busy)
        times.append(t)
        pids.append(pid)
        nodes.append(row[2])
        procs.append(row[3])
        cpus.append(cpu)
        rsss.append(rss)
    return (np.asarray(times, dtype=np.float64), np.asarray(pids, dtype=np.int64), nodes, procs,
            np.asarray(cpus, dtype=np.float64), np.asarray(rsss, dtype=np.int64),
            np.asarray(threads, dtype=np.float64))


def _num(p: Path, lineno: int, name: str, raw: str, kind: Callable[[str], Any]) -> Any:
    try:
        value = kind(raw.strip())
    except ValueError:
        raise InputError(p, f"line {lineno}: {name} {raw!r} is not "
                            f"a{'n integer' if kind is int else ' number'}") from None
    if kind is float and not math.isfinite(value):
        raise InputError(p, f"line {lineno}: {name} {raw!r} is not a finite number")
    problem = number_problem(value) if kind is float else None  # time and CPU %: the stated limit
    if problem is not None:
        raise InputError(p, f"line {lineno}: {name} {problem}")
    return value


def match_label(label: str, process: str, node: str, pattern: str | None) -> bool:
    """Does a trace row (its node label and process name) belong to system node ``node``?

    With a ``process`` regex: it is searched in the label and the process name. Without:
    the label equals the node's name, as a ROS name (``/robot1/amcl`` is node
    ``robot1_amcl``, :func:`~perfros_bag.system.names.system_node_name`) or with its
    namespace ignored (``/a/b/amcl`` is ``amcl``)."""
    if pattern is not None:
        rx = re.compile(pattern)
        return bool(rx.search(label) or rx.search(process))
    from perfros_bag.system.names import system_node_name

    return label == node or label.rsplit("/", 1)[-1] == node or system_node_name(label) == node


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


def sample_seconds(trace: CpuTrace) -> dict[float, float]:
    """Per sample time of the trace, the seconds its rows measure (the weights of
    :func:`node_cpu`'s mean): the time since the trace's previous sample time, at most
    ``interval_s`` (a longer gap follows a round that wrote no row, e.g. one that only primed
    a new process; it is not a longer measurement); the first sample time one interval.
    Without ``interval_s`` every sample weighs the same."""
    times = np.unique(trace.time)
    if times.size == 0:
        return {}
    full = trace.interval_s or 1.0
    seconds = np.minimum(np.concatenate(([full], np.diff(times))), full) if trace.interval_s else np.ones(times.size)
    return dict(zip(times.tolist(), seconds.tolist(), strict=True))


def node_cpu(trace: CpuTrace, capacity: float, *, start_ns: int | None = None,
             end_ns: int | None = None, nodes: Mapping[str, str | None] | None = None) -> dict[str, NodeCpu]:
    """Mean and p95 CPU units per node inside [start_ns, end_ns].

    A node's value at a sample time is the sum over its processes; samples are the sample
    times at which the node had at least one process. Units: ``cpu_percent / (100 N) * R``.
    The mean weighs each sample by the seconds it measures (:func:`sample_seconds`): the
    round ``record-cpu`` takes when it is stopped covers only part of an interval, and
    counted as a whole one its few scheduler ticks move a short run's mean by several per
    cent. The p95 is over the samples, unweighted.
    """
    import pandas as pd

    owner = _owners(trace, nodes)
    keep = in_window(trace, start_ns, end_ns) & (owner != "")
    scale = capacity / (100.0 * trace.logical_cpus)
    result: dict[str, NodeCpu] = {}
    if not keep.any():
        return result
    has_threads = trace.threads.size == trace.time.size and bool(np.isfinite(trace.threads[keep]).any())
    seconds = sample_seconds(trace)
    df = pd.DataFrame({"node": owner[keep], "time": trace.time[keep], "units": trace.cpu_percent[keep] * scale,
                       "threads": trace.threads[keep] if has_threads else np.full(int(keep.sum()), np.nan)})
    grouped = df.groupby(["node", "time"], sort=False)  # a node's processes, per sample
    sums = grouped.units.sum()
    busy = grouped.threads.sum(min_count=1)
    order = list(dict.fromkeys(df["node"].tolist()))
    for name, per_time in sums.groupby(level=0, sort=False):
        values = per_time.to_numpy(dtype=np.float64)
        weights = np.array([seconds[t] for t in per_time.index.get_level_values(1)], dtype=np.float64)
        mean = float(np.average(values, weights=weights)) if weights.sum() > 0 else float(values.mean())
        counts = busy.loc[name].to_numpy(dtype=np.float64)
        counts = counts[np.isfinite(counts) & (counts > 0)]  # samples where it ran
        result[str(name)] = NodeCpu(str(name), mean, float(np.percentile(values, 95)), int(values.size),
                                    float(counts.mean()) if counts.size else None)
    return {n: result[n] for n in order}


def trace_speed(path: str | Path) -> float | None:
    """A trace's ``# speed_factor=`` (None when it has none, or cannot be read): the comment
    lines only, for writers of manifests (``sweep``, ``deploy``)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if not line.startswith("#"):
                    break
                key, _, value = line.lstrip("#").strip().partition("=")
                if key.strip() == "speed_factor":
                    from perfros_bag.cpu.speed import speed_problem

                    try:
                        factor = float(value)
                    except ValueError:
                        return None
                    return factor if speed_problem(factor) is None else None
    except OSError:
        return None
    return None


# --------------------------------------------------------------------------- writing


def trace_header(host: str, logical_cpus: int, interval_s: float, *, speed_factor: float | None = None,
                 reference_s: float | None = None, threads: bool = False) -> str:
    """The comment lines and the header; ``speed_factor`` / ``reference_s`` only when given,
    the ``threads`` column with ``threads``."""
    extra = "" if speed_factor is None else f"# speed_factor={speed_factor:.4g}\n"
    extra += "" if reference_s is None else f"# reference_s={reference_s:.6g}\n"
    columns = TRACE_COLUMNS + (OPTIONAL_TRACE_COLUMNS if threads else ())
    return (f"# host={host}\n# logical_cpus={logical_cpus}\n# interval_s={interval_s:g}\n{extra}"
            + ",".join(columns) + "\n")


def write_cpu_trace(path: str | Path, rows: Iterable[Sequence[Any]], *, host: str,
                    logical_cpus: int, interval_s: float, speed_factor: float | None = None,
                    reference_s: float | None = None, threads: bool = False) -> None:
    """Write a whole trace atomically (rows in :data:`TRACE_COLUMNS` order; with ``threads``
    each row has a seventh value, its busy threads, NaN or None for an empty cell)."""
    from perfros_bag.fileio import atomic_open

    with atomic_open(path, "w") as handle:
        handle.write(trace_header(host, logical_cpus, interval_s, speed_factor=speed_factor,
                                  reference_s=reference_s, threads=threads))
        writer = csv.writer(handle, lineterminator="\n")
        for row in rows:
            writer.writerow(format_row(row if threads else row[:len(TRACE_COLUMNS)]))


def format_row(row: Sequence[Any]) -> list[str]:
    """One trace row (TRACE_COLUMNS order, then optionally ``threads``) as CSV fields: time
    to the millisecond, threads to 0.01."""
    t, pid, node, proc, cpu, rss = row[:len(TRACE_COLUMNS)]
    out = [f"{float(t):.3f}", str(int(pid)), str(node), str(proc), f"{float(cpu):g}", str(int(rss))]
    if len(row) > len(TRACE_COLUMNS):
        busy = row[len(TRACE_COLUMNS)]
        out.append("" if busy is None or not math.isfinite(float(busy)) else f"{float(busy):.2f}")
    return out


def trace_rows(trace: CpuTrace) -> list[tuple[Any, ...]]:
    """The trace's rows as :func:`write_cpu_trace` takes them (with ``threads`` when
    :func:`has_threads`)."""
    base = zip(trace.time.tolist(), trace.pid.tolist(), trace.node, trace.process, trace.cpu_percent.tolist(),
               trace.rss_bytes.tolist(), strict=True)
    if not has_threads(trace):
        return [tuple(r) for r in base]
    return [(*r, b) for r, b in zip(base, trace.threads.tolist(), strict=True)]


def has_threads(trace: CpuTrace) -> bool:
    """Does the trace carry the ``threads`` column (some row with a value)?"""
    return trace.threads.size == trace.time.size and bool(np.isfinite(trace.threads).any())
