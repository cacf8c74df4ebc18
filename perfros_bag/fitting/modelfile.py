"""``model.json``: the typed document, its writer and its reader (format: ``docs/formats.md``).

:func:`read_model` reads and checks the whole document; what ``solve`` needs, the
``system`` part (a system.yaml with fitted curves), is read by the system's own reader
(:func:`perfros_bag.system.modelpart.read_model_system`) without the rest. Light module:
no numpy, no fitting.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.doccheck import Doc
from perfros_bag.errors import InputError
from perfros_bag.fileio import (
    DOCUMENT_KINDS,
    atomic_write_json,
    expect_kind,
    kind_of,
    read_json,
)
from perfros_bag.limits import MAX_COEFFICIENT, MAX_MAGNITUDE, short_repr
from perfros_bag.system.modelpart import MODEL_FORMAT
from perfros_bag.system.types import Curve, CurveForm, curve_form

if TYPE_CHECKING:
    from perfros_bag.system.plan import Plan, PlannedNode
    from perfros_bag.system.types import System


def round9(v: float) -> float:
    """9 significant digits (the measured numbers as written)."""
    return float(f"{v:.9g}") if math.isfinite(v) else v


def same_value(a: float | None, b: float | None) -> bool:
    """Two parameter values are the same setting: equal to 1e-9 (relative, at least absolute
    for values below 1), or both None."""
    if a is None or b is None:
        return a is None and b is None
    return abs(a - b) <= 1e-9 * max(1.0, abs(a), abs(b))


def round6(v: float) -> float:
    """6 significant digits (R², leave-one-out errors as written)."""
    return float(f"{v:.6g}") if math.isfinite(v) else v


def _finite_or_none(v: float | None) -> float | None:
    """A leave-one-out error as written: None when there is none or it is not finite (a
    form whose predictions overflowed; the fit ranked it last)."""
    return None if v is None or not math.isfinite(v) else round6(v)


@dataclass(frozen=True)
class Stat:
    """Mean, sample standard deviation and count of one measured quantity."""

    mean: float
    std: float
    count: int

    @staticmethod
    def of(values: list[float]) -> Stat | None:
        """The statistics of the finite values (None when there is none)."""
        vs = [v for v in values if math.isfinite(v)]
        if not vs:
            return None
        m = sum(vs) / len(vs)
        sd = math.sqrt(sum((v - m) ** 2 for v in vs) / (len(vs) - 1)) if len(vs) > 1 else 0.0
        return Stat(m, sd, len(vs))

    def to_json(self) -> dict[str, float | int]:
        return {"mean": round9(self.mean), "std": round9(self.std), "count": self.count}


@dataclass(frozen=True)
class MeasuredSetting:
    """What the recordings of one node at one parameter value showed."""

    value: float | None
    recordings: int
    cpu: Stat | None
    frequency_hz: Stat | None
    bandwidth_kBps: Stat | None
    topics: dict[str, tuple[Stat | None, Stat | None]] = field(default_factory=dict)  # (frequency, bandwidth)
    input_hz: Stat | None = None  # a driven node's: the measured rate of its input topic

    def to_json(self) -> dict[str, Any]:
        def st(s: Stat | None) -> dict[str, float | int] | None:
            return None if s is None else s.to_json()

        return {
            "value": self.value, "recordings": self.recordings,
            "cpu": st(self.cpu), "frequency_hz": st(self.frequency_hz), "bandwidth_kBps": st(self.bandwidth_kBps),
            "topics": {t: {"frequency_hz": st(f), "bandwidth_kBps": st(b)} for t, (f, b) in self.topics.items()},
            **({} if self.input_hz is None else {"input_hz": st(self.input_hz)}),
        }


#: Where a driven node's setting in model.json's ``system`` part came from: fitted from
#: recordings at that value, kept from the system.yaml (no recording), or evaluated from the
#: fitted curves at a value between the measured ones.
DRIVEN_SOURCES = ("measured", "system", "grid")


@dataclass(frozen=True)
class DrivenSetting:
    """One setting of a driven node (system.yaml ``input:``) as ``fit`` wrote it into the
    ``system`` part, and where its numbers came from (``source``: :data:`DRIVEN_SOURCES`).
    A measured setting also keeps the line CPU = ``cpu`` + ``cpu_per_hz`` x input rate was
    fitted to: ``points`` (input Hz, CPU) per recording, its ``r2`` (None with one input
    rate) and ``notes`` (e.g. one input rate only)."""

    value: float | None
    source: str
    cpu: float
    cpu_per_hz: float
    performance: float
    out_per_in: float | None = None
    bytes_per_msg: float | None = None
    r2: float | None = None
    points: tuple[tuple[float, float], ...] = ()
    notes: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "value": self.value, "source": self.source, "cpu": round9(self.cpu), "cpu_per_hz": round9(self.cpu_per_hz),
            "performance": round9(self.performance),
            "out_per_in": None if self.out_per_in is None else round9(self.out_per_in),
            "bytes_per_msg": None if self.bytes_per_msg is None else round9(self.bytes_per_msg),
            "r2": None if self.r2 is None else round6(self.r2),
            "points": [[float(a), float(b)] for a, b in self.points],
            "notes": list(self.notes),
        }


@dataclass(frozen=True)
class FittedRelation:
    """A fitted relation (what :func:`perfros_bag.fitting.regression.fit_curve` returns and
    model.json keeps): the curve (``form``, ``coef``, ``domain``, ``scale``), how well it
    fits, the points it was fitted to and why this form (``warnings``)."""

    form: CurveForm
    coef: tuple[float, ...]
    domain: tuple[float, float]
    scale: float
    r2: float
    loo_rmse: float | None  # None with 2 points (nothing to leave out)
    points: tuple[tuple[float, float], ...]
    candidates: dict[str, float | None] = field(default_factory=dict)  # form -> leave-one-out RMSE
    warnings: tuple[str, ...] = ()
    #: where a performance relation's performance came from: "metric" (measured, the node's
    #: system.yaml ``metric``) or "settings" (the expert's levels); None for the others
    source: str | None = None

    @property
    def curve(self) -> Curve:
        return Curve(self.form, self.coef, self.domain, self.scale)

    def to_json(self) -> dict[str, Any]:
        return {
            "form": self.form, "coef": [float(c) for c in self.coef],
            "domain": [float(d) for d in self.domain], "scale": self.scale,
            "r2": round6(self.r2),
            "loo_rmse": _finite_or_none(self.loo_rmse),
            "points": [[float(a), float(b)] for a, b in self.points],
            "candidates": {k: _finite_or_none(v) for k, v in self.candidates.items()},
            "warnings": list(self.warnings),
            **({} if self.source is None else {"source": self.source}),
        }


#: a node's fitted quantities -> the relation whose leave-one-out RMSE a value never measured
#: carries: a paper node's CPU, frequency and bandwidth; a driven node's CPU line (base and per
#: input Hz), output per input message and bytes per message
PAPER_QUANTITIES = {"cpu": "parameter->cpu", "frequency_hz": "parameter->frequency",
                    "bandwidth_kBps": "parameter->bandwidth"}
DRIVEN_QUANTITIES = {"cpu_base": "parameter->cpu_base", "cpu_per_hz": "parameter->cpu_per_hz",
                     "out_per_in": "parameter->out_per_in", "bytes_per_msg": "parameter->bytes_per_msg"}


@dataclass(frozen=True)
class Unmeasured:
    """model.json ``unmeasured.<node>``: the parameter values its recordings measured, and per
    fitted quantity (:data:`PAPER_QUANTITIES`, :data:`DRIVEN_QUANTITIES`) the leave-one-out
    RMSE of the fit that gives it at any other value (None: the fit has none, two points);
    ``rule``: a throttle's output follows its rule (``period``) at any value, not a fit."""

    measured_values: tuple[float, ...]
    loo_rmse: dict[str, float | None]
    driven: bool = False
    rule: str | None = None

    def measured(self, value: float | None) -> bool:
        """Did a recording run the node at ``value`` (to 1e-6, relative)? A node without a
        parameter value always did."""
        return value is None or any(abs(value - v) <= 1e-6 * max(1.0, abs(v)) for v in self.measured_values)

    def to_json(self) -> dict[str, Any]:
        return {"measured_values": [float(v) for v in self.measured_values], "driven": self.driven,
                "loo_rmse": {k: _finite_or_none(v) for k, v in self.loo_rmse.items()},
                **({} if self.rule is None else {"rule": self.rule})}


