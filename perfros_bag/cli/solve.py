"""``perfros-bag solve``: a system.yaml or model.json -> plan.json (Problem 1 or 2)."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from perfros_bag.cli._app import command, err, out
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.system.latency import budget_text

if TYPE_CHECKING:
    from perfros_bag.fitting.modelfile import Unmeasured
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.types import System


def parse_settings(system: System, text: str, resolution: float) -> dict[str, float]:
    """``--settings``: a plan.json (each node's CPU) or ``node=value,...`` (a parameter
    value) / ``node=cpu:U`` (a CPU level). Returns node -> CPU level."""
    from perfros_bag.solver import settings_from_plan, settings_from_values
    from perfros_bag.system.planfile import load_plan

    if text.lower().endswith(".json") or Path(text).is_file():
        return settings_from_plan(load_plan(text), system, resolution)
    values: dict[str, float] = {}
    cpus: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        name, sep, raw = item.partition("=")
        if not sep or not name.strip():
            raise InputError(None, f"--settings: expected node=value or node=cpu:U, got {item!r}")
        raw = raw.strip()
        target = values
        if raw.lower().startswith("cpu:"):
            raw, target = raw[4:], cpus
        try:
            target[name.strip()] = float(raw)
        except ValueError:
            raise InputError(None, f"--settings: {item!r}: {raw!r} is not a number") from None
    result = settings_from_values(system, values, resolution)
    for name in cpus:
        if name not in system.node:
            raise InputError(system.source, f"settings: unknown node {name!r}")
    result.update(cpus)
    return result


def parse_headroom(text: str, *, check_range: bool = True) -> float | str:
    """``--headroom``: ``auto`` (keep each node's measured CPU error free) or a share of every
    computer's capacity in [0, 1) (``check_range`` False: any number, the caller checks it);
    anything else is an :class:`InputError`."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise InputError(None, f"--headroom must be 'auto' or a number in [0, 1), got {text!r}") from None
    if check_range and not 0.0 <= value < 1.0:
        raise InputError(None, f"--headroom must be in [0, 1), got {value}")
    return value


#: of ``--time-limit``, what is kept for after the solve (writing plan.json, the tables):
#: this many seconds plus :data:`WIND_DOWN_SHARE` of the limit plus :data:`ROW_S` per row
#: of the plan's tables (rich draws ~1,300 rows in 5-7 s on the shared 2-core machine)
WIND_DOWN_S = 1.0
WIND_DOWN_SHARE = 0.01
ROW_S = 0.005


def process_seconds() -> float:
    """Seconds since this process started: the interpreter's start-up and imports count."""
    import psutil

    try:
        return max(time.time() - psutil.Process().create_time(), 0.0)
    except psutil.Error:
        return 0.0


def spent_seconds(began: float) -> float:
    """What the budget has spent: since the process started when the verb is the process
    (:data:`perfros_bag.cli._app.WHOLE_PROCESS`), else since the verb began (``began``,
    ``time.monotonic()``: the app called from another program)."""
    from perfros_bag.cli import _app

    return process_seconds() if _app.WHOLE_PROCESS else time.monotonic() - began


def solve_budget(time_limit: float, spent: float, rows: int = 0) -> float:
    """What the solver gets of a whole-process ``time_limit`` when the process has spent
    ``spent`` seconds (start-up, reading the input): the rest, less the wind-down after
    the solve (:data:`WIND_DOWN_S`, :data:`WIND_DOWN_SHARE`, :data:`ROW_S` for each of the
    ``rows`` the plan's tables will have); at least 0.01 s."""
    return max(time_limit - spent - (WIND_DOWN_S + WIND_DOWN_SHARE * time_limit + ROW_S * rows), 0.01)


def _num(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}".rstrip("0").rstrip(".") if digits else f"{x:.0f}"


def measured_note(plan: Plan, unmeasured: Mapping[str, Unmeasured]) -> dict[str, str]:
    """Per node of ``plan`` that ``unmeasured`` (model.json) knows: ``yes`` when its planned
    value was measured, else ``no`` and the fit's leave-one-out error at it of CPU, rate and
    bandwidth (``?``: the fit has none, two points)."""
    from perfros_bag.fitting.modelfile import planned_errors

    out: dict[str, str] = {}
    for name, n in plan.nodes.items():
        entry = unmeasured.get(name)
        if entry is None:
            continue
        errors = planned_errors(entry, n)
        if errors is None:
            out[name] = "yes"
            continue
        unit = {"cpu": "CPU", "frequency_hz": "Hz", "bandwidth_kBps": "kB/s"}
        said = [f"{unit[q]} ±{'?' if e is None else _num(e)}" for q, e in errors.items()]
        out[name] = "no: " + ", ".join(said) if said else "no"
    return out


#: a fleet's plan shows this many node rows (rendering 1,180 rows took 10-15 s on a loaded machine)
NODE_ROWS = 200


def print_plan(console: Console, plan: Plan, unmeasured: Mapping[str, Unmeasured] | None = None) -> None:
    """Nodes (computer, parameter value, CPU, performance; with model.json's ``unmeasured``,
    whether the value was measured), computers and links."""
    title = f"Problem {plan.problem} · {plan.method} · {plan.status}"
    nodes = Table(title=title, title_justify="left")
    flow = any(n.input is not None for n in plan.nodes.values())  # driven nodes: their input's rate too
    notes = measured_note(plan, unmeasured) if unmeasured else {}
    cols = ("node", "computer", "parameter", "value", "CPU", "performance", "weight") \
        + (("input Hz",) if flow else ()) \
        + (("measured?",) if notes else ())
    for col in cols:
        nodes.add_column(col, justify="left" if col in ("node", "computer", "parameter") else "right")
    for name, n in plan.nodes.items():
        row = [name, n.computer, n.parameter or "-", _num(n.value, 3), _num(n.cpu), _num(n.performance),
               _num(n.weight, 4)]
        nodes.add_row(*row, *((_num(n.input_hz),) if flow else ()), *((notes.get(name, "-"),) if notes else ()))
        if len(nodes.rows) == NODE_ROWS and len(plan.nodes) > NODE_ROWS:
            nodes.add_row(f"... {len(plan.nodes) - NODE_ROWS} more (plan.json has every node)")
            break
    console.print(nodes)
    comps = Table(title="computers", title_justify="left")
    kept = any(c.margin for c in plan.computers.values())  # --headroom: the CPU each keeps free
    for col in ("computer", "kind", "CPU", "capacity", "use") + (("margin",) if kept else ()):
        comps.add_column(col, justify="left" if col in ("computer", "kind") else "right")
    for name, c in plan.computers.items():
        use = f"{100 * c.cpu / c.capacity:.1f} %" if c.capacity else "-"
        comps.add_row(name, c.kind, _num(c.cpu), _num(c.capacity), use, *((_num(c.margin),) if kept else ()))
    console.print(comps)
    if plan.links:
        links = Table(title="links", title_justify="left")
        for col in ("link", "medium", "load kB/s", "bandwidth kB/s", "use"):
            links.add_column(col, justify="left" if col in ("link", "medium") else "right")
        for lk in plan.links:
            use = f"{100 * lk.load_kBps / lk.bandwidth_kBps:.2f} %" if lk.bandwidth_kBps else "-"
            links.add_row(f"{lk.between[0]} - {lk.between[1]}", lk.medium or "-", _num(lk.load_kBps, 3),
                          _num(lk.bandwidth_kBps), use)
        console.print(links)
    if plan.chains:
        chains = Table(title="chains: predicted latency (ms)", title_justify="left")
        for col in ("chain", "hop", "p50", "p95", "budget"):
            chains.add_column(col, justify="left" if col in ("chain", "hop", "budget") else "right")
        for ch in plan.chains:
            pred = ch.get("predicted_ms") or {}
            chains.add_row(escape(str(ch["name"])), escape(" -> ".join(map(str, ch.get("topics", [])))),
                           _num(pred.get("p50"), 1), _num(pred.get("p95"), 1), escape(budget_text(ch.get("budget_ms"))))
            for h in ch.get("hops", []):
                hp = h.get("predicted_ms") or {}
                chains.add_row("", escape(f"  {h.get('node')} on {h.get('computer')}"), _num(hp.get("p50"), 1),
                               _num(hp.get("p95"), 1), "")
        console.print(chains)
    what = "Σ w·P" if plan.problem == 1 else "Σ server capacity"
    console.print(f"objective ({what}): [bold]{_num(plan.objective, 4)}[/]"
                  + (f"  bound {_num(plan.bound, 4)}" if plan.bound is not None else "")
                  + (f"  solved in {plan.solve_s:.3f} s" if plan.solve_s is not None else ""), highlight=False)


@command("solve")
def solve(
    system_path: Annotated[Path, typer.Argument(metavar="SYSTEM_OR_MODEL", help="system.yaml or model.json")],
    problem: Annotated[int, typer.Option("--problem", "-p", help="1: maximise Σ w·P; 2: minimise server capacity")] = 1,
    method: Annotated[str, typer.Option("--method", "-m", help="greedy | greedy+ | exact | bruteforce")] = "greedy",
    out_path: Annotated[Path | None, typer.Option("--out", "-o", help="write plan.json here")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the plan JSON (only) on stdout")] = False,
    resolution: Annotated[float, typer.Option("--resolution", help="CPU step of a curve's choices")] = 1.0,
    settings: Annotated[str | None, typer.Option(
        "--settings", help="Problem 2: plan.json, or node=value,... (parameter values) / node=cpu:U")] = None,
    time_limit: Annotated[float | None, typer.Option(
        "--time-limit", help="exact: S seconds of wall clock for the whole process: start-up, reading the "
                             "input, building the model, the solve and writing the plan share them (best plan "
                             "so far and its proven bound, status feasible); with --pareto: per point")] = None,
    headroom: Annotated[str, typer.Option(
        "--headroom", metavar="H|auto",
        help="share of every computer's capacity the plan keeps free, in [0, 1), or auto: each node's "
             "measured CPU error (model.json cpu_error, at least 10 % of its CPU) (plan.json gives each "
             "computer its margin)")] = "0",
    measured_only: Annotated[bool, typer.Option(
        "--measured-only", help="a model.json: choose for each fitted node only values its recordings "
                                "ran (no value between them; plan.json says which were measured)")] = False,
    pareto: Annotated[str | None, typer.Option(
        "--pareto", metavar="RANGE", help="Problem 1 per total server capacity: auto, LO:HI or LO:HI:POINTS "
                                          "(-o writes frontier.json and a PNG beside it)")] = None,
    pareto_budget: Annotated[str | None, typer.Option(
        "--pareto-budget", metavar="CHAIN[:p50|p95]",
        help="with --pareto: Problem 1 per latency budget of this chain (p95 by default) instead; RANGE in ms "
             "(auto: from the least latency any plan has to the unbudgeted optimum's); -o writes the JSON, "
             "a CSV and a PNG beside it")] = None,
) -> None:
    """Choose a setting and a computer for every node (the paper's Problems 1 and 2)."""
    began = time.monotonic()
    from perfros_bag.solver import METHODS
    from perfros_bag.solver import solve as run
    from perfros_bag.system.planfile import plan_document, save_plan
    from perfros_bag.system.systemfile import load_system

    if problem not in (1, 2):
        raise InputError(None, f"--problem must be 1 or 2, got {problem}")
    if method not in METHODS:
        raise InputError(None, f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    if not resolution > 0:
        raise InputError(None, f"--resolution must be > 0, got {resolution}")
    if time_limit is not None and not time_limit > 0:
        raise InputError(None, f"--time-limit must be > 0, got {time_limit}")
    kept = parse_headroom(headroom)
    if time_limit is not None and method != "exact":
        warnings.warn(f"--time-limit applies to --method exact only; {method} ignores it", PerfrosWarning, stacklevel=1)
    system = load_system(system_path)
    unmeasured = _unmeasured(system_path)
    if measured_only:
        from perfros_bag.fitting.modelfile import measured_system

        system = measured_system(system, unmeasured, system_path)
    fixed = None
    if settings is not None:
        if problem != 2:
            raise InputError(None, "--settings applies to Problem 2 (Problem 1 chooses the settings)")
        fixed = parse_settings(system, settings, resolution)
    if pareto_budget is not None and pareto is None:
        pareto = "auto"
    if pareto is not None:
        if problem != 1 or fixed is not None:
            raise InputError(None, "--pareto solves Problem 1 at each server capacity or budget "
                                   "(no --problem 2, no --settings)")
        if pareto_budget is not None:
            _budget_frontier(system, pareto_budget, pareto, method, resolution, time_limit, out_path, as_json, kept)
            return
        _frontier(system, pareto, method, resolution, time_limit, out_path, as_json, kept)
        return
    try:
        with _live_progress(method == "exact") as progress:
            rows = len(system.nodes) + len(system.computers) + len(system.links)  # the tables printed after
            budget = None if time_limit is None else solve_budget(time_limit, spent_seconds(began), rows)
            plan = run(system, problem, method, resolution=resolution, settings=fixed, time_limit=budget,
                       progress=progress, headroom=kept)
    except ValueError as exc:  # a model that cannot be evaluated (e.g. a curve off its domain)
        raise InputError(system_path, str(exc)) from None
    if unmeasured:
        from perfros_bag.fitting.modelfile import mark_measured

        mark_measured(plan, unmeasured)
    if out_path is not None:
        save_plan(plan, out_path)
    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(plan_document(plan), indent=2))
    plan.require_feasible(system_path)
    print_plan(err if as_json else out, plan, unmeasured)
    if plan.reason:  # a feasible plan's note (--headroom auto on a model without errors)
        err.print(f"note: {plan.reason}", highlight=False, soft_wrap=True)
    if out_path is not None and not as_json:
        out.print(f"plan written to {out_path}", highlight=False)


def _unmeasured(path: Path) -> dict[str, Unmeasured]:
    """A model.json's ``unmeasured`` part (empty for a system.yaml)."""
    from perfros_bag.fitting.modelfile import read_unmeasured

    if path.suffix.lower() != ".json":
        return {}
    return read_unmeasured(path)


@contextmanager
def _live_progress(enabled: bool) -> Iterator[Callable[[float | None, float, float], None] | None]:
    """The exact method's incumbent, bound and gap as a rich live line on stderr while it
    solves, when stderr is a terminal (else no callback)."""
    if not enabled or not err.is_terminal:
        yield None
        return
    from rich.live import Live
    from rich.text import Text

    with Live(Text("solving ..."), console=err, auto_refresh=False, transient=True) as live:

        def show(incumbent: float | None, bound: float, seconds: float) -> None:
            gap = "" if not incumbent else f"  gap {100 * max(bound - incumbent, 0.0) / abs(incumbent):.3f} %"
            live.update(Text(f"{seconds:7.1f} s  plan {_num(incumbent, 4)}  bound {_num(bound, 4)}{gap}"),
                        refresh=True)

        yield show


def _frontier(system: System, spec: str, method: str, resolution: float, time_limit: float | None,
              out_path: Path | None, as_json: bool, headroom: float | str = 0.0) -> None:
    """``--pareto``: Problem 1 at each total server capacity of the range; a table, the
    frontier JSON (``--json`` / ``-o``) and, with ``-o``, a PNG beside it."""
    from perfros_bag.fileio import atomic_open
    from perfros_bag.report.frontier_plots import plot_frontier
    from perfros_bag.solver.frontier import frontier, frontier_document, parse_range, write_frontier

    low, high, points = parse_range(spec)
    found = frontier(system, low=low, high=high, points=points, resolution=resolution, method=method,
                     time_limit=time_limit, headroom=headroom)
    doc = frontier_document(system, found, method, headroom)
    if out_path is not None:
        png = plot_frontier(doc["points"])
        write_frontier(out_path, doc)
        with atomic_open(out_path.with_suffix(".png"), "wb", encoding=None) as fh:
            fh.write(png)
    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(doc, indent=2))
    table = Table(title=f"Problem 1 per total server capacity · {method}", title_justify="left")
    for col in ("server capacity", "Σ w·P", "bound", "gap", "status", "s"):
        table.add_column(col, justify="left" if col == "status" else "right")
    for p in found:
        gap = "-" if p.gap is None else f"{100 * p.gap:.3f} %"
        status = str(p.status) if p.carried_from is None else f"{p.status} (plan of {_num(p.carried_from)})"
        table.add_row(_num(p.capacity), _num(p.objective, 4), _num(p.bound, 4), gap, status, f"{p.solve_s:.2f}")
    console = err if as_json else out
    console.print(table)
    if out_path is not None and not as_json:
        out.print(f"frontier written to {out_path} and {out_path.with_suffix('.png')}", highlight=False)


def _budget_frontier(system: System, target: str, spec: str, method: str, resolution: float,
                     time_limit: float | None, out_path: Path | None, as_json: bool,
                     headroom: float | str = 0.0) -> None:
    """``--pareto RANGE --pareto-budget CHAIN[:q]``: Problem 1 at each budget of the chain;
    a table, the document (``--json`` / ``-o``) and, with ``-o``, a CSV and a PNG beside it."""
    from perfros_bag.fileio import atomic_open
    from perfros_bag.report.frontier_plots import plot_budget_frontier
    from perfros_bag.solver.budget_frontier import (
        budget_frontier,
        budget_frontier_document,
        parse_target,
        write_budget_frontier,
    )
    from perfros_bag.solver.frontier import parse_range

    chain, quantile = parse_target(system, target)
    low, high, points = parse_range(spec)
    found = budget_frontier(system, chain, quantile, low=low, high=high, points=points, resolution=resolution,
                            method=method, time_limit=time_limit, headroom=headroom)
    doc = budget_frontier_document(system, chain, quantile, found, method, headroom)
    if out_path is not None:
        png = plot_budget_frontier(doc)
        write_budget_frontier(out_path, doc)
        with atomic_open(out_path.with_suffix(".png"), "wb", encoding=None) as fh:
            fh.write(png)
    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(doc, indent=2))
    table = Table(title=f"Problem 1 per {quantile} budget of chain {escape(chain.name)} · {method}",
                  title_justify="left")
    for col in (f"{quantile} budget ms", "Σ w·P", "bound", "predicted p50", "predicted p95", "status", "s"):
        table.add_column(col, justify="left" if col == "status" else "right")
    for p in found:
        pred = p.predicted_ms or {}
        status = str(p.status) if p.carried_from is None else f"{p.status} (plan of {_num(p.carried_from, 1)} ms)"
        table.add_row(_num(p.budget_ms, 1), _num(p.objective, 4), _num(p.bound, 4), _num(pred.get("p50"), 1),
                      _num(pred.get("p95"), 1), status, f"{p.solve_s:.2f}")
    console = err if as_json else out
    console.print(table)
    if out_path is not None and not as_json:
        out.print(f"frontier written to {out_path}, {out_path.with_suffix('.csv')} and "
                  f"{out_path.with_suffix('.png')}", highlight=False)
