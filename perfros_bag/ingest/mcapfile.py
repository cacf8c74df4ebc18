"""MCAP reader (any profile and message encoding): per-channel counts, log times, payload bytes.

Records are ``u8 opcode, u64 length, content`` (https://mcap.dev/spec). No message is ever
deserialised; only record framing is parsed.

* fast path: the summary section (footer -> summary start) gives schemas, channels, chunk
  indexes and statistics (:func:`read_summary`, a :class:`Summary`); each chunk index points
  at the message-index records written after its chunk, which hold ``(log_time, offset)`` per
  message (:func:`read_chunks`, for any subset of the chunks: the whole file reads them all,
  a split task some). A message's payload size is its
  record length minus 22 (channel id, sequence, log and publish time), gathered (numpy) at the
  indexed offsets: straight from the mmapped file for an uncompressed chunk, after one
  decompression for a zstd/lz4 chunk. Statistics' message count cross-checks the indexes.
* streaming path: walk every record from the start, decompressing chunks; also for files
  without summary, unchunked files and files whose summary is damaged or truncated away.

``message_zstd`` (rosbag2 message compression): the payload size is the decompressed size, read
from each zstd frame header (decompressing only frames that do not record it).
"""

from __future__ import annotations

import mmap
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from perfros_bag.ingest import MCAP_MAGIC
from perfros_bag.ingest._accum import (
    I64,
    U8,
    Accumulator,
    Damaged,
    NoIndex,
    gather_u64,
    release,
    release_behind,
    zstd_size,
)
from perfros_bag.ingest._payload import StampAt, StampFinder, payload_stamps

MAGIC = MCAP_MAGIC
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_STATISTICS, OP_DATA_END = 7, 8, 11, 15
OP_METADATA, OP_METADATA_INDEX = 12, 13
#: the Metadata record in which rosbag2's MCAP storage keeps the bag's metadata.yaml
ROSBAG2_METADATA = "rosbag2"
MSG_HEADER = 22  # channel u16 + sequence u32 + log_time u64 + publish_time u64
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
Buf = bytes | memoryview | mmap.mmap


class _Cursor:
    """Bounds-checked little-endian reads inside one record's content."""

    def __init__(self, buf: Buf, pos: int, end: int) -> None:
        self.buf, self.pos, self.end = buf, pos, end

    def _take(self, n: int) -> int:
        p = self.pos
        if n < 0 or p + n > self.end:
            raise Damaged(f"record field overruns its record at byte {p}")
        self.pos = p + n
        return p

    def u16(self) -> int:
        return int(_U16.unpack_from(self.buf, self._take(2))[0])

    def u32(self) -> int:
        return int(_U32.unpack_from(self.buf, self._take(4))[0])

    def u64(self) -> int:
        return int(_U64.unpack_from(self.buf, self._take(8))[0])

    def string(self) -> str:
        n = self.u32()
        p = self._take(n)
        return bytes(self.buf[p:p + n]).decode("utf-8", "replace")

    def skip_prefixed(self) -> tuple[int, int]:
        n = self.u32()
        return self._take(n), n


@dataclass(frozen=True)
class Channel:
    """A channel record: its topic, its schema's id and (ROS 1 profile) the publisher."""

    topic: str
    schema_id: int
    callerid: str = ""  # ROS 1 profile: the publisher, from the channel metadata
    encoding: str = ""  # the message encoding: "cdr", "ros1", "json", ...


@dataclass(frozen=True)
class ChunkIndex:
    """A chunk-index record of the summary: where the chunk and its message-index records
    are, and the message-index record of each channel (channel id -> file offset)."""

    chunk_start_offset: int
    chunk_length: int
    message_index_offsets: Mapping[int, int]
    message_index_length: int
    compression: str
    uncompressed_size: int

    @property
    def end(self) -> int:
        """File offset just after the chunk's message-index records."""
        return self.chunk_start_offset + self.chunk_length + self.message_index_length


