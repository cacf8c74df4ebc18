"""``tune``: sweep -> characterise -> fit -> solve -> deploy, then learn from each deployment.

Round k (1, 2, ...) solves Problem 1 on model k-1, deploys the plan here
(:func:`perfros_bag.sweep.deploy.deploy`: capped cgroups, shaped links) and validates it.
Model 0 is fitted on the sweep alone; model k on the sweep plus the recordings of rounds
1..k, each of which holds every node at its planned setting, co-located and capped, as it
will run. The loop stops when a round holds (:func:`holds`: within the tolerance, eq 10, and
no node held back by its computer's cap), when model k's
plan would deploy exactly what round k deployed, or after ``rounds`` rounds.

How a deployment's recording is weighed in the refit (docs/formats.md, "tune"):

- it is one more characterisation run: its manifest entry (``DIR/manifest.yaml``) gives
  each varied node the value it ran at, and its CPU comes from the host's trace;
- where a deployment measured a node at a value, that measurement stands for the value:
  the sweep's rows of that node at that value are left out of the refit (the sweep ran the
  node alone and uncapped; averaging both would keep half of the sweep's error exactly
  where the plan puts its load);
- a driven node (system.yaml ``input:``) is measured at a value *and an input rate*: the
  sweep ran each value at several input rates (its CPU-vs-input-rate line needs two), the
  deployment at one. Its deployment row stands for (value, input rate): only the sweep's
  rows of that node at that value whose ``input_hz`` is within :data:`SAME_INPUT` of the
  deployment row's measured ``input_hz`` are left out; the others keep the line's other
  rates, and the deployment adds its point (a row without ``input_hz`` stands for nothing);
- a starved node's CPU is a lower bound, not its need. A computer is starved when its
  cgroup was throttled in at least :data:`THROTTLED_SHARE` of the CFS periods of the
  recording (deploy.json's ``throttling``). A node on it that kept a share r below
  :data:`KEPT_ALL` of its planned message rate (validation.json's ``ratio``; a driven
  node's r is its output share over its input's, :func:`kept_share`) is taken to need
  ``measured / r``, its CPU per message at the planned rate (r at least :data:`MIN_KEPT`),
  and its row's rates and bandwidth are scaled the same way (:data:`RESCALED_COLUMNS`: the
  row stands for the node as it would run at its planned rate); a starved node without a
  rate to compare is left out of the refit for that round. A driven node's ``input_hz``
  is not scaled: r is its output share over its input's, so ``measured / r`` is its need
  for every message it got, at the input rate measured (the row's ``input_hz``, the planned
  one unless its upstream fell short): one point of its line, which gives its need at the
  planned input rate;
- each node a round measured is calibrated (:func:`calibrate`): the sweep's rows of it, at
  every value, are scaled by its CPU in the rounds over model 0's at the same values, so a
  value no round ran is predicted in the deployments' scale.

With ``base`` (a characterisation.csv, e.g. a sweep's made elsewhere) nothing is swept:
model 0 is fitted on the base rows alone, and model k on the base rows (weighed as the
sweep's are) plus the rounds' recordings.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import re
import warnings
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.characterisation import table
from perfros_bag.characterisation.csvfile import read_characterisation, write_characterisation
from perfros_bag.characterisation.manifest import load_manifest, write_manifest
from perfros_bag.errors import InputError, PerfrosError, PerfrosWarning
from perfros_bag.fileio import atomic_open
from perfros_bag.fitting.build import build_model
from perfros_bag.fitting.modelfile import write_model
from perfros_bag.solver import METHODS, check_headroom, solve
from perfros_bag.sweep.deploy import deploy, plan_run
from perfros_bag.sweep.launchfile import check_space, read_launch
from perfros_bag.sweep.runner import computer_name, sweep
from perfros_bag.sweep.space import load_space
from perfros_bag.system.planfile import save_plan
from perfros_bag.system.systemfile import load_system
from perfros_bag.system.types import driven_rates
from perfros_bag.tune.tunefile import TUNE_FORMAT, RoundComputer, RoundNode, TuneRound, read_tune, write_tune
from perfros_bag.validation import DEFAULT_TOLERANCE

if TYPE_CHECKING:
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.characterisation.manifest import RecordingEntry
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.types import System
    from perfros_bag.validation.eq10 import NodeCheck, Validation

#: a computer whose cgroup was throttled in at least this share of the CFS periods of the
#: recording is starved: its nodes' CPU is a lower bound
THROTTLED_SHARE = 0.10
#: the least kept rate share a starved node's need is scaled by (1 / MIN_KEPT at most)
MIN_KEPT = 0.05
#: a node that kept at least this share of its planned rate kept up (a rate measured over a
#: short recording is that noisy): its CPU counts as measured
KEPT_ALL = 0.98
#: refit uses of a node's row in a deployment's recording
USE_MEASURED, USE_RESCALED, USE_LEFT_OUT = "measured", "rescaled to its planned rate", "left out"

#: a driven node's deployment row stands for the sweep's rows at its value whose input rate
#: is within this share of the deployment's measured input rate
SAME_INPUT = 0.10
#: a base row's recording named like a round's (``round-K/run.bag``) is renamed with this
#: prefix: it is not this loop's round K
BASE_PREFIX = "base:"
_ROUND_RECORDING = re.compile(r"round-\d+/run\.bag")

#: the columns of a starved node's row that scale with its message rate
RESCALED_COLUMNS = ("cpu_units_mean", "cpu_units_p95", "frequency_hz", "bandwidth_kBps", "median_rate_hz")

Progress = Callable[[str], None]
#: the rounds of tune.json -> a PNG (tune.png)
Plot = Callable[[list[dict[str, Any]]], bytes]


@dataclass
class TuneResult:
    document: dict[str, Any]  # tune.json
    resumed: int  # rounds finished by an earlier start
    ran: int  # rounds this start ran
    rounds: list[TuneRound] = dataclasses.field(default_factory=list)  # tune.json's rounds, typed


def _check_args(rounds: int, tolerance: float, headroom: float | str, method: str, units_per_core: float) -> None:
    check_headroom(headroom)  # a number in [0, 1) or "auto"
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise InputError(None, f"rounds must be a whole number >= 1, got {rounds!r}")
    if not math.isfinite(tolerance) or tolerance < 0:
        raise InputError(None, f"the tolerance must be a number >= 0, got {tolerance!r}")
    if method not in METHODS:
        raise InputError(None, f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if not math.isfinite(units_per_core) or units_per_core <= 0:
        raise InputError(None, f"CPU units per core must be > 0, got {units_per_core!r}")


def tune(launch_path: str | Path, space_path: str | Path, system_path: str | Path, out: str | Path, *,
         rounds: int = 3, tolerance: float | None = None, method: str = "exact", headroom: float | str = 0.0,
         duration: float | None = None, units_per_core: float = 100.0, net: bool = True, interval: float = 0.5,
         progress: Progress | None = None, on_round: Callable[[TuneRound], None] | None = None,
         base: str | Path | None = None, plot: Plot | None = None) -> TuneResult:
    """Run the loop into ``out`` (docs/formats.md, "tune"); resumes after the rounds an
    earlier start finished (``out/tune.json``). ``base``: a characterisation.csv to start
    from instead of sweeping (the launch file and space still say how to deploy).
    ``plot``: the rounds -> a PNG, written to ``out/tune.png`` after every round (the CLI
    passes :func:`perfros_bag.report.tune_plots.plot_tune`: the report sits above the
    loop, whose tune.json it reads)."""
    tol = DEFAULT_TOLERANCE if tolerance is None else tolerance
    _check_args(rounds, tol, headroom, method, units_per_core)
    system = load_system(system_path)
    system.capacities(1)  # Problem 1 needs every capacity: said now, not after the sweep
    space = load_space(space_path).with_duration(duration)
    launch = read_launch(launch_path)
    check_space(launch, space)
    base_path = None if base is None else Path(base).absolute()
    if base_path is not None:
        check_base(base_path, system_path)
    outdir = Path(out).absolute()
    if outdir.exists() and not outdir.is_dir():
        raise InputError(outdir, "is not a directory, expected the folder to tune into")
    say = progress or (lambda stage: None)
    inputs = {"launch": str(Path(launch_path).absolute()), "space": str(Path(space_path).absolute()),
              "system": str(Path(system_path).absolute()), "system_sha256": _sha256(Path(system_path)),
              "method": method, "headroom": headroom, "units_per_core": units_per_core}
    from_base = {} if base_path is None else {"base": str(base_path), "base_sha256": _sha256(base_path)}
    doc = _resume(outdir / "tune.json", inputs, from_base)
    done = [TuneRound.from_json(r) for r in doc["rounds"]]
    resumed = len(done)
    doc.update(tolerance_pct=tol, rounds_max=rounds, stopped=None)

    outdir.mkdir(parents=True, exist_ok=True)
    if base_path is None:
        say("sweep")
        sweep(launch_path, space_path, outdir / "sweep", duration=duration, interval=interval,
              progress=lambda i, n, name, stage, frac: say(f"sweep {i + 1}/{n} {name}: {stage}"))

    ran = 0
    while True:
        last = done[-1] if done else None
        if last is not None and holds(last, tol):  # this start's tolerance (it may differ)
            doc["stopped"] = {"reason": "within tolerance", "after_round": last.round}
            break
        if len(done) >= rounds:
            doc["stopped"] = {"reason": "rounds", "after_round": len(done)}
            break
        k = len(done) + 1
        say(f"round {k}: characterise and fit")
        model_path = fit_rounds(outdir, system_path, system, done, units_per_core, base=base_path)
        say(f"round {k}: solve")
        plan = _solve(model_path, method, headroom)
        values, placement = _deployed(plan, space, dict(launch.args))
        if last is not None and values == last.values and placement == last.placement:
            doc["stopped"] = {"reason": "plan unchanged", "after_round": last.round}
            break
        rdir = outdir / f"round-{k}"
        rdir.mkdir(exist_ok=True)
        plan_path = rdir / "plan.json"
        save_plan(plan, plan_path)
        def deploying(stage: str, frac: float, k: int = k) -> None:
            say(f"round {k}: deploy: {stage}")

        try:
            result = deploy(plan_path, launch_path, space_path, rdir, duration=duration, units_per_core=units_per_core,
                            tolerance=tol, net=net, system_path=system_path, interval=interval,
                            progress=deploying)
        except PerfrosError as exc:
            raise InputError(None, f"round {k}: the deployment failed ({exc}); rounds 1-{k - 1} are kept in "
                                   f"{outdir / 'tune.json'}" if k > 1 else
                             f"round {k}: the deployment failed ({exc})") from None
        say(f"round {k}: refit")
        entry = round_entry(k, plan, plan_path, model_path, result.record, result.validation, tol)
        after = fit_rounds(outdir, system_path, system, [*done, entry], units_per_core, base=base_path)
        _fill_after(entry, after)
        done.append(entry)
        ran += 1
        _save(outdir, doc, done)
        _plot(outdir, doc, plot)
        if on_round is not None:
            on_round(entry)
    _save(outdir, doc, done)
    if done:
        _plot(outdir, doc, plot)
    return TuneResult(doc, resumed, ran, done)


def _save(outdir: Path, doc: dict[str, Any], done: Sequence[TuneRound]) -> None:
    """tune.json: ``doc`` with ``done`` as its rounds (the one place rounds become JSON)."""
    doc["rounds"] = [r.to_json() for r in done]
    write_tune(outdir / "tune.json", doc)


def _sha256(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None


def _resume(path: Path, inputs: dict[str, Any], from_base: dict[str, Any] | None = None) -> dict[str, Any]:
    """The document to continue: tune.json's finished rounds when it exists and was made
    from the same launch file, space, system (byte for byte), method, headroom and CPU
    scale, and the same base characterisation (byte for byte; none when ``from_base`` is
    empty: a document without ``base`` was swept); a new one otherwise (an error naming the
    difference when they differ)."""
    from_base = from_base or {}
    if not path.exists():
        return {"format": TUNE_FORMAT, **inputs, **from_base, "rounds": []}
    doc = read_tune(path)
    checked = {**inputs, "base": from_base.get("base"), "base_sha256": from_base.get("base_sha256")}
    for key, now in checked.items():
        if doc.get(key) != now:
            raise InputError(path, f"its rounds were made with {key} {doc.get(key)!r}, not {now!r}: tune into "
                                   "another folder, or delete tune.json to start over")
    return doc


# --------------------------------------------------------------------------- fit

def _entries(outdir: Path, done: Sequence[TuneRound], units_per_core: float,
             swept: bool = True) -> list[RecordingEntry]:
    """The sweep's recordings (none when not ``swept``: a base characterisation stands for
    them) and each finished round's, as ``outdir/manifest.yaml`` lists them (written here:
    the manifest the refit characterises), every one in the scale the plans are emulated in
    (``units_per_core``: ``cpu_percent / 100 x units_per_core``)."""
    if swept:
        sweep = load_manifest(outdir / "sweep" / "manifest.yaml").recordings
        host = next((e.computer for e in sweep if e.computer), None)
    else:
        sweep, host = (), computer_name()
    items: list[dict[str, Any]] = []
    for e in sweep:
        item: dict[str, Any] = {"path": f"sweep/{e.name}", "units_per_core": units_per_core,
                                "settings": dict(e.settings)}
        if e.cpu is not None:
            item["cpu"] = str(e.cpu.relative_to(outdir)) if e.cpu.is_relative_to(outdir) else str(e.cpu)
        if e.computer is not None:
            item["computer"] = e.computer
        if e.speed_factor is not None:
            item["speed_factor"] = e.speed_factor
        items.append(item)
    for r in done:  # the host's own trace: every node in the measurement's units
        items.append({"path": r.recording, "cpu": f"{r.dir}/run.host.cpu.csv",
                      **({"computer": host} if host else {}), "units_per_core": units_per_core,
                      "settings": dict(r.values)})
    write_manifest(outdir / "manifest.yaml", items)
    return list(load_manifest(outdir / "manifest.yaml").recordings)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    return bool(a == b)


def _scaled(row: Row, columns: Collection[str], factor: float) -> Row:
    """``row`` with ``columns`` (those it has) multiplied by ``factor``."""
    values: dict[str, Any] = {c: None if getattr(row, c) is None else getattr(row, c) * factor for c in columns}
    return dataclasses.replace(row, **values)


def weigh(rows: list[Row], done: Sequence[TuneRound], driven: Collection[str] = ()) -> list[Row]:
    """The rows the refit uses (the rules of this module's docstring): each round's rows as
    its ``nodes[*].refit`` says (kept, rescaled by ``cpu_factor`` or left out), and the
    sweep's rows of a node at a value a round measured and kept left out; of a node in
    ``driven``, only those at that value and about the input rate the round measured
    (:data:`SAME_INPUT`). Rows of recordings no round made are the sweep's (or the base's)."""
    out: list[Row] = []
    measured: list[Row] = []  # the kept deployment rows: each stands for its (node, value[, input rate])
    rounds = {r.recording: r for r in done}
    for row in rows:
        r = rounds.get(row.recording)
        if r is None:
            continue
        node = r.nodes.get(row.node)
        if node is None:  # not a node of the plan: as any run
            out.append(row)
            continue
        if node.refit == USE_LEFT_OUT:
            continue
        factor = node.cpu_factor or 1.0
        if factor != 1.0:  # a starved node as at its planned rate: its CPU, rates and bandwidth
            row = _scaled(row, RESCALED_COLUMNS, factor)
        out.append(row)
        if row.cpu_units_mean is not None:
            measured.append(row)

    def superseded(row: Row) -> bool:
        for m in measured:
            if m.node != row.node or not _same(m.value, row.value):
                continue
            if row.node not in driven:
                return True
            if m.input_hz is not None and row.input_hz is not None and \
                    abs(row.input_hz - m.input_hz) <= SAME_INPUT * m.input_hz:
                return True
        return False

    sweep_rows = [row for row in rows if row.recording not in rounds and not superseded(row)]
    return sweep_rows + out


def check_base(path: Path, system_path: str | Path) -> None:
    """A base characterisation ``tune`` can start from: readable, naming nodes of the
    system and fitting it (tried now, before anything runs); every problem an
    :class:`InputError` naming ``path``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PerfrosWarning)
            build_model(system_path, path)
    except InputError as exc:
        if exc.path == str(path):
            raise
        raise InputError(path, f"cannot fit the system on it: {exc}") from None
    except PerfrosError as exc:
        raise InputError(path, f"cannot fit the system on it: {exc}") from None