def unmeasured_entry(fits: Mapping[str, FittedRelation], values: list[float | None], *, driven: bool,
                     rule: str | None = None) -> Unmeasured:
    """A node's :class:`Unmeasured` from its fits (relation -> fit) and measured ``values``."""
    quantities = DRIVEN_QUANTITIES if driven else PAPER_QUANTITIES
    return Unmeasured(tuple(sorted({float(v) for v in values if v is not None})),
                      {q: fits[rel].loo_rmse for q, rel in quantities.items() if rel in fits}, driven, rule)


def value_errors(entry: Unmeasured, value: float | None, *, input_hz: float | None = None,
                 frequency_hz: float | None = None, bandwidth_kBps: float | None = None
                 ) -> dict[str, float | None] | None:
    """None when ``value`` was measured; else per quantity (``cpu``, ``frequency_hz``,
    ``bandwidth_kBps``) the fit's leave-one-out error at it, in its units (None: the fit has
    none). A driven node's at its planned ``input_hz`` and output (``frequency_hz``,
    ``bandwidth_kBps``): CPU ``rmse(cpu_base) + rmse(cpu_per_hz) x F_in``, rate
    ``rmse(out_per_in) x F_in`` (0 under a ``rule``), bandwidth the bytes per message's error
    times the rate plus the bytes per message times the rate's error."""
    if entry.measured(value):
        return None
    e = entry.loo_rmse
    if not entry.driven:
        return {q: e[q] for q in PAPER_QUANTITIES if q in e}
    out: dict[str, float | None] = {}
    f_in = input_hz or 0.0
    if "cpu_base" in e or "cpu_per_hz" in e:
        base, per = e.get("cpu_base"), e.get("cpu_per_hz")
        out["cpu"] = None if base is None or per is None else base + per * f_in
    rate: float | None = 0.0 if entry.rule is not None else None
    if entry.rule is None and "out_per_in" in e:
        rate = None if e["out_per_in"] is None else e["out_per_in"] * f_in
    out["frequency_hz"] = rate
    f_out, bw = frequency_hz or 0.0, bandwidth_kBps or 0.0
    size = bw * 1000.0 / f_out if f_out > 0 else 0.0
    size_err = e.get("bytes_per_msg", 0.0)
    out["bandwidth_kBps"] = None if rate is None or size_err is None else (size_err * f_out + size * rate) / 1000.0
    return out


