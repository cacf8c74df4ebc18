"""Split one large recording into tasks over chunk ranges; merge their statistics exactly.

A ROS 1 bag (chunk-info records of its index section) or a plain MCAP file (chunk indexes
of its summary) is planned once: :func:`plan_split` reads only the index, and
:meth:`SplitPlan.parts` groups consecutive chunks into :class:`Part` tasks of about
``target_bytes`` of file each. :func:`read_part` (on a worker) reads its chunks exactly as
the readers' fast path does, from the index records (times) and the record headers
(payload sizes), and returns a partial :class:`RecordingStats` that declares every
topic. :func:`merge_parts` merges the partials with :meth:`TopicStats.merge` (counts and
bytes add, times are merged and sorted, so first/last, frequency and the median rates
come from the merged timestamps): the result equals ``read_recording`` on the whole
file. Each part unmaps the pages it has read (``madvise``), so the resident set stays
small however large the file. A file that cannot be split (another format, no index, a damaged index, too
small) is one ``whole`` part read by ``read_recording``; a part whose index turns out
damaged returns ``None`` and the caller reads the whole file instead, as the readers
fall back to streaming.

:func:`read_split` runs the parts through :func:`perfros_bag.characterisation.distributed.run_distributed`
(in-process, on a Dask scheduler, or on a LocalCluster of N workers).
"""

from __future__ import annotations

import mmap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.errors import InputError
from perfros_bag.ingest import detect_format, mcapfile, read_recording, rosbag1
from perfros_bag.ingest._accum import I64, U8, Accumulator, Damaged, NoIndex, gather_u64, release
from perfros_bag.ingest.rosbag2 import open_mmap
from perfros_bag.ingest.stats import RecordingStats

#: Default amount of file per task (compressed bytes as stored).
TARGET_BYTES = 64 << 20


@dataclass(frozen=True)
class Part:
    """One task: some chunks of one file (``format`` "ros1"/"mcap"), or the ``whole`` file."""

    path: Path
    format: str
    header: tuple[Any, ...] = ()  # ROS 1: ((conn id, Connection), ...); MCAP: (schemas, channels)
    chunks: tuple[Any, ...] = ()  # ROS 1: (chunk_pos, {conn: count}); MCAP: _ChunkIndex
    fast: bool = True

    def __str__(self) -> str:
        if self.format == "whole":
            return str(self.path)
        return f"{self.path} [{len(self.chunks)} chunks]"


@dataclass(frozen=True)
class SplitPlan:
    path: Path
    format: str  # "ros1", "mcap", or "whole" (not splittable)
    header: tuple[Any, ...] = ()
    chunks: tuple[Any, ...] = ()
    sizes: tuple[int, ...] = ()  # bytes of each chunk in the file
    count: int | None = None  # MCAP statistics: messages in the file (cross-check)

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
        if flat != list(range(len(self.chunks))):
            raise ValueError("groups must cover every chunk exactly once")
        return [Part(self.path, self.format, self.header, tuple(self.chunks[i] for i in g))
                for g in groups if g]


def plan_split(path: str | Path, *, fast: bool = True) -> SplitPlan:
    """Read the index of ``path``; a plan with one ``whole`` part when it cannot be split."""
    p = Path(path)
    if not fast or not p.is_file():
        return SplitPlan(p, "whole")
    try:
        fmt = detect_format(p)
        if fmt == "ros1":
            with open_mmap(p) as mm:
                return _plan_ros1(p, mm)
        if fmt == "mcap":
            with open_mmap(p) as mm:
                return _plan_mcap(p, mm)
    except (InputError, NoIndex, Damaged, OSError, ValueError):
        pass  # read_recording gives the user the clear error, or falls back to streaming
    return SplitPlan(p, "whole")


def read_part(part: Part) -> RecordingStats | None:
    """Partial statistics of ``part`` (``None``: its index is damaged, read the whole file)."""
    if part.format == "whole":
        return read_recording(part.path, fast=part.fast)
    reader = _read_ros1 if part.format == "ros1" else _read_mcap
    try:
        with open_mmap(part.path) as mm:
            try:
                return reader(part, mm)
            except (NoIndex, Damaged, ValueError, IndexError):
                pass  # handled here, so no traceback keeps a view of the mmap alive
    except (InputError, OSError):
        pass
    return None


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
    if plan.count is not None and merged.messages != plan.count:
        return read_recording(plan.path)  # the statistics disagree with the indexes
    merged.topics = {name: merged.topics[name] for name in sorted(merged.topics)}
    return merged


