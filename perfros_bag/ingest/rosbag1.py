"""ROS 1 bag (format 2.0) reader: per-topic counts, times and payload bytes, no deserialisation.

Record layout (http://wiki.ros.org/Bags/Format/2.0): ``u32 header_len, header fields
(u32 len + "name=value"), u32 data_len, data``. The bag header points at the index section
(connection records + one chunk-info record per chunk); each chunk record is followed by one
index-data record per connection with ``(time, offset)`` for every message of that connection
in the chunk, the offset being the message data record's position in the *uncompressed* chunk.

* fast path: connections and chunk infos from the index section (:func:`read_index`, a
  :class:`BagIndex`), counts and times from the index-data records (:func:`read_chunks`, for
  any subset of the chunks: the whole file reads them all, a split task some); the payload
  size of each message is its data record's ``data_len``, gathered (numpy) at the indexed
  offsets: for an uncompressed chunk straight from the mmapped file (touching one page per
  message), for a bz2/lz4 chunk after decompressing it.
* streaming path: walk every record from the start (also for unindexed bags, e.g. from a
  recorder that was killed): connection and message data records, inside chunks too.
"""

from __future__ import annotations

import bz2
import mmap
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from perfros_bag.ingest._accum import I64, U8, Accumulator, Damaged, NoIndex, gather_u32, release, release_behind
from perfros_bag.ingest._payload import StampAt, payload_stamps
from perfros_bag.ingest.stats import RecordingStats

MAGIC = b"#ROSBAG V2.0\n"
OP_MSG, OP_BAG_HEADER, OP_INDEX, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7
_U32 = struct.Struct("<I")
INDEX_ENTRY_DT = np.dtype([("sec", "<u4"), ("nsec", "<u4"), ("offset", "<u4")])


@dataclass
class Record:
    op: int
    header: dict[str, bytes]
    data_start: int
    data_len: int
    end: int


@dataclass(frozen=True)
class Connection:
    """A connection record: the topic, its message type, the publishing node and the
    message definition it recorded (what :mod:`perfros_bag.ingest.stamps` parses)."""

    topic: str
    msgtype: str
    callerid: str
    msgdef: str = field(default="", compare=False, repr=False)


@dataclass(frozen=True)
class ChunkInfo:
    """A chunk-info record of the index section: where its chunk record starts and how many
    messages of each connection (by id) the chunk holds."""

    chunk_pos: int
    connection_counts: Mapping[int, int]


@dataclass(frozen=True)
class BagIndex:
    """The index section of a bag: connections by id and the chunk infos, in file order as
    recorded, and the position of the index section (the end of the chunk area)."""

    connections: Mapping[int, Connection]
    chunks: tuple[ChunkInfo, ...]
    index_pos: int

    def chunk_sizes(self) -> tuple[int, ...]:
        """Bytes of file each chunk takes with its index-data records (to the next chunk or
        the index section; at least 1)."""
        starts = sorted(c.chunk_pos for c in self.chunks)
        end_of = dict(zip(starts, [*starts[1:], self.index_pos], strict=True))
        return tuple(max(end_of[c.chunk_pos] - c.chunk_pos, 1) for c in self.chunks)

    def select(self, positions: Sequence[int]) -> BagIndex:
        """This index restricted to the chunks at ``positions`` (what :func:`read_chunks` reads)."""
        return replace(self, chunks=tuple(self.chunks[i] for i in positions))


@dataclass
class _ConnAcc:
    times: list[I64] = field(default_factory=list)
    nbytes: int = 0


def parse_fields(buf: bytes | memoryview | mmap.mmap, start: int, end: int) -> dict[str, bytes]:
    """Header fields between ``start`` and ``end``: ``u32 len`` + ``name=value`` each."""
    fields: dict[str, bytes] = {}
    pos = start
    while pos < end:
        if pos + 4 > end:
            raise Damaged(f"header field length cut at byte {pos}")
        (n,) = _U32.unpack_from(buf, pos)
        pos += 4
        if pos + n > end:
            raise Damaged(f"header field overruns its header at byte {pos}")
        raw = bytes(buf[pos:pos + n])
        eq = raw.find(b"=")
        if eq < 0:
            raise Damaged(f"header field without '=' at byte {pos}")
        fields[raw[:eq].decode("latin-1")] = raw[eq + 1:]
        pos += n
    return fields


