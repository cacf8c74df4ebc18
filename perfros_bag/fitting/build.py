"""``model.json``: a system.yaml whose configurable nodes carry fitted curves.

:func:`build_model` joins the expert's numbers of ``system.yaml`` (performance levels and
weights per setting) with the measured ``characterisation.csv`` (CPU, frequency and
bandwidth per setting: the mean over the recordings of the same node and value, with the
spread kept in the ``measured`` part), fits per configurable node the relations of
:mod:`perfros_bag.fitting.regression` and fills each node's ``curve`` (CPU -> performance, what the
solvers use) and ``relations`` in, so :func:`perfros_bag.system.systemfile.load_system` reads the
``system`` part like a system.yaml. A node with a ``metric`` measured at two or more
values takes its performance from the measurements instead of the expert's levels
(:func:`metric_means`, :func:`metric_performance`); each performance fit says which in
its ``source``. Format: ``docs/formats.md``.
"""

from __future__ import annotations

import copy
import math
import statistics
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol, TypeVar

from perfros_bag.characterisation.csvfile import CharacterisationFile, Row, read_characterisation
from perfros_bag.characterisation.settings import by_setting
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fitting.cpu_error import Runs, driven_errors, node_errors
from perfros_bag.fitting.drops import RunRates, dropped_share, processed_hz, split_runs
from perfros_bag.fitting.modelfile import (
    DrivenSetting,
    FittedRelation,
    MeasuredSetting,
    ModelDocument,
    Stat,
    Unmeasured,
    round9,
    same_value,
    unmeasured_entry,
)
from perfros_bag.fitting.regression import FitError, clip_domain, fit_curve
from perfros_bag.system.systemfile import parse_system, read_system_data
from perfros_bag.system.types import Curve, Node, System

CPU_SCALE = 100.0  # x = CPU units / 100, as the paper's Fig 4


@dataclass
class ModelResult:
    """The model.json document plus the fits (for tables and plots)."""

    document: ModelDocument
    fits: dict[str, dict[str, FittedRelation]]
    system: System
    warnings: list[str]


# --- characterisation.csv ---------------------------------------------------------------

#: What a setting's CPU is taken as: the mean of the node's CPU samples in each recording
#: (``cpu_units_mean``), or their 95th percentile (``cpu_units_p95``: a plan with room for
#: the node's bursts, e.g. a server sized by Problem 2 that must not run at 100 %).
CPU_STATISTICS = ("mean", "p95")


def node_rows(table: CharacterisationFile, system: System) -> list[Row]:
    """The rows of ``table`` that name a node of ``system`` (a row without a recording
    named after its line). A value of such a node that is not a number is an error (the
    reader refuses non-finite ones)."""
    path = str(table.path)
    rows = []
    for row, cells, line in zip(table.rows, table.cells, table.lines, strict=True):
        if row.node not in system.node:
            continue
        raw = cells.get("value", "").strip()
        if isinstance(row.value, str):
            raise InputError(path, f"line {line}: node {row.node!r}: parameter value {raw!r} is not a number")
        rows.append(row if row.recording else replace(row, recording=f"(row {line})"))
    return rows


def input_rates(rows: list[Row]) -> dict[tuple[str, str], float]:
    """(node, recording) -> the measured rate of the node's input topic there (the
    ``input_hz`` column; a driven node's rows of one recording share it)."""
    out: dict[tuple[str, str], float] = {}
    for r in rows:
        if r.input_hz is not None:
            out.setdefault((r.node, r.recording), r.input_hz)
    return out


def measured_settings(table: CharacterisationFile, system: System,
                      cpu: str = "mean") -> dict[str, list[MeasuredSetting]]:
    """Per node of ``system``: what was measured at each parameter value, over the
    recordings (rows of other nodes are ignored), the CPU as ``cpu`` says
    (:data:`CPU_STATISTICS`)."""
    rows = node_rows(table, system)
    inputs = input_rates(rows)
    out: dict[str, list[MeasuredSetting]] = {}
    for s in by_setting(rows, {n.name: n.topics for n in system.nodes}):
        per_topic: dict[str, tuple[list[float], list[float]]] = {}
        for m in s.recordings:
            for t in m.topics:
                freqs, bws = per_topic.setdefault(t.topic, ([], []))
                if t.frequency_hz is not None:
                    freqs.append(t.frequency_hz)
                if t.bandwidth_kBps is not None:
                    bws.append(t.bandwidth_kBps)
        fin = [inputs[(s.node, m.recording)] for m in s.recordings if (s.node, m.recording) in inputs]
        out.setdefault(s.node, []).append(MeasuredSetting(
            None if s.value is None else float(s.value), len(s.recordings),
            Stat.of(s.cpus() if cpu == "mean" else s.cpus_p95()), Stat.of(s.frequencies()), Stat.of(s.bandwidths()),
            {t: (Stat.of(fl), Stat.of(bl)) for t, (fl, bl) in sorted(per_topic.items())}, Stat.of(fin)))
    return out