def planned_errors(entry: Unmeasured, node: PlannedNode) -> dict[str, float | None] | None:
    """:func:`value_errors` at a planned node's value, input rate and output (its first topic
    with a rate; its bandwidth, the node's or its topics' sum)."""
    f_out = next((t.frequency_hz for t in node.topics.values() if t.frequency_hz is not None), None)
    bw = node.bandwidth_kBps if node.bandwidth_kBps is not None else \
        sum(t.bandwidth_kBps for t in node.topics.values() if t.bandwidth_kBps is not None)
    return value_errors(entry, node.value, input_hz=node.input_hz, frequency_hz=f_out, bandwidth_kBps=bw)


def mark_measured(plan: Plan, unmeasured: Mapping[str, Unmeasured]) -> None:
    """Set plan.json's ``measured`` (and, for a value never measured, ``loo_error``) on every
    planned node that ``unmeasured`` knows (docs/formats.md, plan.json)."""
    for name, n in plan.nodes.items():
        entry = unmeasured.get(name)
        if entry is None:
            continue
        errors = planned_errors(entry, n)
        n.measured, n.loo_error = errors is None, errors


def measured_system(system: System, unmeasured: Mapping[str, Unmeasured], source: str | Path) -> System:
    """``solve --measured-only``: ``system`` with every node that ``unmeasured`` knows held to
    the settings whose value a recording ran (:meth:`Unmeasured.measured`): its fitted curve
    (a continuum of levels) dropped, its other settings (a driven node's grid) left out. A
    node left with no setting is an :class:`InputError` naming ``source``."""
    from dataclasses import replace

    if not unmeasured:
        raise InputError(source, "--measured-only needs a model.json written by `fit` (its 'unmeasured' "
                                 "part says which values were measured)")
    nodes = []
    for node in system.nodes:
        entry = unmeasured.get(node.name)
        if entry is None:
            nodes.append(node)
            continue
        kept = tuple(s for s in node.settings if s.value is not None and entry.measured(s.value))
        if not kept:
            raise InputError(source, f"--measured-only: node {node.name!r} has no setting at a measured value "
                                     f"({', '.join(f'{v:g}' for v in entry.measured_values) or 'none'})")
        nodes.append(replace(node, settings=kept, curve=None, cpu_error_between=None))
    return replace(system, nodes=tuple(nodes))


