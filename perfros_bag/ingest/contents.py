"""What is inside the messages: per-topic latency (receive/log time - ``header.stamp``) and
nodes' metrics (a field of a topic's messages, aggregated).

Entry points: :func:`read_with_latency` (what ``info --latency`` and ``characterise
--latency`` use: the recording's statistics and its latencies from one index pass),
:func:`read_latency` (latencies only), :func:`read_stamps` (the stamps themselves),
:func:`latencies` (stamps -> latencies, e.g. merged from the parts of a split recording)
and :func:`read_metric` (system.yaml's ``metric:``, decoded by the libraries). The fast
path (:mod:`perfros_bag.ingest.stamps`) has the readers gather each stamp at its known
offset in the payload in their own index pass (ROS 1 index, MCAP summary + message
indexes, rosbag2 sqlite3 B-tree pages); where it cannot (no index, message compression, an
encapsulation it does not know) the recording libraries decode the messages
(:func:`library_stamps`, :mod:`perfros_bag.ingest.decode`).
Both give the same stamps: tests/test_contents.py checks it on every stamped message of
shared/realbags and of generated recordings.

Only topics whose type starts with a ``std_msgs/Header`` (rosbags decides, from the
definitions stored in the recording) have a latency; messages stamped 0 (header left unset)
are left out. A topic that cannot be decoded gets no latency and one
:class:`~perfros_bag.errors.PerfrosWarning` naming it and why; the rest is unaffected.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.errors import PerfrosError, PerfrosWarning
from perfros_bag.ingest._accum import I64, Damaged, NoIndex
from perfros_bag.ingest.decode import TopicType, Undecodable, decoded_messages, topic_types
from perfros_bag.ingest.stamps import Stamps
from perfros_bag.ingest.stats import RecordingStats
from perfros_bag.system.types import Aggregate, Metric

#: what reading the contents may raise on a damaged or unusual recording: a warning
_UNREADABLE = (PerfrosError, Undecodable, NoIndex, Damaged, OSError, ValueError, IndexError, KeyError)


@dataclass(frozen=True)
class TopicLatency:
    """Receive/log time minus ``header.stamp`` over a topic's messages with a non-zero stamp."""

    messages: int
    p50_s: float
    p95_s: float
    max_s: float


def latency_of(times_ns: I64, stamps_ns: I64) -> TopicLatency | None:
    """p50/p95/max of ``times - stamps`` in seconds (numpy's linear percentiles); messages
    stamped 0 are left out; None when none is left."""
    keep = stamps_ns != 0
    if keep.all():  # the usual case: no copies through the mask
        delay = (times_ns - stamps_ns).astype(np.float64) / 1e9
    elif not np.any(keep):
        return None
    else:
        delay = (times_ns[keep] - stamps_ns[keep]).astype(np.float64) / 1e9
    if delay.size == 0:
        return None
    p50, p95 = np.percentile(delay, [50, 95])
    return TopicLatency(int(delay.size), float(p50), float(p95), float(delay.max()))


# --------------------------------------------------------------------------- library path


