"""One self-contained HTML report (plus its PNGs) of a characterisation, a model, a plan
and a validation. Every part is optional: what is not given is left out.

The page has inline CSS and no script; the plots are PNGs written beside ``index.html``
and also inlined as base64 so the page stands alone. Every piece of text from the input
files is HTML-escaped. This module only composes: the inputs are read by their one reader
each, the PNGs drawn by the plot modules of :mod:`perfros_bag.report`.
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from perfros_bag.characterisation.csvfile import CharacterisationFile, read_characterisation
from perfros_bag.errors import InputError
from perfros_bag.fileio import (
    DOCUMENT_KINDS,
    atomic_open,
    atomic_write_text,
    expect_kind,
    read_json,
)
from perfros_bag.fitting.modelfile import FittedRelation, read_model
from perfros_bag.limits import tree_problem
from perfros_bag.report.fit_plots import plot_relations
from perfros_bag.report.frontier_plots import plot_budget_frontier, plot_frontier
from perfros_bag.report.plan_plots import plot_plan_loads
from perfros_bag.report.validation_plots import number, plot_validation
from perfros_bag.system.latency import budget_text
from perfros_bag.system.plan import Plan

MAX_TABLE_ROWS = 2000

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;margin:2em auto;max-width:1100px;
color:#222;padding:0 1em}
h1{font-size:1.6em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:1em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#f0f0f0}td.t,th.t{text-align:left}
tr.bad td{background:#fde8e8}.bad{color:#b00020;font-weight:bold}.ok{color:#0a7d28;font-weight:bold}
.muted{color:#777}img{max-width:100%;border:1px solid #eee;margin:.5em 0}
.summary{font-size:1.05em;margin:.5em 0}.scroll{overflow-x:auto}
"""


def esc(x: Any) -> str:
    return html.escape("" if x is None else str(x), quote=True)


def fmt(x: Any, digits: int = 4) -> str:
    if x is None or x == "":
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        if not math.isfinite(x):
            return str(x)
        if abs(x) >= 10 ** digits and abs(x) < 1e15:
            return f"{x:,.0f}"
        return f"{x:.{digits}g}"
    return str(x)


def table(headers: Sequence[str], rows: Iterable[Sequence[Any]], *, text_cols: Iterable[int] = (0,),
          row_classes: Sequence[str] | None = None, table_id: str | None = None) -> str:
    """An HTML table; cells are escaped (numbers formatted), text columns left-aligned."""
    tcols = set(text_cols)
    out = [f'<div class="scroll"><table{f" id={chr(34)}{esc(table_id)}{chr(34)}" if table_id else ""}><thead><tr>']
    out += [f'<th class="{"t" if i in tcols else ""}">{esc(h)}</th>' for i, h in enumerate(headers)]
    out.append("</tr></thead><tbody>")
    for k, row in enumerate(rows):
        cls = row_classes[k] if row_classes is not None and k < len(row_classes) else ""
        out.append(f'<tr class="{esc(cls)}">' if cls else "<tr>")
        out += [f'<td class="{"t" if i in tcols else ""}">{esc(fmt(v))}</td>' for i, v in enumerate(row)]
        out.append("</tr>")
    out.append("</tbody></table></div>")
    return "".join(out)


# ---------------------------------------------------------------------------------------
# inputs


def read_validation(path: str | Path) -> dict[str, Any]:
    data = read_json(path)
    validation = DOCUMENT_KINDS["perfros-bag/validation@1"]  # validation/eq10.py VALIDATION_FORMAT
    expect_kind(path, data, validation, {validation})
    if (not isinstance(data, dict) or not isinstance(data.get("nodes"), list)
            or not isinstance(data.get("overall"), dict)):
        raise InputError(path, "not a validation (expected a JSON object with a 'nodes' list and an 'overall' object)")
    problem = tree_problem(data)  # every number within the stated limits, the place named
    if problem is not None:
        raise InputError(path, problem)
    return data


@dataclass
class Image:
    name: str
    data: bytes
    alt: str


# ---------------------------------------------------------------------------------------
# sections