def read_unmeasured(path: str | Path) -> dict[str, Unmeasured]:
    """model.json's ``unmeasured`` part, for ``solve``'s table (a system.yaml, or a model
    written before it: empty). Light: no fits read."""
    data = read_json(path)
    if not isinstance(data, Mapping):
        return {}
    return _unmeasured(_Doc(Path(path)), data.get("unmeasured", {}))


def _unmeasured(doc: _Doc, raw: Any) -> dict[str, Unmeasured]:
    out: dict[str, Unmeasured] = {}
    for n, u in doc.mapping(raw, "unmeasured").items():
        where = f"unmeasured.{n}"
        m = doc.mapping(u, where)
        rule = m.get("rule")
        out[str(n)] = Unmeasured(
            doc.numbers(m.get("measured_values", []), f"{where}.measured_values"),
            {str(q): doc.opt_number(v, f"{where}.loo_rmse.{q}", nonneg=True)
             for q, v in doc.mapping(m.get("loo_rmse", {}), f"{where}.loo_rmse").items()},
            bool(m.get("driven", False)),
            None if rule is None else doc.string(rule, f"{where}.rule"))
    return out


@dataclass(frozen=True)
class ModelDocument:
    """A model.json: the system with fitted curves (as a system.yaml mapping), and per
    configurable node its fits and the measured numbers they came from."""

    system_file: str  # where the system came from
    characterisation: str  # the characterisation.csv fitted
    system: dict[str, Any]
    fits: dict[str, dict[str, FittedRelation]]
    measured: dict[str, list[MeasuredSetting]]
    warnings: list[str]
    format: str = MODEL_FORMAT
    cpu_statistic: str = "mean"  # a setting's CPU: the mean of its samples, or their p95
    #: per driven node (system.yaml ``input:``), its settings in ``system`` and where each came from
    driven: dict[str, list[DrivenSetting]] = field(default_factory=dict)
    #: the latency model's fit (perfros_bag.fitting.latency): points per node and its
    #: in-sample error; None when nothing was fitted (the parameters are in ``system.latency``)
    latency_fit: dict[str, Any] | None = None
    #: per fitted node, the values its recordings measured and the leave-one-out errors a value
    #: never measured carries (:func:`unmeasured_entry`, :func:`value_errors`)
    unmeasured: dict[str, Unmeasured] = field(default_factory=dict)
    #: the median machine speed (perfros_bag.cpu.speed) of the recordings fitted (characterisation.csv's
    #: ``speed_factor`` column); None when none was recorded. Recorded, never applied to a fit
    speed_factor: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "format": self.format,
            "system_file": self.system_file,
            "characterisation": self.characterisation,
            "cpu_statistic": self.cpu_statistic,
            "system": self.system,
            "fits": {n: {rel: f.to_json() for rel, f in fs.items()} for n, fs in self.fits.items()},
            "measured": {n: [m.to_json() for m in ms] for n, ms in self.measured.items()},
            **({"driven": {n: [d.to_json() for d in ds] for n, ds in self.driven.items()}} if self.driven else {}),
            **({"latency_fit": self.latency_fit} if self.latency_fit is not None else {}),
            **({"unmeasured": {n: u.to_json() for n, u in self.unmeasured.items()}} if self.unmeasured else {}),
            **({"speed_factor": self.speed_factor} if self.speed_factor is not None else {}),
            "warnings": list(self.warnings),
        }


def write_model(path: str | Path, document: ModelDocument) -> None:
    """Write model.json atomically."""
    atomic_write_json(path, document.to_json())


# --------------------------------------------------------------------------- reading