def read_split(path: str | Path, *, scheduler: str | None = None, workers: int | None = None,
               target_bytes: int = TARGET_BYTES, progress: bool = False) -> RecordingStats:
    """``read_recording(path)``, its chunk ranges read as parallel tasks."""
    from perfros_bag.characterisation.distributed import run_distributed

    plan = plan_split(path)
    outcomes = run_distributed(plan.parts(target_bytes), read_part, scheduler=scheduler,
                               workers=workers, progress=progress, description="chunks")
    for outcome in outcomes:
        if outcome.error is not None:
            raise outcome.error
    return merge_parts(plan, [o.value for o in outcomes])


# --------------------------------------------------------------------------- ROS 1


def _plan_ros1(path: Path, mm: mmap.mmap) -> SplitPlan:
    # the index section, checked as rosbag1.read_fast checks it
    rosbag1._check_magic(mm)
    size = len(mm)
    index_pos, conn_count, chunk_count = rosbag1._bag_header(mm)
    if index_pos == 0 or index_pos >= size:
        raise NoIndex("no index")
    conns: dict[int, rosbag1.Connection] = {}
    chunks: list[tuple[int, dict[int, int]]] = []
    for rec in rosbag1._records(mm, index_pos, size):
        if rec.op == rosbag1.OP_CONNECTION:
            cid, conn = rosbag1._connection(mm, rec)
            conns[cid] = conn
        elif rec.op == rosbag1.OP_CHUNK_INFO:
            if rosbag1._u32(rec.header, "ver") != 1:
                raise NoIndex("unknown chunk-info version")
            n = rosbag1._u32(rec.header, "count")
            if rec.data_len != 8 * n:
                raise NoIndex("chunk-info record size mismatch")
            pairs = np.frombuffer(mm, dtype="<u4", count=2 * n, offset=rec.data_start).reshape(-1, 2)
            chunks.append((rosbag1._u64(rec.header, "chunk_pos"), {int(c): int(k) for c, k in pairs}))
            del pairs
        else:
            raise NoIndex(f"unexpected record op {rec.op} in the index section")
    if len(conns) != conn_count or len(chunks) != chunk_count:
        raise NoIndex("index section disagrees with the bag header")
    starts = [pos for pos, _ in chunks]
    ends = [*sorted(starts)[1:], index_pos]
    end_of = dict(zip(sorted(starts), ends, strict=True))
    sizes = tuple(max(end_of[s] - s, 1) for s in starts)
    return SplitPlan(path, "ros1", tuple(conns.items()), tuple(chunks), sizes)


def _read_ros1(part: Part, mm: mmap.mmap) -> RecordingStats:
    """rosbag1.read_fast's per-chunk work for this part's chunks."""
    size = len(mm)
    conns = dict(part.header)
    times: dict[int, list[I64]] = {cid: [] for cid in conns}
    nbytes = dict.fromkeys(conns, 0)
    whole: U8 = np.frombuffer(mm, dtype=np.uint8)
    for chunk_pos, expected in part.chunks:
        crec = rosbag1.read_record(mm, chunk_pos, size)
        if crec.op != rosbag1.OP_CHUNK:
            raise NoIndex(f"chunk-info points at a non-chunk record (byte {chunk_pos})")
        compression = crec.header.get("compression", b"").decode("latin-1")
        usize = rosbag1._u32(crec.header, "size")
        if compression == "none":
            if usize != crec.data_len:
                raise NoIndex("uncompressed chunk size mismatch")
            buf, base = whole, crec.data_start
        else:
            raw = rosbag1.decompress_chunk(compression, memoryview(mm)[crec.data_start:crec.end], usize)
            buf, base = np.frombuffer(raw, dtype=np.uint8), 0
        pos = crec.end
        parts: list[tuple[int, I64, I64]] = []
        seen: set[int] = set()
        while len(seen) < len(expected):
            irec = rosbag1.read_record(mm, pos, size)
            if irec.op != rosbag1.OP_INDEX or rosbag1._u32(irec.header, "ver") != 1:
                raise NoIndex(f"missing index-data record after the chunk at byte {chunk_pos}")
            cid, n = rosbag1._u32(irec.header, "conn"), rosbag1._u32(irec.header, "count")
            if cid not in conns or irec.data_len != 12 * n or expected.get(cid) != n or cid in seen:
                raise NoIndex("index-data record disagrees with its chunk info")
            entries = np.frombuffer(mm, dtype=rosbag1._IDX_DT, count=n, offset=irec.data_start)
            t = entries["sec"].astype(np.int64) * 1_000_000_000 + entries["nsec"].astype(np.int64)
            parts.append((cid, t, entries["offset"].astype(np.int64)))
            del entries
            seen.add(cid)
            pos = irec.end
        offs = np.concatenate([p[2] for p in parts]) if parts else np.empty(0, dtype=np.int64)
        dlen = rosbag1._message_sizes(buf, base, offs, usize)
        k = 0
        for cid, t, o in parts:
            times[cid].append(t)
            nbytes[cid] += int(dlen[k:k + o.size].sum())
            k += o.size
        del buf
        release(mm, chunk_pos, pos)
    del whole
    out = Accumulator()
    for cid, conn in conns.items():
        t = np.concatenate(times[cid]) if times[cid] else np.empty(0, dtype=np.int64)
        out.add(conn.topic, conn.msgtype, t, nbytes[cid], conn.callerid)
    out.method = "index"
    return out.build(part.path, "ros1")


