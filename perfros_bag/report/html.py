"""One self-contained HTML report (plus its PNGs) of a characterisation, a model, a plan
and a validation. Every part is optional: what is not given is left out.

The page has inline CSS and no script; the plots are PNGs written beside ``index.html``
and also inlined as base64 so the page stands alone. Every piece of text from the input
files is HTML-escaped. matplotlib (Agg) is imported only when a plot is drawn.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import atomic_open, atomic_write_text, read_json, read_text
from perfros_bag.system.plan import Plan
from perfros_bag.system.types import Curve

MAX_TABLE_ROWS = 2000
MAX_PLOT_NODES = 40

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


def read_characterisation(path: str | Path) -> tuple[list[str], list[dict[str, str]]]:
    p = Path(path)
    text = read_text(p, "characterisation CSV", newline="")
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        rows = list(reader)
        return list(reader.fieldnames or []), rows
    except csv.Error as exc:
        raise InputError(p, f"cannot read the characterisation CSV: {exc}") from None


@dataclass
class FitView:
    node: str
    relation: str
    form: str | None
    curve: Curve | None
    r2: float | None
    points: list[tuple[float, float]] = field(default_factory=list)


def _num(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(float(x)):
        return None
    return float(x)


def _points(raw: Any) -> list[tuple[float, float]]:
    """[[x, y], ...] or {"x": [...], "y": [...]} (anything else: no points)."""
    pts: list[tuple[float, float]] = []
    if isinstance(raw, dict):
        xs, ys = raw.get("x"), raw.get("y")
        if isinstance(xs, list) and isinstance(ys, list):
            raw = list(zip(xs, ys, strict=False))
    if isinstance(raw, list):
        for item in raw:
            if isinstance(item, list | tuple) and len(item) >= 2:
                x, y = _num(item[0]), _num(item[1])
                if x is not None and y is not None:
                    pts.append((x, y))
    return pts


def read_fits(path: str | Path) -> list[FitView]:
    """The ``fits`` of a model.json, tolerantly: a relation whose curve cannot be built is
    kept with its points only; anything not shaped like a fit is skipped."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise InputError(path, "not a model: expected a JSON object")
    fits = data.get("fits")
    out: list[FitView] = []
    if not isinstance(fits, dict):
        return out
    for node, rels in fits.items():
        if not isinstance(rels, dict):
            continue
        for rel, f in rels.items():
            if not isinstance(f, dict):
                continue
            curve: Curve | None = None
            coef, dom = f.get("coef"), f.get("domain")
            scale = _num(f.get("scale")) or 1.0
            try:
                if isinstance(coef, list) and isinstance(dom, list) and len(dom) == 2:
                    c = tuple(float(v) for v in coef)
                    curve = Curve(str(f.get("form")), c, (float(dom[0]), float(dom[1])), scale)
            except (TypeError, ValueError):
                curve = None
            form = f.get("form")
            out.append(FitView(str(node), str(rel), None if form is None else str(form), curve,
                               _num(f.get("r2")), _points(f.get("points"))))
    return out


def read_validation(path: str | Path) -> dict[str, Any]:
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("nodes"), list) or not isinstance(data.get("overall"), dict):
        raise InputError(path, "not a validation (expected the JSON of 'perfros-bag validate --json')")
    return data


# ---------------------------------------------------------------------------------------
# plots


@dataclass
class Image:
    name: str
    data: bytes
    alt: str


def _label(text: str, limit: int = 40) -> str:
    """User text for matplotlib: shortened, with ``$`` escaped (no mathtext from data)."""
    return text[:limit].replace("$", r"\$")