def base_rows(path: Path) -> list[Row]:
    """The rows of a base characterisation, a recording named like one of the loop's rounds
    renamed with :data:`BASE_PREFIX` (the refit tells the rounds' rows by their recording)."""
    return [dataclasses.replace(r, recording=BASE_PREFIX + r.recording) if _ROUND_RECORDING.fullmatch(r.recording)
            else r for r in read_characterisation(path).rows]


#: a node's calibration factor is kept within these bounds (a deployment that ran its node
#: at a fifth of the sweep's CPU says more about the run than about the node)
CALIBRATION_BOUNDS = (0.5, 2.0)


def calibrate(rows: list[Row], done: Sequence[TuneRound], model0: System) -> tuple[list[Row], dict[str, float]]:
    """The sweep's (or base's) rows of each node the rounds measured, scaled by how that node
    ran in the deployments: factor = Σ its CPU in the rounds' kept rows / Σ model 0's CPU at
    the same values (and input rates), model 0 being the fit on the sweep alone. A deployment
    runs the node as it will run (co-located, capped, its input across a link where the plan
    puts it there), which a sweep on one computer does not; the factor carries that to the
    values the rounds did not run, so a refit's next plan is not predicted from the sweep's
    scale again. Only rows that measured the node as it ran unhindered (refit ``measured``)
    set a factor: a starved node's rescaled need is an estimate. The rounds' own rows are not
    scaled. Returns the rows and node -> factor."""
    by_run = {r.recording: r for r in done}
    measured: dict[str, float] = {}
    predicted: dict[str, float] = {}
    seen: set[tuple[str, str]] = set()
    for row in rows:
        if row.recording not in by_run or row.cpu_units_mean is None or (row.recording, row.node) in seen:
            continue
        node = by_run[row.recording].nodes.get(row.node)
        use = USE_MEASURED if node is None or node.refit is None else node.refit
        if use != USE_MEASURED:  # a starved node's rescaled need is an estimate: not a scale to carry
            continue
        seen.add((row.recording, row.node))
        pred = model_cpu(model0, row.node, row.value, row.input_hz)  # input_hz counts for a driven node only
        if pred is None or not math.isfinite(pred) or pred <= 0:
            continue
        measured[row.node] = measured.get(row.node, 0.0) + row.cpu_units_mean
        predicted[row.node] = predicted.get(row.node, 0.0) + pred
    lo, hi = CALIBRATION_BOUNDS
    factors = {n: min(hi, max(lo, measured[n] / predicted[n])) for n in measured}
    out: list[Row] = []
    for row in rows:
        f = factors.get(row.node)
        out.append(row if f is None or row.recording in by_run
                   else _scaled(row, ("cpu_units_mean", "cpu_units_p95"), f))
    return out, factors


