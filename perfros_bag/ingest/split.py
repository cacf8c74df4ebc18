"""Split one large recording into tasks over chunk ranges; merge their statistics exactly.

A ROS 1 bag or a plain MCAP file is planned once: :func:`plan_split` reads only its index
(:func:`rosbag1.read_index <perfros_bag.ingest.rosbag1.read_index>`,
:func:`mcapfile.read_summary <perfros_bag.ingest.mcapfile.read_summary>`), and
:meth:`SplitPlan.parts` groups consecutive chunks into :class:`Part` tasks of about
``target_bytes`` of file each, each carrying the index restricted to its chunks.
:func:`read_part` (on a worker) reads them with the format's ``read_chunks``, the very
function the whole-file fast path runs over all chunks, and returns a partial
:class:`RecordingStats` that declares every topic. :func:`merge_parts` merges the partials
with :meth:`TopicStats.merge` (counts and bytes add, times are merged and sorted, so
first/last, frequency and the median rates come from the merged timestamps): the result
equals ``read_recording`` on the whole file. Each part unmaps the pages it has read
(``madvise``), so the resident set stays small however large the file. A file that cannot
be split (another format, no index, a damaged index, no chunks) is one ``whole`` part read
by ``read_recording``; a part whose index turns out damaged returns ``None`` and the caller
reads the whole file instead, as the readers fall back to streaming.

Header stamps (``characterise --latency`` on Dask): :func:`read_part_stamps` gathers each
part's stamps in the same pass (the readers' ``stamps`` argument), :func:`merge_stamps`
concatenates them in chunk order, so the latencies
(:func:`perfros_bag.ingest.contents.latencies`: p50/p95 need the whole sample) come from
every stamped message of the file, exactly as from the whole file.

The parts run as tasks wherever the caller runs them: :mod:`perfros_bag.characterisation.cluster`
(``read_split``, ``characterise --workers``) hands them to its task runner (in-process, a
Dask scheduler or a LocalCluster of N workers); this module imports no runner.
"""

from __future__ import annotations

import mmap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from perfros_bag.errors import InputError
from perfros_bag.ingest import detect_format, mcapfile, read_recording, rosbag1
from perfros_bag.ingest._accum import I64, Accumulator, Damaged, NoIndex
from perfros_bag.ingest._payload import StampAt
from perfros_bag.ingest.rosbag2 import open_mmap
from perfros_bag.ingest.stats import RecordingStats

if TYPE_CHECKING:
    from perfros_bag.ingest.decode import TopicType

#: topic -> (receive/log times ns, header stamps ns): :data:`perfros_bag.ingest.stamps.Stamps`
Stamps = dict[str, tuple[I64, I64]]

#: Default amount of file per task (compressed bytes as stored).
TARGET_BYTES = 64 << 20

#: A container's index: a ROS 1 bag's index section or an MCAP file's summary.
Index = rosbag1.BagIndex | mcapfile.Summary
#: One chunk's entry in an :data:`Index`.
Chunk = rosbag1.ChunkInfo | mcapfile.ChunkIndex


@dataclass(frozen=True)
class _Indexed:
    """A file (``format`` "ros1"/"mcap", or "whole": read as one) and, when it is split, an
    index (of the whole file, or restricted to one part's chunks)."""

    path: Path
    format: str
    index: Index | None = None

    @property
    def chunks(self) -> tuple[Chunk, ...]:
        return chunks_of(self.index) if self.index is not None else ()


@dataclass(frozen=True)
class Part(_Indexed):
    """One task: the chunks of one file (``index`` is the file's index restricted to
    them), or the ``whole`` file."""

    def __str__(self) -> str:
        if self.format == "whole":
            return str(self.path)
        return f"{self.path} [{len(self.chunks)} chunks]"


@dataclass(frozen=True)
class SplitPlan(_Indexed):
    """How one file is split: its format ("ros1", "mcap", or "whole": not splittable) and,
    when splittable, its index."""

    @property
    def sizes(self) -> tuple[int, ...]:
        """Bytes of file each chunk takes (with its index records)."""
        return self.index.chunk_sizes() if self.index is not None else ()

    def parts(self, target_bytes: int = TARGET_BYTES) -> list[Part]:
        """Consecutive chunks grouped into parts of about ``target_bytes`` each."""
        if self.format == "whole" or not self.chunks:
            return [Part(self.path, "whole")]
        groups: list[list[int]] = [[]]
        size = 0
        for i, n in enumerate(self.sizes):
            if groups[-1] and size + n > target_bytes:
                groups.append([])
                size = 0
            groups[-1].append(i)
            size += n
        return self.parts_of(groups)

    def parts_of(self, groups: Sequence[Sequence[int]]) -> list[Part]:
        """Parts for any grouping of chunk numbers (each chunk in exactly one group)."""
        flat = sorted(i for g in groups for i in g)
        if self.index is None or flat != list(range(len(self.chunks))):
            raise ValueError("groups must cover every chunk exactly once")
        index = self.index
        return [Part(self.path, self.format, index.select(g)) for g in groups if g]