class _Doc(Doc):
    """Checks with the place in the document named in the error (JSON's words: an object)."""

    container = "an object"
    list_wording = "expected a list"

    def number(self, obj: Any, where: str, *, positive: bool = False, nonneg: bool = False,
               limit: float = MAX_MAGNITUDE) -> float:
        """A finite number within ``limit`` (:mod:`perfros_bag.limits`)."""
        if isinstance(obj, bool) or not isinstance(obj, int | float):
            raise self.fail(where, f"expected a number, got {obj!r}")
        return super().number(obj, where, positive=positive, nonneg=nonneg, limit=limit)

    def string(self, obj: Any, where: str) -> str:
        if not isinstance(obj, str):
            raise self.fail(where, f"expected a string, got {kind_of(obj)}")
        return obj

    def numbers(self, obj: Any, where: str, n: int | None = None, *, limit: float = MAX_MAGNITUDE) -> tuple[float, ...]:
        out = tuple(self.number(v, f"{where}[{i}]", limit=limit) for i, v in enumerate(self.items(obj, where)))
        if n is not None and len(out) != n:
            raise self.fail(where, f"expected {n} numbers, got {len(out)}")
        return out

    def stat(self, obj: Any, where: str) -> Stat | None:
        if obj is None:
            return None
        m = self.mapping(obj, where)
        count = m.get("count")
        count = _whole(self, count, f"{where}.count")
        return Stat(self.number(m.get("mean"), f"{where}.mean"),
                    self.number(m.get("std"), f"{where}.std", nonneg=True), count)


def _whole(doc: _Doc, obj: Any, where: str) -> int:
    """``obj`` must be a count: a whole number in [0, MAX_MAGNITUDE]."""
    if isinstance(obj, bool) or not isinstance(obj, int):
        raise doc.fail(where, f"expected a whole number, got {obj!r}")
    if not 0 <= obj <= MAX_MAGNITUDE:
        raise doc.fail(where, f"must be a whole number in [0, {MAX_MAGNITUDE:g}], got {short_repr(obj)}")
    return obj



def _relation(doc: _Doc, raw: Any, where: str) -> FittedRelation:
    m = doc.mapping(raw, where)
    lo, hi = doc.numbers(m.get("domain"), f"{where}.domain", 2)
    candidates = {str(k): doc.opt_number(v, f"{where}.candidates.{k}", nonneg=True)
                  for k, v in doc.mapping(m.get("candidates", {}), f"{where}.candidates").items()}
    try:
        form = curve_form(m.get("form"))
    except ValueError as exc:
        raise doc.fail(f"{where}.form", str(exc)) from None
    fit = FittedRelation(
        form=form,
        coef=doc.numbers(m.get("coef"), f"{where}.coef", limit=MAX_COEFFICIENT),
        domain=(lo, hi),
        scale=doc.number(m.get("scale", 1.0), f"{where}.scale", positive=True),
        r2=doc.number(m.get("r2"), f"{where}.r2"),
        loo_rmse=doc.opt_number(m.get("loo_rmse"), f"{where}.loo_rmse", nonneg=True),
        points=tuple((x, y) for x, y in (doc.numbers(p, f"{where}.points[{i}]", 2)
                                          for i, p in enumerate(doc.items(m.get("points", []), f"{where}.points")))),
        candidates=candidates,
        warnings=tuple(doc.string(w, f"{where}.warnings[{i}]")
                       for i, w in enumerate(doc.items(m.get("warnings", []), f"{where}.warnings"))),
        source=None if m.get("source") is None else doc.string(m.get("source"), f"{where}.source"),
    )
    try:
        fit.curve  # noqa: B018 - the coefficients and domain must make a curve
    except ValueError as exc:
        raise doc.fail(where, str(exc)) from None
    return fit


def _measured(doc: _Doc, raw: Any, where: str) -> MeasuredSetting:
    m = doc.mapping(raw, where)
    topics = {str(t): (doc.stat(tm.get("frequency_hz"), f"{where}.topics.{t}.frequency_hz"),
                       doc.stat(tm.get("bandwidth_kBps"), f"{where}.topics.{t}.bandwidth_kBps"))
              for t, tm in ((t, doc.mapping(v, f"{where}.topics.{t}"))
                            for t, v in doc.mapping(m.get("topics", {}), f"{where}.topics").items())}
    recordings = m.get("recordings")
    recordings = _whole(doc, recordings, f"{where}.recordings")
    return MeasuredSetting(doc.opt_number(m.get("value"), f"{where}.value"), recordings,
                           doc.stat(m.get("cpu"), f"{where}.cpu"),
                           doc.stat(m.get("frequency_hz"), f"{where}.frequency_hz"),
                           doc.stat(m.get("bandwidth_kBps"), f"{where}.bandwidth_kBps"), topics,
                           doc.stat(m.get("input_hz"), f"{where}.input_hz"))