def _img(img: Image) -> str:
    b64 = base64.b64encode(img.data).decode("ascii")
    return f'<img src="data:image/png;base64,{b64}" alt="{esc(img.alt)}" title="{esc(img.name)}">'


def section_characterisation(char: CharacterisationFile) -> str:
    columns, rows = char.columns, char.cells
    shown = rows[:MAX_TABLE_ROWS]
    text = [i for i, c in enumerate(columns) if c in ("recording", "node", "parameter", "topic", "msgtype")]

    def cell(v: str | None) -> Any:
        if v is None or v == "":
            return v
        try:
            f = float(v)
        except ValueError:
            return v
        return int(f) if f.is_integer() and "." not in v and "e" not in v.lower() else f

    body = table(columns, ([cell(r.get(c)) for c in columns] for r in shown), text_cols=text,
                 table_id="characterisation-table")
    more = (f'<p class="muted">first {MAX_TABLE_ROWS} of {len(rows)} rows</p>' if len(rows) > MAX_TABLE_ROWS else "")
    return (f'<h2 id="characterisation">Characterisation</h2><p>{len(rows)} rows.</p>'
            f"{section_contents(char)}{body}{more}")


CONTENTS_COLUMNS = ("metric_value", "latency_p50_s", "latency_p95_s", "latency_max_s")


def section_contents(char: CharacterisationFile) -> str:
    """What the messages held: each row's metric and header-stamp latency (only the rows
    that have either); empty when the file has none."""
    rows = [r for r in char.rows if any(getattr(r, c) is not None for c in CONTENTS_COLUMNS)]
    if not rows:
        return ""
    body = table(("recording", "node", "value", "topic", "metric", "latency p50 s", "latency p95 s", "latency max s"),
                 [(r.recording, r.node, r.value, r.topic, *(getattr(r, c) for c in CONTENTS_COLUMNS))
                  for r in rows[:MAX_TABLE_ROWS]],
                 text_cols=(0, 1, 3), table_id="contents-table")
    return f"<h3>Message contents: metric and latency</h3>{body}"


def section_fits(fits: dict[str, dict[str, FittedRelation]], images: list[Image]) -> str:
    rows = [(node, rel, f.form, ", ".join(f"{c:.5g}" for c in f.coef), f"[{f.domain[0]:g}, {f.domain[1]:g}]",
             f.r2, len(f.points)) for node, rels in fits.items() for rel, f in rels.items()]
    parts = ['<h2 id="regressions">Regressions</h2>',
             table(("node", "relation", "form", "coefficients", "domain", "R²", "points"), rows,
                   text_cols=(0, 1, 2, 3, 4), table_id="fits-table")]
    for k, (node, rels) in enumerate((n, r) for n, r in fits.items() if r):
        img = Image(f"fit_{k:02d}.png", plot_relations(node, rels), f"regressions of {node}")
        images.append(img)
        parts.append(_img(img))
    return "".join(parts)


