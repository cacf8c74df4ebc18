"""``perfros-bag info RECORDING``: per-topic counts, rates and bandwidth of one recording."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated

import typer

from perfros_bag.cli._app import command, err, out
from perfros_bag.errors import PerfrosError

_HOW = {"index": "read from the index records", "sqlite-pages": "read from the SQLite pages",
        "sql": "read with one SQL pass", "stream": "every record streamed",
        "mixed": "files read in different ways"}


def _utc(ns: int | None) -> str:
    if ns is None:
        return "-"
    return datetime.fromtimestamp(ns / 1e9, tz=UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


@command("info")
def info(
    recording: Annotated[Path, typer.Argument(help="A .bag, .mcap or .db3 file or a rosbag2 directory.")],
    as_json: Annotated[bool, typer.Option(
        "--json", help="Print the perfros-bag/info@1 JSON document on stdout.")] = False,
    slow: Annotated[bool, typer.Option(
        "--slow", help="Stream every record instead of reading the indexes (same numbers, slower).")] = False,
    latency: Annotated[bool, typer.Option(
        "--latency", help="Also read header.stamp of the topics with a std_msgs/Header: "
                          "receive time - stamp, p50/p95/max.")] = False,
    system: Annotated[Path | None, typer.Option(
        "--system", help="With --latency: also the end-to-end latency of this system.yaml's chains.")] = None,
) -> None:
    """Per-topic table like `rosbag info` / `ros2 bag info`, with rates and bandwidth."""
    from rich.console import Console
    from rich.table import Table

    from perfros_bag.ingest import read_recording
    from perfros_bag.ingest.document import recording_document

    chains = None
    if system is not None:
        if not latency:
            raise PerfrosError("--system gives the chains whose latency --latency reads: add --latency")
        from perfros_bag.system.systemfile import load_system

        chains = load_system(system).chains
    with err.status(f"reading {recording}", spinner="dots"):  # animates on a terminal only
        lat = None
        measured = []
        if latency and chains:  # the chains need every stamp: read once, shared with the latency
            from perfros_bag.ingest.chains import chain_latencies
            from perfros_bag.ingest.contents import read_contents_stamps, topic_latencies

            rec = read_recording(recording, fast=not slow)
            read = read_contents_stamps(recording, fast=not slow)
            lat = topic_latencies(recording, read)
            measured = chain_latencies(chains, read, where=f"{recording}: ")
        elif latency:  # one pass reads both
            from perfros_bag.ingest.contents import read_with_latency

            rec, lat = read_with_latency(recording, fast=not slow)
        else:
            rec = read_recording(recording, fast=not slow)
    doc = recording_document(rec, lat)
    if chains is not None:
        doc["chains"] = [c.to_dict() for c in measured]
    if as_json:
        from perfros_bag.fileio import json_text  # strict: no NaN/Infinity

        print(json_text(doc, indent=2))
        return
    # piped output is not cut to 80 columns: the table is for reading and for grep
    console = out if out.is_terminal else Console(width=240, highlight=False)
    console.print(f"[bold]path[/]:      {rec.path}\n[bold]format[/]:    {rec.format} "
                  f"({doc['file_bytes']:,} bytes on disk; {_HOW.get(rec.method, rec.method)})\n"
                  f"[bold]start[/]:     {_utc(rec.start_ns)}\n[bold]end[/]:       {_utc(rec.end_ns)}\n"
                  f"[bold]duration[/]:  {doc['duration_s']:.3f} s\n"
                  f"[bold]messages[/]:  {rec.messages}   [bold]payload[/]: {doc['bytes']} bytes",
                  highlight=False)
    table = Table(show_edge=False, header_style="bold")
    columns = [("topic", "left"), ("type", "left"), ("msgs", "right"), ("freq Hz", "right"),
               ("median Hz", "right"), ("p95 gap s", "right"), ("kB/s", "right"),
               ("first s", "right"), ("last s", "right"), ("publishers", "left")]
    for name, justify in columns + [("latency p50/p95/max s", "right")] * latency:
        table.add_column(name, justify=justify, no_wrap=name != "publishers")  # type: ignore[arg-type]
    start = rec.start_ns or 0

    def rel(ns: int | None) -> str:
        return "-" if ns is None else f"{(ns - start) / 1e9:.3f}"

    for t, td in zip(rec.topics.values(), doc["topics"], strict=True):
        delays = [td[k] for k in ("latency_p50_s", "latency_p95_s", "latency_max_s")]
        few = t.rate_note is not None  # too few messages: no rate to print
        table.add_row(t.topic, t.msgtype, str(t.messages), "too few msgs" if few else f"{t.frequency_hz:.3f}",
                      "-" if few else f"{t.median_rate_hz:.3f}", f"{t.p95_gap_s:.4f}", f"{t.bandwidth_kBps:.3f}",
                      rel(t.first_ns), rel(t.last_ns), ", ".join(t.publishers),
                      *["/".join("-" if d is None else f"{d:.4f}" for d in delays)] * latency)
    console.print(table)
    for c in doc.get("chains", []):
        console.print(f"chain {c['name']} ({' -> '.join(c['topics'])}): end-to-end "
                      + ("-" if c["p50_s"] is None
                         else f"p50/p95/max {c['p50_s']:.4f}/{c['p95_s']:.4f}/{c['max_s']:.4f} s")
                      + f", {c['matched']} of {c['messages']} matched", highlight=False, markup=False)
    if not rec.topics:
        err.print("(no topics)")