def read_record(buf: bytes | memoryview | mmap.mmap, pos: int, end: int) -> Record:
    if pos + 4 > end:
        raise Damaged(f"truncated record header at byte {pos}")
    (hlen,) = _U32.unpack_from(buf, pos)
    hstart = pos + 4
    if hstart + hlen + 4 > end:
        raise Damaged(f"truncated record at byte {pos} (header of {hlen} bytes)")
    header = parse_fields(buf, hstart, hstart + hlen)
    (dlen,) = _U32.unpack_from(buf, hstart + hlen)
    dstart = hstart + hlen + 4
    if dstart + dlen > end:
        raise Damaged(f"truncated record at byte {pos} (data of {dlen} bytes)")
    op = header.get("op")
    if op is None or len(op) != 1:
        raise Damaged(f"record without op code at byte {pos}")
    return Record(op[0], header, dstart, dlen, dstart + dlen)


def _u32(h: dict[str, bytes], key: str) -> int:
    v = h.get(key)
    if v is None or len(v) != 4:
        raise Damaged(f"record field {key!r} missing or malformed")
    return int(_U32.unpack(v)[0])


def _u64(h: dict[str, bytes], key: str) -> int:
    v = h.get(key)
    if v is None or len(v) != 8:
        raise Damaged(f"record field {key!r} missing or malformed")
    return int(struct.unpack("<Q", v)[0])


def _time(h: dict[str, bytes], key: str = "time") -> int:
    v = h.get(key)
    if v is None or len(v) != 8:
        raise Damaged(f"record field {key!r} missing or malformed")
    sec, nsec = struct.unpack("<II", v)
    return int(sec) * 1_000_000_000 + int(nsec)


def _connection(buf: bytes | memoryview | mmap.mmap, rec: Record) -> tuple[int, Connection]:
    cid = _u32(rec.header, "conn")
    topic = rec.header.get("topic", b"").decode("utf-8", "replace")
    fields = parse_fields(buf, rec.data_start, rec.data_start + rec.data_len)
    msgtype = fields.get("type", b"").decode("utf-8", "replace")
    callerid = fields.get("callerid", b"").decode("utf-8", "replace")
    msgdef = fields.get("message_definition", b"").decode("utf-8", "replace")
    return cid, Connection(topic or fields.get("topic", b"").decode("utf-8", "replace"),
                           msgtype, callerid, msgdef)


def decompress_chunk(compression: str, data: bytes | memoryview, size: int) -> bytes:
    if compression == "none":
        out = bytes(data)
    elif compression == "bz2":
        out = bz2.decompress(data)
    elif compression == "lz4":
        import lz4.frame

        out = lz4.frame.decompress(bytes(data))
    else:
        raise Damaged(f"unknown chunk compression {compression!r}")
    if len(out) != size:
        raise Damaged(f"chunk decompressed to {len(out)} bytes, header says {size}")
    return out


def _check_magic(mm: mmap.mmap) -> None:
    if mm[:len(MAGIC)] != MAGIC:
        head = bytes(mm[:13])
        if head.startswith(b"#ROSBAG V"):
            raise Damaged(f"unsupported bag format {head.decode('latin-1').strip()!r} (only 2.0)")
        raise Damaged("not a ROS 1 bag (no '#ROSBAG V2.0' magic)")


def _bag_header(mm: mmap.mmap) -> tuple[int, int, int]:
    rec = read_record(mm, len(MAGIC), len(mm))
    if rec.op != OP_BAG_HEADER:
        raise Damaged("first record is not a bag header")
    return _u64(rec.header, "index_pos"), _u32(rec.header, "conn_count"), _u32(rec.header, "chunk_count")


def _records(buf: bytes | memoryview | mmap.mmap, pos: int, end: int) -> Iterator[Record]:
    while pos < end:
        rec = read_record(buf, pos, end)
        yield rec
        pos = rec.end