@dataclass(frozen=True)
class Summary:
    """The summary section: schema names and channels by id, the chunk indexes (in file
    order as recorded) and the Statistics record's message count (None without one);
    ``definitions``: each schema's (encoding, data) by id (what
    :mod:`perfros_bag.ingest.stamps` parses)."""

    schemas: Mapping[int, str]
    channels: Mapping[int, Channel]
    chunk_indexes: tuple[ChunkIndex, ...]
    message_count: int | None
    #: a rosbag2 storage file whose ``rosbag2`` Metadata record says each payload is a zstd
    #: frame (``compression_mode: message``): the sizes to report are the decompressed ones
    message_zstd: bool = False
    definitions: Mapping[int, tuple[str, bytes]] = field(default_factory=dict)

    def chunk_sizes(self) -> tuple[int, ...]:
        """Bytes of file each chunk takes with its message indexes (at least 1)."""
        return tuple(max(ci.end - ci.chunk_start_offset, 1) for ci in self.chunk_indexes)

    def select(self, positions: Sequence[int]) -> Summary:
        """This summary restricted to the chunk indexes at ``positions`` (what
        :func:`read_chunks` reads)."""
        return replace(self, chunk_indexes=tuple(self.chunk_indexes[i] for i in positions))

    def check_message_count(self, messages: int) -> None:
        """Raises :class:`NoIndex` when ``messages`` read from all chunk indexes disagrees
        with the Statistics record."""
        if self.message_count is not None and messages != self.message_count:
            raise NoIndex(f"statistics count {self.message_count} disagrees with the indexes ({messages})")


@dataclass
class _State:
    schemas: dict[int, str] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    times: dict[int, list[I64]] = field(default_factory=dict)
    nbytes: dict[int, int] = field(default_factory=dict)
    definitions: dict[int, tuple[str, bytes]] = field(default_factory=dict)
    stamps: list[tuple[str, I64, I64]] = field(default_factory=list)  # (topic, times, stamps)

    def add(self, cid: int, times: I64, nbytes: int) -> None:
        self.times.setdefault(cid, []).append(times)
        self.nbytes[cid] = self.nbytes.get(cid, 0) + nbytes

    def accumulator(self) -> Accumulator:
        unknown = set(self.times) - set(self.channels)
        if unknown:
            raise Damaged(f"messages on undeclared channel(s) {sorted(unknown)}")
        acc = Accumulator()
        for cid, ch in sorted(self.channels.items()):
            parts = self.times.get(cid, [])
            times = np.concatenate(parts) if parts else np.empty(0, dtype=np.int64)
            acc.add(ch.topic, self.schemas.get(ch.schema_id, ""), times, self.nbytes.get(cid, 0),
                    ch.callerid or None)
        for topic, times, stamps in self.stamps:
            acc.add_stamps(topic, times, stamps)
        return acc


def record_at(buf: Buf, pos: int, end: int) -> tuple[int, int, int]:
    """(opcode, content start, content length) of the record at ``pos``."""
    if pos + 9 > end:
        raise Damaged(f"truncated record at byte {pos}")
    op = buf[pos]
    (length,) = _U64.unpack_from(buf, pos + 1)
    if pos + 9 + length > end:
        raise Damaged(f"truncated record at byte {pos} (opcode {op:#x}, {length} bytes)")
    return int(op), pos + 9, int(length)


def _schema(buf: Buf, start: int, length: int, st: _State) -> None:
    c = _Cursor(buf, start, start + length)
    sid = c.u16()
    st.schemas[sid] = c.string()
    encoding = c.string()
    start, n = c.skip_prefixed()
    st.definitions[sid] = (encoding, bytes(buf[start:start + n]))


def _channel(buf: Buf, start: int, length: int, st: _State) -> None:
    c = _Cursor(buf, start, start + length)
    cid, schema_id = c.u16(), c.u16()
    topic = c.string()
    encoding = c.string()
    callerid = ""
    if c.pos < c.end:  # metadata map<string, string> (the ros1 profile records callerid)
        mstart, mlen = c.skip_prefixed()
        m = _Cursor(buf, mstart, mstart + mlen)
        while m.pos < m.end:
            key, value = m.string(), m.string()
            if key == "callerid":
                callerid = value
    st.channels[cid] = Channel(topic, schema_id, callerid, encoding)