def _stamp_of(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def library_stamps(path: Path, types: dict[str, TopicType] | None = None) -> Stamps:
    """The stamps of every stamped topic, each message deserialised by the libraries. A topic
    that does not decode is left out with a warning."""
    types = topic_types(path) if types is None else types
    topics = {t for t, tt in types.items() if tt.stamped}
    while topics:
        times: dict[str, list[int]] = {t: [] for t in topics}
        stamps: dict[str, list[int]] = {t: [] for t in topics}
        try:
            for topic, log_ns, msg in decoded_messages(path, topics):
                times[topic].append(log_ns)
                stamps[topic].append(_stamp_of(msg))
        except Undecodable as exc:
            bad = next((t for t in topics if str(exc).startswith(f"{t}: ")), None)
            if bad is None:
                raise
            warnings.warn(f"{path}: {exc}: no latency for it", PerfrosWarning, stacklevel=2)
            topics.discard(bad)
            continue
        return {t: (np.asarray(times[t], dtype=np.int64), np.asarray(stamps[t], dtype=np.int64))
                for t in sorted(topics)}
    return {}


# --------------------------------------------------------------------------- fast path


def fast_stamps(path: Path) -> tuple[Stamps, dict[str, TopicType]]:
    """The stamps read at their offset (no deserialisation) in the readers' own pass over
    the chunks holding stamped messages, and every topic's type; raises when the fast path
    cannot read this recording (the caller decodes instead)."""
    from perfros_bag.ingest.stamps import read_with_stamps

    acc, _fmt, finder = read_with_stamps(path, stamped_only=True)
    return finder.stamps(acc), finder.types


def read_stamps(path: str | Path, *, fast: bool = True) -> tuple[Stamps, dict[str, TopicType]]:
    """(stamps of every stamped topic, every topic's type): the fast path, else the libraries.
    Raises :class:`Undecodable` when neither can read the recording's contents."""
    p = _recording(path)
    if fast:
        try:
            return fast_stamps(p)
        except Exception:  # noqa: S110 - any failure of the fast path: the libraries decode instead
            pass
    types = topic_types(p)
    return library_stamps(p, types), types


def read_contents_stamps(path: str | Path, *, fast: bool = True) -> tuple[Stamps, dict[str, TopicType]] | None:
    """:func:`read_stamps`, with a recording whose contents cannot be read (e.g. an empty
    file: the index reader says so) as one warning and None."""
    try:
        return read_stamps(path, fast=fast)
    except _UNREADABLE as exc:
        warnings.warn(f"{path}: latency not read: {exc}", PerfrosWarning, stacklevel=3)
        return None


def _recording(path: str | Path) -> Path:
    p = Path(path)
    return p.parent if p.is_file() and p.name == "metadata.yaml" else p


def latencies(path: Path, stamps: Stamps, types: dict[str, TopicType]) -> dict[str, TopicLatency | None]:
    """Per stamped topic of ``types``: its :class:`TopicLatency` from ``stamps`` (None, with a
    warning, when every stamp is 0); a warning per ``cdr``/``ros1`` topic whose type no
    recorded definition tells."""
    out: dict[str, TopicLatency | None] = {}
    for topic, tt in sorted(types.items()):
        if tt.stamped is None and tt.encoding in ("cdr", "ros1"):
            warnings.warn(f"{path}: {topic}: no definition of {tt.msgtype or 'its type'} that rosbags can parse "
                          "in the recording: "
                          "no latency for it", PerfrosWarning, stacklevel=3)
        if not tt.stamped:
            continue
        t, s = stamps.get(topic, (np.empty(0, np.int64), np.empty(0, np.int64)))
        out[topic] = latency_of(t, s)
        if t.size and out[topic] is None:
            warnings.warn(f"{path}: {topic}: every header.stamp is 0 (unset): no latency for it",
                          PerfrosWarning, stacklevel=3)
    return out


def read_latency(path: str | Path, *, fast: bool = True) -> dict[str, TopicLatency | None]:
    """Per topic of the recording with a header: its :class:`TopicLatency` (None when no
    message carries a non-zero stamp or it does not decode). Topics without a header are
    absent. Never raises on contents: a recording or topic that cannot be decoded is a
    warning."""
    p = Path(path)
    return topic_latencies(p, read_contents_stamps(p, fast=fast))


def topic_latencies(path: str | Path, read: tuple[Stamps, dict[str, TopicType]] | None
                    ) -> dict[str, TopicLatency | None]:
    """:func:`read_latency` from one reading of the stamps (:func:`read_contents_stamps`),
    so other measures (chains) can share it; ``read`` None: empty."""
    if read is None:
        return {}
    stamps, types = read
    return latencies(Path(path), stamps, types)


def read_with_latency(path: str | Path, *, fast: bool = True,
                      ) -> tuple[RecordingStats, dict[str, TopicLatency | None]]:
    """``read_recording(path, fast=fast)`` and ``read_latency(path, fast=fast)`` in one pass:
    the index reader gathers the stamps as it goes
    (:func:`~perfros_bag.ingest.stamps.read_with_stamps`). Where that pass cannot be used
    (no index, compression, ``fast=False``, ...) the two are read one after the other, with
    the same results."""
    from perfros_bag.ingest import read_recording
    from perfros_bag.ingest.stamps import read_with_stamps

    p = Path(path)
    if fast and p.exists():
        try:
            acc, fmt, finder = read_with_stamps(_recording(p))
            stats = acc.build(_recording(p), fmt)
        except Exception:  # noqa: S110 - the two separate reads below say what is wrong
            pass
        else:
            return stats, latencies(p, finder.stamps(acc), finder.types)
    return read_recording(p, fast=fast), read_latency(p, fast=fast)


# --------------------------------------------------------------------------- metrics

_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$")


def _path(field: str) -> list[str | int]:
    """``pose.covariance[0]`` -> ["pose", "covariance", 0]; ValueError on anything else."""
    steps: list[str | int] = []
    for part in field.split("."):
        m = _STEP.match(part)
        if m is None:
            raise ValueError(f"field {field!r}: {part!r} is not a name with optional [index]")
        steps.append(m.group(1))
        steps += [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    return steps


def field_value(msg: Any, field: str) -> float:
    """The number at ``field`` in a decoded message (a rosbags object or, for ``json``
    payloads, a dict); a list, array or string counts its elements. Raises ValueError when
    the path does not lead to a number."""
    value = msg
    for step in _path(field):
        try:
            if isinstance(step, int):
                value = value[step]
            elif isinstance(value, dict):
                value = value[step]
            else:
                value = getattr(value, step)
        except (AttributeError, KeyError, IndexError, TypeError):
            raise ValueError(f"field {field!r}: no {step!r} in the message") from None
    if isinstance(value, bool | int | float | np.integer | np.floating | np.bool_):
        return float(value)
    if isinstance(value, list | tuple | str | bytes | np.ndarray):
        return float(len(value))
    raise ValueError(f"field {field!r} is a {type(value).__name__}, not a number or a list")


def aggregate(values: Sequence[float], how: Aggregate) -> float:
    """mean, median, p5 or p95 (numpy's linear percentiles) of ``values`` (not empty)."""
    arr = np.asarray(values, dtype=np.float64)
    if how is Aggregate.MEAN:
        return float(arr.mean())
    if how is Aggregate.MEDIAN:
        return float(np.median(arr))
    if how in (Aggregate.P5, Aggregate.P95):
        return float(np.percentile(arr, 5 if how is Aggregate.P5 else 95))
    raise ValueError(f"aggregate {how.value!r} is not over field values")


def read_metric(path: str | Path, metric: Metric, stats: RecordingStats | None = None) -> float | None:
    """A node's metric in one recording: its field over the messages of its topic (decoded by
    the libraries, only that topic's chunks read), aggregated; ``rate`` is the topic's
    frequency (``stats`` when given: no decoding). None, with one warning naming the topic
    and why, when the topic is absent, empty or does not decode."""
    return read_metrics(path, {"": metric}, stats)[""]


def read_metrics(path: str | Path, metrics: Mapping[str, Metric],
                 stats: RecordingStats | None = None) -> dict[str, float | None]:
    """:func:`read_metric` of several metrics (keyed, e.g. by node) in ONE pass over the
    messages of all their topics; a topic that does not decode fails only the metrics on
    it (the others are read again without it), a field that is not there only its metric."""
    p = Path(path)
    out: dict[str, float | None] = {}
    for key, metric in metrics.items():
        if metric.aggregate is Aggregate.RATE:
            if stats is None:
                from perfros_bag.ingest import read_recording

                stats = read_recording(p)
            ts = stats.topics.get(metric.topic)
            if ts is None or ts.messages < 2:
                warnings.warn(f"{p}: metric {metric.topic}: fewer than 2 messages: no rate", PerfrosWarning,
                              stacklevel=2)
                out[key] = None
            else:
                out[key] = ts.frequency_hz
    fields = {k: m for k, m in metrics.items() if m.aggregate is not Aggregate.RATE}
    on_topic: dict[str, list[str]] = {}
    for key, metric in fields.items():
        on_topic.setdefault(metric.topic, []).append(key)
    values: dict[str, list[float]] = {k: [] for k in fields}
    failed: dict[str, str] = {}
    topics = set(on_topic)
    while topics:
        for v in values.values():
            v.clear()
        try:
            for topic, _t, msg in decoded_messages(p, topics):
                for key in on_topic[topic]:
                    if key not in failed:
                        try:
                            values[key].append(field_value(msg, fields[key].field))
                        except ValueError as exc:
                            failed[key] = str(exc)
            break
        except (PerfrosError, Undecodable, ValueError, OSError) as exc:
            bad = next((t for t in topics if str(exc).startswith(f"{t}: ")), None)
            for t in topics if bad is None else (bad,):
                failed.update(dict.fromkeys((k for k in on_topic[t] if k not in failed), str(exc)))
            topics = set() if bad is None else topics - {bad}
    for key, metric in fields.items():
        where = f"{p}: metric {metric.topic}"
        if key in failed:
            warnings.warn(f"{where}: not read: {failed[key]}", PerfrosWarning, stacklevel=2)
        elif not values[key]:
            warnings.warn(f"{where}: no message on the topic", PerfrosWarning, stacklevel=2)
        out[key] = None if key in failed or not values[key] else aggregate(values[key], metric.aggregate)
    return {k: out[k] for k in metrics}
