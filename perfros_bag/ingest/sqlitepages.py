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

Two implementations of the same decoder: the C extension ``_sqlitecells`` (one pass per cell,
built at install time; ~4x less CPU than numpy on 1M small messages) and the numpy one below (whole-array
passes), used when the extension is not built (no C compiler) and compared against the C one
and against SQLite itself in the tests. :data:`DECODER` says which one runs.
"""

from __future__ import annotations

import functools
import mmap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from perfros_bag.ingest._accum import I64, RELEASE_STEP, U8, NoIndex, close_mmap, release

#: "c" (the extension) or "numpy": which decoder :func:`read_messages` uses.
DECODER = "c"
try:
    from perfros_bag.ingest import _sqlitecells
except ImportError:  # built without a C compiler: the numpy decoder does the same work
    DECODER = "numpy"

_WIDTH = np.array([0, 1, 2, 3, 4, 6, 8, -1, 0, 0], dtype=np.int64)  # serial type -> int width
MESSAGES_COLUMNS = ["id", "topic_id", "timestamp", "data"]


def _be(buf: U8, pos: I64, width: int) -> I64:
    """Unsigned big-endian integers of a fixed width at ``pos``."""
    val = np.zeros(pos.size, dtype=np.int64)
    for k in range(width):
        val = (val << 8) | buf[pos + k].astype(np.int64)
    return val


SLICE = 1 << 16  # positions per slice of a page-releasing gather


def _be_released(mm: mmap.mmap | None, buf: U8, pos: I64, width: int) -> I64:
    """:func:`_be` in slices, unmapping the pages each slice touched (see
    :func:`perfros_bag.ingest._accum.release`): reading one value from every page of a large
    file would otherwise keep the whole file resident."""
    if mm is None or pos.size <= SLICE:
        val = _be(buf, pos, width)
        if mm is not None and pos.size:
            release(mm, int(pos.min()), int(pos.max()) + width)
        return val
    out = np.empty(pos.size, dtype=np.int64)
    for a in range(0, pos.size, SLICE):
        part = pos[a:a + SLICE]
        out[a:a + SLICE] = _be(buf, part, width)
        release(mm, int(part.min()), int(part.max()) + width)
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


def _leaves(buf: U8, root: int, page_size: int, n_pages: int,
            mm: mmap.mmap | None = None) -> I64:
    """Leaf pages of the table B-tree under ``root`` (interior pages walked level by level)."""
    seen = np.zeros(n_pages + 1, dtype=bool)
    leaves: list[I64] = []
    level = np.array([root], dtype=np.int64)
    while level.size:
        if int(level.min()) < 2 or int(level.max()) > n_pages or seen[level].any():
            raise NoIndex("bad or repeated page number in the messages B-tree")
        before = int(np.count_nonzero(seen))
        seen[level] = True
        if int(np.count_nonzero(seen)) - before != level.size:
            raise NoIndex("repeated page number in the messages B-tree")
        flags = _be_released(mm, buf, (level - 1) * page_size, 1)
        if not np.all((flags == 0x0D) | (flags == 0x05)):
            raise NoIndex("a page of the messages B-tree is not a table B-tree page")
        leaves.append(level[flags == 0x0D])
        children: list[int] = []
        for pg in level[flags == 0x05].tolist():
            off = (pg - 1) * page_size
            children.extend(_interior_children(buf, off, off, page_size))
        level = np.asarray(children, dtype=np.int64)
    return np.concatenate(leaves)


W = 48  # bytes of a cell that hold every varint and both integer values of a valid record
BATCH = 500_000  # cells per window matrix (48 bytes each)


def _mvarint(m: U8, rowbase: I64, col: I64, value: bool = True) -> tuple[I64, I64]:
    """Varints at per-row columns ``col`` of the flattened window matrix ``m`` (rows start at
    ``rowbase``): (values, lengths); ``value=False`` computes the lengths only."""
    if col.size and int(col.max()) + 9 > W:
        raise NoIndex("record header longer than expected")
    pos = rowbase + col
    b8 = m[pos]
    if col.size == 0 or int(b8.max()) < 0x80:  # all one byte (serial types of integers)
        return b8.astype(np.int64), np.ones(col.size, dtype=np.int64)
    cont = b8 >= 0x80
    n = np.ones(col.size, dtype=np.int64)
    val = (b8 & 0x7F).astype(np.int64) if value else n
    active = np.flatnonzero(cont)
    if active.size * 4 < col.size:  # few multi-byte varints: work on that subset only
        for k in range(1, 9):
            byte = m[pos[active] + k].astype(np.int64)
            if value:
                val[active] = (val[active] << (7 if k < 8 else 8)) | (byte & (0x7F if k < 8 else 0xFF))
            n[active] += 1
            active = active[(byte & 0x80) != 0] if k < 8 else active[:0]
            if active.size == 0:
                break
        return val, n
    for k in range(1, 9):
        bk = m[pos + k]
        if value:
            if k < 8:
                val = np.where(cont, (val << 7) | (bk & 0x7F), val)
            else:
                val = np.where(cont, (val << 8) | bk, val)
        n += cont
        cont &= bk >= 0x80
        if not cont.any():
            break
    return val, n


def _mint(m: U8, rowbase: I64, col: I64, types: I64) -> I64:
    """Integers of serial types 1-6, 8 (0) and 9 (1) at per-row columns ``col`` of ``m``.

    Whole-array passes, one per byte of the widest value; 8-byte values (rosbag2 timestamps)
    are read as one big-endian word each."""
    if col.size == 0:
        return np.empty(0, dtype=np.int64)
    widths = _WIDTH[types]
    maxw = int(widths.max())
    if int(col.max()) + maxw > W:
        raise NoIndex("record values outside the expected window")
    pos = rowbase + col
    eight = widths == 8
    if eight.all():
        return np.lib.stride_tricks.sliding_window_view(m, 8)[pos].view(">i8").reshape(-1).astype(np.int64)
    v = np.zeros(col.size, dtype=np.int64)
    for k in range(min(maxw, 6)):
        v = np.where(k < widths, (v << 8) | m[pos + k], v)
    small = (widths > 0) & (widths < 8)
    if small.any():  # two's complement of 1-6 byte values
        bits = 8 * np.where(small, widths, 1)
        v = np.where(small & (v >= (1 << (bits - 1))), v - (1 << bits), v)
    v = np.where(types == 9, 1, np.where(types == 8, 0, v))
    if eight.any():
        sel = np.flatnonzero(eight)
        v[sel] = np.lib.stride_tricks.sliding_window_view(m, 8)[pos[sel]].view(">i8").reshape(-1)
    return v


def _window(buf: U8, cell: I64, w: int = W) -> U8:
    """The ``w`` bytes at every cell as a (cells, w) matrix, gathered as whole rows of a strided view (no index matrix);
    cells closer than W to the end of the file read zero padding past it."""
    view = np.lib.stride_tricks.sliding_window_view(buf, w)
    near_end = cell > buf.size - w
    if not near_end.any():
        return view[cell]
    m = view[np.where(near_end, 0, cell)]
    tail = np.concatenate([buf[buf.size - w:], np.zeros(w, dtype=np.uint8)])
    tview = np.lib.stride_tricks.sliding_window_view(tail, w)
    m[near_end] = tview[cell[near_end] - (buf.size - w)]
    return m


K = 16  # leading bytes of a cell whose continuation bits fix the record header's layout
WF = 32  # bytes per cell the fast path reads: a header within K bytes, then two <= 8-byte values
VALID = np.zeros(256, dtype=bool)
VALID[[1, 2, 3, 4, 5, 6, 8, 9]] = True  # integer serial types
WIDTH256 = np.zeros(256, dtype=np.int64)
WIDTH256[:10] = np.maximum(_WIDTH, 0)


@functools.lru_cache(maxsize=1 << K)
def _layout(key: int) -> tuple[int, int, int] | None:
    """Varint lengths implied by the continuation bits ``key`` (bit j: byte j >= 0x80) of a
    cell's first K bytes: (payload size varint length, header start, data serial type length);
    None unless the 7 leading varints (payload size, rowid, header size, 4 serial types) fit in
    K bytes, each at most 4 bytes long, with the header size and the first 3 types one byte."""
    pos, lens = 0, []
    for _ in range(7):
        n = 1
        while (key >> (pos + n - 1)) & 1:
            n += 1
            if n > 4 or pos + n > K:
                return None
        lens.append(n)
        pos += n
    if lens[2:6] != [1, 1, 1, 1]:
        return None
    return lens[0], lens[0] + lens[1], lens[6]


def _cont_bits(m: U8) -> I64:
    """Per row of the (cells, W) matrix ``m``: bit j set when byte j (< K) is >= 0x80 (a
    movemask: each 8-byte word's high bits gathered into one byte by one multiplication)."""
    words = m.view("<u8")[:, :2]
    x = (words >> np.uint64(7)) & np.uint64(0x0101010101010101)
    packed = (x * np.uint64(0x0102040810204080)) >> np.uint64(56)
    return (packed[:, 0] | (packed[:, 1] << np.uint64(8))).astype(np.intp)


def _lengths(bits: I64) -> tuple[np.ndarray, I64, np.ndarray, np.ndarray]:
    """(payload varint length, header start, data type length, layout known) per cell, looked
    up per distinct continuation-bit key."""
    table = np.zeros(1 << K, dtype=np.int16)  # n1 | r << 4 | nd << 8 | known << 12
    for key in np.flatnonzero(np.bincount(bits, minlength=1 << K)).tolist():
        lay = _layout(int(key))
        if lay is not None:
            table[key] = lay[0] | lay[1] << 4 | lay[2] << 8 | 1 << 12
    code = table[bits]
    return code & 15, (code >> 4 & 15).astype(np.int64), code >> 8 & 15, code >= 1 << 12


def _varint_n(cols: list[U8], n: np.ndarray) -> I64:
    """Varints whose per-row length ``n`` (<= len(cols)) is known; ``cols`` their bytes."""
    v = (cols[0] & 0x7F).astype(np.int64)
    for k in range(1, int(n.max()) if n.size else 0):
        v = np.where(n > k, (v << 7) | (cols[k] & 0x7F), v)
    return v


def _cells(buf: U8, cell: I64, page_end: I64) -> tuple[I64, I64, I64]:
    """Decode a batch of leaf cells: (topic ids, timestamps, payload sizes).

    Fast path: the continuation bits of a cell's first K bytes fix every varint boundary of its
    record header (looked up per distinct pattern), so the header is one 8-byte gather per
    cell instead of a varint decode per field. Cells it does not accept (unusual layouts, or
    any failed check) go through :func:`_cells_general`, which decodes them varint by varint
    and raises :class:`NoIndex` on what is really wrong."""
    m = _window(buf, cell, WF)
    n1, r, nd, ok = _lengths(_cont_bits(m))
    flat = m.reshape(-1)
    rowbase = np.arange(cell.size, dtype=np.int64) * WF
    hdr = np.lib.stride_tricks.sliding_window_view(flat, 8)[rowbase + r]
    hsize, t_top, t_time = hdr[:, 0], hdr[:, 2], hdr[:, 3]
    ok &= (hsize == 4 + nd) & (hdr[:, 1] == 0) & VALID[t_top] & VALID[t_time]
    t_data = _varint_n([hdr[:, 4 + k] for k in range(4)], nd)
    sizes = (t_data - 12) // 2
    w_topic, w_time = WIDTH256[t_top], WIDTH256[t_time]
    body = r + 4 + nd  # = r + hsize where ok (a damaged hsize must not move the reads)
    values = w_topic + w_time
    ok &= (t_data >= 12) & ((t_data & 1) == 0) & (cell + body + values <= page_end)
    ok &= _varint_n([m[:, k] for k in range(4)], n1) == hsize + values + sizes
    all_ok = bool(ok.all())
    safe_top = t_top if all_ok else np.where(ok, t_top, 8)
    if int(w_topic.max()) <= 1:  # topic ids 0-127: one signed byte, or types 8 / 9 (0, 1)
        topic = np.where(w_topic == 1, flat.view(np.int8)[rowbase + body], safe_top == 9).astype(np.int64)
    else:
        topic = _mint(flat, rowbase, body, safe_top)
    time = _mint(flat, rowbase, body + w_topic, t_time if all_ok else np.where(ok, t_time, 8))
    if not all_ok:
        bad = np.flatnonzero(~ok)
        topic[bad], time[bad], sizes[bad] = _cells_general(_window(buf, cell[bad]), cell[bad], page_end[bad])
    return topic, time, sizes


def _cells_general(m2: U8, cell: I64, page_end: I64) -> tuple[I64, I64, I64]:
    """:func:`_cells` for any layout, from the cells' (cells, W) byte matrix."""
    topic, time, sizes, _data, _payload_start, _payload = _records(m2, cell, page_end)
    return topic, time, sizes


def _records(m2: U8, cell: I64, page_end: I64) -> tuple[I64, I64, I64, I64, I64, I64]:
    """Every checked field of the cells' records: (topic ids, timestamps, blob sizes, where
    each blob starts in the file, where each record (the cell's payload) starts, its size)."""
    m = m2.reshape(-1)
    rowbase = np.arange(cell.size, dtype=np.int64) * W
    payload, n1 = _mvarint(m, rowbase, np.zeros(cell.size, dtype=np.int64))
    _, n2 = _mvarint(m, rowbase, n1, value=False)  # the rowid itself is not needed
    rec = n1 + n2
    hsize, n3 = _mvarint(m, rowbase, rec)
    p = rec + n3
    types = []
    for _ in range(4):
        t, n = _mvarint(m, rowbase, p)
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
    if np.any(cell + body + w_topic + w_time > page_end):
        raise NoIndex("record values outside their page")
    sizes = (t_data - 12) // 2
    if np.any(payload != hsize + w_topic + w_time + sizes):
        raise NoIndex("payload size disagrees with the record")
    return (_mint(m, rowbase, body, t_topic), _mint(m, rowbase, body + w_topic, t_time), sizes,
            cell + body + w_topic + w_time, cell + rec, payload)


def _local(payload: I64, usable: int) -> I64:
    """Bytes of a table leaf cell's payload stored on its page (SQLite file format, B-tree
    pages): all of it up to X = U - 35, else K when K <= X, else M."""
    x = usable - 35
    m = ((usable - 12) * 32 // 255) - 23
    k = m + (payload - m) % (usable - 4)
    return np.where(payload <= x, payload, np.where(k <= x, k, m))


def _page_geometry(mm: mmap.mmap) -> tuple[int, int]:
    """(page size, usable bytes per page) from the database header."""
    if len(mm) < 100 or mm[:16] != b"SQLite format 3\0":
        raise NoIndex("not an SQLite database")
    page_size = int.from_bytes(mm[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    if page_size < 512 or page_size & (page_size - 1):
        raise NoIndex("bad page size")
    usable = page_size - mm[20]
    if usable < 480:
        raise NoIndex("bad reserved space per page")
    return page_size, usable


def read_messages(mm: mmap.mmap, root: int, expected_rows: int) -> tuple[I64, I64, I64]:
    """(topic ids, timestamps, payload sizes) of every row of the messages table."""
    page_size, usable = _page_geometry(mm)
    if DECODER == "c":
        return _read_c(mm, root, expected_rows, page_size, usable)
    return _read_numpy(mm, root, expected_rows, page_size, usable)


def _read_c(mm: mmap.mmap, root: int, expected_rows: int, page_size: int,
            usable: int) -> tuple[I64, I64, I64]:
    """:func:`read_messages` by the C extension (pages released every RELEASE_STEP bytes)."""
    topic, time, size = (np.empty(expected_rows, dtype=np.int64) for _ in range(3))
    try:
        n = _sqlitecells.decode(mm, root, page_size, usable, topic, time, size,
                                lambda a, b: release(mm, a, b), RELEASE_STEP)
    except _sqlitecells.Malformed as exc:
        raise NoIndex(str(exc)) from None
    if n != expected_rows:
        raise NoIndex(f"{n} cells in the B-tree, count(*) says {expected_rows}")
    return topic, time, size


def read_messages_heads(mm: mmap.mmap, root: int, expected_rows: int, want: Sequence[int],
                        nbytes: int) -> tuple[I64, I64, I64, I64, U8]:
    """:func:`read_messages` and, in the same walk (C extension only: NoIndex without it),
    the first ``nbytes`` of the data blob of every row whose topic id is in ``want``: (topic
    ids, timestamps, sizes, those rows' numbers, their heads as a (rows, nbytes) matrix, zero
    filled past a shorter blob). The outputs are allocated for every row but only the wanted
    rows' pages are written."""
    if DECODER != "c" or not hasattr(_sqlitecells, "decode_heads"):  # not built, or built before it
        raise NoIndex("blob heads in the page walk need the C extension (rebuilt: pip install -e .)")
    page_size, usable = _page_geometry(mm)
    topic, time, size, rows = (np.empty(expected_rows, dtype=np.int64) for _ in range(4))
    heads = np.empty((expected_rows, nbytes), dtype=np.uint8)
    if expected_rows == 0 or not want:
        return topic, time, size, rows[:0], heads[:0]
    try:
        n, m = _sqlitecells.decode_heads(mm, root, page_size, usable, topic, time, size,
                                         lambda a, b: release(mm, a, b), RELEASE_STEP,
                                         np.asarray(list(want), dtype=np.int64), heads.reshape(-1), rows)
    except _sqlitecells.Malformed as exc:
        raise NoIndex(str(exc)) from None
    if n != expected_rows:
        raise NoIndex(f"{n} cells in the B-tree, count(*) says {expected_rows}")
    return topic, time, size, rows[:m], heads[:m]


def group_by_topic(tids: I64, times: I64, sizes: I64,
                   ids: list[int]) -> tuple[list[I64], list[int]] | None:
    """Times of each topic id of ``ids`` (in row order) and its byte total, by the extension's
    counting sort; None when the extension is not built, a row's id is not in ``ids`` or the
    ids are too sparse for its lookup table (the caller then groups with numpy)."""
    if DECODER != "c" or not ids:
        return None
    idarr = np.asarray(ids, dtype=np.int64)
    tids, times, sizes = (np.ascontiguousarray(a, dtype=np.int64) for a in (tids, times, sizes))
    counts, nbytes = np.empty(idarr.size, np.int64), np.empty(idarr.size, np.int64)
    grouped = np.empty(tids.size, dtype=np.int64)
    if not _sqlitecells.group(tids, times, sizes, idarr, counts, nbytes, grouped):
        return None
    return np.split(grouped, np.cumsum(counts)[:-1]), nbytes.tolist()


def _read_numpy(mm: mmap.mmap, root: int, expected_rows: int, page_size: int,
                usable: int) -> tuple[I64, I64, I64]:
    """:func:`read_messages` by whole-array numpy passes."""
    buf: U8 = np.frombuffer(mm, dtype=np.uint8)
    cell, page_end = _leaf_cells(mm, buf, root, expected_rows, page_size, usable)
    if cell.size == 0:
        empty = np.empty(0, dtype=np.int64)
        return empty, empty.copy(), empty.copy()
    parts = []
    for a in range(0, cell.size, BATCH):
        parts.append(_cells(buf, cell[a:a + BATCH], page_end[a:a + BATCH]))
        release(mm, int(cell[a:a + BATCH].min()), int(cell[a:a + BATCH].max()) + W)
    if len(parts) == 1:
        return parts[0]
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


def _leaf_cells(mm: mmap.mmap, buf: U8, root: int, expected_rows: int, page_size: int,
                usable: int) -> tuple[I64, I64]:
    """Where every cell of the messages table starts in the file, and the end of its page's
    usable area, in rowid order; the cell count must equal ``expected_rows``."""
    n_pages = buf.size // page_size
    leaves = _leaves(buf, root, page_size, n_pages, mm)
    off = (leaves - 1) * page_size
    ncells = _be_released(mm, buf, off + 3, 2)
    if np.any(8 + 2 * ncells > usable):
        raise NoIndex("leaf cell count out of range")
    total = int(ncells.sum())
    if total != expected_rows:
        raise NoIndex(f"{total} cells in the B-tree, count(*) says {expected_rows}")
    if total == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    base = np.repeat(off, ncells)
    u16 = buf[:buf.size & ~1].view(">u2")  # cell pointers sit at even offsets of a page
    # u16 index of cell pointer j of a page: (page offset + 8) / 2 + j, with j = i - first(i)
    at = np.repeat((off + 8) // 2 - (np.cumsum(ncells) - ncells), ncells) + np.arange(total, dtype=np.int64)
    ptr = np.empty(total, dtype=np.int64)
    for a in range(0, total, SLICE):  # pages released slice by slice, as in _be_released
        ptr[a:a + SLICE] = u16[at[a:a + SLICE]]
        part = base[a:a + SLICE]
        release(mm, int(part.min()), int(part.max()) + page_size)
    if int(ptr.min()) < 8 or int(ptr.max()) + 4 > usable:
        raise NoIndex("leaf cell outside its page")
    return base + ptr, base + usable


def read_blob_heads(mm: mmap.mmap, root: int, expected_rows: int, topic_ids: Sequence[int],
                    nbytes: int) -> tuple[I64, I64, U8]:
    """(topic ids, timestamps, the first ``nbytes`` of the ``data`` blob as a (rows, nbytes)
    matrix) of the rows of the messages table whose topic is in ``topic_ids``, in rowid
    order, from the B-tree pages (numpy; every record checked as in :func:`_cells_general`).
    NoIndex when such a blob is shorter than ``nbytes`` or its first bytes are not on the
    leaf page (the caller uses SQL)."""
    page_size, usable = _page_geometry(mm)
    buf: U8 = np.frombuffer(mm, dtype=np.uint8)
    cell, page_end = _leaf_cells(mm, buf, root, expected_rows, page_size, usable)
    wanted = np.asarray(list(topic_ids), dtype=np.int64)
    parts = []
    for a in range(0, cell.size, BATCH):
        c, e = cell[a:a + BATCH], page_end[a:a + BATCH]
        topic, time, sizes, data, start, payload = _records(_window(buf, c), c, e)
        keep = np.isin(topic, wanted)
        topic, time, sizes, data, start, payload, e = (x[keep] for x in (topic, time, sizes, data, start, payload, e))
        if sizes.size and (int(sizes.min()) < nbytes
                           or np.any(data + nbytes > np.minimum(start + _local(payload, usable), e))):
            raise NoIndex("a blob shorter than asked, or its first bytes off the leaf page")
        parts.append((topic, time, np.lib.stride_tricks.sliding_window_view(buf, nbytes)[data].copy()))
        release(mm, int(c.min()), int(c.max()) + W)
    if not parts:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, nbytes), np.uint8)
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


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
            close_mmap(mm)