def decompress(compression: str, data: Buf, usize: int) -> bytes:
    if compression == "zstd":
        import zstandard

        # zstandard and lz4 read any buffer: no copy of the compressed bytes out of the mmap
        view = memoryview(data)
        declared = zstandard.frame_content_size(view[:18]) if len(view) >= 18 else -1
        if declared == usize:  # one allocation of the right size
            out = zstandard.ZstdDecompressor().decompress(view)
        else:  # no content size in the frame: grow as needed (never trust usize to allocate)
            out = zstandard.ZstdDecompressor().decompressobj().decompress(view)
    elif compression == "lz4":
        import lz4.frame

        out = lz4.frame.decompress(memoryview(data))
    elif compression == "":
        out = bytes(data)
    else:
        raise Damaged(f"unsupported chunk compression {compression!r}")
    if len(out) != usize:
        raise Damaged(f"chunk decompressed to {len(out)} bytes, its header says {usize}")
    return out


def zstd_payload_sizes(buf: U8, data_pos: I64, data_len: I64) -> int:
    """Sum of decompressed sizes of zstd-compressed payloads (rosbag2 message compression)."""
    total = 0
    raw = buf.tobytes() if buf.size < 1 << 16 else None
    for p, n in zip(data_pos.tolist(), data_len.tolist(), strict=True):
        total += zstd_size(raw[p:p + n] if raw is not None else buf[p:p + n].tobytes())
    return total


def _chunk_records(buf: Buf, start: int, length: int) -> tuple[str, int, int, int]:
    """(compression, records start, records length, uncompressed size) of a chunk record."""
    c = _Cursor(buf, start, start + length)
    c.u64()
    c.u64()
    usize = c.u64()
    c.u32()
    compression = c.string()
    n = c.u64()
    p = c._take(n)
    return compression, p, n, usize


def _scan_records(buf: Buf, pos: int, end: int, st: _State, message_zstd: bool,
                  in_chunk: bool) -> tuple[bool, bool]:
    """Walk records; returns (saw data end, saw footer)."""
    times: dict[int, list[int]] = {}
    sizes: dict[int, int] = {}
    data_end = footer = False
    mapped = isinstance(buf, mmap.mmap)
    released = 0
    while pos < end:
        try:
            op, start, length = record_at(buf, pos, end)
        except Damaged:
            if data_end:  # summary cut off after the data section: every message was read
                break
            raise
        if mapped:  # pages behind this record: unmap
            released = release_behind(buf, released, start)  # type: ignore[arg-type]
        pos = start + length
        if op == OP_MESSAGE:
            c = _Cursor(buf, start, start + length)
            cid = c.u16()
            c.u32()
            log_time = c.u64()
            c.u64()
            n = length - MSG_HEADER
            if message_zstd:
                arr = np.frombuffer(bytes(buf[start + MSG_HEADER:start + length]), dtype=np.uint8)
                n = zstd_payload_sizes(arr, np.zeros(1, np.int64), np.array([n], np.int64))
            times.setdefault(cid, []).append(log_time)
            sizes[cid] = sizes.get(cid, 0) + n
        elif op == OP_SCHEMA:
            _schema(buf, start, length, st)
        elif op == OP_CHANNEL:
            _channel(buf, start, length, st)
        elif op == OP_CHUNK and not in_chunk:
            compression, rstart, rlen, usize = _chunk_records(buf, start, length)
            raw = decompress(compression, memoryview(buf)[rstart:rstart + rlen], usize)
            _scan_records(raw, 0, len(raw), st, message_zstd, in_chunk=True)
        elif op == OP_DATA_END:
            data_end = True
        elif op == OP_FOOTER:
            footer = True
            break
    for cid, ts in times.items():
        st.add(cid, np.asarray(ts, dtype=np.int64), sizes[cid])
    return data_end, footer


