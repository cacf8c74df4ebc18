"""The latency model's parameters, fitted from the sweep's measured hop latencies.

characterisation.csv (``characterise --latency``) gives every stamped topic of every run its
``latency_p50_s`` / ``latency_p95_s`` (receive time - header.stamp). A driven node ``n``
publishing ``b`` from its input ``a`` adds, in that run, ``lat(b) - lat(a)`` (``lat(b)`` alone
when ``a``'s publisher is a source: the chain starts at its stamp). The sweep runs every node
on this machine, uncapped, without links, so the model's hop there is
``overhead + scale_n x g`` with ``g = S + W50`` at ``S = w / (threads x units_per_core)``
(its threads' cores: the node is not capped) and its wait at ``rho = lam x w /
units_per_core`` (0 below utilisation 1: the input is periodic;
:mod:`perfros_bag.system.latency`). A run where the node fell behind its input (published
less than 90 % of what its input asked) is left out: its delay is the sweep machine's
contention, bounded by the queue. Least squares over every (node, run) gives the one
``overhead_ms`` (>= 0) and each node's ``service_scale`` (> 0); each node's ``p95_ratio`` is the
median over its runs of what its measured p95 leaves for ``ratio x S``, at least 1. The
in-sample error (mean |predicted - measured| / measured, p50 and p95) is written beside them
(model.json ``latency_fit``).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.system.latency import chain_hops, queue_wait
from perfros_bag.system.types import LatencyParams, System

#: a node's fitted p95 ratio is kept within [1, MAX_RATIO]
MAX_RATIO = 50.0


@dataclass(frozen=True)
class HopSample:
    """One driven node in one run: its per-message CPU time (s, at one core), utilisation and
    the hop latency measured (s)."""

    node: str
    recording: str
    service_s: float
    rho: float
    p50_s: float
    p95_s: float | None


@dataclass
class LatencyFit:
    params: LatencyParams
    samples: list[HopSample]
    p50_error_pct: float | None
    p95_error_pct: float | None
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        per: dict[str, int] = {}
        for s in self.samples:
            per[s.node] = per.get(s.node, 0) + 1
        return {"points": len(self.samples), "nodes": per,
                "p50_error_pct": _round(self.p50_error_pct), "p95_error_pct": _round(self.p95_error_pct)}


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 3)


def hop_samples(rows: Sequence[Row], system: System, units_per_core: float) -> list[HopSample]:
    """Every (driven node, run) whose output and, for a driven input, input latency were
    measured."""
    lat: dict[tuple[str, str, str], Row] = {}
    for r in rows:
        if r.topic is not None and r.latency_p50_s is not None:
            lat.setdefault((r.recording, r.node, r.topic), r)
    out: list[HopSample] = []
    for name in system.flow_order:
        node = system.node[name]
        parent = system.flow_parent[name]
        assert node.input is not None
        for (rec, who, topic), rb in sorted(lat.items()):
            if who != name or topic not in node.topics:
                continue
            base50, base95 = 0.0, 0.0
            ra = lat.get((rec, parent, node.input))
            if system.node[parent].driven:
                if ra is None:
                    continue
                base50, base95 = ra.latency_p50_s or 0.0, ra.latency_p95_s or 0.0
            lam = rb.input_hz or (ra.frequency_hz if ra is not None else None)
            if not lam or rb.cpu_units_mean is None or lam <= 0:
                continue
            if _fell_behind(system, name, rb, lam):
                continue
            w = rb.cpu_units_mean / lam
            value = rb.value if isinstance(rb.value, int | float) else None
            s = w / (max(1.0, node.threads_at(value)) * units_per_core)  # its threads' cores
            p50 = (rb.latency_p50_s or 0.0) - base50
            p95 = None if rb.latency_p95_s is None else rb.latency_p95_s - base95
            if p50 <= 0 or s <= 0:
                continue
            if all((o.node, o.recording) != (name, rec) for o in out):  # its first stamped output
                out.append(HopSample(name, rec, s, lam * s, p50, p95))
    return out


#: a run whose node published less than this share of what its input asks is left out
KEPT_SHARE = 0.9


def _fell_behind(system: System, name: str, row: Row, lam: float) -> bool:
    """Did the node fall behind its input in this run (its output below ``KEPT_SHARE`` of
    ``out_per_in x lam`` at its setting)? Its latency then measures the sweep machine's
    contention, bounded by the queue, not the node: such runs are not fitted."""
    node = system.node[name]
    j = node.setting_index(row.value if isinstance(row.value, int | float) else None)
    setting = node.settings[j] if j is not None else None
    ratio = 1.0 if setting is None or setting.out_per_in is None else setting.out_per_in
    want = ratio * lam
    if setting is not None and setting.max_frequency_hz is not None:
        want = min(want, setting.max_frequency_hz)
    return row.frequency_hz is not None and row.frequency_hz < KEPT_SHARE * want


def _period(smp: HopSample) -> float:
    """The sample's input period (s): ``rho = lam x service_s``."""
    return smp.service_s / smp.rho