def fit_rounds(outdir: Path, system_path: str | Path, system: System, done: Sequence[TuneRound],
               units_per_core: float, base: Path | None = None) -> Path:
    """Characterise the sweep (or take ``base``'s rows instead) and the finished rounds,
    weigh the rows (:func:`weigh`) and fit: ``outdir/characterisation-<k>.csv`` and
    ``outdir/model-<k>.json``, k = len(done)."""
    rows = [] if base is None else base_rows(base)
    if base is None or done:
        # the latency model is fitted on the sweep's runs (uncapped, without links, as its rule
        # assumes there); each deployment recalibrates it below, beside its prediction
        result = table.characterise(_entries(outdir, done, units_per_core, swept=base is None), system,
                                    latency=bool(system.chains) and system.has_flow)
        if result.failures:
            f = result.failures[0]
            raise InputError(outdir / "manifest.yaml", f"recording {f.recording}: {f.message}")
        rounds = {r.recording for r in done}
        rows += [dataclasses.replace(r, latency_p50_s=None, latency_p95_s=None, latency_max_s=None)
                 if r.recording in rounds else r for r in result.rows]
    k = len(done)
    csv_path, model_path = outdir / f"characterisation-{k}.csv", outdir / f"model-{k}.json"
    weighed = weigh(rows, done, {n.name for n in system.nodes if n.driven})
    if done and (outdir / "model-0.json").exists():
        weighed, _factors = calibrate(weighed, done, load_model(outdir / "model-0.json"))
    write_characterisation(csv_path, weighed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)  # the fit's notes are in model.json
        model = build_model(system_path, csv_path)
    if done and system.chains:
        _recalibrate_latency(outdir, model.document.system, done)
    write_model(model_path, model.document)
    return model_path