def message_records(buf: U8, base: int, offs: I64, usize: int) -> tuple[I64, I64]:
    """(``header_len``, ``data_len``) of the message data records at chunk offsets ``offs``
    (vectorised); a record's data starts at ``offs + 8 + header_len``.

    The records must lie inside the chunk and must not overlap: a damaged index fails here
    rather than giving wrong byte totals.
    """
    if offs.size == 0:
        return offs, offs
    if int(offs.min()) < 0 or int(offs.max()) + 8 > usize:
        raise NoIndex("index offset outside its chunk")
    hlen = gather_u32(buf, base + offs)
    if int(hlen.max()) + int(offs.max()) + 8 > usize:
        raise NoIndex("indexed record header overruns its chunk")
    dlen = gather_u32(buf, base + offs + 4 + hlen)
    ends = offs + 8 + hlen + dlen
    order = np.argsort(offs, kind="stable")
    if int(ends.max()) > usize or np.any(offs[order][1:] < ends[order][:-1]):
        raise NoIndex("indexed message records overlap or overrun their chunk")
    return hlen, dlen


def read_index(mm: mmap.mmap) -> BagIndex:
    """The index section of the bag in ``mm``, checked against the bag header.

    Raises :class:`NoIndex` when the bag has no usable index (not closed cleanly, or the
    index disagrees with the header) and :class:`Damaged` when it is not a readable bag.
    """
    _check_magic(mm)
    size = len(mm)
    index_pos, conn_count, chunk_count = _bag_header(mm)
    if index_pos == 0:
        raise NoIndex("bag has no index (not closed cleanly)")
    if index_pos > size:
        raise NoIndex("index position beyond the end of the file (truncated?)")
    conns: dict[int, Connection] = {}
    chunks: list[ChunkInfo] = []
    for rec in _records(mm, index_pos, size):
        if rec.op == OP_CONNECTION:
            cid, conn = _connection(mm, rec)
            conns[cid] = conn
        elif rec.op == OP_CHUNK_INFO:
            if _u32(rec.header, "ver") != 1:
                raise NoIndex("unknown chunk-info version")
            n = _u32(rec.header, "count")
            if rec.data_len != 8 * n:
                raise NoIndex("chunk-info record size mismatch")
            pairs = np.frombuffer(mm, dtype="<u4", count=2 * n, offset=rec.data_start).reshape(-1, 2)
            chunks.append(ChunkInfo(_u64(rec.header, "chunk_pos"),
                                    {int(c): int(k) for c, k in pairs.tolist()}))
            del pairs  # no view of the mmap outlives the loop
        else:
            raise NoIndex(f"unexpected record op {rec.op} in the index section")
    if len(conns) != conn_count or len(chunks) != chunk_count:
        raise NoIndex("index section disagrees with the bag header")
    return BagIndex(conns, tuple(chunks), index_pos)


@dataclass
class LoadedChunk:
    """One indexed chunk, ready to gather from: its records are at ``base + offset`` in
    ``buf`` (the mmapped file for an uncompressed chunk, else the decompressed bytes), and
    ``records`` holds ``(connection, receive times ns, offsets)`` of each of its index-data
    records; ``end`` is the file position after them."""

    buf: U8
    base: int
    usize: int
    end: int
    records: list[tuple[int, I64, I64]]


def load_chunk(mm: mmap.mmap, whole: U8, info: ChunkInfo, connections: Mapping[int, Connection]) -> LoadedChunk:
    """The chunk of ``info`` (``whole``: the mmap as bytes) with its index-data records,
    every one checked against the chunk info (version 1, one per connection it counts,
    its count, its size). Raises :class:`NoIndex` when they disagree."""
    size = len(mm)
    chunk_pos, expected = info.chunk_pos, info.connection_counts
    crec = read_record(mm, chunk_pos, size)
    if crec.op != OP_CHUNK:
        raise NoIndex(f"chunk-info points at a non-chunk record (byte {chunk_pos})")
    compression = crec.header.get("compression", b"").decode("latin-1")
    usize = _u32(crec.header, "size")
    if compression == "none":
        if usize != crec.data_len:
            raise NoIndex("uncompressed chunk size mismatch")
        buf, base = whole, crec.data_start
    else:
        raw = decompress_chunk(compression, memoryview(mm)[crec.data_start:crec.end], usize)
        buf, base = np.frombuffer(raw, dtype=np.uint8), 0
    pos = crec.end
    records: list[tuple[int, I64, I64]] = []
    seen: set[int] = set()
    while len(seen) < len(expected):
        irec = read_record(mm, pos, size)
        if irec.op != OP_INDEX or _u32(irec.header, "ver") != 1:
            raise NoIndex(f"missing index-data record after the chunk at byte {chunk_pos}")
        cid, n = _u32(irec.header, "conn"), _u32(irec.header, "count")
        if cid not in connections or irec.data_len != 12 * n or expected.get(cid) != n or cid in seen:
            raise NoIndex("index-data record disagrees with its chunk info")
        entries = np.frombuffer(mm, dtype=INDEX_ENTRY_DT, count=n, offset=irec.data_start)
        times = entries["sec"].astype(np.int64) * 1_000_000_000 + entries["nsec"].astype(np.int64)
        records.append((cid, times, entries["offset"].astype(np.int64)))
        del entries
        seen.add(cid)
        pos = irec.end
    return LoadedChunk(buf, base, usize, pos, records)


