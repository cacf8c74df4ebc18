"""rosbag2's ``messages`` table read straight from the SQLite file's B-tree pages (numpy).

Why: any SQL path costs SQLite's per-row virtual machine plus a per-row (or per-value) Python
or text conversion; for a million small messages that is most of the time. The table is a
plain rowid B-tree (https://www.sqlite.org/fileformat2.html): interior pages (flag 0x05) point
at children, leaf pages (0x0D) hold cells ``varint payload size, varint rowid, record``; a
record is ``varint header size, serial types..., values``. rosbag2's table is
``messages(id INTEGER PRIMARY KEY, topic_id INTEGER, timestamp INTEGER, data BLOB)``, so each
record has four serial types (id is NULL: it is the rowid) and the blob's serial type gives
its length ``(type - 12) / 2`` -- the blob itself (and its overflow pages) is never touched.

Every structural fact is checked (page flags, cell bounds, header sizes, payload size equals
the sum of the column sizes, cell count equals ``count(*)``); any surprise raises
:class:`~perfros_bag.ingest._accum.NoIndex` and the caller uses SQL instead.
"""

from __future__ import annotations

import mmap
from pathlib import Path

import numpy as np

from perfros_bag.ingest._accum import I64, U8, NoIndex

_WIDTH = np.array([0, 1, 2, 3, 4, 6, 8, -1, 0, 0], dtype=np.int64)  # serial type -> int width
MESSAGES_COLUMNS = ["id", "topic_id", "timestamp", "data"]


def _be(buf: U8, pos: I64, width: int) -> I64:
    """Unsigned big-endian integers of a fixed width at ``pos``."""
    val = np.zeros(pos.size, dtype=np.int64)
    for k in range(width):
        val = (val << 8) | buf[pos + k].astype(np.int64)
    return val


def _varint(buf: U8, pos: I64) -> tuple[I64, I64]:
    """SQLite varints at ``pos``: (values, byte lengths). Shrinking subsets: most are 1 byte."""
    if pos.size and int(pos.max()) + 9 > buf.size:
        raise NoIndex("varint outside the file")
    b = buf[pos]
    high = b >= 0x80
    if not high.any():
        return b.astype(np.int64), np.ones(pos.size, dtype=np.int64)
    val = (b & 0x7F).astype(np.int64)
    n = np.ones(pos.size, dtype=np.int64)
    active = np.flatnonzero(high)
    for k in range(1, 9):
        if active.size == 0:
            break
        byte = buf[pos[active] + k].astype(np.int64)
        if k < 8:
            val[active] = (val[active] << 7) | (byte & 0x7F)
            n[active] += 1
            active = active[(byte & 0x80) != 0]
        else:
            val[active] = (val[active] << 8) | byte  # 9th byte: all 8 bits
            n[active] += 1
    return val, n


def _signed_be(buf: U8, pos: I64, types: I64) -> I64:
    """Integer values of serial types 1-6, 8 (0) and 9 (1) at ``pos``, one pass per distinct
    type present (usually one: rosbag2 writes every timestamp as 8 bytes)."""
    out = np.empty(pos.size, dtype=np.int64)
    for t in np.unique(types).tolist():
        sel = types == t
        if t in (8, 9):
            out[sel] = t - 8
            continue
        w = int(_WIDTH[t])
        idx = pos[sel] if not sel.all() else pos
        if w == 8:
            v = buf[idx[:, None] + np.arange(8)].view(">i8").reshape(-1).astype(np.int64)
        else:
            v = _be(buf, idx, w)
            v = np.where(v >= (1 << (8 * w - 1)), v - (1 << (8 * w)), v)
        out[sel] = v
    return out


def _interior_children(buf: U8, off: int, hdr: int, page_size: int) -> list[int]:
    ncells = int(_be(buf, np.array([hdr + 3]), 2)[0])
    if 12 + 2 * ncells > page_size:
        raise NoIndex("interior page cell count out of range")
    ptrs = _be(buf, hdr + 12 + 2 * np.arange(ncells, dtype=np.int64), 2)
    if ncells and (int(ptrs.max()) + 4 > page_size or int(ptrs.min()) < 12):
        raise NoIndex("interior cell outside its page")
    children = _be(buf, off + ptrs, 4).tolist()
    children.append(int(_be(buf, np.array([hdr + 8]), 4)[0]))
    return [int(c) for c in children]


