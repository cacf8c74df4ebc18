"""``perfros-bag validate RUN PLAN``: eq 10 per node, overall, CPU and link loads."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from perfros_bag.cli._app import command, err, out
from perfros_bag.system.latency import budget_text
from perfros_bag.validation import DEFAULT_TOLERANCE

if TYPE_CHECKING:
    from perfros_bag.ingest.contents import TopicLatency
    from perfros_bag.validation.eq10 import TopicCheck, Validation


def _f(x: float | None, fmt: str = ".3g") -> str:
    return "-" if x is None else format(x, fmt)


def _delays(d: TopicLatency | None) -> tuple[str, str, str]:
    return ("-", "-", "-") if d is None else (_f(d.p50_s), _f(d.p95_s), _f(d.max_s))


def _predicted(pred: object) -> tuple[str, str]:
    """A ``predicted_ms`` {p50, p95} in seconds, as the measured columns."""
    if not isinstance(pred, dict):
        return "-", "-"
    return tuple(_f(None if pred.get(q) is None else pred[q] / 1000.0) for q in ("p50", "p95"))  # type: ignore[return-value]


def render(v: Validation, console: Console) -> None:
    """The validation as rich tables."""
    t = Table(title="eq 10 per node: P_meas = P_exp x F_meas / F_exp (F in Hz)",
              box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for col in ("node", "computer", "topic", "F exp", "F meas", "ratio", "P exp", "P meas", "dev%"):
        text = col in ("node", "computer", "topic")
        t.add_column(col, justify="left" if text else "right", overflow="fold", no_wrap=not text)
    for n in v.nodes:
        first = True
        rows: list[TopicCheck | None] = list(n.topics) or [None]
        for tc in rows:
            topic = "-" if tc is None else escape(tc.topic)
            if tc is not None and tc.status == "missing":
                topic = f"[red]{topic} (missing)[/]"
            elif tc is not None and tc.status == "no-expectation":
                topic = f"[yellow]{topic} (no F expected)[/]"
            if tc is not None and tc.rate_note is not None:
                topic += f" [yellow]({escape(tc.rate_note)}: F = messages / recording span)[/]"
            dev = f"{n.deviation_pct:.1f}" if n.counted else "[dim]not counted[/]"
            t.add_row(
                escape(n.node) if first else "", escape(n.computer) if first else "", topic,
                _f(None if tc is None else tc.f_expected), _f(None if tc is None else tc.f_measured),
                _f(None if tc is None else tc.ratio, ".3f"),
                _f(n.p_expected) if first else "", _f(n.p_measured) if first else "",
                dev if first else "",
            )
            first = False
    console.print(t)
    style = "green" if v.passed else "red"
    console.print(
        f"overall  Σ w·P expected {v.overall_expected:.4g}   measured {v.overall_measured:.4g}   "
        f"deviation [{style}]{v.deviation_pct:.2f} %[/] (tolerance {v.tolerance_pct:g} %)"
        + ("  [dim](capped)[/]" if v.cap else "")
    )
    driven = [n for n in v.nodes if n.input is not None]
    if driven:
        dt = Table(title="driven nodes: input rate expected (plan) vs measured (Hz)")
        for col in ("node", "input", "expected", "measured", "dev%"):
            dt.add_column(col, justify="left" if col in ("node", "input") else "right")
        for n in driven:
            measured = (_f(n.input_hz_measured) if n.input_rate_note is None
                        else f"[yellow]{escape(n.input_rate_note)}[/]")
            dt.add_row(escape(n.node), escape(n.input or ""), _f(n.input_hz_expected), measured,
                       _f(n.input_deviation_pct, ".1f"))
        console.print(dt)
    if v.computers:
        ct = Table(title="CPU per computer (normalised units)")
        for col in ("computer", "capacity", "planned", "measured", "status"):
            ct.add_column(col, justify="left" if col in ("computer", "status") else "right")
        for c in v.computers:
            status = ("[red]overloaded[/]" if c.overloaded else "ok" if c.overloaded is False
                      else "[dim]not in trace[/]")
            if c.unmatched_nodes and c.cpu_measured is not None:
                status += f" [dim](not traced: {escape(', '.join(c.unmatched_nodes))})[/]"
            ct.add_row(escape(c.name), _f(c.capacity), _f(c.cpu_expected), _f(c.cpu_measured), status)
        console.print(ct)
    if v.links or v.media:
        lt = Table(title="bandwidth per link (kB/s)")
        for col in ("link", "capacity", "planned", "measured", "status"):
            lt.add_column(col, justify="left" if col in ("link", "status") else "right")
        for lc in v.links:
            lt.add_row(escape(" - ".join(lc.between)), _f(lc.capacity_kBps), _f(lc.expected_kBps),
                       _f(lc.measured_kBps), "[red]overloaded[/]" if lc.overloaded else "ok")
        for m in v.media:
            lt.add_row(f"medium {escape(m.between[0])}", _f(m.capacity_kBps), _f(m.expected_kBps),
                       _f(m.measured_kBps), "[red]overloaded[/]" if m.overloaded else "ok")
        console.print(lt)
    if any(n.metric_value is not None for n in v.nodes):
        mt = Table(title="measured metric (system.yaml metric) beside eq 10")
        for col in ("node", "metric", "P metric", "P exp", "P eq 10", "dev%"):
            mt.add_column(col, justify="left" if col == "node" else "right")
        for n in v.nodes:
            if n.metric_value is not None:
                mt.add_row(escape(n.node), _f(n.metric_value, ".4g"), _f(n.p_metric), _f(n.p_expected),
                           _f(n.p_measured), _f(n.metric_deviation_pct, ".1f"))
        console.print(mt)
    if v.network:
        nt = Table(title="network: transfer delay per message the plan adds, beside the measured latency (s)")
        for col in ("edge", "topic", "route", "bytes/msg", "added", "latency p50", "latency p95"):
            nt.add_column(col, justify="left" if col in ("edge", "topic", "route") else "right")
        for nc in v.network:
            nt.add_row(escape(nc.edge), escape(nc.topic), escape(", ".join("-".join(b) for b in nc.links)),
                       _f(nc.message_bytes, ".4g"), _f(nc.predicted_delay_s, ".3g"), _f(nc.latency_p50_s, ".3g"),
                       _f(nc.latency_p95_s, ".3g"))
        console.print(nt)
    if v.chains:
        ch = Table(title="chains: end-to-end latency (last topic's log time - first topic's stamp, s), "
                         "beside the plan's prediction and budget")
        for col in ("chain", "from -> to", "matched", "p50", "p95", "max", "pred p50", "pred p95", "budget"):
            ch.add_column(col, justify="left" if col in ("chain", "from -> to", "budget") else "right")
        predicted = {c.get("name"): c for c in v.predicted_chains}
        for cl in v.chains:
            e = cl.end_to_end
            pc = predicted.get(cl.name, {})
            ch.add_row(escape(cl.name), escape(f"{cl.topics[0]} -> {cl.topics[-1]}"),
                       f"{0 if e is None else e.messages}/{cl.messages}",
                       *_delays(e), *_predicted(pc.get("predicted_ms")), escape(budget_text(pc.get("budget_ms"))))
            hops = {(h.get("from"), h.get("to")): h for h in pc.get("hops") or []}
            for h in cl.hops:
                d = h.delays
                ch.add_row("", escape(f"  hop {h.src} -> {h.dst}"), str(0 if d is None else d.messages),
                           *_delays(d), *_predicted(hops.get((h.src, h.dst), {}).get("predicted_ms")), "")
        console.print(ch)
    if v.kept is not None:
        kt = Table(title="kept rates: a capped computer shares its CPU in proportion to need; "
                         "a starved node slows what it drives (Hz, CPU units)")
        for col in ("node", "computer", "CPU need", "CPU share", "kept", "F planned", "F predicted", "F measured"):
            kt.add_column(col, justify="left" if col in ("node", "computer") else "right")
        for k in v.kept.nodes:
            kt.add_row(escape(k.node), escape(k.computer), _f(k.cpu_need), _f(k.cpu_share), f"{k.factor:.0%}",
                       _f(k.f_planned), _f(k.f_predicted), _f(k.f_measured))
        console.print(kt)
        console.print("capped: " + (", ".join(f"{escape(c.computer)} (needs {c.need:.4g} of {c.capacity:.4g})"
                                              for c in v.kept.computers if c.capped) or "none predicted"))
    if v.unplanned_topics:
        console.print("topics not in the plan (not counted): "
                      + ", ".join(f"{escape(u.topic)} ({u.f_measured:.3g} Hz)" if u.f_measured is not None
                                  else f"{escape(u.topic)} ({escape(u.rate_note or 'no rate')})"
                                  for u in v.unplanned_topics))
    for note in v.notes:
        console.print(f"[dim]note: {escape(note)}[/]")


@command("validate")
def validate(
    run: Annotated[Path, typer.Argument(help="The run's recording: .mcap, .bag, rosbag2 directory or .db3.")],
    plan: Annotated[Path, typer.Argument(help="The plan.json the run was configured from.")],
    cpu: Annotated[list[Path] | None, typer.Option(
        "--cpu", help="CPU trace(s) of the run (repeatable); default <stem>.cpu.csv beside RUN.")] = None,
    system: Annotated[Path | None, typer.Option(
        "--system", help="system.yaml (process patterns, edges for link loads); default: the plan's.")] = None,
    tolerance: Annotated[float, typer.Option(
        "--tolerance", help="Largest overall deviation in % that still passes (exit 0).")] = DEFAULT_TOLERANCE,
    cap: Annotated[bool, typer.Option("--cap", help="Cap P_measured at P_expected.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the validation as JSON on stdout.")] = False,
    save: Annotated[Path | None, typer.Option(
        "--out", help="Also write the JSON document to this file (atomic).")] = None,
) -> None:
    """Compare a run with its plan (the paper's eq 10); exit 1 when the overall deviation
    exceeds --tolerance."""
    from perfros_bag.fileio import atomic_write_json
    from perfros_bag.validation.eq10 import validate_files

    result = validate_files(run, plan, cpu=cpu, system_path=system, tolerance=tolerance, cap=cap)
    doc = result.to_dict()
    if save is not None:
        atomic_write_json(save, doc)
    if as_json:
        render(result, err)
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(doc, indent=2))
    else:
        render(result, out)
    if not result.passed:
        raise typer.Exit(1)
