"""The characterisation rows per (node, setting value, recording): the one aggregation that
Table I (:func:`perfros_bag.characterisation.table.table_one`), the fit
(:mod:`perfros_bag.fitting.build`) and the characterisation plot all start from.

Per recording of a node at a value: the CPU is the mean of its rows' ``cpu_units_mean``
(they are equal in a file ``characterise`` wrote), the frequency the mean over its
topics, the bandwidth the sum over its topics. How to combine the recordings is the
caller's choice (a mean, or mean and spread).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.characterisation.manifest import SettingValue


@dataclass(frozen=True)
class TopicMeasure:
    """One topic of a node in one recording."""

    topic: str
    frequency_hz: float | None
    bandwidth_kBps: float | None


@dataclass(frozen=True)
class RecordingMeasure:
    """What one recording showed of a node at one setting value."""

    recording: str
    cpu: float | None
    cpu_p95: float | None
    frequency_hz: float | None  # mean over the topics
    bandwidth_kBps: float | None  # sum over the topics
    topics: tuple[TopicMeasure, ...]


@dataclass(frozen=True)
class SettingMeasures:
    """A node at one setting value, one measure per recording (in row order)."""

    node: str
    parameter: str | None
    value: SettingValue | None
    recordings: tuple[RecordingMeasure, ...]

    def cpus(self) -> list[float]:
        return [m.cpu for m in self.recordings if m.cpu is not None]

    def cpus_p95(self) -> list[float]:
        """Per recording, the 95th percentile of the node's CPU samples (``cpu_units_p95``)."""
        return [m.cpu_p95 for m in self.recordings if m.cpu_p95 is not None]

    def frequencies(self) -> list[float]:
        return [m.frequency_hz for m in self.recordings if m.frequency_hz is not None]

    def bandwidths(self) -> list[float]:
        return [m.bandwidth_kBps for m in self.recordings if m.bandwidth_kBps is not None]


def mean(xs: Sequence[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def sort_key(value: SettingValue | None) -> tuple[int, float, str]:
    """No value first, then numbers by size, then text."""
    if value is None:
        return (0, 0.0, "")
    if isinstance(value, int | float):
        return (1, float(value), "")
    return (2, 0.0, value)


def _value_key(value: SettingValue | None) -> tuple[int, float, str]:
    """Numbers by value (10 and 10.0 are one setting); text and non-finite by text."""
    if isinstance(value, int | float) and math.isfinite(value):
        return (1, float(value), "")
    return (0, 0.0, "") if value is None else (2, 0.0, str(value))


def _recording(name: str, rows: Sequence[Row], declared: Collection[str]) -> RecordingMeasure:
    cpus = [r.cpu_units_mean for r in rows if r.cpu_units_mean is not None]
    p95s = [r.cpu_units_p95 for r in rows if r.cpu_units_p95 is not None]
    topic_rows = [r for r in rows if r.topic]
    if declared and any(r.topic in declared for r in topic_rows):
        topic_rows = [r for r in topic_rows if r.topic in declared]
    freqs = [r.frequency_hz for r in topic_rows if r.frequency_hz is not None]
    bws = [r.bandwidth_kBps for r in topic_rows if r.bandwidth_kBps is not None]
    return RecordingMeasure(name, mean(cpus), mean(p95s), mean(freqs), sum(bws) if bws else None,
                            tuple(TopicMeasure(r.topic or "", r.frequency_hz, r.bandwidth_kBps) for r in topic_rows))


def by_setting(rows: Sequence[Row], topics_of: Mapping[str, Collection[str]] | None = None) -> list[SettingMeasures]:
    """Per node (in order of first row) and setting value (by :func:`sort_key`): one measure
    per recording. Rows without a node are left out. ``topics_of``: a node's declared
    topics; when a recording has any of them, only those count for its rates."""
    grouped: dict[str, dict[tuple[int, float, str], dict[str, list[Row]]]] = {}
    for r in rows:
        if r.node:
            grouped.setdefault(r.node, {}).setdefault(_value_key(r.value), {}).setdefault(r.recording, []).append(r)
    out: list[SettingMeasures] = []
    for node, by_value in grouped.items():
        declared = (topics_of or {}).get(node, ())
        settings = []
        for by_recording in by_value.values():
            first = next(iter(by_recording.values()))[0]
            settings.append(SettingMeasures(node, first.parameter, first.value, tuple(
                _recording(name, rs, declared) for name, rs in by_recording.items())))
        out += sorted(settings, key=lambda s: sort_key(s.value))
    return out