def _recalibrate_latency(outdir: Path, doc_system: dict[str, Any], done: Sequence[TuneRound]) -> None:
    """The latency model refitted from the deployments (validation.json's chains beside the
    round's plan.json and model), with the new fit's overhead:

    - each hop node's service in a round is restated at the refitted model's CPU: the
      round's predicted service, at scale 1, times the new model's CPU at that round's value
      (and input rate) over the CPU the round's plan gave it. The CPU refit has already
      learnt what the deployment's CPU said (:func:`calibrate`); a scale learnt against the
      old CPU would count it twice;
    - the scale a round implies is what its measured p50 left after overhead, transfer and
      the predicted wait over that service (the wait of a periodic input does not grow with
      the scale: it is 0 below utilisation 1 and a share of the input period above);
    - the node's new ``service_scale`` is the geometric mean of the new fit's own scale (the
      sweep's, 1 when it has none), counted once, and each round's: one 12-15 s deployment
      also carries how fast the host ran in it (record-cpu's speed reading moved 0.40-0.79
      within one case-study run), which a scale learnt from it alone carries into every
      later plan;
    - its p95 ratio: what its measured p95 leaves after overhead, transfer and the p95 wait
      over what its p50 left (the round's own service: at least 1), the mean over the rounds.
      Taken over the new scale instead, the ratio would carry all of a slow round's p95 into
      the next plans, whatever the scale's mean kept of it. ``queue_factor`` (now only the
      wait behind other traffic on a link) is kept.
    """
    from perfros_bag.fileio import read_json
    from perfros_bag.fitting.latency import params_json
    from perfros_bag.system.systemfile import parse_system

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        system = parse_system(doc_system, "model")
    over = system.latency.overhead_ms
    # node, the measured hop, the planned hop, its service (ms) at scale 1 at the refitted CPU,
    # and what its measured p50 left for the node (ms)
    seen: list[tuple[str, dict[str, Any], dict[str, Any], float, float]] = []
    for r in done:
        path = outdir / r.dir / "validation.json"
        if not path.is_file() or r.model is None or not (outdir / r.model).is_file():
            continue
        used = ((read_json(outdir / r.model).get("system") or {}).get("latency") or {})
        plan_doc = read_json(outdir / r.dir / "plan.json")
        plan_chains = {c.get("name"): c for c in (plan_doc.get("chains") or [])}
        planned = plan_doc.get("nodes") or {}
        for chain in read_json(path).get("chains") or []:
            hops = {(h.get("from"), h.get("to")): h for h in plan_chains.get(chain.get("name"), {}).get("hops") or []}
            for h in chain.get("hops") or []:
                ph = hops.get((h.get("from"), h.get("to")))
                if ph is None or h.get("p50_s") is None or not ph.get("service_ms"):
                    continue
                node = ph["node"]
                service = float(ph["service_ms"]) / float((used.get("service_scale") or {}).get(node, 1.0))
                pn = planned.get(node) or {}
                now = model_cpu(system, node, pn.get("value"), pn.get("input_hz"))
                if pn.get("cpu") and now is not None and math.isfinite(now) and now > 0:
                    service *= now / float(pn["cpu"])
                left = 1000.0 * h["p50_s"] - over - (ph.get("transfer_ms") or 0.0) - (ph.get("wait_ms") or 0.0)
                if left > 0:
                    seen.append((node, h, ph, service, left))
    logs: dict[str, list[float]] = {}
    for node, _h, _ph, service, left in seen:
        logs.setdefault(node, []).append(math.log(left / service))
    if not logs:
        return
    prior = system.latency.service_scale
    fitted = {n: math.exp((math.log(prior.get(n, 1.0)) + sum(v)) / (len(v) + 1)) for n, v in logs.items()}
    ratios: dict[str, list[float]] = {}
    for node, h, ph, _service, left in seen:
        if h.get("p95_s") is None:
            continue
        left95 = 1000.0 * h["p95_s"] - over - (ph.get("transfer_p95_ms") or 0.0) - (ph.get("wait_p95_ms") or 0.0)
        # the spread of the node's own part in that round: its p95 over its p50 (the round's
        # implied scale times the service), so a slow round's p95 is weighed as its p50 is
        ratios.setdefault(node, []).append(max(1.0, left95 / left))
    params = dataclasses.replace(
        system.latency, service_scale={**prior, **fitted},
        node_p95_ratio={**system.latency.node_p95_ratio, **{n: sum(v) / len(v) for n, v in ratios.items()}},
        source="tune")
    doc_system["latency"] = params_json(params)