def _leaves(buf: U8, root: int, page_size: int, n_pages: int) -> I64:
    leaves: list[int] = []
    stack, seen = [root], set()
    while stack:
        pg = stack.pop()
        if pg < 2 or pg > n_pages or pg in seen:
            raise NoIndex(f"bad or repeated page number {pg} in the messages B-tree")
        seen.add(pg)
        off = (pg - 1) * page_size
        flag = int(buf[off])
        if flag == 0x0D:
            leaves.append(pg)
        elif flag == 0x05:
            stack.extend(_interior_children(buf, off, off, page_size))
        else:
            raise NoIndex(f"page {pg} is not a table B-tree page (flag {flag:#x})")
    return np.asarray(leaves, dtype=np.int64)


def read_messages(mm: mmap.mmap, root: int, expected_rows: int) -> tuple[I64, I64, I64]:
    """(topic ids, timestamps, payload sizes) of every row of the messages table."""
    buf: U8 = np.frombuffer(mm, dtype=np.uint8)
    if buf.size < 100 or bytes(mm[:16]) != b"SQLite format 3\0":
        raise NoIndex("not an SQLite database")
    page_size = int(_be(buf, np.array([16]), 2)[0])
    page_size = 65536 if page_size == 1 else page_size
    if page_size < 512 or page_size & (page_size - 1):
        raise NoIndex("bad page size")
    usable = page_size - int(buf[20])
    n_pages = buf.size // page_size
    leaves = _leaves(buf, root, page_size, n_pages)
    off = (leaves - 1) * page_size
    ncells = _be(buf, off + 3, 2)
    if np.any(8 + 2 * ncells > usable):
        raise NoIndex("leaf cell count out of range")
    total = int(ncells.sum())
    if total != expected_rows:
        raise NoIndex(f"{total} cells in the B-tree, count(*) says {expected_rows}")
    if total == 0:
        empty = np.empty(0, dtype=np.int64)
        return empty, empty.copy(), empty.copy()
    page_of = np.repeat(np.arange(leaves.size), ncells)
    first = np.repeat(np.cumsum(ncells) - ncells, ncells)
    j = np.arange(total, dtype=np.int64) - first
    base = off[page_of]
    ptr = _be(buf, base + 8 + 2 * j, 2)
    if int(ptr.min()) < 8 or int(ptr.max()) + 4 > usable:
        raise NoIndex("leaf cell outside its page")
    cell = base + ptr
    page_end = base + usable
    payload, n1 = _varint(buf, cell)
    _rowid, n2 = _varint(buf, cell + n1)
    rec = cell + n1 + n2
    hsize, n3 = _varint(buf, rec)
    p = rec + n3
    types = []
    for _ in range(4):
        t, n = _varint(buf, p)
        types.append(t)
        p = p + n
    if np.any(p - rec != hsize):
        raise NoIndex("records are not 4 columns (id, topic_id, timestamp, data)")
    t_id, t_topic, t_time, t_data = types
    ints_ok = ((t_topic <= 6) & (t_topic >= 1)) | (t_topic == 8) | (t_topic == 9)
    ints_ok &= ((t_time <= 6) & (t_time >= 1)) | (t_time == 8) | (t_time == 9)
    if np.any(t_id != 0) or not np.all(ints_ok) or np.any((t_data < 12) | (t_data % 2 == 1)):
        raise NoIndex("unexpected column types in the messages table")
    body = rec + hsize
    w_topic, w_time = _WIDTH[t_topic], _WIDTH[t_time]
    if np.any(body + w_topic + w_time > page_end):
        raise NoIndex("record values outside their page")
    sizes = (t_data - 12) // 2
    if np.any(payload != hsize + w_topic + w_time + sizes):
        raise NoIndex("payload size disagrees with the record")
    tids = _signed_be(buf, body, t_topic)
    times = _signed_be(buf, body + w_topic, t_time)
    return tids, times, sizes


def messages_root(con: object) -> int | None:
    """Root page of rosbag2's messages table, or None when its schema is not the expected one."""
    import sqlite3

    assert isinstance(con, sqlite3.Connection)
    cols = con.execute("PRAGMA table_info(messages)").fetchall()
    if [c[1] for c in cols] != MESSAGES_COLUMNS or cols[0][5] != 1 or str(cols[0][2]).upper() != "INTEGER":
        return None
    row = con.execute("SELECT rootpage, sql FROM sqlite_master WHERE type = 'table' AND name = 'messages'").fetchone()
    if row is None or "WITHOUT ROWID" in str(row[1]).upper():
        return None
    return int(row[0])


def read_file(db: Path, con: object) -> tuple[I64, I64, I64]:
    """Convenience: root page via ``con``, rows straight from the file."""
    import sqlite3

    assert isinstance(con, sqlite3.Connection)
    root = messages_root(con)
    if root is None:
        raise NoIndex("unexpected messages table schema")
    (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
    with db.open("rb") as f:
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            return read_messages(mm, root, int(count))
        finally:
            mm.close()