def chunks_of(index: Index) -> tuple[Chunk, ...]:
    """The chunk entries of ``index``, in file order as recorded."""
    return index.chunks if isinstance(index, rosbag1.BagIndex) else index.chunk_indexes


def plan_split(path: str | Path) -> SplitPlan:
    """Read the index of ``path``; a plan with one ``whole`` part when it cannot be split
    (the fast path's split: a caller that streams reads the whole file itself)."""
    p = Path(path)
    if not p.is_file():
        return SplitPlan(p, "whole")
    try:
        fmt = detect_format(p)
        if fmt in ("ros1", "mcap"):
            with open_mmap(p) as mm:
                index: Index = rosbag1.read_index(mm) if fmt == "ros1" else mcapfile.read_summary(mm)
            if chunks_of(index):
                return SplitPlan(p, fmt, index)
    except (InputError, NoIndex, Damaged, OSError, ValueError):
        pass  # read_recording gives the user the clear error, or falls back to streaming
    return SplitPlan(p, "whole")


def read_part(part: Part) -> RecordingStats | None:
    """Partial statistics of ``part`` (``None``: its index is damaged, read the whole file)."""
    if part.format == "whole" or part.index is None:
        return read_recording(part.path)
    try:
        with open_mmap(part.path) as mm:
            try:
                return _read_chunks(mm, part.index).build(part.path, part.format)
            except (NoIndex, Damaged, ValueError, IndexError):
                pass  # handled here, so no traceback keeps a view of the mmap alive
    except (InputError, OSError):
        pass
    return None


def read_part_stamps(part: Part) -> tuple[RecordingStats, Stamps, dict[str, TopicType]] | None:
    """:func:`read_part` and, in the same pass, the header stamps of the part's messages and
    every topic's type (:class:`perfros_bag.ingest.stamps.Finder`, from the index's own
    definitions). ``None``: a ``whole`` part, a damaged index, or stamps that cannot be read
    in place: read the whole file instead."""
    if part.format == "whole" or part.index is None:
        return None
    from perfros_bag.ingest.stamps import Finder

    finder = Finder()
    try:
        with open_mmap(part.path) as mm:
            try:
                acc = _read_chunks(mm, part.index, finder(part.index))
                return acc.build(part.path, part.format), finder.stamps(acc), finder.types
            except (NoIndex, Damaged, ValueError, IndexError):
                pass  # handled here, so no traceback keeps a view of the mmap alive
    except (InputError, OSError):
        pass
    return None


def merge_stamps(parts: Sequence[Stamps]) -> Stamps:
    """The parts' stamps, concatenated per topic in part order (the whole file's order)."""
    import numpy as np

    topics = {topic for part in parts for topic in part}
    return {topic: (np.concatenate([p[topic][0] for p in parts if topic in p]),
                    np.concatenate([p[topic][1] for p in parts if topic in p])) for topic in sorted(topics)}


def _read_chunks(mm: mmap.mmap, index: Index, stamps: Mapping[int, StampAt] | None = None) -> Accumulator:
    if isinstance(index, rosbag1.BagIndex):
        return rosbag1.read_chunks(mm, index, stamps)
    return mcapfile.read_chunks(mm, index, None, stamps)  # payload compression: as the summary says


def merge_parts(plan: SplitPlan, parts: Sequence[RecordingStats | None]) -> RecordingStats:
    """Exact merge of the parts' statistics (``read_recording`` when a part is missing)."""
    if plan.format == "whole" or not parts or any(p is None for p in parts):
        return read_recording(plan.path)
    done = [p for p in parts if p is not None]
    merged = RecordingStats(plan.path, plan.format, dict(done[0].topics), "index")
    for part in done[1:]:
        for name, ts in part.topics.items():
            mine = merged.topics.get(name)
            merged.topics[name] = ts if mine is None else mine.merge(ts)
    if isinstance(plan.index, mcapfile.Summary):
        try:
            plan.index.check_message_count(merged.messages)
        except NoIndex:
            return read_recording(plan.path)  # the statistics disagree with the indexes
    merged.topics = {name: merged.topics[name] for name in sorted(merged.topics)}
    return merged