def load_model(model_path: Path) -> System:
    """model.json's system (its fits' notes are in the file, not repeated as warnings)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        return load_system(model_path)


def model_cpu(model: System, node: str, value: Any, input_hz: float | None = None) -> float | None:
    """The model's CPU for ``node`` at ``value``: its fitted ``parameter->cpu`` when it has
    one, else the setting at that value (the only setting of a node without a parameter); a
    driven node's at ``input_hz`` (:func:`~perfros_bag.system.types.driven_rates`)."""
    n = model.node.get(node)
    if n is None:
        return None
    rel = n.relations.get("parameter->cpu")
    if not n.driven and rel is not None and isinstance(value, int | float) and not isinstance(value, bool):
        return float(rel(float(value)))
    s = n.settings[0] if len(n.settings) == 1 and value is None else next(
        (s for s in n.settings if _same(s.value, value)), None)
    if s is None:
        return None
    return driven_rates(s, input_hz)[0] if n.driven and input_hz is not None else s.cpu


def kept_share(node: NodeCheck) -> float | None:
    """The share of its planned rate a node of validation.json kept by itself: its topics'
    mean F_measured / F_expected; for a driven node, over the share its input kept (what it
    made of the messages it got); None without a rate to compare."""
    if not node.counted:
        return None
    ratio = float(node.ratio)
    given, planned = node.input_hz_measured, node.input_hz_expected
    if given and planned:
        return ratio * planned / given
    return ratio


