"""Helpers shared by the readers: a per-topic accumulator and little-endian gathers.

Readers feed :class:`Accumulator` with arrays of receive times and payload byte totals per
connection/channel; :meth:`Accumulator.build` merges connections of one topic and sorts the
times once, giving the :class:`~perfros_bag.ingest.stats.RecordingStats` contract.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from perfros_bag.ingest.stats import RecordingStats, TopicStats

I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

#: Streaming readers release the mapped pages behind them every this many bytes.
RELEASE_STEP = 16 << 20


def release(mm: mmap.mmap, start: int, end: int) -> None:
    """Unmap the pages of ``[start, end)`` that this process touched (they stay in the page
    cache). Without it the resident set of a reader walking one mmap of a 2 GB file grows
    to the file's size, though nothing is copied: RSS counts mapped page-cache pages.
    Harmless for correctness: a page touched again is mapped again from the page cache."""
    lo = max(start, 0) - max(start, 0) % mmap.PAGESIZE
    hi = min(end, len(mm))
    if hi > lo and hasattr(mm, "madvise"):  # no madvise on Windows
        mm.madvise(mmap.MADV_DONTNEED, lo, hi - lo)


def release_behind(mm: mmap.mmap, released: int, pos: int, reached: int | None = None) -> int:
    """A streaming reader's step: once it has ``reached`` (default ``pos``) :data:`RELEASE_STEP`
    bytes past the last release mark ``released``, :func:`release` the pages from the mark to
    the page boundary at or below ``pos``; returns the new mark."""
    if (pos if reached is None else reached) - released < RELEASE_STEP:
        return released
    cut = pos - pos % mmap.PAGESIZE
    release(mm, released, cut)
    return cut


def close_mmap(mm: mmap.mmap) -> None:
    """Close ``mm``; if a numpy view of it is still referenced (on a Dask worker the
    statistical profiler can hold a reader's finished frame for a moment), leave the
    mapping to be freed with the last view instead of failing a read that succeeded."""
    try:
        mm.close()
    except BufferError:
        pass


class Damaged(Exception):  # noqa: N818 - internal signal, never escapes read_recording
    """The file's structure is inconsistent; the caller turns it into an InputError or falls back."""


class NoIndex(Exception):  # noqa: N818
    """The fast path cannot be used (index missing or inconsistent): stream instead."""


def describe(exc: BaseException) -> str:
    """One line for a failure while parsing a recording."""
    if isinstance(exc, Damaged):
        return f"corrupt or truncated recording: {exc}"
    if isinstance(exc, MemoryError):
        return "corrupt recording (implausible sizes: out of memory)"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"corrupt or unreadable recording ({type(exc).__name__}{': ' + text if text else ''})"


def zstd_header_size(head: bytes | None) -> int:
    """Decompressed size of a zstd frame as its header (the first bytes) states it; -1 when
    the header does not say or cannot be read."""
    import zstandard

    if head is None or len(head) < 6:
        return -1
    try:
        return int(zstandard.frame_content_size(bytes(head[:18])))
    except zstandard.ZstdError:
        return -1


def zstd_size(frame: bytes) -> int:
    """Decompressed size of one zstd frame: from its header, else by decompressing it."""
    import zstandard

    size = zstd_header_size(frame)
    if size < 0:
        size = len(zstandard.ZstdDecompressor().decompressobj().decompress(frame))
    return int(size)


def gather_u32(buf: U8, pos: I64) -> I64:
    """Little-endian uint32 at every byte position ``pos`` of ``buf`` (vectorised, unaligned):
    rows of a strided 4-byte window view, no index matrix."""
    if pos.size == 0:
        return np.empty(0, dtype=np.int64)
    if int(pos.min()) < 0 or int(pos.max()) + 4 > buf.size:
        raise Damaged("record offset outside its chunk")
    rows = np.lib.stride_tricks.sliding_window_view(buf, 4)[pos]
    return rows.view("<u4").reshape(-1).astype(np.int64)


def gather_u64(buf: U8, pos: I64) -> I64:
    if pos.size == 0:
        return np.empty(0, dtype=np.int64)
    if int(pos.min()) < 0 or int(pos.max()) + 8 > buf.size:
        raise Damaged("record offset outside its chunk")
    vals = np.lib.stride_tricks.sliding_window_view(buf, 8)[pos].view("<i8").reshape(-1)
    if vals.size and not (0 <= int(vals.min()) and int(vals.max()) < 2**62):
        raise Damaged("implausible record length")
    return vals


# --------------------------------------------------------------------------- accumulator


@dataclass
class _Topic:
    msgtype: str
    times: list[I64] = field(default_factory=list)
    nbytes: int = 0
    publishers: set[str] = field(default_factory=set)


class Accumulator:
    """Collects per-topic times and byte totals; connections of one topic merge."""

    def __init__(self) -> None:
        self._topics: dict[str, _Topic] = {}
        #: how the numbers were read: "index" (fast path) or "stream"; "mixed" across files
        self.method = "stream"
        self._files = 0  # how many per-file accumulators were merged in by extend()
        #: topic -> (receive/log times, header stamps) parts, when a reader was asked for stamps
        self._stamps: dict[str, list[tuple[I64, I64]]] = {}

    @property
    def messages(self) -> int:
        """Messages added so far."""
        return sum(int(a.size) for t in self._topics.values() for a in t.times)

    def declare(self, topic: str, msgtype: str, publisher: str | None = None) -> None:
        t = self._topics.get(topic)
        if t is None:
            t = self._topics[topic] = _Topic(msgtype)
        elif not t.msgtype:
            t.msgtype = msgtype
        if publisher:
            t.publishers.add(publisher)

    def add(self, topic: str, msgtype: str, times: I64, nbytes: int,
            publisher: str | None = None) -> None:
        self.declare(topic, msgtype, publisher)
        t = self._topics[topic]
        if times.size:
            t.times.append(np.asarray(times, dtype=np.int64))
        t.nbytes += int(nbytes)

    def add_stamps(self, topic: str, times: I64, stamps: I64) -> None:
        """Header stamps of some of ``topic``'s messages (one per receive time, file order)."""
        self._stamps.setdefault(topic, []).append((times, stamps))

    def stamps(self) -> dict[str, tuple[I64, I64]]:
        """topic -> (receive/log times ns, header stamps ns) of every message whose stamp was
        read, in file order (the ``Stamps`` of :mod:`perfros_bag.ingest.stamps`)."""
        return {topic: (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))
                for topic, parts in self._stamps.items()}

    def extend(self, other: Accumulator) -> None:
        """Add every topic of ``other`` (another file of the same recording)."""
        if self._files == 0:
            self.method = other.method
        elif self.method != other.method:
            self.method = "mixed"
        self._files += 1
        for name, t in other._topics.items():
            self.declare(name, t.msgtype)
            mine = self._topics[name]
            mine.times.extend(t.times)
            mine.nbytes += t.nbytes
            mine.publishers |= t.publishers
        for name, parts in other._stamps.items():
            self._stamps.setdefault(name, []).extend(parts)

    def build(self, path: Path, fmt: str) -> RecordingStats:
        topics: dict[str, TopicStats] = {}
        for name in sorted(self._topics):
            t = self._topics[name]
            times = (np.concatenate(t.times) if len(t.times) > 1
                     else t.times[0] if t.times else np.empty(0, dtype=np.int64))
            times = np.sort(times, kind="stable")
            topics[name] = TopicStats(name, t.msgtype, int(times.size), t.nbytes, times,
                                      tuple(sorted(t.publishers)))
        return RecordingStats(path, fmt, topics, self.method)
