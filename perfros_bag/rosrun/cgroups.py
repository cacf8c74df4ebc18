"""Computers emulated as Linux cgroups: one CPU-capped group per computer.

A computer of capacity R CPU units gets ``R / units_per_core`` cores of CPU time
(CFS bandwidth: ``cpu.cfs_quota_us`` on cgroup v1, ``cpu.max`` on cgroup v2) and a large
CPU weight, so the emulated computers are not starved by unrelated load on the host.

The bandwidth period is :data:`PERIOD_US`, 10 ms (v1 and v2 alike). A group that spends its
quota waits for the next period: with the kernel's default 100 ms a light node on a busy
computer was stalled up to 100 ms at a time (p95 of 94-140 ms where its p50 was 20 ms), fast
between stalls, which no real computer of that size does. At 10 ms a message is served at
about the computer's speed (its CPU per message / its cores), as a smaller computer would
serve it; 5 ms is no better on this kernel (its bandwidth slice is 5 ms) and throttles twice
as often. Measured: docs/benchmarks.md, "CFS period" (tests/bench/bench_cfs_period.py), which
also states the risk: on a machine loaded by other work, a group with little headroom lost
more frames at 10 ms than at 100 ms. ``PERFROS_CFS_PERIOD_US`` (:data:`PERIOD_ENV`) sets
another period for a run.
A process joins its computer's group before it execs (see :meth:`CpuGroups.wrap`), so
its whole life is capped.

Where cgroups cannot be created (no root, read-only cgroupfs, no cpu controller), the
groups fall back to ``uncapped``: a clear warning, processes run without a cap, and the
run is marked uncapped. :meth:`CpuGroups.remove` deletes every group it created.
:func:`emulated_trace` rescales a host's CPU trace to the emulated computers' units.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from perfros_bag.errors import InputError, PerfrosWarning

if TYPE_CHECKING:
    from perfros_bag.system.plan import Plan

CGROUP_ROOT = Path(os.environ.get("PERFROS_CGROUP_ROOT", "/sys/fs/cgroup"))
PREFIX = "perfros-"
PERIOD_US = 10_000  # the CFS bandwidth period (was 100_000 before issue 29: see the module's docstring)
#: environment variable overriding :data:`PERIOD_US` for a run (µs, 1000-1000000), e.g. 100000
#: to emulate as before issue 29
PERIOD_ENV = "PERFROS_CFS_PERIOD_US"
MIN_QUOTA_US = 1000  # the kernel's smallest CFS quota (v1 and v2)
MAX_PERIOD_US = 1_000_000  # the kernel's longest CFS period
WEIGHT_V1 = 10240  # cpu.shares (default 1024)
WEIGHT_V2 = 1000  # cpu.weight (default 100)


def cgroup_version(root: Path = CGROUP_ROOT) -> str:
    """``v2`` (unified), ``v1`` (a ``cpu`` controller hierarchy) or ``none``."""
    if (root / "cgroup.controllers").exists():
        return "v2"
    if (root / "cpu" / "cpu.cfs_quota_us").exists():
        return "v1"
    return "none"


@dataclass
class CpuGroups:
    """One cgroup per computer for the run ``run_id`` (names ``perfros-<run_id>-<computer>``)."""

    run_id: str
    cores: dict[str, float]  # computer -> cores of CPU time
    root: Path = CGROUP_ROOT
    period_us: int = field(default_factory=lambda: default_period_us())  # the CFS period (quota = cores x period)
    burst: float = 0.0  # CFS burst as a share of the quota (0-1; kernels >= 5.14), 0: none
    mode: str = "uncapped"  # "cgroup-v1" | "cgroup-v2" | "uncapped"
    reason: str = ""
    dirs: dict[str, Path] = field(default_factory=dict)

    @property
    def capped(self) -> bool:
        return self.mode != "uncapped"

    def create(self, *, capped: bool = True, quiet: bool = False) -> None:
        """Create the groups; with ``capped=False`` without a quota yet (see :meth:`apply`).
        ``quiet``: no warning when that fails (a run that was not going to cap anyway)."""
        version = cgroup_version(self.root)
        try:
            if version == "v1":
                base = self.root / "cpu"
                for comp in self.cores:
                    d = base / f"{PREFIX}{self.run_id}-{comp}"
                    d.mkdir()
                    self.dirs[comp] = d
                    (d / "cpu.cfs_period_us").write_text(str(self.group_period_us(comp)))
                    (d / "cpu.cfs_quota_us").write_text(str(self._quota(comp)) if capped else "-1")
                    (d / "cpu.shares").write_text(str(WEIGHT_V1))
                self.mode = "cgroup-v1"
            elif version == "v2":
                ctl = self.root / "cgroup.subtree_control"
                if "cpu" not in ctl.read_text().split():
                    ctl.write_text("+cpu")
                for comp in self.cores:
                    d = self.root / f"{PREFIX}{self.run_id}-{comp}"
                    d.mkdir()
                    self.dirs[comp] = d
                    (d / "cpu.max").write_text(f"{self._quota(comp) if capped else 'max'} {self.group_period_us(comp)}")
                    (d / "cpu.weight").write_text(str(WEIGHT_V2))
                self.mode = "cgroup-v2"
            else:
                raise OSError(f"no cgroup cpu controller under {self.root}")
            self._probe()
        except OSError as exc:
            self.remove()
            self.mode = "uncapped"
            self.reason = str(exc)
            if quiet:
                return
            warnings.warn(f"cannot create CPU-capped cgroups ({exc}); the computers run UNCAPPED "
                          "(results are marked uncapped: overloads will not show)", PerfrosWarning,
                          stacklevel=2)

    def _probe(self) -> None:
        """A process can join each group (the same shell step :meth:`wrap` uses)."""
        import subprocess

        for comp in self.dirs:
            argv = self.wrap(comp, ["/bin/true"])
            done = subprocess.run(argv, capture_output=True, text=True, timeout=10, check=False)
            if done.returncode != 0:
                raise OSError(f"cannot move a process into {self.dirs[comp]}: {done.stderr.strip() or done.returncode}")

    def apply(self) -> None:
        """Set every group's CPU quota and period (the nodes start uncapped: rospy's imports
        are slow); the period may have changed since :meth:`create` (the benchmarks')."""
        for comp, d in self.dirs.items():
            quota, period = self._quota(comp), self.group_period_us(comp)
            if self.mode == "cgroup-v1":  # no quota while the period changes: quota/period is checked
                (d / "cpu.cfs_quota_us").write_text("-1")
                (d / "cpu.cfs_period_us").write_text(str(period))
                (d / "cpu.cfs_quota_us").write_text(str(quota))
            elif self.mode == "cgroup-v2":
                (d / "cpu.max").write_text(f"{quota} {period}")
            burst = self._burst_file(d)
            if burst is not None:  # at most the quota (the kernel's rule): written after it
                burst.write_text(str(int(min(1.0, max(0.0, self.burst)) * quota)))

    def _burst_file(self, d: Path) -> Path | None:
        """The group's CFS burst file (``cpu.cfs_burst_us`` v1, ``cpu.max.burst`` v2), None
        where the kernel has none."""
        f = d / ("cpu.cfs_burst_us" if self.mode == "cgroup-v1" else "cpu.max.burst")
        return f if self.mode != "uncapped" and f.exists() else None

    def group_period_us(self, computer: str) -> int:
        """The CFS period of ``computer``'s group: :attr:`period_us`, made longer where the
        quota would fall under the kernel's 1 ms minimum (a computer of less than
        1 ms / period cores: e.g. under 0.2 cores at 5 ms), so the cap stays its size."""
        return group_period_us(self.cores[computer], self.period_us)

    def cap_record(self) -> dict[str, object]:
        """What deploy.json's ``cpu_cap`` states of the CFS bandwidth: ``period_us`` (the
        default period) and ``periods_us`` (each computer's group: longer where its quota
        would fall under 1 ms)."""
        return {"period_us": self.period_us, "periods_us": {c: self.group_period_us(c) for c in self.cores},
                "burst": self.burst}

    def _quota(self, computer: str) -> int:
        return _quota_us(self.cores[computer], self.group_period_us(computer))

    def procs_file(self, computer: str) -> Path | None:
        d = self.dirs.get(computer)
        return None if d is None else d / "cgroup.procs"

    def wrap(self, computer: str, argv: list[str]) -> list[str]:
        """``argv`` prefixed so the process joins ``computer``'s group, then execs."""
        procs = self.procs_file(computer)
        if procs is None:
            return argv
        return ["/bin/sh", "-c", 'echo $$ > "$0" && exec "$@"', str(procs), *argv]

    def throttled(self, computer: str) -> dict[str, float]:
        """CFS throttling counters of the group (nr_periods, nr_throttled, throttled seconds)."""
        d = self.dirs.get(computer)
        out: dict[str, float] = {}
        if d is None:
            return out
        try:
            for line in (d / "cpu.stat").read_text().splitlines():
                key, _, val = line.partition(" ")
                if key in ("nr_periods", "nr_throttled"):
                    out[key] = float(val)
                elif key == "throttled_time":  # v1, ns
                    out["throttled_s"] = float(val) / 1e9
                elif key == "throttled_usec":  # v2
                    out["throttled_s"] = float(val) / 1e6
        except (OSError, ValueError):
            pass
        return out

    def remove(self, timeout: float = 5.0) -> list[Path]:
        """Delete the groups (waiting for their processes to be gone); returns those left."""
        left: list[Path] = []
        for comp, d in list(self.dirs.items()):
            deadline = time.monotonic() + timeout
            while True:
                try:
                    d.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        left.append(d)
                        break
                    time.sleep(0.05)
            if d not in left:
                del self.dirs[comp]
        return left


def default_period_us() -> int:
    """:data:`PERIOD_US`, or :data:`PERIOD_ENV`'s value when set (a bad one is an InputError)."""
    raw = os.environ.get(PERIOD_ENV, "").strip()
    if not raw:
        return PERIOD_US
    try:
        value = int(raw)
    except ValueError:
        raise InputError(None, f"{PERIOD_ENV}={raw!r} is not a whole number of microseconds") from None
    if not MIN_QUOTA_US <= value <= MAX_PERIOD_US:
        raise InputError(None, f"{PERIOD_ENV}={value} must be {MIN_QUOTA_US}-{MAX_PERIOD_US} µs (the kernel's range)")
    return value


def _quota_us(cores: float, period_us: int = PERIOD_US) -> int:
    return max(MIN_QUOTA_US, int(round(cores * period_us)))


def group_period_us(cores: float, period_us: int = PERIOD_US) -> int:
    """The period for a group of ``cores``: ``period_us``, or the shortest that keeps its
    quota at the kernel's minimum (:data:`MIN_QUOTA_US`), at most :data:`MAX_PERIOD_US`."""
    if cores <= 0 or cores * period_us >= MIN_QUOTA_US:
        return period_us
    return min(MAX_PERIOD_US, math.ceil(MIN_QUOTA_US / cores))


def leftover_groups(root: Path = CGROUP_ROOT, run_id: str | None = None) -> list[Path]:
    """perfros cgroups still present (of one run, or of any)."""
    pattern = f"{PREFIX}{run_id}-*" if run_id else f"{PREFIX}*"
    found: list[Path] = []
    for base in (root / "cpu", root):
        if base.is_dir():
            found += sorted(base.glob(pattern))
    return found


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
    from perfros_bag.cpu.trace import has_threads, read_cpu_trace, trace_rows, write_cpu_trace

    tr = read_cpu_trace(raw)
    rows = []
    for row in trace_rows(tr):
        comp = where.get(row[2])
        if comp is None:
            continue
        rows.append((*row[:4], row[4] * tr.logical_cpus * units_per_core / capacity[comp], *row[5:]))
    write_cpu_trace(dest, rows, host=f"{tr.host or 'host'} (emulated computers: cpu_percent scaled by "
                    f"N*{units_per_core:g}/capacity; raw psutil trace: {raw.name})",
                    logical_cpus=tr.logical_cpus, interval_s=tr.interval_s or 0.5,
                    speed_factor=tr.speed_factor, reference_s=tr.reference_s, threads=has_threads(tr))


def computer_cores(plan: Plan, units_per_core: float,
                   capacities: Mapping[str, float | None] | None = None) -> dict[str, float]:
    """Cores of CPU time per computer the plan uses: its capacity / ``units_per_core``; the
    plan's capacity, else ``capacities[name]`` (e.g. the system's)."""
    cores: dict[str, float] = {}
    for name in sorted({pn.computer for pn in plan.nodes.values()}):
        cap = plan.computers[name].capacity if name in plan.computers else None
        if cap is None and capacities is not None:
            cap = capacities.get(name)
        if cap is None or cap <= 0:
            raise InputError(plan.system, f"the plan's computer {name!r} has no capacity to emulate")
        cores[name] = cap / units_per_core
    return cores