def node_threads(table: CharacterisationFile, system: System) -> dict[str, float]:
    """Per node of ``system`` with a ``threads`` column in ``table``: its busy threads, the
    mean over its recordings (each recording's value once), rounded to 0.01 and at least 1
    (the CFS weight of :mod:`perfros_bag.system.cpushare`)."""
    per: dict[str, dict[str, float]] = {}
    for r in node_rows(table, system):
        if r.threads is not None and r.threads > 0:
            per.setdefault(r.node, {}).setdefault(r.recording, r.threads)
    return {n: max(1.0, round(sum(v.values()) / len(v), 2)) for n, v in per.items()}


def error_runs(table: CharacterisationFile, system: System, cpu: str = "mean") -> dict[str, list[Runs]]:
    """Per node of ``system`` and measured value: each run's CPU statistic (``cpu``), its p95
    and, for a driven node, its input rate (a driven node's run without one is left out):
    what each setting's CPU error is computed from (:mod:`perfros_bag.fitting.cpu_error`)."""
    rows = node_rows(table, system)
    inputs = input_rates(rows)
    out: dict[str, list[Runs]] = {}
    for s in by_setting(rows, {n.name: n.topics for n in system.nodes}):
        driven = system.node[s.node].driven
        xs: list[float] = []
        p95s: list[float | None] = []
        fins: list[float] = []
        for m in s.recordings:
            x = m.cpu if cpu == "mean" else m.cpu_p95
            f = inputs.get((s.node, m.recording))
            if x is None or (driven and f is None):
                continue
            xs.append(x)
            p95s.append(m.cpu_p95)
            if f is not None and driven:
                fins.append(f)
        value = None if s.value is None else float(s.value)
        out.setdefault(s.node, []).append(Runs(value, tuple(xs), tuple(p95s), tuple(fins)))
    return out


def metric_means(table: CharacterisationFile, system: System) -> dict[str, dict[float, float]]:
    """Per node of ``system`` with a ``metric``: parameter value -> its ``metric_value``,
    the mean over the recordings at that value (one value per recording: characterise
    writes it on each of the node's rows)."""
    per: dict[str, dict[float, dict[str, float]]] = {}
    for row, line in zip(table.rows, table.lines, strict=True):
        node = system.node.get(row.node)
        if (node is None or node.metric is None or row.metric_value is None
                or not isinstance(row.value, int | float) or not math.isfinite(row.value)):
            continue
        per.setdefault(row.node, {}).setdefault(float(row.value), {}).setdefault(
            row.recording or f"(row {line})", row.metric_value)
    return {n: {v: sum(by_rec.values()) / len(by_rec) for v, by_rec in by_value.items()}
            for n, by_value in per.items()}


def metric_performance(node: Node, means: dict[float, float]) -> dict[float, float]:
    """Parameter value -> performance 0-100 from the node's metric: over its ``range``, else
    over the range of ``means`` (empty when that range is a single value)."""
    if node.metric is None or not means:
        return {}
    measured = (min(means.values()), max(means.values()))
    out = {}
    for value, mean in means.items():
        perf = node.metric.performance(mean, measured)
        if perf is not None:
            out[value] = perf
    return out


# --- building the model -----------------------------------------------------------------

class _Warn:
    def __init__(self) -> None:
        self.messages: list[str] = []

    def __call__(self, msg: str) -> None:
        self.messages.append(msg)
        warnings.warn(msg, PerfrosWarning, stacklevel=3)


