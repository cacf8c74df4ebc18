"""``header.stamp`` of every message of the stamped topics, read at its known offset (fast path).

A message whose type starts with ``std_msgs/Header`` has its stamp at a fixed place:

* ROS 1 serialisation: after the recorded Header's leading fixed-size fields (ROS 1's
  ``uint32 seq``: bytes 4-12 of the payload; :func:`~perfros_bag.ingest.decode.stamp_offset`);
* CDR (ROS 2): a 4-byte encapsulation header (``00 01`` little-endian, ``00 00`` big-endian),
  then ``int32 sec, uint32 nanosec`` -> bytes 4-12.

Which topics are stamped is decided by rosbags from the definitions stored in the recording
(:func:`perfros_bag.ingest.decode.starts_with_header`); only the chunks of those topics are
touched, through the existing readers' index access (:func:`perfros_bag.ingest.rosbag1.read_index`,
:func:`perfros_bag.ingest.mcapfile.read_summary`); rosbag2 sqlite3 files give each blob's first
bytes from their B-tree pages (:func:`perfros_bag.ingest.sqlitepages.read_blob_heads`).
Every structural fact is checked; anything unexpected (another CDR encapsulation, a payload
shorter than a header, an index that disagrees with its chunk) raises
:class:`~perfros_bag.ingest._accum.NoIndex` and the caller decodes with the libraries instead
(:mod:`perfros_bag.ingest.decode`). tests/test_contents.py proves these stamps equal the
libraries' full deserialisation on every stamped message of shared/realbags and of generated
recordings.
"""

from __future__ import annotations

import mmap
import sqlite3
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from perfros_bag.ingest import mcapfile, rosbag1
from perfros_bag.ingest._accum import I64, U8, Damaged, NoIndex, gather_u32, gather_u64, release
from perfros_bag.ingest.decode import TopicType, topic_type

#: topic -> (receive/log times ns, header stamps ns), one entry per message, in file order
Stamps = dict[str, tuple[I64, I64]]
STAMP_SIZE = 8  # sec, nanosec: 4 bytes each


def _offset(tt: TopicType) -> int:
    """The stamp's offset in ``tt``'s payloads; NoIndex when it has none (library path)."""
    if tt.stamp_offset is None:
        raise NoIndex(f"{tt.topic}: no fixed offset of header.stamp in the recorded definitions")
    return tt.stamp_offset


def _stamp_ns(sec: I64, nsec: I64) -> I64:
    return sec * 1_000_000_000 + nsec


class StampParts:
    """Parts of each topic's (times, stamps), concatenated once at the end."""

    def __init__(self) -> None:
        self.parts: dict[str, list[tuple[I64, I64]]] = {}

    def add(self, topic: str, times: I64, stamps: I64) -> None:
        self.parts.setdefault(topic, []).append((times, stamps))

    def extend(self, stamps: Stamps) -> None:
        for topic, (t, s) in stamps.items():
            self.add(topic, t, s)

    def stamps(self) -> Stamps:
        return {topic: (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))
                for topic, parts in self.parts.items()}


def _pairs_u32(buf: U8, pos: I64) -> tuple[I64, I64]:
    """Two consecutive little-endian uint32 at every position ``pos`` (one 8-byte gather)."""
    if pos.size == 0:
        return pos, pos
    if int(pos.min()) < 0 or int(pos.max()) + 8 > buf.size:
        raise Damaged("stamp outside its chunk")
    pairs = np.lib.stride_tricks.sliding_window_view(buf, 8)[pos].view("<u4").astype(np.int64)
    return pairs[:, 0], pairs[:, 1]


# --------------------------------------------------------------------------- ROS 1


