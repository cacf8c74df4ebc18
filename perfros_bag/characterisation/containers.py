"""CPU per node inside one process: a container's measured CPU split among the nodes it
hosts (system.yaml ``container``; docs/formats.md, "Nodelets").

A nodelet manager's worker threads are pooled, so neither its process nor its threads say
which nodelet used the CPU. The split is fitted over the runs:

- in every run r where the nodelets run inside their container H, H's measured CPU is
  modelled as the sum of its nodelets' CPU, each a function of its own setting only::

      M_r = lambda * sum_k S_k  +  sum_k d_k(v_kr)

  ``S_k``: nodelet k's CPU measured in the runs where it ran standalone (``nodelet
  standalone``, manifest ``standalone:``) at its reference value ``ref_k`` (the value it had
  there); ``d_k(v)``: what k's value v adds over ``ref_k`` (``d_k(ref_k) = 0``); ``lambda``:
  one factor for the whole container (inside, a frame passes by pointer: no copy and no
  deserialisation, and the manager's own threads are shared). Least squares over the runs
  (numpy ``lstsq``); identifiable when, across the runs, each non-reference value appears in
  a run whose other nodelets' values the remaining runs also cover (one setting moving at a
  time does this);
- nodelet k at value v then gets ``lambda S_k + d_k(v)`` (clipped at 0) plus its own
  loader process's CPU; the container keeps the run's residual ``M_r - sum_k c_k(v_kr)``
  (clipped at 0): its own work beyond the fitted sum;
- with more runs than unknowns (``repeats``), each step ``d_k(v)`` whose size is under twice
  its standard error (the residuals' variance x ``(A^T A)^-1``) is a warning: the runs'
  spread in the container's CPU hides that nodelet's setting there;
- without a standalone run of a nodelet, ``S_k`` = 1 for every nodelet of that container (its
  reference level split evenly) and a warning says so; a nodelet the runs cannot separate
  (the system's design matrix has a rank below its unknowns) is a warning too.

The copy price, apart from lambda (:func:`copy_price`): what the same configuration costs in
all when the container's nodes run standalone rather than inside it. For each standalone run
s and the in-container runs i at the same values (repeats averaged), with T the sum of every
system node's process CPU in a run (camera, loaders, manager, standalone nodelets alike) and X
the copies that splitting the container adds (kB/s): per topic t that n_t >= 1 of its nodes
receive from outside it, ``(n_t - 1) * B_t`` (inside, one connection carries t to the whole
process; standalone, one per node), plus ``B_e`` for every edge between two of its nodes
(inside, a pointer), B the topic's bandwidth measured in s::

    price = (T_s - T_i) / (X / 1000)      CPU units per MB/s of copies

averaged over the pairs; a negative mean (the runs' spread larger than the copies) is 0,
with a note. Every edge of the container gets the container's price (one
standalone run per setting moves all its nodes at once, so edges are not told apart). No pair,
or no copy to price (X = 0): no price, with a note.

The standalone runs' own rows are left out of the characterisation: a standalone nodelet is
not the configuration the system describes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.characterisation.manifest import RecordingEntry
    from perfros_bag.system.types import System


@dataclass(frozen=True)
class Split:
    """One container's fit: per nodelet, its CPU at each value; the fit's per-run error."""

    container: str
    cpu: dict[str, dict[str, float]]  # nodelet -> repr(value) -> CPU inside the container (loader not included)
    reference: dict[str, float]  # nodelet -> its standalone CPU at its reference value (the anchor S_k)
    factor: float  # lambda
    runs: dict[str, tuple[float, float]]  # recording -> (measured container CPU, sum of the estimates)
    notes: tuple[str, ...]
    #: the copy price (:func:`copy_price`): CPU units per MB/s of copies that running the
    #: container's nodes standalone adds; None: not measured
    copy_per_MBps: float | None = None
    #: per (in-container runs, standalone run): (extra CPU units, extra copies kB/s)
    copy_runs: dict[str, tuple[float, float]] | None = None


def _total(rows: Sequence[Row], recording: str, nodes: Sequence[str]) -> float | None:
    """The sum of ``nodes``' process CPU in ``recording`` (None: no node measured)."""
    cpus = [c for n in nodes if (c := _cpu(rows, recording, n)) is not None]
    return sum(cpus) if cpus else None


def _bandwidth(rows: Sequence[Row], recording: str, topic: str) -> float | None:
    return next((r.bandwidth_kBps for r in rows if r.recording == recording and r.topic == topic
                 and r.bandwidth_kBps is not None), None)