def read_stream(mm: mmap.mmap, message_zstd: bool = False) -> Accumulator:
    if mm[:8] != MAGIC:
        raise Damaged("not an MCAP file (no MCAP magic)")
    st = _State()
    data_end, footer = _scan_records(mm, 8, len(mm), st, message_zstd, in_chunk=False)
    if not (data_end or footer):
        raise Damaged("truncated: no data-end or footer record")
    return st.accumulator()


def read_summary(mm: mmap.mmap) -> Summary:
    """The summary section of the MCAP file in ``mm`` (footer -> summary start).

    Raises :class:`NoIndex` when there is no usable summary (the caller streams) and
    :class:`Damaged` when a summary record is malformed.
    """
    if mm[:8] != MAGIC:
        raise Damaged("not an MCAP file (no MCAP magic)")
    size = len(mm)
    if size < 8 + 29 + 8 or mm[size - 8:] != MAGIC:
        raise NoIndex("no trailing magic")
    fpos = size - 8 - 29
    op, start, length = record_at(mm, fpos, size - 8)
    if op != OP_FOOTER or length != 20:
        raise NoIndex("no footer")
    c = _Cursor(mm, start, start + length)
    summary_start, summary_offset_start = c.u64(), c.u64()
    if summary_start == 0:
        raise NoIndex("no summary section")
    end = summary_offset_start or fpos
    if not 8 <= summary_start <= end <= fpos:
        raise NoIndex("summary offsets out of range")
    st = _State()
    chunks: list[ChunkIndex] = []
    count: int | None = None
    rosbag2_metadata: tuple[int, int] | None = None
    pos = summary_start
    while pos < end:
        op, start, length = record_at(mm, pos, end)
        pos = start + length
        if op == OP_SCHEMA:
            _schema(mm, start, length, st)
        elif op == OP_CHANNEL:
            _channel(mm, start, length, st)
        elif op == OP_CHUNK_INDEX:
            c = _Cursor(mm, start, start + length)
            c.u64()
            c.u64()
            cstart, clen = c.u64(), c.u64()
            mstart, mlen = c.skip_prefixed()
            if mlen % 10:
                raise NoIndex("malformed message-index offsets")
            offsets = {int(_U16.unpack_from(mm, mstart + i)[0]): int(_U64.unpack_from(mm, mstart + i + 2)[0])
                       for i in range(0, mlen, 10)}
            ilen = c.u64()
            compression = c.string()
            c.u64()
            usize = c.u64()
            chunks.append(ChunkIndex(cstart, clen, offsets, ilen, compression, usize))
        elif op == OP_STATISTICS:
            count = _Cursor(mm, start, start + length).u64()
        elif op == OP_METADATA_INDEX:
            c = _Cursor(mm, start, start + length)
            moffset, mlength = c.u64(), c.u64()
            if c.string() == ROSBAG2_METADATA:
                rosbag2_metadata = (moffset, mlength)
    message_zstd = rosbag2_metadata is not None and _says_message_zstd(mm, *rosbag2_metadata)
    return Summary(st.schemas, st.channels, tuple(chunks), count, message_zstd, st.definitions)


def rosbag2_message_compressed(mm: mmap.mmap) -> bool:
    """Whether the MCAP file in ``mm`` is a rosbag2 storage file written with per-message
    compression (:attr:`Summary.message_zstd`), as for the same file inside its rosbag2
    directory. Found through the summary's metadata index; a file without a usable summary
    is taken as not compressed."""
    try:
        return read_summary(mm).message_zstd
    except (NoIndex, Damaged):
        return False