# --------------------------------------------------------------------------- solve, deploy

def _solve(model_path: Path, method: str, headroom: float | str) -> Plan:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        plan = solve(load_model(model_path), 1, method, headroom=headroom)
    plan.require_feasible(model_path, "deploy")
    return plan


def _deployed(plan: Plan, space: Any, arg_defaults: dict[str, str | None]) -> tuple[dict[str, Any], dict[str, str]]:
    """What deploying ``plan`` runs: each varied node's value (as deploy sets it) and each
    node's computer."""
    run = plan_run(plan, space, arg_defaults)
    return dict(run.values), {n: pn.computer for n, pn in sorted(plan.nodes.items())}


def round_entry(k: int, plan: Plan, plan_path: Path, model_path: Path, record: dict[str, Any],
                validation: Validation, tolerance: float) -> TuneRound:
    """Round ``k``'s entry of tune.json from its plan, deploy.json and validation: per
    computer its throttling, per node predicted vs measured CPU and how the refit uses it."""
    throttling = record.get("throttling") or {}
    computers: dict[str, RoundComputer] = {}
    for c in validation.computers:
        t = throttling.get(c.name) or {}
        share = t["nr_throttled"] / t["nr_periods"] if t.get("nr_periods") else 0.0
        computers[c.name] = RoundComputer(c.capacity, c.cpu_expected, c.cpu_measured, round(share, 4),
                                          share >= THROTTLED_SHARE)
    values = dict(record["values"])
    model = load_model(model_path)
    nodes: dict[str, RoundNode] = {}
    for n in validation.nodes:
        # ratio: the node's kept share of its planned rate; None without a rate to compare
        name, measured = n.node, n.cpu_measured
        ratio = kept_share(n)
        here = computers.get(n.computer)
        starved = here is not None and here.starved
        factor, use = 1.0, USE_MEASURED
        if measured is None or (starved and ratio is None):
            use = USE_LEFT_OUT
        elif starved and ratio is not None and ratio < KEPT_ALL:
            factor, use = 1.0 / max(ratio, MIN_KEPT), USE_RESCALED
        value = values.get(name, plan.nodes[name].value if name in plan.nodes else None)
        input_hz = plan.nodes[name].input_hz if name in plan.nodes else None
        nodes[name] = RoundNode(n.computer, value, n.cpu_expected, measured, ratio, starved,
                                None if measured is None or use == USE_LEFT_OUT else measured * factor,
                                factor, use, input_hz, model_cpu(model, name, value, input_hz), None)
    entry = TuneRound(
        k, f"round-{k}", str(plan_path.relative_to(plan_path.parent.parent)), model_path.name, None, plan.objective,
        values, {name: pn.computer for name, pn in sorted(plan.nodes.items())},
        validation.overall_expected, validation.overall_measured, validation.deviation_pct, None,
        record["run_id"], record["cpu_cap"]["mode"], record["network"]["mode"], computers, nodes)
    entry.within_tolerance = holds(entry, tolerance)
    return entry