def _png(fig: Any) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_fits(node: str, fits: list[FitView]) -> bytes:
    plt = _pyplot()
    import numpy as np

    n = len(fits)
    ncols = min(n, 3)
    nrows = (n + ncols - 1) // ncols
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.4 * nrows), squeeze=False)
    flat = [ax for row in axes for ax in row]
    for ax in flat[n:]:
        ax.set_visible(False)
    for ax, f in zip(flat, fits, strict=False):
        xs = [p[0] for p in f.points]
        if f.points:
            ax.scatter(xs, [p[1] for p in f.points], color="black", zorder=3, label="measured")
        if f.curve is not None:
            lo, hi = f.curve.domain
            if xs:
                lo, hi = min(lo, min(xs)), max(hi, max(xs))
            if f.curve.form in ("log", "power"):
                lo = max(lo, f.curve.domain[0])
            grid = np.linspace(lo, hi, 200) if hi > lo else np.array([lo])
            try:
                ys = [f.curve(float(x)) for x in grid]
                r2 = "" if f.r2 is None else f", R²={f.r2:.3f}"
                ax.plot(grid, ys, color="tab:blue", label=f"{f.curve.form}{r2}")
            except (ValueError, OverflowError, ZeroDivisionError):
                pass
        src, _, dst = f.relation.partition("->")
        ax.set_xlabel(_label(src or "input"))
        ax.set_ylabel(_label(dst or f.relation))
        ax.set_title(_label(f"{node}: {f.relation}", 60), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def plot_plan_loads(plan: Plan) -> bytes:
    plt = _pyplot()
    names = list(plan.computers)
    fig, ax = plt.subplots(figsize=(min(24.0, max(4.0, 1.6 * len(names) + 2)), 3.6))
    bottoms = [0.0] * len(names)
    loads = [sum(pn.cpu for pn in plan.nodes.values() if pn.computer == c) for c in names]
    caps = [plan.computers[c].capacity or 0.0 for c in names]
    top = max([*loads, *caps, 1e-9])
    for node, pn in plan.nodes.items():
        if pn.computer not in plan.computers:
            continue
        i = names.index(pn.computer)
        ax.bar(i, pn.cpu, bottom=bottoms[i], edgecolor="white")
        if pn.cpu >= 0.04 * top:  # label only the bars tall enough to hold it
            ax.text(i, bottoms[i] + pn.cpu / 2, _label(node, 18), ha="center", va="center", fontsize=7)
        bottoms[i] += pn.cpu
    for i, c in enumerate(names):
        cap = plan.computers[c].capacity
        if cap is not None:
            ax.hlines(cap, i - 0.45, i + 0.45, colors="red", linestyles="--",
                      label="capacity" if i == 0 else None)
    ax.set_xticks(range(len(names)), [_label(n, 20) for n in names])
    ax.set_ylabel("CPU (normalised units)")
    ax.set_title("planned CPU per computer (stacked by node)")
    if any(plan.computers[c].capacity is not None for c in names):
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def plot_validation(v: dict[str, Any]) -> bytes:
    """The paper's Fig 5 for one run: expected vs measured performance per node and overall
    (the overall panel normalised to expected = 1)."""
    plt = _pyplot()
    nodes = [n for n in v["nodes"] if isinstance(n, dict)]
    title = "per node (eq 10)"
    if len(nodes) > MAX_PLOT_NODES:  # keep the figure readable: the largest deviations
        nodes = sorted(nodes, key=lambda n: -(_num(n.get("deviation_pct")) or 0.0))[:MAX_PLOT_NODES]
        title = f"per node (eq 10), the {MAX_PLOT_NODES} largest deviations"
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(max(6.0, 0.8 * len(nodes) + 4), 3.8),
                                  gridspec_kw={"width_ratios": [max(1, len(nodes)), 1.2]})
    xs = range(len(nodes))
    pe = [_num(n.get("p_expected")) or 0.0 for n in nodes]
    pm = [_num(n.get("p_measured")) or 0.0 for n in nodes]
    ax.bar([x - 0.2 for x in xs], pe, 0.4, label="Expected", color="tab:blue")
    ax.bar([x + 0.2 for x in xs], pm, 0.4, label="Measured", color="tab:orange")
    ax.set_xticks(list(xs), [_label(str(n.get("node", "")), 14) for n in nodes], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("performance")
    ax.set_title(title)
    ax.set_ylim(0, max([*pe, *pm, 1e-9]) * 1.25)  # room for the legend above the bars
    ax.legend(fontsize=8, ncol=2, loc="upper right")
    ov = v["overall"]
    e, m = _num(ov.get("expected")) or 0.0, _num(ov.get("measured")) or 0.0
    ax2.bar([0], [1.0], 0.4, color="tab:blue", label="Expected")
    ax2.bar([0.45], [m / e if e else 0.0], 0.4, color="tab:orange", label="Measured")
    ax2.set_xticks([0.225], ["overall Σ w·P"])
    ax2.set_ylim(0, max(1.2, (m / e if e else 0) * 1.1))
    dev = _num(ov.get("deviation_pct"))
    ax2.set_title("overall (normalised)" + ("" if dev is None else f", dev {dev:.1f} %"), fontsize=9)
    fig.tight_layout()
    return _png(fig)


# ---------------------------------------------------------------------------------------
# sections


def _img(img: Image) -> str:
    b64 = base64.b64encode(img.data).decode("ascii")
    return f'<img src="data:image/png;base64,{b64}" alt="{esc(img.alt)}" title="{esc(img.name)}">'


def section_characterisation(columns: list[str], rows: list[dict[str, str]]) -> str:
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
    return f'<h2 id="characterisation">Characterisation</h2><p>{len(rows)} rows.</p>{body}{more}'


def section_fits(fits: list[FitView], images: list[Image]) -> str:
    by_node: dict[str, list[FitView]] = {}
    for f in fits:
        by_node.setdefault(f.node, []).append(f)
    rows = [(f.node, f.relation, f.form, None if f.curve is None else ", ".join(f"{c:.5g}" for c in f.curve.coef),
             None if f.curve is None else f"[{f.curve.domain[0]:g}, {f.curve.domain[1]:g}]", f.r2, len(f.points))
            for f in fits]
    parts = ['<h2 id="regressions">Regressions</h2>',
             table(("node", "relation", "form", "coefficients", "domain", "R²", "points"), rows,
                   text_cols=(0, 1, 2, 3, 4), table_id="fits-table")]
    for k, (node, nf) in enumerate(by_node.items()):
        img = Image(f"fit_{k:02d}.png", plot_fits(node, nf), f"regressions of {node}")
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
    img = Image("plan_cpu.png", plot_plan_loads(plan), "planned CPU per computer")
    images.append(img)
    return f'<h2 id="plan">Plan</h2>{head}<h3>Placement per computer</h3>{comp}{_img(img)}<h3>Nodes</h3>{nodes}{links}'


def _link_name(lc: dict[str, Any]) -> str:
    between = [str(b) for b in lc.get("between", []) if b is not None]
    if len(between) == 2 and between[0] == between[1]:
        return f"medium {between[0]}"
    return " – ".join(between)


def section_validation(v: dict[str, Any], images: list[Image]) -> str:
    ov = v["overall"]
    passed = ov.get("passed")
    verdict = ('<span class="ok">within tolerance</span>' if passed
               else '<span class="bad">deviation above tolerance</span>' if passed is False else "")
    head = (f'<p class="summary">Recording {esc(v.get("recording"))}: overall Σ w·P expected '
            f'{esc(fmt(_num(ov.get("expected"))))}, measured {esc(fmt(_num(ov.get("measured"))))}, deviation '
            f'{esc(fmt(_num(ov.get("deviation_pct")), 3))} % (tolerance {esc(fmt(_num(v.get("tolerance_pct"))))} %) '
            f'{verdict}</p>')
    rows, classes = [], []
    for n in v["nodes"]:
        if not isinstance(n, dict):
            continue
        topics = [t for t in n.get("topics", []) if isinstance(t, dict)]
        freq = "; ".join(f"{t.get('topic')}: {fmt(_num(t.get('f_measured')))} / {fmt(_num(t.get('f_expected')))} Hz"
                         + (f" ({t.get('status')})" if t.get("status") != "ok" else "") for t in topics)
        rows.append((n.get("node"), n.get("computer"), freq or "–", _num(n.get("p_expected")),
                     _num(n.get("p_measured")), _num(n.get("deviation_pct")) if n.get("counted", True) else "not counted"))
        classes.append("bad" if n.get("flagged") else "")
    nodes = table(("node", "computer", "F measured / expected", "P expected", "P measured", "deviation %"),
                  rows, text_cols=(0, 1, 2), row_classes=classes, table_id="validation-table")
    img = Image("validation.png", plot_validation(v), "expected vs measured performance")
    images.append(img)
    parts = [f'<h2 id="validation">Validation (eq 10)</h2>{head}{_img(img)}{nodes}']
    comps = [c for c in v.get("computers", []) if isinstance(c, dict)]
    if comps:
        parts.append("<h3>CPU per computer</h3>" + table(
            ("computer", "capacity", "planned", "measured", "overloaded"),
            [(c.get("computer"), _num(c.get("capacity")), _num(c.get("cpu_expected")), _num(c.get("cpu_measured")),
              c.get("overloaded")) for c in comps],
            row_classes=["bad" if c.get("overloaded") else "" for c in comps], table_id="validation-cpu"))
    links = [c for c in v.get("links", []) + v.get("media", []) if isinstance(c, dict)]
    if links:
        parts.append("<h3>Bandwidth</h3>" + table(
            ("link", "capacity kB/s", "planned", "measured", "overloaded"),
            [(_link_name(lc), _num(lc.get("capacity_kBps")),
              _num(lc.get("expected_kBps")), _num(lc.get("measured_kBps")), lc.get("overloaded")) for lc in links],
            row_classes=["bad" if lc.get("overloaded") else "" for lc in links]))
    extra = [u for u in v.get("unplanned_topics", []) if isinstance(u, dict)]
    if extra:
        parts.append("<h3>Topics not in the plan (not counted)</h3>" + table(
            ("topic", "type", "messages", "frequency Hz"),
            [(u.get("topic"), u.get("msgtype"), u.get("messages"), _num(u.get("f_measured"))) for u in extra],
            text_cols=(0, 1)))
    notes = [n for n in v.get("notes", []) if isinstance(n, str)]
    if notes:
        parts.append("<ul class=\"muted\">" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>")
    return "".join(parts)


# ---------------------------------------------------------------------------------------
# the page


def build_report(out_dir: str | Path, *, characterisation: str | Path | None = None,
                 model: str | Path | None = None, plan: str | Path | None = None,
                 validation: str | Path | None = None, title: str = "perfros-bag report") -> Path:
    """Write ``out_dir/index.html`` and its PNGs; returns the page's path. Inputs are read
    (and checked) before anything is written."""
    from perfros_bag.system.planfile import load_plan

    char = read_characterisation(characterisation) if characterisation is not None else None
    fits = read_fits(model) if model is not None else None
    the_plan = load_plan(plan) if plan is not None else None
    val = read_validation(validation) if validation is not None else None

    images: list[Image] = []
    sections: list[str] = []
    if the_plan is not None:
        sections.append(section_plan(the_plan, images))
    if val is not None:
        sections.append(section_validation(val, images))
    if fits:
        sections.append(section_fits(fits, images))
    if char is not None:
        sections.append(section_characterisation(*char))
    sources = [(k, p) for k, p in (("characterisation", characterisation), ("model", model), ("plan", plan),
                                   ("validation", validation)) if p is not None]
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