def ros1_types(mm: mmap.mmap, index: rosbag1.BagIndex) -> dict[int, TopicType]:
    """Connection id -> :class:`TopicType`, rosbags parsing each connection record's
    ``message_definition``."""
    from rosbags.typesys import get_types_from_msg, get_typestore
    from rosbags.typesys.msg import normalize_msgtype
    from rosbags.typesys.stores import Stores

    typestore = get_typestore(Stores.EMPTY)
    names: dict[int, str] = {}
    pos, end = index.index_pos, len(mm)
    while pos < end:
        rec = rosbag1.read_record(mm, pos, end)
        pos = rec.end
        if rec.op != rosbag1.OP_CONNECTION:
            continue
        cid = int.from_bytes(rec.header.get("conn", b"\0\0\0\0"), "little")
        fields = rosbag1.parse_fields(mm, rec.data_start, rec.data_start + rec.data_len)
        name = normalize_msgtype(fields.get("type", b"").decode("utf-8", "replace"))
        names[cid] = name
        msgdef = fields.get("message_definition", b"").decode("utf-8", "replace")
        if name not in typestore.fielddefs:
            try:
                typestore.register(get_types_from_msg(msgdef, name))
            except Exception:  # noqa: S112 - a definition rosbags cannot parse: not stamped
                continue
    return {cid: topic_type(typestore, conn.topic, names.get(cid, conn.msgtype), "ros1")
            for cid, conn in index.connections.items()}


def ros1_stamps(mm: mmap.mmap) -> tuple[Stamps, dict[str, TopicType]]:
    """Stamps of the stamped connections of a ROS 1 bag from its index; the chunks holding
    none of them are not touched. Raises NoIndex/Damaged when the index cannot be used."""
    index = rosbag1.read_index(mm)
    types = ros1_types(mm, index)
    wanted = {cid: _offset(t) for cid, t in types.items() if t.stamped}
    out = StampParts()
    size = len(mm)
    whole: U8 = np.frombuffer(mm, dtype=np.uint8)
    for info in index.chunks:
        if not wanted & info.connection_counts.keys():
            continue
        crec = rosbag1.read_record(mm, info.chunk_pos, size)
        if crec.op != rosbag1.OP_CHUNK:
            raise NoIndex("chunk-info points at a non-chunk record")
        compression = crec.header.get("compression", b"").decode("latin-1")
        usize = int.from_bytes(crec.header.get("size", b""), "little")
        if compression == "none":
            if usize != crec.data_len:
                raise NoIndex("uncompressed chunk size mismatch")
            buf, base = whole, crec.data_start
        else:
            raw = rosbag1.decompress_chunk(compression, memoryview(mm)[crec.data_start:crec.end], usize)
            buf, base = np.frombuffer(raw, dtype=np.uint8), 0
        pos = crec.end
        parts: list[tuple[int, I64, I64]] = []  # (connection, times, offsets) of the wanted ones
        for _ in range(len(info.connection_counts)):
            irec = rosbag1.read_record(mm, pos, size)
            pos = irec.end
            if irec.op != rosbag1.OP_INDEX:
                raise NoIndex("missing index-data record after a chunk")
            cid = int.from_bytes(irec.header.get("conn", b""), "little")
            n = int.from_bytes(irec.header.get("count", b""), "little")
            if cid not in wanted:
                continue
            if irec.data_len != 12 * n:
                raise NoIndex("index-data record size mismatch")
            entries = np.frombuffer(mm, dtype=rosbag1.INDEX_ENTRY_DT, count=n, offset=irec.data_start)
            parts.append((cid, _stamp_ns(entries["sec"].astype(np.int64), entries["nsec"].astype(np.int64)),
                          entries["offset"].astype(np.int64)))
            del entries
        offs = np.concatenate([p[2] for p in parts])
        at = np.concatenate([np.full(p[2].size, wanted[p[0]], dtype=np.int64) for p in parts])
        dlen = rosbag1.message_sizes(buf, base, offs, usize)  # checks the records' bounds
        if dlen.size and int((dlen - at).min()) < STAMP_SIZE:
            raise NoIndex("a stamped message shorter than its header")
        sec, nsec = _pairs_u32(buf, base + offs + 8 + gather_u32(buf, base + offs) + at)
        stamps = _stamp_ns(sec, nsec)
        k = 0
        for cid, times, o in parts:
            out.add(types[cid].topic, times, stamps[k:k + o.size])
            k += o.size
        del buf
        release(mm, info.chunk_pos, pos)
    del whole
    return out.stamps(), {t.topic: t for t in types.values()}