def holds(entry: TuneRound, tolerance: float) -> bool:
    """Does a round's plan hold? Its deviation (eq 10) is within ``tolerance`` and no node was
    held back by its computer's cap: on a starved computer (throttled in at least
    :data:`THROTTLED_SHARE` of the CFS periods) no node kept less than :data:`KEPT_ALL` of its
    planned rate. A plan that met its overall performance while a capped node fell behind met
    it by luck, and is learned from again (that node's CPU rescaled to its planned rate). A
    throttled computer whose nodes all kept up holds: a multi-threaded node bursts past its
    quota within a period and is throttled there without missing a message (measured:
    people_detect on a server planned to 58 % of its cap, throttled in 27-43 % of periods,
    kept 99-100 %)."""
    behind = any(n.starved and n.kept_ratio is not None and n.kept_ratio < KEPT_ALL for n in entry.nodes.values())
    return bool(entry.deviation_pct <= tolerance and not behind)


def _fill_after(entry: TuneRound, model_path: Path) -> None:
    entry.refit_model = model_path.name
    model = load_model(model_path)
    for name, n in entry.nodes.items():
        n.model_cpu_after = model_cpu(model, name, n.value, n.input_hz)


def _plot(outdir: Path, doc: dict[str, Any], plot: Plot | None) -> None:
    if plot is None:
        return
    with atomic_open(outdir / "tune.png", "wb", encoding=None) as fh:
        fh.write(plot(doc["rounds"]))