def _says_message_zstd(mm: mmap.mmap, offset: int, length: int) -> bool:
    """The ``rosbag2`` Metadata record at ``offset``: does its metadata say
    ``compression_mode: message`` with zstd? (False when it cannot be read.)"""
    try:
        op, start, rlen = record_at(mm, offset, min(len(mm), offset + length))
        if op != OP_METADATA:
            return False
        c = _Cursor(mm, start, start + rlen)
        if c.string() != ROSBAG2_METADATA:
            return False
        map_end = c.u32() + c.pos
        text = None
        while c.pos < map_end:
            key, value = c.string(), c.string()
            if key == "serialized_metadata":
                text = value
    except (Damaged, UnicodeDecodeError):
        return False
    if text is None:
        return False
    import yaml

    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError:
        return False
    if not isinstance(meta, dict):
        return False
    info = meta.get("rosbag2_bagfile_information", meta)  # metadata.yaml's top key, when present
    mode = str(info.get("compression_mode") or "").lower() if isinstance(info, dict) else ""
    fmt = str(info.get("compression_format") or "").lower() if isinstance(info, dict) else ""
    return mode == "message" and fmt == "zstd"


def read_chunks(mm: mmap.mmap, summary: Summary, message_zstd: bool | None = None,
                stamps: Mapping[int, StampAt] | None = None) -> Accumulator:
    """Counts, log times and payload bytes of the messages in ``summary.chunk_indexes``
    (every channel of the summary declared), from their message indexes; method "index".
    ``message_zstd``: whether payloads are zstd frames (None: as the file says,
    :attr:`Summary.message_zstd`). ``stamps``: the channels whose ``header.stamp`` to read
    too, in the same pass (the accumulator's
    :meth:`~perfros_bag.ingest._accum.Accumulator.stamps`; NoIndex with zstd payloads).

    The whole-file fast path reads all chunks, a split task some of them
    (:meth:`Summary.select`). Raises :class:`NoIndex` when a message index disagrees
    with its chunk (the caller streams instead).
    """
    if message_zstd is None:
        message_zstd = summary.message_zstd
    if stamps and message_zstd:
        raise NoIndex("stamps of zstd-compressed payloads are not read in place")
    st = _State(dict(summary.schemas), dict(summary.channels))
    for ci in summary.chunk_indexes:
        buf, base, blen = load_chunk(mm, ci)
        _index_chunk(mm, ci, buf, base, blen, st, message_zstd, stamps or {})
        del buf
        release(mm, ci.chunk_start_offset, ci.end)  # keep the resident set small (see _accum.release)
    acc = st.accumulator()
    acc.method = "index"
    return acc


def read_fast(mm: mmap.mmap, message_zstd: bool | None = None, stamps: StampFinder | None = None) -> Accumulator:
    """The whole file from its summary: :func:`read_chunks` over every chunk index,
    cross-checked with the Statistics record; ``stamps``: which channels' header stamps to
    read in the same pass, given the summary."""
    summary = read_summary(mm)
    if not summary.chunk_indexes and summary.message_count != 0:
        raise NoIndex("no chunk index")
    acc = read_chunks(mm, summary, message_zstd, stamps(summary) if stamps is not None else None)
    summary.check_message_count(acc.messages)
    return acc


def load_chunk(mm: mmap.mmap, ci: ChunkIndex) -> tuple[U8, int, int]:
    """(buffer, records start in it, records length) of an indexed chunk."""
    op, start, length = record_at(mm, ci.chunk_start_offset, len(mm))
    if op != OP_CHUNK:
        raise NoIndex(f"chunk index points at a non-chunk record (byte {ci.chunk_start_offset})")
    compression, rstart, rlen, usize = _chunk_records(mm, start, length)
    if usize and not ci.message_index_offsets:
        raise NoIndex("chunk without message indexes")
    if compression == "":
        return np.frombuffer(mm, dtype=np.uint8), rstart, rlen
    raw = decompress(compression, memoryview(mm)[rstart:rstart + rlen], usize)
    return np.frombuffer(raw, dtype=np.uint8), 0, len(raw)