def _g50(smp: HopSample, params: LatencyParams) -> float:
    return smp.service_s + queue_wait(smp.service_s, smp.rho, params, 0.5, _period(smp))


def predict_sample(smp: HopSample, params: LatencyParams) -> tuple[float, float]:
    """The model's (p50, p95) seconds for a sweep sample (one core, no link)."""
    scale = params.service_scale.get(smp.node, 1.0)
    ratio = params.node_p95_ratio.get(smp.node, params.p95_ratio)
    s = scale * smp.service_s
    over = params.overhead_ms / 1000.0
    return (over + s + queue_wait(s, smp.rho, params, 0.5, _period(smp)),
            over + ratio * s + queue_wait(s, smp.rho, params, 0.95, _period(smp)))


def fit_latency(rows: Sequence[Row], system: System) -> LatencyFit:
    """The parameters of ``system.latency`` fitted to the rows (see the module); without a
    sample they stay as they were, with a warning when the system has chains."""
    import numpy as np

    base = system.latency
    samples = hop_samples(rows, system, base.units_per_core)
    warn: list[str] = []
    for chain in system.chains:
        hops = chain_hops(system, chain)
        if isinstance(hops, str):
            continue
        missing = [h.node for h in hops if not any(s.node == h.node for s in samples)]
        if missing:
            warn.append(f"chain {chain.name!r}: no measured latency for its hop node(s) {', '.join(missing)} "
                        "(characterise --latency; their outputs need a std_msgs/Header): their service scale "
                        "stays unfitted (1)")
    if not samples:
        return LatencyFit(base, [], None, None, warn)
    nodes = sorted({s.node for s in samples})
    col = {n: i + 1 for i, n in enumerate(nodes)}
    a = np.zeros((len(samples), len(nodes) + 1))
    y = np.array([s.p50_s for s in samples])
    unit = replace(base, service_scale={}, node_p95_ratio={})
    for i, s in enumerate(samples):
        a[i, 0] = 1.0
        a[i, col[s.node]] = _g50(s, unit)
    coef = np.linalg.lstsq(a, y, rcond=None)[0] if len(samples) > len(nodes) else None
    if coef is None or coef[0] < 0 or any(c <= 0 for c in coef[1:]):
        overhead = 0.0
        scales = {}
        for n in nodes:
            g = a[:, col[n]]
            scales[n] = float((g @ y) / (g @ g)) if g @ g > 0 else 1.0
    else:
        overhead = float(coef[0])
        scales = {n: float(coef[col[n]]) for n in nodes}
    scales = {n: v for n, v in scales.items() if v > 0 and math.isfinite(v)}
    fitted = replace(base, overhead_ms=1000.0 * overhead, service_scale={**base.service_scale, **scales}, source="fit")
    ratios: dict[str, float] = {}
    for n in nodes:
        got = []
        for s in (s for s in samples if s.node == n and s.p95_s is not None):
            sc = fitted.service_scale.get(n, 1.0) * s.service_s
            assert s.p95_s is not None
            left = s.p95_s - overhead - queue_wait(sc, s.rho, fitted, 0.95, _period(s))
            got.append(left / sc)
        if got:
            ratios[n] = min(max(statistics.median(got), 1.0), MAX_RATIO)
    glob = statistics.median(ratios.values()) if ratios else base.p95_ratio
    fitted = replace(fitted, node_p95_ratio={**base.node_p95_ratio, **ratios}, p95_ratio=glob)
    e50, e95 = [], []
    for s in samples:
        p50, p95 = predict_sample(s, fitted)
        e50.append(abs(p50 - s.p50_s) / s.p50_s)
        if s.p95_s is not None and s.p95_s > 0:
            e95.append(abs(p95 - s.p95_s) / s.p95_s)
    return LatencyFit(fitted, samples, 100 * statistics.mean(e50), 100 * statistics.mean(e95) if e95 else None, warn)


def params_json(params: LatencyParams) -> dict[str, Any]:
    """``params`` as system.yaml's ``latency:`` mapping (what model.json's system carries)."""
    return {"units_per_core": params.units_per_core, "overhead_ms": round(params.overhead_ms, 6),
            "queue_factor": params.queue_factor, "p95_ratio": round(params.p95_ratio, 6),
            "queue_size": params.queue_size, "link_efficiency": params.link_efficiency,
            "backlog_msgs": params.backlog_msgs, "cfs_period_ms": params.cfs_period_ms,
            "link_burst_ms": params.link_burst_ms,
            "service_scale": {n: round(v, 6) for n, v in sorted(params.service_scale.items())},
            "node_p95_ratio": {n: round(v, 6) for n, v in sorted(params.node_p95_ratio.items())},
            "source": params.source}