def read_chunks(mm: mmap.mmap, index: BagIndex, stamps: Mapping[int, StampAt] | None = None) -> Accumulator:
    """Counts, times and payload bytes of the messages in ``index.chunks`` (every connection
    of the index declared), from their index-data records; method "index". ``stamps``: the
    connections whose ``header.stamp`` to read too, in the same pass (the accumulator's
    :meth:`~perfros_bag.ingest._accum.Accumulator.stamps`).

    The whole-file fast path reads all chunks, a split task some of them
    (:meth:`BagIndex.select`). Raises :class:`NoIndex` when an index-data record
    disagrees with its chunk (the caller streams instead).
    """
    accs: dict[int, _ConnAcc] = {cid: _ConnAcc() for cid in index.connections}
    out = Accumulator()
    whole: U8 = np.frombuffer(mm, dtype=np.uint8)
    for info in index.chunks:
        chunk = load_chunk(mm, whole, info, index.connections)
        parts = chunk.records
        offs = np.concatenate([p[2] for p in parts]) if parts else np.empty(0, dtype=np.int64)
        hlen, dlen = message_records(chunk.buf, chunk.base, offs, chunk.usize)
        k = 0
        for cid, times, o in parts:
            acc = accs[cid]
            acc.times.append(times)
            acc.nbytes += int(dlen[k:k + o.size].sum())
            at = stamps.get(cid) if stamps else None
            if at is not None and o.size:
                data = offs[k:k + o.size] + 8 + hlen[k:k + o.size]
                out.add_stamps(at.topic, times, payload_stamps(chunk.buf, chunk.base + data, dlen[k:k + o.size], at))
            k += o.size
        end = chunk.end
        del chunk, parts
        release(mm, info.chunk_pos, end)  # keep the resident set small however large the file
    del whole
    for cid, conn in index.connections.items():
        acc = accs[cid]
        times = np.concatenate(acc.times) if acc.times else np.empty(0, dtype=np.int64)
        out.add(conn.topic, conn.msgtype, times, acc.nbytes, conn.callerid)
    out.method = "index"
    return out


def read_fast(path: Path, mm: mmap.mmap) -> RecordingStats:
    """The whole bag from its index: :func:`read_chunks` over every chunk of :func:`read_index`."""
    return read_chunks(mm, read_index(mm)).build(path, "ros1")