# --------------------------------------------------------------------------- MCAP


def _plan_mcap(path: Path, mm: mmap.mmap) -> SplitPlan:
    if mm[:8] != mcapfile.MAGIC:
        raise Damaged("not an MCAP file")
    st = mcapfile._State()
    chunks, count = mcapfile._summary(mm, st)
    if not chunks:
        raise NoIndex("no chunk index")
    sizes = tuple(max(ci.chunk_length + ci.index_length, 1) for ci in chunks)
    return SplitPlan(path, "mcap", (st.schemas, st.channels), tuple(chunks), sizes, count)


def _read_mcap(part: Part, mm: mmap.mmap) -> RecordingStats:
    """mcapfile.read_fast's per-chunk work for this part's chunks (plain MCAP)."""
    schemas, channels = part.header
    st = mcapfile._State(dict(schemas), dict(channels))
    size = len(mm)
    whole: U8 = np.frombuffer(mm, dtype=np.uint8)
    for ci in part.chunks:
        op, start, length = mcapfile._record(mm, ci.chunk_start, size)
        if op != mcapfile.OP_CHUNK:
            raise NoIndex(f"chunk index points at a non-chunk record (byte {ci.chunk_start})")
        compression, rstart, rlen, usize = mcapfile._chunk_records(mm, start, length)
        if usize and not ci.index_offsets:
            raise NoIndex("chunk without message indexes")
        if compression == "":
            buf, base, blen = whole, rstart, rlen
        else:
            raw = mcapfile.decompress(compression, memoryview(mm)[rstart:rstart + rlen], usize)
            buf, base, blen = np.frombuffer(raw, dtype=np.uint8), 0, len(raw)
        chunk_offs: list[I64] = []
        chunk_ends: list[I64] = []
        for cid, ipos in ci.index_offsets.items():
            offs, ends, log_times = _mcap_index(mm, size, buf, base, blen, cid, ipos)
            chunk_offs.append(offs)
            chunk_ends.append(ends)
            nbytes = int((ends - offs).sum()) - (9 + mcapfile.MSG_HEADER) * int(offs.size)
            st.add(cid, log_times, nbytes)
        if len(chunk_offs) > 1:
            o, e = np.concatenate(chunk_offs), np.concatenate(chunk_ends)
            order = np.argsort(o, kind="stable")
            if np.any(o[order][1:] < e[order][:-1]):
                raise NoIndex("indexed message records overlap")
        del buf
        release(mm, ci.chunk_start, ci.chunk_start + ci.chunk_length + ci.index_length)
    del whole
    acc = st.accumulator()
    acc.method = "index"
    return acc.build(part.path, "mcap")


def _mcap_index(mm: mmap.mmap, size: int, buf: U8, base: int, blen: int, cid: int,
                ipos: int) -> tuple[I64, I64, I64]:
    """(offsets, record ends, log times) of one channel's messages in one chunk."""
    op, istart, ilen = mcapfile._record(mm, ipos, size)
    if op != mcapfile.OP_MESSAGE_INDEX:
        raise NoIndex("message-index offset does not point at a message index")
    c = mcapfile._Cursor(mm, istart, istart + ilen)
    if c.u16() != cid:
        raise NoIndex("message index for the wrong channel")
    ppos, plen = c.skip_prefixed()
    if plen % 16:
        raise NoIndex("malformed message index")
    pairs = np.frombuffer(mm, dtype="<u8", count=plen // 8, offset=ppos).reshape(-1, 2).copy()
    offs = pairs[:, 1].astype(np.int64)
    if offs.size and (int(offs.max()) + 9 + mcapfile.MSG_HEADER > blen):
        raise NoIndex("message-index offset outside its chunk")
    if offs.size and not np.all(buf[base + offs] == mcapfile.OP_MESSAGE):
        raise NoIndex("message-index offset does not point at a message")
    lengths = gather_u64(buf, base + offs + 1)
    if offs.size and (int(lengths.min()) < mcapfile.MSG_HEADER
                      or int((offs + 9 + lengths).max()) > blen):
        raise NoIndex("indexed message overruns its chunk")
    chan = buf[base + offs + 9].astype(np.int64) | (buf[base + offs + 10].astype(np.int64) << 8)
    if np.any(chan != cid):
        raise NoIndex("message index points at another channel's message")
    if offs.size and int(pairs[:, 0].max()) >= 2**63:
        raise NoIndex("log time out of range")
    return offs, offs + 9 + lengths, pairs[:, 0].astype(np.int64)