def section_plan(plan: Plan, images: list[Image]) -> str:
    head = (f'<p class="summary">Problem {plan.problem}, method {esc(plan.method)}, status '
            f'<b>{esc(plan.status)}</b>, objective {esc(fmt(plan.objective))}'
            + ("" if plan.bound is None else f", bound {esc(fmt(plan.bound))}") + "</p>")
    if plan.status == "infeasible":
        return f'<h2 id="plan">Plan</h2>{head}<p class="bad">infeasible: {esc(plan.reason)}</p>'
    crow = []
    classes = []
    for c, pc in plan.computers.items():
        members = [f"{n}" + ("" if pn.value is None else f" ({pn.parameter}={fmt(pn.value)})")
                   for n, pn in plan.nodes.items() if pn.computer == c]
        crow.append((c, pc.kind, pc.capacity, pc.cpu, "; ".join(members) or "–"))
        classes.append("bad" if pc.capacity is not None and pc.cpu > pc.capacity + 1e-9 else "")
    comp = table(("computer", "kind", "capacity", "planned CPU", "nodes"), crow, text_cols=(0, 1, 4),
                 row_classes=classes, table_id="plan-table")
    nrow = [(n, pn.computer, pn.parameter, pn.value, pn.cpu, pn.performance, pn.weight,
             "; ".join(f"{t} {fmt(r.frequency_hz)} Hz" for t, r in pn.topics.items()) or "–")
            for n, pn in plan.nodes.items()]
    nodes = table(("node", "computer", "parameter", "value", "CPU", "performance", "weight", "topics"),
                  nrow, text_cols=(0, 1, 2, 7), table_id="plan-nodes")
    links = ""
    if plan.links:
        links = "<h3>Links</h3>" + table(
            ("link", "medium", "bandwidth kB/s", "planned load kB/s"),
            [(" – ".join(link.between), link.medium, link.bandwidth_kBps, link.load_kBps) for link in plan.links],
            text_cols=(0, 1), table_id="plan-links")
    chains = ""
    if plan.chains:
        chains = "<h3>Chains: predicted latency</h3>" + table(
            ("chain", "topics", "predicted p50 ms", "predicted p95 ms", "budget"),
            [row for c in plan.chains for row in _plan_chain_rows(c)], text_cols=(0, 1, 4), table_id="plan-chains")
    img = Image("plan_cpu.png", plot_plan_loads(plan), "planned CPU per computer")
    images.append(img)
    return (f'<h2 id="plan">Plan</h2>{head}<h3>Placement per computer</h3>{comp}{_img(img)}<h3>Nodes</h3>{nodes}'
            f'{links}{chains}')


def _plan_chain_rows(c: dict[str, Any]) -> list[tuple[Any, ...]]:
    """A plan.json chain and its hops as rows: predicted p50/p95 (ms) and the budget."""
    def pred(d: dict[str, Any]) -> tuple[Any, Any]:
        p = d.get("predicted_ms")
        return (number(p.get("p50")), number(p.get("p95"))) if isinstance(p, dict) else ("-", "-")

    rows: list[tuple[Any, ...]] = [(c.get("name"), " -> ".join(map(str, c.get("topics", []))), *pred(c),
                                    budget_text(c.get("budget_ms")) if "unpredicted" not in c
                                    else f"{budget_text(c.get('budget_ms'))} (not predicted: {c['unpredicted']})")]
    rows += [("", f"hop {h.get('from')} -> {h.get('to')} ({h.get('node')} on {h.get('computer')})", *pred(h), "")
             for h in c.get("hops", []) if isinstance(h, dict)]
    return rows


def _link_name(lc: dict[str, Any]) -> str:
    between = [str(b) for b in lc.get("between", []) if b is not None]
    if len(between) == 2 and between[0] == between[1]:
        return f"medium {between[0]}"
    return " – ".join(between)


def _predicted_s(pred: Any) -> tuple[str, str]:
    """A ``predicted_ms`` {p50, p95} as seconds, beside the measured columns."""
    if not isinstance(pred, dict):
        return "-", "-"
    return tuple(number(p / 1000.0) if isinstance(p := pred.get(q), int | float) else "-"  # type: ignore[return-value]
                 for q in ("p50", "p95"))


def _held(held: Any) -> str:
    return "-" if held is None else "yes" if held is True else "no"