def extra_copies(system: System, host: str, members: Sequence[str], rows: Sequence[Row],
                 recording: str) -> float | None:
    """The copies (kB/s) that running ``members`` standalone adds over running them inside
    ``host``, at the topic bandwidths of ``recording`` (see the module's doc); None: an edge
    into or inside the container has no topic or no measured bandwidth."""
    inside = set(members) | {host}
    receivers: dict[str, set[str]] = {}
    extra = 0.0
    for e in system.edges:
        if e.dst not in members:
            continue
        if e.topic is None:
            return None
        b = e.bandwidth_kBps if e.bandwidth_kBps is not None else _bandwidth(rows, recording, e.topic)
        if b is None:
            return None
        if e.src in inside:
            extra += b  # inside: a pointer; standalone: a copy
        else:
            receivers.setdefault(e.topic, set()).add(e.dst)
    for topic, who in receivers.items():
        extra += (len(who) - 1) * (_bandwidth(rows, recording, topic) or 0.0)
    return extra


def copy_price(rows: Sequence[Row], system: System, host: str, members: Sequence[str],
               standalone: Mapping[str, Sequence[str]]
               ) -> tuple[float | None, dict[str, tuple[float, float]], str | None]:
    """The container's copy price (see the module's doc): (CPU units per MB/s or None, per
    pair ``"INSIDE+...|STANDALONE"`` -> (extra CPU, extra copies kB/s), a note or None)."""
    names = [n.name for n in system.nodes]
    recordings = list(dict.fromkeys(r.recording for r in rows))

    def values(rec: str) -> dict[str, str]:
        return {n: repr(v) for n in names if (v := _value(rows, rec, n)) is not None}

    pairs: dict[str, tuple[float, float]] = {}
    alone_runs = [s for s in recordings if set(members) <= set(standalone.get(s, ()))]
    if not alone_runs:  # the split's own note says the nodes never ran standalone
        return None, pairs, None
    why = "no standalone run has an in-container run at the same values"
    for s in alone_runs:
        twins = [rec for rec in recordings if not standalone.get(rec) and values(rec) == values(s)]
        totals = [t for rec in twins if (t := _total(rows, rec, names)) is not None]
        alone = _total(rows, s, names)
        extra = extra_copies(system, host, members, rows, s)
        if totals and alone is not None and extra is None:
            why = "an edge into or inside it has no topic, or its topic no measured bandwidth"
        if not totals or alone is None or extra is None:
            continue
        pairs[f"{'+'.join(twins)}|{s}"] = (alone - sum(totals) / len(totals), extra)
    priced = [(cpu, x) for cpu, x in pairs.values() if x > 0]
    if not priced:
        if pairs:
            why = "its nodes share no topic and pass nothing to each other: splitting it adds no copy"
        return None, pairs, f"container {host}: no copy price: {why}"
    price = sum(cpu / (x / 1000.0) for cpu, x in priced) / len(priced)
    if price < 0:  # standalone measured cheaper in all: the runs' spread is larger than the copies
        return 0.0, pairs, (f"container {host}: its copy price measured {price:.4g} CPU units per MB/s (its nodes "
                            "standalone cost less in all than inside it): the runs' spread hides the copies; "
                            "drafted as 0")
    return price, pairs, None


def _cpu(rows: Sequence[Row], recording: str, node: str) -> float | None:
    return next((r.cpu_units_mean for r in rows if r.recording == recording and r.node == node
                 and r.cpu_units_mean is not None and math.isfinite(r.cpu_units_mean)), None)


def _value(rows: Sequence[Row], recording: str, node: str) -> object:
    return next((r.value for r in rows if r.recording == recording and r.node == node), None)


