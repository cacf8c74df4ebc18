"""The JSON document of ``perfros-bag info --json`` (format ``perfros-bag/info@1``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from perfros_bag.ingest.stats import RecordingStats, TopicStats

FORMAT = "perfros-bag/info@1"


def _num(x: float) -> float:
    return round(float(x), 6)


def topic_document(t: TopicStats) -> dict[str, Any]:
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
        "publishers": list(t.publishers),
    }


def file_bytes(path: Path) -> int:
    """Size on disk: the file, or every file of a rosbag2 directory."""
    if path.is_dir():
        return sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    return path.stat().st_size if path.exists() else 0


def recording_document(rec: RecordingStats) -> dict[str, Any]:
    start, end = rec.start_ns, rec.end_ns
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
        "topics": [topic_document(t) for t in rec.topics.values()],
    }