# --------------------------------------------------------------------------- CDR


def cdr_stamps(payload: U8, starts: I64) -> I64:
    """Stamps of CDR payloads starting at ``starts`` in ``payload`` (each at least 12 bytes,
    checked by the caller; the stamp right after the encapsulation, as
    :func:`~perfros_bag.ingest.decode.stamp_offset` requires); NoIndex on an encapsulation
    other than plain CDR."""
    if starts.size == 0:
        return starts
    kind = (payload[starts].astype(np.int64) << 8) | payload[starts + 1].astype(np.int64)
    little = kind == 1
    if not np.all(little | (kind == 0)):
        raise NoIndex("CDR encapsulation other than plain CDR (XCDR/parameter lists)")
    sec, nsec = _pairs_u32(payload, starts + 4)
    if not np.all(little):  # big-endian payloads: swap the four bytes
        big = ~little
        sec[big] = sec[big].astype(np.uint32).byteswap().astype(np.int64)
        nsec[big] = nsec[big].astype(np.uint32).byteswap().astype(np.int64)
    sec = sec.astype(np.uint32).view(np.int32).astype(np.int64)  # builtin_interfaces/Time: int32 sec
    return _stamp_ns(sec, nsec)


# --------------------------------------------------------------------------- MCAP


def mcap_stamps(mm: mmap.mmap, path: Path) -> tuple[Stamps, dict[str, TopicType]]:
    """Stamps of the stamped channels (``cdr`` or ``ros1`` payloads) of an MCAP file from
    its summary and message indexes; only the chunks holding them are decompressed."""
    from perfros_bag.ingest.decode import mcap_types

    summary = mcapfile.read_summary(mm)
    types = mcap_types(path)
    wanted = {cid: ch for cid, ch in summary.channels.items()
              if types.get(ch.topic) is not None and types[ch.topic].stamped}
    encodings = {cid: types[ch.topic].encoding for cid, ch in wanted.items()}
    out = StampParts()
    size = len(mm)
    for ci in summary.chunk_indexes:
        cids = [cid for cid in ci.message_index_offsets if cid in wanted]
        if not cids:
            continue
        buf, base, blen = mcapfile.load_chunk(mm, ci)
        for cid in cids:
            op, istart, ilen = mcapfile.record_at(mm, ci.message_index_offsets[cid], size)
            if op != mcapfile.OP_MESSAGE_INDEX or int.from_bytes(mm[istart:istart + 2], "little") != cid:
                raise NoIndex("message index disagrees with its chunk index")
            plen = int.from_bytes(mm[istart + 2:istart + 6], "little")
            if plen % 16 or 6 + plen > ilen:
                raise NoIndex("malformed message index")
            pairs = np.frombuffer(mm, dtype="<u8", count=plen // 8, offset=istart + 6).reshape(-1, 2)
            if pairs.size == 0:
                continue
            if int(pairs[:, 0].max()) >= 2**63 or int(pairs[:, 1].max()) + 9 + mcapfile.MSG_HEADER > blen:
                raise NoIndex("message-index entry out of range")
            offs = pairs[:, 1].astype(np.int64)
            times = pairs[:, 0].astype(np.int64)
            del pairs
            at = base + offs
            lengths = gather_u64(buf, at + 1)
            chan = buf[at + 9].astype(np.int64) | (buf[at + 10].astype(np.int64) << 8)
            stamp_at = _offset(types[wanted[cid].topic])
            if (not np.all(buf[at] == mcapfile.OP_MESSAGE) or np.any(chan != cid)
                    or int(lengths.min()) < mcapfile.MSG_HEADER + stamp_at + STAMP_SIZE
                    or int((offs + 9 + lengths).max()) > blen):
                raise NoIndex("message index points at something other than this channel's messages")
            starts = at + 9 + mcapfile.MSG_HEADER
            if encodings[cid] == "cdr":
                stamps = cdr_stamps(buf, starts)
            else:
                stamps = _stamp_ns(*_pairs_u32(buf, starts + stamp_at))
            out.add(wanted[cid].topic, times, stamps)
        del buf
        release(mm, ci.chunk_start_offset, ci.end)
    return out.stamps(), types


# --------------------------------------------------------------------------- rosbag2 sqlite3


def sqlite_types(con: sqlite3.Connection) -> dict[int, TopicType]:
    """Topic id -> :class:`TopicType` of a rosbag2 sqlite3 file: rosbags parses the
    ``message_definitions`` table (rosbag2 >= Iron); a file without one uses rosbags'
    standard ROS 2 types (as its AnyReader does)."""
    from rosbags.typesys.msg import normalize_msgtype

    from perfros_bag.ingest.decode import standard_typestore, typestore_from_definitions

    try:
        stored = [(str(t), str(e), str(d)) for t, e, d in con.execute(
            "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions") if d]
    except sqlite3.Error:  # older rosbag2: no such table
        stored = []
    typestore = typestore_from_definitions(stored) if stored else standard_typestore()
    return {int(tid): topic_type(typestore, str(name), normalize_msgtype(str(mtype or "")), str(fmt or "cdr"))
            for tid, name, mtype, fmt in con.execute("SELECT id, name, type, serialization_format FROM topics")}


def sqlite_stamps(db: Path) -> tuple[Stamps, dict[str, TopicType]]:
    """Stamps of the stamped topics of one rosbag2 sqlite3 file (CDR payloads) and every
    topic's type: the first 12 bytes of each of their blobs from the B-tree pages
    (:func:`perfros_bag.ingest.sqlitepages.read_blob_heads`), else (a WAL, an unusual table)
    one SQL pass returning them as hex text."""
    from perfros_bag.ingest import sqlitepages
    from perfros_bag.ingest.rosbag2 import connect_db, open_mmap

    with connect_db(db) as (con, wal):
        try:
            by_id = sqlite_types(con)
            types = {t.topic: t for t in by_id.values()}
            wanted = {tid: t.topic for tid, t in by_id.items() if t.stamped}
            if not wanted:
                return {}, types
            if any(_offset(types[name]) != 4 for name in wanted.values()):
                raise NoIndex("header.stamp not right after the CDR encapsulation")
            root = None if wal else sqlitepages.messages_root(con)
            if root is not None:
                (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
                try:
                    with open_mmap(db) as mm:
                        tids, times, heads = sqlitepages.read_blob_heads(mm, root, int(count), list(wanted), 12)
                    stamps = cdr_stamps(heads.reshape(-1), np.arange(tids.size, dtype=np.int64) * 12)
                    return {name: (times[tids == tid], stamps[tids == tid]) for tid, name in wanted.items()}, types
                except NoIndex:
                    pass  # the SQL pass below
            return _sql_stamps(con, wanted), types
        except (sqlite3.Error, ValueError) as exc:
            raise Damaged(f"cannot read the messages table: {exc}") from None


def _sql_stamps(con: sqlite3.Connection, wanted: Mapping[int, str]) -> Stamps:
    from perfros_bag.ingest.rosbag2 import parse_ints

    marks = ",".join("?" * len(wanted))
    n, tids_text, times_text, heads, shortest = con.execute(
        "SELECT count(*), group_concat(topic_id), group_concat(timestamp), "
        "group_concat(hex(substr(data, 1, 12)), ''), min(length(data)) "
        f"FROM messages WHERE topic_id IN ({marks})", tuple(wanted)).fetchone()  # noqa: S608 - only '?'
    if n == 0:
        return {}
    if shortest is None or int(shortest) < 4 + STAMP_SIZE:
        raise NoIndex("a stamped message shorter than its header")
    raw = np.frombuffer(bytes.fromhex(heads), dtype=np.uint8)
    if raw.size != n * 12:
        raise NoIndex("stamp bytes do not match the message count")
    tids, times = parse_ints(tids_text, n), parse_ints(times_text, n)
    stamps = cdr_stamps(raw, np.arange(n, dtype=np.int64) * 12)
    return {name: (times[tids == tid], stamps[tids == tid]) for tid, name in wanted.items()}