def _scan_chunk(raw: bytes, conns: dict[int, Connection], times: dict[int, list[int]],
                nbytes: dict[int, int]) -> None:
    """The records of one decompressed chunk, with the header fields of message records read
    in place (no dict per record): the streaming path's inner loop."""
    end = len(raw)
    unpack_u32 = _U32.unpack_from
    pos = 0
    while pos < end:
        if pos + 4 > end:
            raise Damaged(f"truncated record header at chunk byte {pos}")
        (hlen,) = unpack_u32(raw, pos)
        hstart, hend = pos + 4, pos + 4 + hlen
        if hend + 4 > end:
            raise Damaged(f"truncated record at chunk byte {pos}")
        (dlen,) = unpack_u32(raw, hend)
        if hend + 4 + dlen > end:
            raise Damaged(f"truncated record at chunk byte {pos} (data of {dlen} bytes)")
        op = conn = stamp = None
        f = hstart
        while f < hend:  # fields: u32 length + name=value
            if f + 4 > hend:
                raise Damaged(f"header field length cut at chunk byte {f}")
            (flen,) = unpack_u32(raw, f)
            f += 4
            if f + flen > hend:
                raise Damaged(f"header field overruns its header at chunk byte {f}")
            eq = raw.find(b"=", f, f + flen)
            if eq < 0:
                raise Damaged(f"header field without '=' at chunk byte {f}")
            name = raw[f:eq]
            if name == b"op":
                op = raw[eq + 1:f + flen]
            elif name == b"conn":
                conn = raw[eq + 1:f + flen]
            elif name == b"time":
                stamp = raw[eq + 1:f + flen]
            f += flen
        if op is None or len(op) != 1:
            raise Damaged(f"record without op code at chunk byte {pos}")
        if op[0] == OP_MSG:
            if conn is None or len(conn) != 4 or stamp is None or len(stamp) != 8:
                raise Damaged(f"message record without conn/time at chunk byte {pos}")
            cid = unpack_u32(conn)[0]
            sec, nsec = struct.unpack("<II", stamp)
            lst = times.get(cid)
            if lst is None:
                lst = times[cid] = []
            lst.append(sec * 1_000_000_000 + nsec)
            nbytes[cid] = nbytes.get(cid, 0) + dlen
        elif op[0] == OP_CONNECTION:
            rec = Record(OP_CONNECTION, parse_fields(raw, hstart, hend), hend + 4, dlen, hend + 4 + dlen)
            cid, c = _connection(raw, rec)
            conns.setdefault(cid, c)
        pos = hend + 4 + dlen


def read_stream(path: Path, mm: mmap.mmap) -> RecordingStats:
    """Walk every record (chunks decompressed); needs no index."""
    _check_magic(mm)
    size = len(mm)
    conns: dict[int, Connection] = {}
    times: dict[int, list[int]] = {}
    nbytes: dict[int, int] = {}

    def visit(buf: bytes | memoryview | mmap.mmap, rec: Record) -> None:
        if rec.op == OP_CONNECTION:
            cid, conn = _connection(buf, rec)
            conns.setdefault(cid, conn)
        elif rec.op == OP_MSG:
            cid = _u32(rec.header, "conn")
            times.setdefault(cid, []).append(_time(rec.header))
            nbytes[cid] = nbytes.get(cid, 0) + rec.data_len

    index_pos, chunk_count, chunks_seen = None, 0, 0
    released = 0
    for rec in _records(mm, len(MAGIC), size):
        released = release_behind(mm, released, rec.data_start, reached=rec.end)  # pages behind this record
        if rec.op == OP_BAG_HEADER:
            index_pos = _u64(rec.header, "index_pos")
            chunk_count = _u32(rec.header, "chunk_count")
        elif rec.op == OP_CHUNK:
            chunks_seen += 1
            compression = rec.header.get("compression", b"").decode("latin-1")
            raw = decompress_chunk(compression, memoryview(mm)[rec.data_start:rec.end],
                                   _u32(rec.header, "size"))
            _scan_chunk(raw, conns, times, nbytes)
        else:
            visit(mm, rec)
    if index_pos is None:
        raise Damaged("no bag header record")
    if index_pos and chunks_seen != chunk_count:
        raise Damaged(f"bag header declares {chunk_count} chunks, the file holds {chunks_seen} "
                      "(truncated?)")
    unknown = set(times) - set(conns)
    if unknown:
        raise Damaged(f"messages for undeclared connection(s) {sorted(unknown)}")
    out = Accumulator()
    for cid, conn in conns.items():
        out.add(conn.topic, conn.msgtype, np.asarray(times.get(cid, []), dtype=np.int64),
                nbytes.get(cid, 0), conn.callerid)
    return out.build(path, "ros1")


def read(path: Path, mm: mmap.mmap, fast: bool = True) -> RecordingStats:
    if fast:
        try:
            return read_fast(path, mm)
        except (NoIndex, Damaged):
            pass  # index missing or damaged: stream (raises Damaged if the data is too)
    return read_stream(path, mm)
