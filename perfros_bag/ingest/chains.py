"""End-to-end latency along a chain of topics (system.yaml ``chains:``), from the stamps.

A node that processes an input and copies its ``header`` into its output (image_publisher
-> opencv_apps, most perception pipelines) lets the recording follow one input through the
chain: the messages of every topic of the chain that carry the *same* ``header.stamp`` are
the same input. With the stamps of :func:`perfros_bag.ingest.contents.read_stamps`:

* **end to end**: for every message of the LAST topic whose stamp is also the stamp of a
  message on the FIRST topic, its receive/log time minus that stamp;
* **per hop** (consecutive topics ``a -> b``): for every message of ``b`` whose stamp is
  also on ``a``, its log time minus the log time of the (earliest) message of ``a`` with
  that stamp: what the hop adds, as the recorder saw it (both ends timed by the recorder's
  clock, so it includes the difference of the recorder's receive delays).

Each is p50/p95/max (numpy's linear percentiles, as :func:`latency_of`) and how many
messages matched. Stamps 0 (unset) never match. A chain whose first or last topic has no
header, is absent from the recording or shares no stamp gets no end-to-end latency and one
:class:`~perfros_bag.errors.PerfrosWarning` naming the chain and why; a hop likewise (no
extra warning when the end-to-end one already named the cause).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.errors import PerfrosWarning
from perfros_bag.ingest._accum import I64
from perfros_bag.ingest.contents import TopicLatency, latency_of
from perfros_bag.ingest.decode import TopicType
from perfros_bag.ingest.stamps import Stamps
from perfros_bag.system.types import Chain


@dataclass(frozen=True)
class HopLatency:
    src: str
    dst: str
    delays: TopicLatency | None  # None: no message of dst shares a stamp with src

    def to_dict(self) -> dict[str, Any]:
        return {"from": self.src, "to": self.dst, **_delays_dict(self.delays)}


@dataclass(frozen=True)
class ChainLatency:
    """One chain measured in one recording; ``messages``: messages of the last topic with a
    non-zero stamp, ``end_to_end.messages`` how many of them matched the first topic."""

    name: str
    topics: tuple[str, ...]
    messages: int
    end_to_end: TopicLatency | None
    hops: tuple[HopLatency, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "topics": list(self.topics), "messages": self.messages,
                **_delays_dict(self.end_to_end), "hops": [h.to_dict() for h in self.hops]}


def _delays_dict(d: TopicLatency | None) -> dict[str, Any]:
    return {"matched": 0 if d is None else d.messages, "p50_s": None if d is None else d.p50_s,
            "p95_s": None if d is None else d.p95_s, "max_s": None if d is None else d.max_s}


def _first_seen(times: I64, stamps: I64) -> tuple[I64, I64]:
    """(distinct non-zero stamps sorted, the earliest log time of each)."""
    keep = stamps != 0
    t, s = times[keep], stamps[keep]
    order = np.lexsort((t, s))
    s, t = s[order], t[order]
    uniq, first = np.unique(s, return_index=True)
    return uniq, t[first]


def _match(stamps: I64, uniq: I64) -> tuple[np.ndarray, np.ndarray]:
    """(mask of ``stamps`` found in ``uniq`` and non-zero, their index in ``uniq``)."""
    if uniq.size == 0:
        return np.zeros(stamps.shape, dtype=bool), np.zeros(stamps.shape, dtype=np.int64)
    idx = np.minimum(np.searchsorted(uniq, stamps), uniq.size - 1)
    return (uniq[idx] == stamps) & (stamps != 0), idx


def chain_latency(chain: Chain, stamps: Stamps, types: Mapping[str, TopicType],
                  where: str = "") -> ChainLatency:
    """``chain`` measured from a recording's stamps and topic types (see the module)."""
    names = tuple(_recorded(t, types) for t in chain.topics)
    problems = {t: _problem(t, stamps, types) for t in names}
    first, last = names[0], names[-1]
    lt, ls = stamps.get(last, (np.empty(0, np.int64), np.empty(0, np.int64)))
    messages = int(np.count_nonzero(ls))
    e2e: TopicLatency | None = None
    why = problems[first] or problems[last]
    if why is None:
        uniq, _ = _first_seen(*stamps[first])
        hit, _ = _match(ls, uniq)
        e2e = latency_of(lt[hit], ls[hit]) if hit.any() else None
        if e2e is None:
            why = f"no message of {last} carries the header.stamp of a message of {first}"
    if why is not None:
        warnings.warn(f"{where}chain {chain.name!r}: {why}: no end-to-end latency", PerfrosWarning, stacklevel=2)
    hops = []
    for a, b in zip(names, names[1:], strict=False):
        hop_why = problems[a] or problems[b]
        delays = None
        if hop_why is None:
            uniq, t_a = _first_seen(*stamps[a])
            bt, bs = stamps[b]
            hit, idx = _match(bs, uniq)
            delays = latency_of(bt[hit], t_a[idx[hit]]) if hit.any() else None
            if delays is None:
                hop_why = f"no message of {b} carries the header.stamp of a message of {a}"
        if hop_why is not None and hop_why != why:
            warnings.warn(f"{where}chain {chain.name!r}: hop {a} -> {b}: {hop_why}: no hop latency",
                          PerfrosWarning, stacklevel=2)
        hops.append(HopLatency(a, b, delays))
    return ChainLatency(chain.name, chain.topics, messages, e2e, tuple(hops))


def _recorded(topic: str, types: Mapping[str, TopicType]) -> str:
    """The recording's name for a system topic (a leading ``/`` may differ)."""
    alt = topic[1:] if topic.startswith("/") else "/" + topic
    return alt if topic not in types and alt in types else topic


def _problem(topic: str, stamps: Stamps, types: Mapping[str, TopicType]) -> str | None:
    tt = types.get(topic)
    if tt is None:
        return f"{topic} is not in the recording"
    if not tt.stamped:
        return f"{topic} has no std_msgs/Header ({tt.msgtype or 'type unknown'})"
    t, s = stamps.get(topic, (np.empty(0, np.int64), np.empty(0, np.int64)))
    if not np.count_nonzero(s):
        return f"{topic} has no message with a non-zero header.stamp"
    return None


def chain_latencies(chains: Sequence[Chain], read: tuple[Stamps, Mapping[str, TopicType]] | None,
                    where: str = "") -> list[ChainLatency]:
    """Every chain from one reading of the stamps (:func:`read_contents_stamps`); ``read``
    None (the recording's contents could not be read, already a warning): every chain empty."""
    if read is None:
        return [ChainLatency(c.name, c.topics, 0, None,
                             tuple(HopLatency(a, b, None) for a, b in zip(c.topics, c.topics[1:], strict=False)))
                for c in chains]
    return [chain_latency(c, read[0], read[1], where) for c in chains]


def read_chain_latencies(path: str | Path, chains: Sequence[Chain]) -> list[ChainLatency]:
    """Every chain measured in the recording at ``path`` (the stamps read once); a recording
    whose contents cannot be read is one warning and every chain empty."""
    from perfros_bag.ingest.contents import read_contents_stamps

    return chain_latencies(chains, read_contents_stamps(path), where=f"{path}: ")