def build_model(system_path: str | Path, characterisation_path: str | Path, *, cpu: str = "mean") -> ModelResult:
    """Fit the configurable nodes of ``system_path`` to ``characterisation_path``, a
    setting's CPU taken as ``cpu`` (:data:`CPU_STATISTICS`)."""
    if cpu not in CPU_STATISTICS:
        raise InputError(None, f"the CPU statistic must be one of {', '.join(CPU_STATISTICS)}, got {cpu!r}")
    sys_path, csv_path = str(system_path), str(characterisation_path)
    raw = read_system_data(system_path)  # a model.json: refitted from its system part
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)  # reported when the model is loaded
        system = parse_system(raw, sys_path)
    table = read_characterisation(csv_path)
    measured = measured_settings(table, system, cpu)
    metrics = metric_means(table, system)
    if not measured:
        known = sorted({r.node for r in table.rows if r.node})
        raise InputError(csv_path, "no row names a node of " + sys_path
                         + (f" (its nodes: {', '.join(known[:8])}{'...' if len(known) > 8 else ''})" if known
                            else " (the node column is empty)"))
    warn = _Warn()
    doc_system = copy.deepcopy(dict(raw))
    raw_nodes = {str(n.get("name")): n for n in doc_system["nodes"]}
    fits: dict[str, dict[str, FittedRelation]] = {}
    unmeasured = [n.name for n in system.nodes if n.name not in measured]
    if unmeasured:
        warn(f"{csv_path}: no rows for node(s) {', '.join(unmeasured)}: kept the numbers of {sys_path}")
    samples = driven_samples(table, system, cpu) if system.has_flow else {}
    runs = error_runs(table, system, cpu)
    driven: dict[str, list[DrivenSetting]] = {}
    unmeasured_at: dict[str, Unmeasured] = {}
    for node in system.nodes:
        if node.name not in measured:
            continue
        perf = _performance_source(node, metrics.get(node.name, {}), warn)
        if node.driven:
            fits_n, driven[node.name] = _fit_driven_node(node, samples.get(node.name, {}), raw_nodes[node.name],
                                                         warn, sys_path, perf)
            driven_errors(raw_nodes[node.name], driven[node.name], runs.get(node.name, []), fits_n)
        else:
            fits_n = _fit_node(node, measured[node.name], raw_nodes[node.name], warn, sys_path, perf)
            node_errors(raw_nodes[node.name], runs.get(node.name, []), fits_n.get("parameter->cpu") if fits_n else None)
        if fits_n:
            fits[node.name] = fits_n
            unmeasured_at[node.name] = unmeasured_entry(
                fits_n, [m.value for m in measured[node.name]], driven=node.driven,
                rule="period" if node.driven and is_throttle(node) else None)
    for name, threads in node_threads(table, system).items():
        raw_nodes[name]["threads"] = threads
    latency_fit = _fit_latency(table, system, doc_system, warn)
    speeds = [r.speed_factor for r in table.rows if r.speed_factor is not None]
    document = ModelDocument(sys_path, csv_path, doc_system,
                             {n: dict(fs) for n, fs in fits.items()},
                             measured, warn.messages, cpu_statistic=cpu, driven=driven, latency_fit=latency_fit,
                             unmeasured=unmeasured_at,
                             speed_factor=statistics.median(speeds) if speeds else None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        final = parse_system(doc_system, sys_path)  # what solve will read: must load
    return ModelResult(document, fits, final, warn.messages)


def _fit_latency(table: CharacterisationFile, system: System, doc_system: dict[str, Any],
                 warn: _Warn) -> dict[str, Any] | None:
    """The latency model's parameters fitted to the sweep's hop latencies into the model's
    ``system.latency`` (perfros_bag.fitting.latency); its summary, or None when nothing was fitted."""
    if not system.has_flow:
        return None
    from perfros_bag.fitting.latency import fit_latency, params_json

    fitted = fit_latency(node_rows(table, system), system)
    for w in fitted.warnings:
        warn(f"{table.path}: {w}")
    if not fitted.samples:
        return None
    doc_system["latency"] = params_json(fitted.params)
    return fitted.to_json()


class _Valued(Protocol):
    @property
    def value(self) -> float | None: ...


_V = TypeVar("_V", bound=_Valued)


def _match(node: Node, value: float | None, measured: list[_V]) -> _V | None:
    for m in measured:
        if same_value(m.value, value):
            return m
    if len(node.settings) == 1 and len(measured) == 1:
        return measured[0]
    return None


def _performance_source(node: Node, means: dict[float, float], warn: _Warn) -> dict[float, float] | None:
    """The measured performance per value when the node's metric was measured at two or
    more values (the fit then uses it instead of system.yaml's levels); else None."""
    if node.metric is None:
        return None
    perf = metric_performance(node, means)
    if len(perf) < 2:
        warn(f"node {node.name!r}: metric {node.metric.topic} measured at {len(means)} value(s)"
             + (" (all equal, no range given)" if means and not perf else "")
             + ": performance from the settings of the system instead")
        return None
    return perf


def _measured_perf(perf: dict[float, float], value: float | None) -> float | None:
    return next((p for v, p in perf.items() if same_value(v, value)), None)


def _fit_node(node: Node, measured: list[MeasuredSetting], raw: dict[str, Any], warn: _Warn,
              sys_path: str, perf: dict[float, float] | None = None) -> dict[str, FittedRelation]:
    """Fill ``raw`` (the node's system.yaml mapping, changed in place) with measured
    numbers and fitted curves; return the fits. ``perf``: performance per value from the
    node's metric, replacing the settings' levels (:func:`_performance_source`)."""
    who = f"node {node.name!r}"
    new_settings: list[dict[str, Any]] = []
    # Points: (value, cpu, performance, frequency, bandwidth); performance None when unrated.
    points: list[tuple[float | None, float, float | None, float | None, float | None]] = []
    used: set[int] = set()
    raw_settings = raw.get("settings") or []
    for s, rs in zip(node.settings, raw_settings, strict=True):
        m = _match(node, s.value, measured)
        rs = dict(rs)
        cpu, freq, bw = s.cpu, s.frequency_hz, s.bandwidth_kBps
        if m is None:
            if node.parameter is not None:
                warn(f"{who}: setting {s.value:g} has no recording: kept {sys_path}'s cpu/frequency/bandwidth"
                     if s.value is not None else f"{who}: a setting has no value and no recording")
        else:
            used.add(id(m))
            if m.cpu is not None and m.cpu.mean > 0:
                cpu = round9(m.cpu.mean)
            elif m.cpu is not None:
                warn(f"{who}: measured CPU {m.cpu.mean:g} at value {m.value}: kept {sys_path}'s cpu {s.cpu:g}")
            else:
                warn(f"{who}: no CPU measured at value {m.value}: kept {sys_path}'s cpu {s.cpu:g}")
            if m.frequency_hz is not None:
                freq = round9(m.frequency_hz.mean)
            if m.bandwidth_kBps is not None:
                bw = round9(m.bandwidth_kBps.mean)
            rs["cpu"] = round9(cpu)
            if freq is not None:
                rs["frequency_hz"] = round9(freq)
            if bw is not None:
                rs["bandwidth_kBps"] = round9(bw)
            topics = {t: {k: round9(st.mean) for k, st in (("frequency_hz", f), ("bandwidth_kBps", b))
                          if st is not None}
                      for t, (f, b) in m.topics.items()}
            if "topics" not in rs and len(topics) > 1:
                rs["topics"] = topics
        performance: float | None = s.performance
        if perf is not None:
            performance = _measured_perf(perf, s.value)
            if performance is not None:
                rs["performance"] = round9(performance)
        new_settings.append(rs)
        points.append((s.value, cpu, performance, freq, bw))
    if raw_settings:
        raw["settings"] = new_settings
    for m in measured:  # measured values the expert did not rate: CPU/frequency/bandwidth only
        if id(m) not in used and m.value is not None and m.cpu is not None and m.cpu.mean > 0:
            points.append((m.value, m.cpu.mean,
                           None if perf is None else _measured_perf(perf, m.value),
                           None if m.frequency_hz is None else m.frequency_hz.mean,
                           None if m.bandwidth_kBps is None else m.bandwidth_kBps.mean))

    if node.parameter is None:
        return {}
    values = {p[0] for p in points if p[0] is not None}
    rated = [p for p in points if p[0] is not None and p[2] is not None]
    if len(values) < 2 or len({p[0] for p in rated}) < 2:
        warn(f"{who}: a single setting of {node.parameter.name} "
             f"({len(values)} value(s) measured, {len(rated)} rated): nothing to fit, the node stays discrete")
        return {}

    def pts(ix: int, iy: int, source: list[Any]) -> tuple[list[float], list[float]]:
        sel = [p for p in source if p[ix] is not None and p[iy] is not None and math.isfinite(p[iy])]
        return [float(p[ix]) for p in sel], [float(p[iy]) for p in sel]

    fits: dict[str, FittedRelation] = {}
    specs: list[tuple[str, int, int, list[Any], float, Any]] = [
        ("parameter->cpu", 0, 1, points, 1.0, "either"),
        ("parameter->performance", 0, 2, rated, 1.0, None),
        ("cpu->performance", 1, 2, rated, CPU_SCALE, "nondecreasing"),
        ("parameter->frequency", 0, 3, points, 1.0, None),
        ("parameter->bandwidth", 0, 4, points, 1.0, None),
    ]
    for rel, ix, iy, source, scale, mono in specs:
        xs, ys = pts(ix, iy, source)
        if len(set(xs)) < 2:
            if rel in ("parameter->frequency", "parameter->bandwidth"):
                continue  # nothing measured: the solver interpolates the settings
            warn(f"{who}: {rel}: fewer than 2 distinct points: the node stays discrete")
            return {}
        try:
            fit = fit_curve(xs, ys, scale=scale, monotone=mono)
        except FitError as exc:
            warn(f"{who}: {rel}: {exc}: the node stays discrete")
            return {}
        for note in fit.warnings:
            warn(f"{who}: {rel}: {note}")
        if rel.endswith("->performance"):
            fit = replace(fit, source="settings" if perf is None else "metric")
        fits[rel] = fit

    fits.update(_topic_fits(who, measured, warn))
    curve, notes = solver_curve(fits["cpu->performance"], fits["parameter->cpu"],
                                max(p[2] for p in rated if p[2] is not None))
    for note in notes:
        warn(f"{who}: solver's CPU range: {note}")
    extra = fits["cpu->performance"].warnings + tuple(notes)
    fits["cpu->performance"] = _with_warnings(fits["cpu->performance"], extra)
    raw["curve"] = curve.to_dict()
    raw["relations"] = {rel: f.curve.to_dict() for rel, f in fits.items()}
    return fits


def _topic_fits(who: str, measured: list[MeasuredSetting], warn: _Warn) -> dict[str, FittedRelation]:
    """``parameter->frequency:<topic>`` and ``parameter->bandwidth:<topic>`` for a node that
    publishes several topics (their rates differ; the node-level relations are a mean and
    a sum). Topics measured at fewer than 2 values are skipped."""
    topics = sorted({t for m in measured for t in m.topics})
    out: dict[str, FittedRelation] = {}
    if len(topics) < 2:
        return out
    for t in topics:
        for k, kind in ((0, "parameter->frequency"), (1, "parameter->bandwidth")):
            xs: list[float] = []
            ys: list[float] = []
            for m in measured:
                st = m.topics.get(t, (None, None))[k]
                if m.value is not None and st is not None:
                    xs.append(m.value)
                    ys.append(st.mean)
            if len(set(xs)) < 2:
                continue
            rel = f"{kind}:{t}"
            try:
                fit = fit_curve(xs, ys)
            except FitError:
                continue
            for note in fit.warnings:
                warn(f"{who}: {rel}: {note}")
            out[rel] = fit
    return out


def _with_warnings(fit: FittedRelation, notes: tuple[str, ...]) -> FittedRelation:
    return replace(fit, warnings=notes)


def solver_curve(c2p: FittedRelation, p2c: FittedRelation, max_perf: float) -> tuple[Curve, list[str]]:
    """The node's CPU -> performance curve for the solvers: the fitted curve on the measured
    CPU range, narrowed where its performance leaves [0, max observed], with whole-CPU-unit
    ends (rounded inwards, when that leaves at least one unit). CPU levels the
    parameter -> CPU fit does not reach from inside the measured parameter range map to
    that range's end (a note says so when that spans more than one CPU unit)."""
    notes: list[str] = []
    curve, msg = clip_domain(c2p.curve, 0.0, max_perf)
    if msg:
        notes.append(f"cpu->performance {msg}")
    lo, hi = curve.domain
    ilo, ihi = math.ceil(lo - 1e-9), math.floor(hi + 1e-9)
    if ihi - ilo >= 1 and ilo > 0:
        lo, hi = float(ilo), float(ihi)
    pc = p2c.curve
    ends = sorted(((pc(p2c.domain[0]), p2c.domain[0]), (pc(p2c.domain[1]), p2c.domain[1])))
    (img_lo, v_lo), (img_hi, v_hi) = ends
    if img_lo - lo > 1:
        notes.append(f"CPU levels [{lo:g}, {img_lo:.4g}] all map to parameter value {v_lo:g} "
                     f"(the parameter->cpu fit gives {img_lo:.4g} there)")
    if hi - img_hi > 1:
        notes.append(f"CPU levels [{img_hi:.4g}, {hi:g}] all map to parameter value {v_hi:g} "
                     f"(the parameter->cpu fit gives {img_hi:.4g} there)")
    return Curve(curve.form, curve.coef, (lo, hi), curve.scale), notes


# --- driven nodes (system.yaml ``input:``; docs/formats.md "model.json: driven nodes") ---

#: how many parameter values (ends included) the grid of settings evaluated from a driven
#: node's curves spans between its lowest and highest measured value
GRID_POINTS = 9
#: a recording whose output runs within this fraction of its setting's ``max_frequency_hz``
#: is throttled: its output rate says nothing about ``out_per_in``
THROTTLED = 0.98
#: input rates of one setting spread by less than this share of their mean are one rate: a
#: line through them is fixed by the noise of the counts, not by the node (RQ4, 2026-11-28:
#: three live windows at 4.94-5.11 Hz gave a slope below 0, clipped to 0, and the re-plan
#: then ran the node at 9.85 Hz for the CPU of 5)
ONE_RATE_SPREAD = 0.2


@dataclass(frozen=True)
class DrivenSample:
    """One recording of a driven node at one parameter value."""

    recording: str
    input_hz: float
    cpu: float | None
    frequency_hz: float | None  # F_out: the mean over its topics
    bandwidth_kBps: float | None  # all its topics


def driven_samples(table: CharacterisationFile, system: System,
                   cpu: str = "mean") -> dict[str, dict[float | None, list[DrivenSample]]]:
    """Per driven node of ``system`` and parameter value: one sample per recording that
    measured its input rate (``input_hz``), the CPU as ``cpu`` says (:data:`CPU_STATISTICS`)."""
    rows = [r for r in node_rows(table, system) if system.node[r.node].driven]
    inputs = input_rates(rows)
    out: dict[str, dict[float | None, list[DrivenSample]]] = {}
    for s in by_setting(rows, {n.name: n.topics for n in system.nodes}):
        value = None if s.value is None else float(s.value)
        for m in s.recordings:
            fin = inputs.get((s.node, m.recording))
            if fin is not None:
                out.setdefault(s.node, {}).setdefault(value, []).append(DrivenSample(
                    m.recording, fin, m.cpu if cpu == "mean" else m.cpu_p95, m.frequency_hz, m.bandwidth_kBps))
    return out


def cpu_line(points: list[tuple[float, float]]) -> tuple[float, float, float | None, list[str]]:
    """``(cpu, cpu_per_hz, r2, notes)`` of CPU = cpu + cpu_per_hz x F_in through the
    (F_in, CPU) ``points`` of one setting (least squares; the base clipped at 0, refitted
    through the origin; a slope below 0 clipped to 0). With one input rate only (rates
    within :data:`ONE_RATE_SPREAD` of their mean count as one): the base is 0 and
    cpu_per_hz the mean CPU over the mean rate (``r2`` None; a note says so)."""
    import numpy as np

    from perfros_bag.fitting.regression import fit_form, r_squared

    fin = np.array([p[0] for p in points], dtype=float)
    cpu = np.array([p[1] for p in points], dtype=float)
    notes: list[str] = []
    if len(np.unique(fin)) < 2 or float(fin.max() - fin.min()) < ONE_RATE_SPREAD * float(fin.mean()):
        f = float(fin.mean())
        if f <= 0:
            raise FitError(f"measured at input rate {f:g} Hz only: no CPU per Hz can be told")
        notes.append(f"one input rate only ({f:g} Hz): cpu_per_hz = mean CPU / input rate, base cpu 0")
        return 0.0, float(cpu.mean()) / f, None, notes
    k, base = fit_form("linear", fin, cpu)
    if base < 0:
        k, base = float(fin @ cpu) / float(fin @ fin), 0.0
        notes.append("the fitted base cpu was below 0: clipped to 0, cpu_per_hz fitted through the origin")
    if k < 0:
        k, base = 0.0, float(cpu.mean())
        notes.append("CPU fell as the input rate rose: cpu_per_hz clipped to 0, base cpu = the mean CPU")
    return float(base), float(k), r_squared(cpu, base + k * fin), notes


def scaled_line(reference: tuple[float, float], input_hz: float, cpu: float) -> tuple[float, float]:
    """One-at-a-time sweeps: a setting measured at one input rate takes the line ``(cpu,
    cpu_per_hz)`` of a ``reference`` setting measured at several, scaled by its CPU over the
    reference line's at that rate (the own parameter scales the per-message work and the
    base alike); a reference line at 0 there leaves the mean ``cpu`` as the base."""
    base, slope = reference
    at = base + slope * input_hz
    if at <= 0:
        return cpu, 0.0
    k = cpu / at
    return k * base, k * slope


@dataclass(frozen=True)
class _DrivenMeasure:
    """One parameter value of a driven node, from its recordings."""

    value: float | None
    cpu: float
    cpu_per_hz: float
    r2: float | None
    out_per_in: float | None
    bytes_per_msg: float | None
    points: tuple[tuple[float, float], ...]
    notes: tuple[str, ...]


def _mean(xs: list[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def _one_at_a_time(measures: list[_DrivenMeasure]) -> list[_DrivenMeasure]:
    """Settings measured at one input rate (``r2`` None) take the line of the setting with a
    line and the most recordings, scaled (:func:`scaled_line`), as ``init`` drafts them; with
    no such setting they keep :func:`cpu_line`'s one-rate answer."""
    lines = [m for m in measures if m.r2 is not None]
    if not lines:
        return measures
    ref = max(lines, key=lambda m: len(m.points))
    out = []
    for m in measures:
        if m.r2 is not None:
            out.append(m)
            continue
        f_in = sum(p[0] for p in m.points) / len(m.points)
        cpu = sum(p[1] for p in m.points) / len(m.points)
        base, slope = scaled_line((ref.cpu, ref.cpu_per_hz), f_in, cpu)
        ref_value = "its setting" if ref.value is None else f"{ref.value:g}"
        note = f"one input rate only ({f_in:g} Hz): the line of setting {ref_value} scaled by the CPU ratio there"
        out.append(replace(m, cpu=base, cpu_per_hz=slope, notes=(note,)))
    return out


def _driven_measure(value: float | None, samples: list[DrivenSample], cap: float | None,
                    step: str | None = None) -> _DrivenMeasure:
    """The setting's line (:func:`cpu_line`), ``out_per_in`` = mean F_out / F_in over its
    recordings (those throttled by ``cap`` left out: with ``step: period`` every recording
    whose input reached the cap, since the step's output lies below it) and
    ``bytes_per_msg`` = mean bandwidth x 1000 / F_out. A recording where the node was
    overloaded (:mod:`perfros_bag.fitting.drops`) is left out of ``out_per_in`` and its CPU
    counts at the rate it processed."""
    free = [s for s in samples if s.frequency_hz is not None and s.input_hz > 0
            and (cap is None or s.frequency_hz < THROTTLED * cap)
            and (cap is None or step != "period" or s.input_hz < THROTTLED * cap)]
    rates = [RunRates(s.input_hz, s.frequency_hz or 0.0, s.cpu) for s in free]
    drops = split_runs(rates)
    processed = {id(free[i]): processed_hz(rates, drops, i) for i in drops.overloaded}
    notes_drop = [f"overloaded at input {free[i].input_hz:.3g} Hz in {free[i].recording} (dropped "
                  f"{100 * dropped_share(rates, drops, i):.0f} %): its ratio left out, its CPU at the rate processed"
                  for i in drops.overloaded]
    points = [(processed.get(id(s), s.input_hz), s.cpu) for s in samples if s.cpu is not None]
    if not points:
        raise FitError("no CPU measured")
    base, k, r2, notes = cpu_line(points)
    ratios = [rates[i].ratio for i in range(len(free)) if i not in drops.overloaded]
    sizes = [s.bandwidth_kBps * 1000.0 / s.frequency_hz for s in samples
             if s.bandwidth_kBps is not None and s.frequency_hz is not None and s.frequency_hz > 0]
    return _DrivenMeasure(value, base, k, r2, _mean(ratios), _mean(sizes), tuple(points), tuple(notes + notes_drop))


def _fit_driven_node(node: Node, samples: dict[float | None, list[DrivenSample]], raw: dict[str, Any], warn: _Warn,
                     sys_path: str, perf: dict[float, float] | None = None
                     ) -> tuple[dict[str, FittedRelation], list[DrivenSetting]]:
    """A driven node: each setting's ``cpu``, ``cpu_per_hz``, ``out_per_in`` and
    ``bytes_per_msg`` from its recordings (:func:`_driven_measure`), then over the parameter
    the curves of those and of performance, and settings on a grid of values between the
    measured ones evaluated from the curves. ``raw`` (the node's system.yaml mapping) is
    filled in place; returns the curves and every setting written with its source."""
    who = f"node {node.name!r}"
    caps = {s.max_frequency_hz for s in node.settings}
    common_cap = next(iter(caps)) if len(caps) == 1 else None
    throttle = is_throttle(node)
    measures: list[_DrivenMeasure] = []
    for value, ss in samples.items():
        own = next((s for s in node.settings if same_value(s.value, value)), None)
        cap = own.max_frequency_hz if own is not None else value if throttle else common_cap
        step = own.step if own is not None else "period" if throttle else None
        try:
            measures.append(_driven_measure(value, ss, cap, step))
        except FitError as exc:
            warn(f"{who}: value {value if value is None else f'{value:g}'}: {exc}: nothing fitted there")
    measures = _one_at_a_time(measures)
    if not samples:
        warn(f"{who}: no row gives the rate of its input {node.input} (input_hz): kept {sys_path}'s settings")
    written: list[DrivenSetting] = []
    new_settings: list[dict[str, Any]] = []
    used: set[int] = set()
    for s, rs in zip(node.settings, raw.get("settings") or [], strict=True):
        rs = dict(rs)
        performance = s.performance
        if perf is not None:
            measured_perf = _measured_perf(perf, s.value)
            if measured_perf is not None:
                performance = measured_perf
                rs["performance"] = round9(performance)
        m = _match(node, s.value, measures)
        setting = "its setting" if s.value is None else f"setting {s.value:g}"
        if m is None:
            if samples:
                warn(f"{who}: {setting} has no recording with an input rate: kept {sys_path}'s numbers")
            written.append(DrivenSetting(s.value, "system", s.cpu, s.cpu_per_hz or 0.0, performance,
                                         s.out_per_in, s.bytes_per_msg))
        else:
            used.add(id(m))
            rs["cpu"], rs["cpu_per_hz"] = round9(m.cpu), round9(m.cpu_per_hz)
            if m.out_per_in is not None:
                rs["out_per_in"] = round9(m.out_per_in)
            if m.bytes_per_msg is not None:
                rs["bytes_per_msg"] = round9(m.bytes_per_msg)
            for note in m.notes:
                warn(f"{who}: {setting}: {note}")
            written.append(DrivenSetting(s.value, "measured", m.cpu, m.cpu_per_hz, performance,
                                         rs.get("out_per_in"), rs.get("bytes_per_msg"), m.r2, m.points, m.notes))
        new_settings.append(rs)
    if new_settings:
        raw["settings"] = new_settings
    if node.parameter is None:
        return {}, written

    # The curves over the parameter: every setting written, and measured values not rated.
    extra = [m for m in measures if id(m) not in used and m.value is not None]
    known = [(d.value, d.cpu, d.cpu_per_hz, d.out_per_in, d.bytes_per_msg) for d in written if d.value is not None]
    known += [(m.value, m.cpu, m.cpu_per_hz, m.out_per_in, m.bytes_per_msg) for m in extra if m.value is not None]
    rated = [(d.value, d.performance) for d in written if d.value is not None]
    if perf is not None:
        rated += [(m.value, p) for m in extra
                  if m.value is not None and (p := _measured_perf(perf, m.value)) is not None]
    fits: dict[str, FittedRelation] = {}
    for rel, pts in (("parameter->cpu_base", [(k[0], k[1]) for k in known]),
                     ("parameter->cpu_per_hz", [(k[0], k[2]) for k in known]),
                     ("parameter->performance", rated),
                     ("parameter->out_per_in", [(k[0], k[3]) for k in known]),
                     ("parameter->bytes_per_msg", [(k[0], k[4]) for k in known])):
        xy = [(float(x), float(y)) for x, y in pts if x is not None and y is not None]
        if len({x for x, _ in xy}) < 2:
            continue
        try:
            fit = fit_curve([x for x, _ in xy], [y for _, y in xy])
        except FitError as exc:
            warn(f"{who}: {rel}: {exc}")
            continue
        for note in fit.warnings:
            warn(f"{who}: {rel}: {note}")
        if rel == "parameter->performance":
            fit = replace(fit, source="settings" if perf is None else "metric")
        fits[rel] = fit
    needed = ("parameter->cpu_base", "parameter->cpu_per_hz", "parameter->performance")
    if not all(r in fits for r in needed):
        warn(f"{who}: {len({k[0] for k in known})} value(s) of {node.parameter.name} measured, "
             f"{len({r[0] for r in rated})} rated: no curves over the parameter, the node keeps its settings")
        return fits, written
    if len(caps) > 1 and not throttle:
        warn(f"{who}: its settings have different max_frequency_hz: no settings between them")
        return fits, written
    means = {"parameter->out_per_in": _mean([k[3] for k in known if k[3] is not None]),
             "parameter->bytes_per_msg": _mean([k[4] for k in known if k[4] is not None])}
    taken = [d.value for d in written if d.value is not None]
    # a throttle swept at whole rates only is deployed at whole rates (sweep/deploy.plan_run
    # rounds): its grid is too, so the step planned is the step run
    whole = throttle and all(float(v).is_integer() for v in taken)
    grid = _grid_settings(node, fits, means, taken, max(r[1] for r in rated), whole)
    if throttle:  # its value is its cap: a grid value's output is the step's, told by the rule
        raw["settings"] = new_settings + [_setting_json(g, g.value, "period") for g in grid]
    else:
        raw["settings"] = new_settings + [_setting_json(g, common_cap) for g in grid]
    return fits, written + grid


def is_throttle(node: Node) -> bool:
    """A period throttle whose parameter is its rate: every setting ``step: period`` with
    ``max_frequency_hz`` equal to its value (``init`` drafts a throttle so)."""
    return bool(node.settings) and all(
        s.step == "period" and s.value is not None and s.max_frequency_hz is not None
        and same_value(s.max_frequency_hz, s.value) for s in node.settings)


def _grid_settings(node: Node, fits: dict[str, FittedRelation], means: dict[str, float | None], taken: list[float],
                   max_perf: float, whole: bool = False) -> list[DrivenSetting]:
    """Settings at :data:`GRID_POINTS` values over the range every needed curve covers
    (rounded for an ``int`` parameter or when ``whole``; values already ``taken`` left out), each number from
    its curve (clipped at 0, performance at ``max_perf``); ``out_per_in`` and
    ``bytes_per_msg`` without a curve: ``means`` (the measured ones' mean)."""
    needed = [fits[r] for r in ("parameter->cpu_base", "parameter->cpu_per_hz", "parameter->performance")]
    lo, hi = max(f.domain[0] for f in needed), min(f.domain[1] for f in needed)
    integer = whole or (node.parameter is not None and node.parameter.type == "int")
    values: list[float] = []
    for i in range(GRID_POINTS):
        v = lo + (hi - lo) * i / (GRID_POINTS - 1)
        v = float(round(v)) if integer else round9(v)
        if lo <= v <= hi and not any(same_value(v, t) for t in taken + values):
            values.append(v)

    def at(rel: str, v: float) -> float | None:
        fit = fits.get(rel)
        if fit is None:
            return means.get(rel)
        lo_y, hi_y = bracket(fit.points, v)
        return max(0.0, min(max(fit.curve(min(max(v, fit.domain[0]), fit.domain[1])), lo_y), hi_y))

    return [DrivenSetting(v, "grid", at("parameter->cpu_base", v) or 0.0, at("parameter->cpu_per_hz", v) or 0.0,
                          min(at("parameter->performance", v) or 0.0, max_perf),
                          at("parameter->out_per_in", v), at("parameter->bytes_per_msg", v))
            for v in values]


def bracket(points: Sequence[tuple[float, float]], v: float) -> tuple[float, float]:
    """The range a curve's value at ``v`` is held to: between the (mean) measured numbers at
    the nearest measured values either side of ``v`` (both at ``v`` itself when measured
    there; unbounded on a side with none). A value never measured costs no less than the
    cheaper of its measured neighbours and no more than the dearer: a curve that dips between
    two measurements (a fit through a steep drop) is not taken at its word where the solver
    would favour it most (docs/solvers.md, "Values never measured")."""
    at: dict[float, list[float]] = {}
    for x, y in points:
        at.setdefault(float(x), []).append(float(y))
    below = [x for x in at if x <= v]
    above = [x for x in at if x >= v]
    if not below or not above:
        return -math.inf, math.inf
    ys = [sum(at[x]) / len(at[x]) for x in (max(below), min(above))]
    return min(ys), max(ys)


def _setting_json(d: DrivenSetting, cap: float | None, step: str | None = None) -> dict[str, Any]:
    """A grid setting as the ``system`` part writes it (``cap``: every setting's
    ``max_frequency_hz``, when they share one, or a throttle's value with its ``step``)."""
    out: dict[str, Any] = {"value": d.value, "cpu": round9(d.cpu), "cpu_per_hz": round9(d.cpu_per_hz),
                           "performance": round9(d.performance)}
    for key, v in (("out_per_in", d.out_per_in), ("bytes_per_msg", d.bytes_per_msg), ("max_frequency_hz", cap)):
        if v is not None:
            out[key] = round9(v)
    if step is not None:
        out["step"] = step
    return out
