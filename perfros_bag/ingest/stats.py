"""Per-topic statistics of a recording: the reader contract every format implements.

All readers (ROS 1 bag, rosbag2 sqlite3/mcap, plain MCAP) return a
:class:`RecordingStats`; they need only timestamps and payload sizes, never
deserialisation. Statistics of parts of one recording (chunks) merge exactly with
:meth:`TopicStats.merge`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

#: A measured rate needs at least this many messages ...
RATE_MIN_MESSAGES = 3
#: ... over at least this span (s): two messages microseconds apart are not a rate of 1e5 Hz.
RATE_MIN_SPAN_S = 0.5


@dataclass
class TopicStats:
    """One topic (all its connections merged).

    ``times_ns`` holds every message's receive/log time, sorted (int64): needed for the
    robust rates and for exact merges of partial statistics.
    """

    topic: str
    msgtype: str
    messages: int = 0
    bytes: int = 0  # serialised payload bytes as stored (decompressed)
    times_ns: npt.NDArray[np.int64] = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    publishers: tuple[str, ...] = ()  # ROS 1 callerid where recorded

    @property
    def first_ns(self) -> int | None:
        return int(self.times_ns[0]) if self.times_ns.size else None

    @property
    def last_ns(self) -> int | None:
        return int(self.times_ns[-1]) if self.times_ns.size else None

    @property
    def span_s(self) -> float:
        if self.times_ns.size < 2:
            return 0.0
        return float(int(self.times_ns[-1]) - int(self.times_ns[0])) / 1e9  # no int64 overflow

    @property
    def frequency_hz(self) -> float:
        """(n - 1) / (t_last - t_first); 0 with fewer than 2 messages or a zero span."""
        span = self.span_s
        return (self.messages - 1) / span if self.messages >= 2 and span > 0 else 0.0

    @property
    def rate_note(self) -> str | None:
        """Why :attr:`frequency_hz` is not a rate (fewer than :data:`RATE_MIN_MESSAGES`
        messages, or a span below :data:`RATE_MIN_SPAN_S`), as printed instead of it; None
        when it is one."""
        if self.messages >= RATE_MIN_MESSAGES and self.span_s >= RATE_MIN_SPAN_S:
            return None
        return f"too few messages for a rate ({self.messages} in {self.span_s:.3g} s)"

    @property
    def bandwidth_kBps(self) -> float:
        """Payload bytes / span / 1000; 0 when the span is zero."""
        span = self.span_s
        return self.bytes / span / 1000.0 if span > 0 else 0.0

    @property
    def median_rate_hz(self) -> float:
        """1 / median inter-arrival gap: robust to gaps in the recording."""
        if self.times_ns.size < 2:
            return 0.0
        gaps = np.diff(self.times_ns)
        med = float(np.median(gaps))
        return 1e9 / med if med > 0 else 0.0

    @property
    def p95_gap_s(self) -> float:
        if self.times_ns.size < 2:
            return 0.0
        return float(np.percentile(np.diff(self.times_ns), 95)) / 1e9

    def merge(self, other: TopicStats) -> TopicStats:
        """Exact merge of two parts of the same topic."""
        times = np.sort(np.concatenate([self.times_ns, other.times_ns]), kind="stable")
        pubs = tuple(sorted(set(self.publishers) | set(other.publishers)))
        return TopicStats(self.topic, self.msgtype or other.msgtype, self.messages + other.messages,
                          self.bytes + other.bytes, times, pubs)


@dataclass
class RecordingStats:
    path: Path
    format: str  # "ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap"
    topics: dict[str, TopicStats] = field(default_factory=dict)
    #: how the readers got the numbers: "index" (fast path: index records / one SQL pass),
    #: "stream" (every record walked), "mixed" (files of one rosbag2 recording differ); "" unknown
    method: str = ""

    @property
    def messages(self) -> int:
        return sum(t.messages for t in self.topics.values())

    @property
    def start_ns(self) -> int | None:
        firsts = [t.first_ns for t in self.topics.values() if t.first_ns is not None]
        return min(firsts) if firsts else None

    @property
    def end_ns(self) -> int | None:
        lasts = [t.last_ns for t in self.topics.values() if t.last_ns is not None]
        return max(lasts) if lasts else None