def message_index(mm: mmap.mmap, ci: ChunkIndex, cid: int) -> npt.NDArray[np.uint64]:
    """Channel ``cid``'s message index after the chunk of ``ci``: its ``(log_time, offset)``
    pairs as an (n, 2) array viewing the mmap. NoIndex when the record is not that
    channel's message index."""
    op, istart, ilen = record_at(mm, ci.message_index_offsets[cid], len(mm))
    if op != OP_MESSAGE_INDEX:
        raise NoIndex("message-index offset does not point at a message index")
    c = _Cursor(mm, istart, istart + ilen)
    if c.u16() != cid:
        raise NoIndex("message index for the wrong channel")
    ppos, plen = c.skip_prefixed()
    if plen % 16:
        raise NoIndex("malformed message index")
    return np.frombuffer(mm, dtype="<u8", count=plen // 8, offset=ppos).reshape(-1, 2)


def _index_chunk(mm: mmap.mmap, ci: ChunkIndex, buf: U8, base: int, blen: int, st: _State,
                 message_zstd: bool, stamps: Mapping[int, StampAt]) -> None:
    """Adds one chunk's indexed messages (and the header stamps of the channels in
    ``stamps``) to ``st``."""
    cids = list(ci.message_index_offsets)
    parts = [message_index(mm, ci, cid) for cid in cids]
    counts = np.array([len(p) for p in parts], dtype=np.int64)
    n = int(counts.sum())
    if n == 0:
        return
    pairs = np.concatenate(parts)
    del parts
    # bounds checked on the unsigned values, before any cast to int64 could wrap them
    if int(pairs[:, 0].max()) >= 2**63:
        raise NoIndex("log time out of range")
    if int(pairs[:, 1].max()) + 9 + MSG_HEADER > blen:
        raise NoIndex("message-index offset outside its chunk")
    offs = pairs[:, 1].astype(np.int64)
    at = base + offs
    if not np.all(buf[at] == OP_MESSAGE):
        raise NoIndex("message-index offset does not point at a message")
    lengths = gather_u64(buf, at + 1)
    ends = offs + 9 + lengths
    if int(lengths.min()) < MSG_HEADER or int(ends.max()) > blen:
        raise NoIndex("indexed message overruns its chunk")
    chan = buf[at + 9].astype(np.uint16) | (buf[at + 10].astype(np.uint16) << 8)  # u16 LE
    if np.any(chan != np.repeat(np.array(cids, dtype=np.uint16), counts)):
        raise NoIndex("message index points at another channel's message")
    order = np.argsort(offs, kind="stable")
    if np.any(offs[order][1:] < ends[order][:-1]):
        raise NoIndex("indexed message records overlap")
    if message_zstd:
        per = [zstd_payload_sizes(buf, base + o + 9 + MSG_HEADER, ln - MSG_HEADER)
               for o, ln in zip(np.split(offs, np.cumsum(counts)[:-1]),
                                np.split(lengths, np.cumsum(counts)[:-1]), strict=True)]
    else:  # record lengths summed per channel (a channel's index may be empty)
        bounds = np.concatenate(([0], np.cumsum(counts)))
        cum = np.concatenate(([0], np.cumsum(lengths)))
        per = (cum[bounds[1:]] - cum[bounds[:-1]] - MSG_HEADER * counts).tolist()
    times = pairs[:, 0].astype(np.int64)
    k = 0
    for cid, cnt, nbytes in zip(cids, counts.tolist(), per, strict=True):
        st.add(cid, times[k:k + cnt], nbytes)
        where = stamps.get(cid)
        if where is not None and cnt:
            st.stamps.append((where.topic, times[k:k + cnt],
                              payload_stamps(buf, at[k:k + cnt] + 9 + MSG_HEADER, lengths[k:k + cnt] - MSG_HEADER,
                                             where)))
        k += cnt


def read(mm: mmap.mmap, fast: bool = True, message_zstd: bool | None = None,
         stamps: StampFinder | None = None) -> Accumulator:
    """The whole file, from its indexes when ``fast`` (else, or when they are missing or
    damaged, by streaming). ``message_zstd`` None: as the file's summary says. ``stamps``:
    header stamps read in the index pass (:func:`read_fast`; no streaming fallback then)."""
    if stamps is not None:
        return read_fast(mm, message_zstd, stamps)
    if fast:
        try:
            return read_fast(mm, message_zstd)
        except (NoIndex, Damaged):
            pass  # summary or indexes missing or damaged: stream
    return read_stream(mm, rosbag2_message_compressed(mm) if message_zstd is None else message_zstd)