def _section_latency(v: dict[str, Any]) -> str:
    """The validation's network delays (``network``) and chain latencies (``chains``)."""
    parts = []
    net = [c for c in v.get("network", []) if isinstance(c, dict)]
    if net:
        parts.append("<h3>Network: transfer delay per message the plan adds</h3>" + table(
            ("edge", "topic", "route", "bytes/msg", "added delay s", "latency p50 s", "latency p95 s"),
            [(c.get("edge"), c.get("topic"), ", ".join(_link_name({"between": b}) for b in c.get("links", [])
                                                        if isinstance(b, list)),
              number(c.get("message_bytes")), number(c.get("predicted_delay_s")), number(c.get("latency_p50_s")),
              number(c.get("latency_p95_s"))) for c in net],
            text_cols=(0, 1, 2), table_id="validation-network"))
    rows = []
    for c in (c for c in v.get("chains", []) if isinstance(c, dict)):
        topics = [str(t) for t in c.get("topics", [])]
        rows.append((c.get("name"), " -> ".join(topics), c.get("matched"), c.get("messages"), number(c.get("p50_s")),
                     number(c.get("p95_s")), number(c.get("max_s")), *_predicted_s(c.get("predicted_ms")),
                     budget_text(c.get("budget_ms")), _held(c.get("budget_held"))))
        rows += [("", f"hop {h.get('from')} -> {h.get('to')}", h.get("matched"), "", number(h.get("p50_s")),
                  number(h.get("p95_s")), number(h.get("max_s")), *_predicted_s(h.get("predicted_ms")), "", "")
                 for h in c.get("hops", []) if isinstance(h, dict)]
    if rows:
        parts.append("<h3>Chains: end-to-end latency, measured beside predicted</h3>" + table(
            ("chain", "topics", "matched", "messages", "p50 s", "p95 s", "max s", "predicted p50 s",
             "predicted p95 s", "budget", "budget held"), rows, text_cols=(0, 1, 9, 10),
            table_id="validation-chains"))
    return "".join(parts)


def _section_flow(v: dict[str, Any]) -> str:
    """Driven nodes' input rates (expected vs measured) and, for an overloaded plan, the
    rates it was predicted to keep beside those measured (validation's ``kept``)."""
    parts = []
    driven = [n for n in v["nodes"] if isinstance(n, dict) and n.get("input") is not None]
    if driven:
        parts.append("<h3>Driven nodes: input rate</h3>" + table(
            ("node", "input", "expected Hz", "measured Hz", "deviation %"),
            [(n.get("node"), n.get("input"), number(n.get("input_hz_expected")),
              number(n.get("input_hz_measured")) if n.get("input_rate_note") is None else n.get("input_rate_note"),
              number(n.get("input_deviation_pct"))) for n in driven],
            text_cols=(0, 1), table_id="validation-inputs"))
    kept = v.get("kept")
    if isinstance(kept, dict):
        nodes = [n for n in kept.get("nodes", []) if isinstance(n, dict)]
        parts.append("<h3>Overloaded: the rates each node keeps, predicted and measured</h3>" + table(
            ("node", "computer", "CPU need", "CPU share", "F planned", "F predicted", "F measured"),
            [(n.get("node"), n.get("computer"), number(n.get("cpu_need")), number(n.get("cpu_share")),
              number(n.get("f_planned")), number(n.get("f_predicted")), number(n.get("f_measured"))) for n in nodes],
            text_cols=(0, 1), table_id="validation-kept"))
    return "".join(parts)