def fit_split(rows: Sequence[Row], host: str, members: Sequence[str],
              standalone: Mapping[str, Sequence[str]]) -> Split | None:
    """The split of container ``host`` among ``members`` (``standalone``: recording -> the
    nodes that ran standalone in it); None when no run measured the container."""
    import numpy as np

    notes: list[str] = []
    recordings = list(dict.fromkeys(r.recording for r in rows))
    inside = [rec for rec in recordings if not set(standalone.get(rec, ())) & set(members)
              and _cpu(rows, rec, host) is not None]
    if not inside:
        return None
    anchors: dict[str, float] = {}
    ref: dict[str, str] = {}
    for k in members:
        alone = [rec for rec in recordings if k in standalone.get(rec, ())]
        cpus = [c for rec in alone if (c := _cpu(rows, rec, k)) is not None]
        if cpus:
            anchors[k] = sum(cpus) / len(cpus)
            ref[k] = repr(_value(rows, alone[0], k))
    if len(anchors) < len(members):
        missing = [k for k in members if k not in anchors]
        notes.append(f"nodelet(s) {', '.join(missing)} of container {host} never ran standalone: the container's CPU "
                     "at the reference setting is split evenly among its nodelets")
        anchors = dict.fromkeys(members, 1.0)
        ref = {}
    values = {k: [repr(_value(rows, rec, k)) for rec in inside] for k in members}
    for k in members:
        if k not in ref:  # the value most runs had: the default of a one-at-a-time design
            ref[k] = max(dict.fromkeys(values[k]), key=values[k].count)
    columns: list[tuple[str, str]] = [(k, v) for k in members for v in dict.fromkeys(values[k]) if v != ref[k]]
    a = np.zeros((len(inside), 1 + len(columns)))
    b = np.array([_cpu(rows, rec, host) or 0.0 for rec in inside])
    a[:, 0] = sum(anchors.values())
    for i in range(len(inside)):
        for j, (k, v) in enumerate(columns):
            a[i, 1 + j] = 1.0 if values[k][i] == v else 0.0
    coef, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < a.shape[1]:
        notes.append(f"container {host}: the runs do not separate its nodelets' settings (rank {rank} of "
                     f"{a.shape[1]}): vary one nodelet's setting at a time")
    dof = len(inside) - a.shape[1]
    if rank == a.shape[1] and dof > 0:  # repeated runs: is each value's step above the runs' own spread?
        sigma2 = float(np.sum((b - a @ coef) ** 2)) / dof
        se = np.sqrt(np.maximum(np.diag(np.linalg.inv(a.T @ a)) * sigma2, 0.0))
        for j, (k, v) in enumerate(columns):
            if abs(coef[1 + j]) < 2 * se[1 + j]:
                notes.append(f"node {k}: at value {v} its step over its value {ref[k]} ({coef[1 + j]:+.3g} CPU units) "
                             f"is within twice its standard error ({se[1 + j]:.3g}): the runs' spread in "
                             f"{host}'s CPU hides it, so its share there is uncertain")
    factor = float(coef[0])
    cpu: dict[str, dict[str, float]] = {k: {ref[k]: max(0.0, factor * anchors[k])} for k in members}
    for j, (k, v) in enumerate(columns):
        cpu[k][v] = max(0.0, factor * anchors[k] + float(coef[1 + j]))
    runs = {rec: (float(b[i]), sum(cpu[k][values[k][i]] for k in members)) for i, rec in enumerate(inside)}
    return Split(host, cpu, {k: anchors[k] for k in members} if len(ref) == len(members) else {}, factor, runs,
                 tuple(notes))


def split_containers(rows: Sequence[Row], system: System, entries: Sequence[RecordingEntry]
                     ) -> tuple[list[Row], list[Split]]:
    """``rows`` with every hosted node's CPU its share of its container's (plus its own
    process's, a nodelet's loader) and each container's the rest; the standalone runs' rows
    left out. Returns the rows and each container's :class:`Split`."""
    standalone = {e.name: tuple(e.standalone) for e in entries if e.standalone}
    splits = []
    for host, members in system.containers.items():
        s = fit_split(rows, host, members, standalone)
        if s is not None:
            price, pairs, note = copy_price(rows, system, host, members, standalone)
            s = replace(s, copy_per_MBps=price, copy_runs=pairs, notes=s.notes + ((note,) if note else ()))
            splits.append(s)
    if not splits:
        return [r for r in rows if r.recording not in standalone], splits
    by_host = {s.container: s for s in splits}
    member_of = {m: s for s in splits for m in s.cpu}
    out: list[Row] = []
    for r in rows:
        if r.recording in standalone:
            continue
        if r.node in member_of and r.cpu_units_mean is not None and r.recording in member_of[r.node].runs:
            s = member_of[r.node]
            share = s.cpu[r.node].get(repr(r.value))
            if share is not None:
                r = _scaled(r, share + r.cpu_units_mean, rows, s.container)
        elif r.node in by_host and r.cpu_units_mean is not None and r.recording in by_host[r.node].runs:
            measured, fitted = by_host[r.node].runs[r.recording]
            r = _scaled(r, max(0.0, measured - fitted), rows, r.node)
        out.append(r)
    return out, splits


def _scaled(r: Row, cpu: float, rows: Sequence[Row], host: str) -> Row:
    """The row with CPU ``cpu``; its p95 the container's p95 scaled by the same share."""
    ref = next((x for x in rows if x.recording == r.recording and x.node == host and x.cpu_units_mean), None)
    p95 = None
    if ref is not None and ref.cpu_units_p95 is not None and ref.cpu_units_mean:
        p95 = cpu * ref.cpu_units_p95 / ref.cpu_units_mean
    return replace(r, cpu_units_mean=cpu, cpu_units_p95=p95)