def _driven(doc: _Doc, raw: Any, where: str) -> DrivenSetting:
    m = doc.mapping(raw, where)
    source = doc.string(m.get("source"), f"{where}.source")
    if source not in DRIVEN_SOURCES:
        raise doc.fail(f"{where}.source", f"must be one of {', '.join(DRIVEN_SOURCES)}, got {source!r}")
    r2 = m.get("r2")
    return DrivenSetting(
        doc.opt_number(m.get("value"), f"{where}.value"), source,
        doc.number(m.get("cpu"), f"{where}.cpu", nonneg=True),
        doc.number(m.get("cpu_per_hz"), f"{where}.cpu_per_hz", nonneg=True),
        doc.number(m.get("performance"), f"{where}.performance", nonneg=True),
        doc.opt_number(m.get("out_per_in"), f"{where}.out_per_in", nonneg=True),
        doc.opt_number(m.get("bytes_per_msg"), f"{where}.bytes_per_msg", nonneg=True),
        None if r2 is None else doc.number(r2, f"{where}.r2"),
        tuple((x, y) for x, y in (doc.numbers(p, f"{where}.points[{i}]", 2)
                                  for i, p in enumerate(doc.items(m.get("points", []), f"{where}.points")))),
        tuple(doc.string(w, f"{where}.notes[{i}]")
              for i, w in enumerate(doc.items(m.get("notes", []), f"{where}.notes"))),
    )


def parse_model(data: Any, path: str | Path) -> ModelDocument:
    """Check a parsed model.json; a problem is an :class:`InputError` naming the file and
    the place (``fits.tracker1.cpu->performance.coef[1]: expected a number``)."""
    p = Path(path)
    doc = _Doc(p)
    expect_kind(p, data, DOCUMENT_KINDS[MODEL_FORMAT], {DOCUMENT_KINDS[MODEL_FORMAT]})
    fmt = data.get("format") if isinstance(data, Mapping) else None
    if not isinstance(data, Mapping) or fmt != MODEL_FORMAT:
        raise InputError(p, f"not a perfros-bag model (format {fmt!r}, expected {MODEL_FORMAT!r})")
    if not isinstance(data.get("system"), dict):
        raise InputError(p, "has no 'system' object")
    fits = {str(n): {str(rel): _relation(doc, f, f"fits.{n}.{rel}")
                     for rel, f in doc.mapping(rels, f"fits.{n}").items()}
            for n, rels in doc.mapping(data.get("fits", {}), "fits").items()}
    measured = {str(n): [_measured(doc, v, f"measured.{n}[{i}]") for i, v in enumerate(doc.items(ms, f"measured.{n}"))]
                for n, ms in doc.mapping(data.get("measured", {}), "measured").items()}
    driven = {str(n): [_driven(doc, v, f"driven.{n}[{i}]") for i, v in enumerate(doc.items(ds, f"driven.{n}"))]
              for n, ds in doc.mapping(data.get("driven", {}), "driven").items()}
    warnings = [doc.string(w, f"warnings[{i}]") for i, w in enumerate(doc.items(data.get("warnings", []), "warnings"))]
    statistic = doc.string(data.get("cpu_statistic", "mean"), "cpu_statistic")
    if statistic not in ("mean", "p95"):
        raise InputError(p, f"cpu_statistic: must be 'mean' or 'p95', got {statistic!r}")
    latency_fit = data.get("latency_fit")
    if latency_fit is not None:
        doc.mapping(latency_fit, "latency_fit")
    speed = data.get("speed_factor")
    if speed is not None and (isinstance(speed, bool) or not isinstance(speed, int | float)
                              or not math.isfinite(speed) or speed <= 0):
        raise InputError(p, f"speed_factor: must be a finite number > 0, got {speed!r}")
    return ModelDocument(doc.string(data.get("system_file", ""), "system_file"),
                         doc.string(data.get("characterisation", ""), "characterisation"),
                         data["system"], fits, measured, warnings, fmt, statistic, driven,
                         None if latency_fit is None else dict(latency_fit),
                         _unmeasured(doc, data.get("unmeasured", {})),
                         None if speed is None else float(speed))


def read_model(path: str | Path) -> ModelDocument:
    """Read and check a model.json (the ``system`` part is checked by
    :func:`perfros_bag.system.systemfile.parse_system` when it is loaded)."""
    return parse_model(read_json(path), path)