def section_validation(v: dict[str, Any], images: list[Image]) -> str:
    ov = v["overall"]
    passed = ov.get("passed")
    verdict = ('<span class="ok">within tolerance</span>' if passed
               else '<span class="bad">deviation above tolerance</span>' if passed is False else "")
    head = (f'<p class="summary">Recording {esc(v.get("recording"))}: overall Σ w·P expected '
            f'{esc(fmt(number(ov.get("expected"))))}, measured {esc(fmt(number(ov.get("measured"))))}, deviation '
            f'{esc(fmt(number(ov.get("deviation_pct")), 3))} % '
            f'(tolerance {esc(fmt(number(v.get("tolerance_pct"))))} %) '
            f'{verdict}</p>')
    rows, classes = [], []
    for n in v["nodes"]:
        if not isinstance(n, dict):
            continue
        topics = [t for t in n.get("topics", []) if isinstance(t, dict)]
        freq = "; ".join(f"{t.get('topic')}: {fmt(number(t.get('f_measured')))} / {fmt(number(t.get('f_expected')))} Hz"
                         + (f" ({t.get('status')})" if t.get("status") != "ok" else "") for t in topics)
        rows.append((n.get("node"), n.get("computer"), freq or "–", number(n.get("p_expected")),
                     number(n.get("p_measured")),
                     number(n.get("deviation_pct")) if n.get("counted", True) else "not counted"))
        classes.append("bad" if n.get("flagged") else "")
    nodes = table(("node", "computer", "F measured / expected", "P expected", "P measured", "deviation %"),
                  rows, text_cols=(0, 1, 2), row_classes=classes, table_id="validation-table")
    img = Image("validation.png", plot_validation(v), "expected vs measured performance")
    images.append(img)
    parts = [f'<h2 id="validation">Validation (eq 10)</h2>{head}{_img(img)}{nodes}']
    metric_nodes = [n for n in v["nodes"] if isinstance(n, dict) and n.get("metric_value") is not None]
    if metric_nodes:
        parts.append("<h3>Measured metric beside eq 10</h3>" + table(
            ("node", "metric", "P metric", "P expected", "P eq 10", "deviation %"),
            [(n.get("node"), number(n.get("metric_value")), number(n.get("p_metric")), number(n.get("p_expected")),
              number(n.get("p_measured")), number(n.get("metric_deviation_pct"))) for n in metric_nodes],
            table_id="validation-metric"))
    parts.append(_section_flow(v))
    parts.append(_section_latency(v))
    comps = [c for c in v.get("computers", []) if isinstance(c, dict)]
    if comps:
        parts.append("<h3>CPU per computer</h3>" + table(
            ("computer", "capacity", "planned", "measured", "overloaded"),
            [(c.get("computer"), number(c.get("capacity")), number(c.get("cpu_expected")),
              number(c.get("cpu_measured")),
              c.get("overloaded")) for c in comps],
            row_classes=["bad" if c.get("overloaded") else "" for c in comps], table_id="validation-cpu"))
    links = [c for c in v.get("links", []) + v.get("media", []) if isinstance(c, dict)]
    if links:
        parts.append("<h3>Bandwidth</h3>" + table(
            ("link", "capacity kB/s", "planned", "measured", "overloaded"),
            [(_link_name(lc), number(lc.get("capacity_kBps")),
              number(lc.get("expected_kBps")), number(lc.get("measured_kBps")), lc.get("overloaded")) for lc in links],
            row_classes=["bad" if lc.get("overloaded") else "" for lc in links]))
    extra = [u for u in v.get("unplanned_topics", []) if isinstance(u, dict)]
    if extra:
        parts.append("<h3>Topics not in the plan (not counted)</h3>" + table(
            ("topic", "type", "messages", "frequency Hz"),
            [(u.get("topic"), u.get("msgtype"), u.get("messages"), number(u.get("f_measured"))) for u in extra],
            text_cols=(0, 1)))
    notes = [n for n in v.get("notes", []) if isinstance(n, str)]
    if notes:
        parts.append("<ul class=\"muted\">" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>")
    return "".join(parts)


def section_frontier(doc: dict[str, Any], images: list[Image]) -> str:
    """The performance / server-capacity frontier (``solve --pareto``): the plot and the points."""
    points = doc["points"]
    rows = [(p["server_capacity"], p["objective"], p["bound"],
             "–" if p.get("gap") is None else f"{100 * p['gap']:.3f} %", p["status"]) for p in points]
    solved = [p for p in points if p.get("objective") is not None]
    gains = ""
    if len(solved) >= 2:
        first, last = solved[0], solved[-1]
        per_unit = ((last["objective"] - first["objective"])
                    / max(last["server_capacity"] - first["server_capacity"], 1e-12))
        gains = (f'<p class="summary">From {esc(fmt(first["server_capacity"]))} to '
                 f'{esc(fmt(last["server_capacity"]))} CPU units of server capacity Σ w·P rises from '
                 f'{esc(fmt(first["objective"]))} to {esc(fmt(last["objective"]))} '
                 f"({esc(fmt(per_unit, 3))} per unit on average; the table shows where it flattens).</p>")
    img = Image("frontier.png", plot_frontier(points), "Σ w·P per total server capacity")
    images.append(img)
    tab = table(("server capacity", "Σ w·P", "bound", "gap", "status"), rows, text_cols=(4,), table_id="frontier")
    return (f'<h2 id="frontier">What server capacity buys</h2><p class="muted">servers: '
            f'{esc(", ".join(map(str, doc.get("servers", []))))}; method {esc(doc.get("method"))}</p>'
            f"{gains}{_img(img)}{tab}")


#: solve --pareto-budget's document format (perfros_bag.solver.budget_frontier.FORMAT)
BUDGET_FORMAT = "perfros-bag budget frontier 1"


def read_any_frontier(path: str | Path) -> dict[str, Any]:
    """``--frontier``: a frontier.json of ``solve --pareto`` or a budget frontier of
    ``--pareto-budget``, by its ``format``, each checked by its own reader."""
    from perfros_bag.fileio import read_json
    from perfros_bag.solver.budget_frontier import read_budget_frontier
    from perfros_bag.solver.frontier import read_frontier

    doc = read_json(path)
    if isinstance(doc, dict) and doc.get("format") == BUDGET_FORMAT:
        return read_budget_frontier(path)
    return read_frontier(path)


def section_budget_frontier(doc: dict[str, Any], images: list[Image]) -> str:
    """Performance per latency budget of a chain (``solve --pareto-budget``): the plot and the points."""
    q = doc["quantile"]
    rows = []
    for p in doc["points"]:
        pred = p.get("predicted_ms") or {}
        rows.append((p["budget_ms"], p["objective"], p["bound"], pred.get("p50"), pred.get("p95"), p["status"]))
    img = Image("budget_frontier.png", plot_budget_frontier(doc), f"Σ w·P per {q} budget of chain {doc['chain']}")
    images.append(img)
    tab = table((f"{q} budget ms", "Σ w·P", "bound", "predicted p50 ms", "predicted p95 ms", "status"), rows,
                text_cols=(5,), table_id="budget-frontier-points")
    return (f'<h2 id="budget-frontier">What latency costs: chain {esc(doc["chain"])}</h2>'
            f'<p class="muted">{esc(" -> ".join(map(str, doc.get("topics", []))))}; {esc(q)} budget; '
            f'method {esc(doc.get("method"))}</p>{_img(img)}{tab}')


def section_tune(doc: dict[str, Any], images: list[Image]) -> str:
    """The tuning loop (``tune``, tune.json): per round the values deployed, expected vs
    measured Σ w·P, and per node planned vs measured CPU with the fit before and after."""
    from perfros_bag.report.tune_plots import plot_tune

    rounds = doc["rounds"]
    stopped = doc.get("stopped") or {}
    ended = "not yet" if not stopped else f"{stopped['reason']} after round {stopped['after_round']}"
    summary = (f'<p class="summary">{len(rounds)} round(s); stopped: {esc(ended)}; method {esc(doc.get("method"))}, '
               f'headroom {esc(fmt(doc.get("headroom")))}, tolerance {esc(fmt(doc.get("tolerance_pct")))} %.</p>')
    if doc.get("base"):  # tune --base: model 0 is that characterisation's fit, not a sweep's
        summary += f'<p>Model 0: fitted on the base characterisation {esc(doc["base"])} (no sweep).</p>'
    img = Image("tune.png", plot_tune(rounds), "per round: planned vs measured CPU; expected vs measured Σ w·P")
    images.append(img)
    per_round = table(("round", "values deployed", "expected Σ w·P", "measured Σ w·P", "deviation %", "starved"),
                      [(r["round"], ", ".join(f"{n}={v}" for n, v in r["values"].items()), r["expected"],
                        r["measured"], r["deviation_pct"],
                        ", ".join(c for c, v in r["computers"].items() if v.get("starved")) or "–")
                       for r in rounds], text_cols=(1, 5), table_id="tune-rounds",
                      row_classes=["" if r["within_tolerance"] else "bad" for r in rounds])
    per_node = table(("round", "node", "computer", "value", "CPU planned", "CPU measured", "kept rate", "need",
                      "model before", "model after", "refit"),
                     [(r["round"], name, n["computer"], n["value"], n["cpu_planned"], n["cpu_measured"],
                       n["kept_ratio"], n["cpu_need"], n["model_cpu_before"], n["model_cpu_after"], n["refit"])
                      for r in rounds for name, n in r["nodes"].items()], text_cols=(1, 2, 10), table_id="tune-nodes")
    return (f'<h2 id="tune">The tuning loop: each deployment refits the model</h2>{summary}{_img(img)}'
            f"{per_round}{per_node}")


def section_watch(doc: dict[str, Any], images: list[Image]) -> str:
    """A watch (``watch --out DIR``): the timeline of its windows, alarms and re-plans."""
    from perfros_bag.report.watch_plots import plot_watch

    windows, replans = doc["windows"], doc["replans"]
    t0 = float(windows[0]["t"])
    img = Image("watch.png", plot_watch(windows, replans), "per window: expected vs measured Σ w·P; alarms; re-plans")
    images.append(img)
    raised = [a for w in windows for a in w["alarms"] if a.get("new")]
    summary = (f'<p class="summary">{len(windows)} window(s) over {float(windows[-1]["t"]) - t0:.0f} s; '
               f"{len(raised)} alarm(s); {len(replans)} re-plan(s).</p>")
    events = [(float(w["t"]) - t0, w["window"], "alarm", a.get("line", "")) for w in windows for a in w["alarms"]
              if a.get("new")]
    events += [(float(r["t"]) - t0, r["window"], "re-plan",
                f"{r['plan']}: {'; '.join(r.get('changes') or ['no change'])} (why: {'; '.join(r.get('why', []))})")
               for r in replans]
    tab = table(("s", "window", "event", "what"), sorted(events, key=lambda e: e[0]), text_cols=(2, 3),
                table_id="watch-events")
    return f'<h2 id="watch">Watched live: windows, alarms, re-plans</h2>{summary}{_img(img)}{tab}'


# ---------------------------------------------------------------------------------------
# the page


def build_report(out_dir: str | Path, *, characterisation: str | Path | None = None,
                 model: str | Path | None = None, plan: str | Path | None = None,
                 validation: str | Path | None = None, frontier: str | Path | None = None,
                 tune: str | Path | None = None, watch: str | Path | None = None,
                 title: str = "perfros-bag report") -> Path:
    """Write ``out_dir/index.html`` and its PNGs; returns the page's path. Inputs are read
    (and checked) before anything is written."""
    from perfros_bag.system.planfile import load_plan
    from perfros_bag.tune.tunefile import read_tune

    char = read_characterisation(characterisation) if characterisation is not None else None
    fits = read_model(model).fits if model is not None else None
    the_plan = load_plan(plan) if plan is not None else None
    val = read_validation(validation) if validation is not None else None
    front = read_any_frontier(frontier) if frontier is not None else None
    tuned = read_tune(tune) if tune is not None else None
    watched = None
    if watch is not None:
        from perfros_bag.watch.watchfile import read_watch

        watched = read_watch(watch)

    images: list[Image] = []
    sections: list[str] = []
    if the_plan is not None:
        sections.append(section_plan(the_plan, images))
    if val is not None:
        sections.append(section_validation(val, images))
    if front is not None:
        budget = front.get("format") == BUDGET_FORMAT
        sections.append(section_budget_frontier(front, images) if budget else section_frontier(front, images))
    if tuned is not None and tuned["rounds"]:
        sections.append(section_tune(tuned, images))
    if watched is not None and watched["windows"]:
        sections.append(section_watch(watched, images))
    if fits and any(fits.values()):
        sections.append(section_fits(fits, images))
    if char is not None:
        sections.append(section_characterisation(char))
    sources = [(k, p) for k, p in (("characterisation", characterisation), ("model", model), ("plan", plan),
                                   ("validation", validation), ("frontier", frontier), ("tune", tune),
                                   ("watch", watch))
               if p is not None]
    src = "".join(f"<li>{esc(k)}: <code>{esc(p)}</code></li>" for k, p in sources)
    body = "".join(sections) or '<p class="muted">Nothing to report: no input was given.</p>'
    page = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>'
            f"<style>{CSS}</style></head><body><h1>{esc(title)}</h1><ul class=\"muted\">{src}</ul>"
            f"{body}</body></html>\n")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for img in images:
        with atomic_open(out / img.name, "wb") as f:
            f.write(img.data)
    index = out / "index.html"
    atomic_write_text(index, page)
    return index
