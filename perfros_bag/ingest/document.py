"""The JSON document of ``perfros-bag info --json`` (format ``perfros-bag/info@1``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.ingest.stats import RecordingStats, TopicStats

if TYPE_CHECKING:
    from perfros_bag.ingest.contents import TopicLatency

FORMAT = "perfros-bag/info@1"


def _num(x: float) -> float:
    return round(float(x), 6)


def _opt(x: float | None) -> float | None:
    return None if x is None else _num(x)


def topic_document(t: TopicStats, latency: TopicLatency | None = None) -> dict[str, Any]:
    """One topic; ``latency_*`` are null when the topic has no header (or was not read)."""
    return {
        "topic": t.topic,
        "msgtype": t.msgtype,
        "messages": t.messages,
        "bytes": t.bytes,
        "first_ns": t.first_ns,
        "last_ns": t.last_ns,
        "duration_s": _num(t.span_s),
        "frequency_hz": _num(t.frequency_hz),
        "bandwidth_kBps": _num(t.bandwidth_kBps),
        "median_rate_hz": _num(t.median_rate_hz),
        "p95_gap_s": _num(t.p95_gap_s),
        "rate_note": t.rate_note,  # the rates above are no rate (too few messages): why
        "publishers": list(t.publishers),
        "latency_p50_s": _opt(latency.p50_s if latency else None),
        "latency_p95_s": _opt(latency.p95_s if latency else None),
        "latency_max_s": _opt(latency.max_s if latency else None),
    }


def file_bytes(path: Path) -> int:
    """Size on disk: the file, or every file of a rosbag2 directory."""
    if path.is_dir():
        return sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    return path.stat().st_size if path.exists() else 0


def recording_document(rec: RecordingStats,
                       latency: Mapping[str, TopicLatency | None] | None = None) -> dict[str, Any]:
    """The document; ``latency`` (:func:`perfros_bag.ingest.contents.read_latency`) when the
    headers were read (``latency_read`` says whether they were)."""
    start, end = rec.start_ns, rec.end_ns
    lat = latency or {}
    return {
        "format": FORMAT,
        "path": str(rec.path),
        "recording_format": rec.format,
        "read_method": rec.method,
        "file_bytes": file_bytes(Path(rec.path)),
        "messages": rec.messages,
        "bytes": sum(t.bytes for t in rec.topics.values()),
        "start_ns": start,
        "end_ns": end,
        "duration_s": _num((end - start) / 1e9) if start is not None and end is not None else 0.0,
        "latency_read": latency is not None,
        "topics": [topic_document(t, lat.get(t.topic)) for t in rec.topics.values()],
    }
