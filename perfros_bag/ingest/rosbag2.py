"""rosbag2 recordings: directories (metadata.yaml + sqlite3/mcap files, split or not) and loose .db3.

Storage is inferred per file from its suffix (``.db3``, ``.mcap``, optionally ``.zstd`` for
file compression), so metadata quirks do not matter: ``storage_identifier: ""`` (v5),
``files: []``, stale directory prefixes in ``relative_file_paths`` (v2), or no metadata.yaml
at all. The metadata contributes only the declared topics (so topics without messages are
listed) and the compression mode; counts and durations always come from the messages.

sqlite3 (database opened read-only and immutable), cheapest exact way first:

1. ``sqlite-pages``: the ``messages`` table decoded straight from its B-tree pages
   (:mod:`perfros_bag.ingest.sqlitepages`; blob sizes from the record headers, blobs and their
   overflow pages never read);
2. ``sql``: one pass ``group_concat(topic_id), group_concat(timestamp),
   group_concat(length(data))`` per batch of rowids (no Python per row; ``length`` reads the
   size from the record header), used when a WAL holds committed rows (the database and WAL
   are copied to a temp dir first: ``immutable`` would ignore the WAL) or the table looks
   unusual; a plain row loop if even that fails;
3. with zstd *message* compression the payload size is the decompressed size, read from each
   frame header (``substr(data, 1, 18)``);
4. ``stream`` (``fast=False``): every row with its blob.

Header stamps (``stamps``: a :data:`~perfros_bag.ingest._payload.StampFinder` given the
connection): the first 12 bytes of the stamped topics' blobs are copied in the same page
walk (:func:`~perfros_bag.ingest.sqlitepages.read_messages_heads`, C); without the extension
or with a WAL, from a second page walk (numpy) or one SQL pass.
"""

from __future__ import annotations

import itertools
import mmap
import shutil
import sqlite3
import tempfile
import urllib.parse
import warnings
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fileio import read_yaml
from perfros_bag.ingest import mcapfile, read_head, sniff, sqlitepages
from perfros_bag.ingest._accum import (
    I64,
    U8,
    Accumulator,
    Damaged,
    NoIndex,
    close_mmap,
    describe,
    zstd_header_size,
    zstd_size,
)
from perfros_bag.ingest._payload import STAMP_SIZE, StampAt, StampFinder, cdr_head_stamps
from perfros_bag.ingest.discover import natural_key, storage_of


@dataclass
class Metadata:
    storage: str = ""
    files: list[str] = field(default_factory=list)
    compression_mode: str = ""  # "", "FILE", "MESSAGE"
    compression_format: str = ""  # "", "zstd"
    topics: list[tuple[str, str]] = field(default_factory=list)  # (name, type)


def parse_metadata(path: Path) -> Metadata:
    doc = read_yaml(path)
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise InputError(path, "not rosbag2 metadata (no 'rosbag2_bagfile_information' mapping)")
    meta = Metadata()
    meta.storage = str(info.get("storage_identifier") or "")
    rel = info.get("relative_file_paths") or []
    if not isinstance(rel, list):
        raise InputError(path, "relative_file_paths is not a list")
    meta.files = [str(r) for r in rel if r]
    meta.compression_mode = str(info.get("compression_mode") or "").upper()
    meta.compression_format = str(info.get("compression_format") or "").lower()
    for entry in info.get("topics_with_message_count") or []:
        tm = entry.get("topic_metadata") if isinstance(entry, dict) else None
        if isinstance(tm, dict) and tm.get("name"):
            meta.topics.append((str(tm["name"]), str(tm.get("type") or "")))
    if meta.compression_mode not in ("", "NONE", "FILE", "MESSAGE"):
        raise InputError(path, f"unknown compression_mode {meta.compression_mode!r}")
    if meta.compression_mode in ("FILE", "MESSAGE") and meta.compression_format not in ("zstd", ""):
        raise InputError(path, f"unsupported compression_format {meta.compression_format!r}")
    return meta


def resolve_files(root: Path, meta: Metadata | None) -> list[Path]:
    """The storage files of a rosbag2 directory: those the metadata lists (tolerating stale
    prefixes), plus any other storage file present (with a warning)."""
    present = sorted((p for p in root.iterdir() if p.is_file() and storage_of(p)), key=natural_key)
    if meta is None or not meta.files:
        return present
    listed: list[Path] = []
    for rel in meta.files:
        base = Path(rel).name
        candidates = [root / rel, root / base, root / (base + ".zstd")]
        if base.endswith(".zstd"):
            candidates.append(root / base[:-5])
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise InputError(root, f"metadata.yaml lists {rel!r}, which does not exist")
        if storage_of(found) is None:
            what = meta.storage or "none"
            raise InputError(found, f"unknown storage {what!r} (expected a .db3 or .mcap file)")
        if found not in listed:
            listed.append(found)
    extra = [p for p in present if p not in listed]
    if extra:
        warnings.warn(f"{root}: storage files not listed in metadata.yaml also read: "
                      + ", ".join(p.name for p in extra), PerfrosWarning, stacklevel=2)
    return listed + extra


@contextmanager
def _decompressed(path: Path) -> Iterator[Path]:
    """A zstd-compressed storage file (rosbag2 FILE compression) decompressed to a temp file."""
    import zstandard

    with tempfile.TemporaryDirectory(prefix="perfros-") as tmp:
        target = Path(tmp) / path.name[:-5] if path.name.endswith(".zstd") else Path(tmp) / path.name
        with path.open("rb") as src, target.open("wb") as dst:
            zstandard.ZstdDecompressor().copy_stream(src, dst)
        yield target


@contextmanager
def open_mmap(path: Path) -> Iterator[mmap.mmap]:
    with path.open("rb") as f:
        if path.stat().st_size == 0:
            raise InputError(path, "empty file (0 bytes)")
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            yield mm
        finally:
            close_mmap(mm)



@contextmanager
def connect_db(db: Path) -> Iterator[tuple[sqlite3.Connection, bool]]:
    """Read-only, immutable connection; a database with a non-empty WAL is copied with it first
    (immutable would ignore the WAL's committed messages). Yields (connection, WAL in use)."""
    wal = db.with_name(db.name + "-wal")
    tmp: tempfile.TemporaryDirectory[str] | None = None
    try:
        if wal.is_file() and wal.stat().st_size > 0:
            tmp = tempfile.TemporaryDirectory(prefix="perfros-")
            shutil.copy(db, Path(tmp.name) / db.name)
            shutil.copy(wal, Path(tmp.name) / wal.name)
            uri = "file:" + urllib.parse.quote(str(Path(tmp.name) / db.name)) + "?mode=ro"
        else:
            uri = "file:" + urllib.parse.quote(str(db.resolve())) + "?mode=ro&immutable=1"
        con = sqlite3.connect(uri, uri=True)
        try:
            yield con, tmp is not None
        finally:
            con.close()
    finally:
        if tmp is not None:
            tmp.cleanup()


SQL_BATCH = 1_000_000  # rowids per query: bounds the size of the concatenated strings


def parse_ints(text: str | None, n: int) -> I64:
    if n == 0:
        return np.empty(0, dtype=np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns (here: raises) on text it cannot parse
        arr = np.fromstring(text or "", sep=",", dtype=np.int64)
    if arr.size != n:
        raise ValueError("column count mismatch")
    return arr


def _sql_columns(con: sqlite3.Connection) -> tuple[I64, I64, I64] | None:
    """topic ids, timestamps, payload sizes of all messages, aggregated by SQLite itself.

    ``group_concat`` builds one text column per batch of rowids inside SQLite, so Python never
    sees a row (a row loop costs ~1 us per message, 10x the scan); numpy parses the text. One
    table scan; ``length(data)`` reads the blob size from the record header, not the blob.
    None when the table does not look as expected (NULLs, non-integers): the caller then loops
    over rows.
    """
    try:
        lo, hi = con.execute("SELECT min(rowid), max(rowid) FROM messages").fetchone()
        if lo is None:
            return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int64)
        parts: list[tuple[I64, I64, I64]] = []
        for a in range(int(lo), int(hi) + 1, SQL_BATCH):
            n, t, ts, ln = con.execute(
                "SELECT count(*), group_concat(topic_id), group_concat(timestamp), "
                "group_concat(length(data)) FROM messages WHERE rowid >= ? AND rowid < ?",
                (a, a + SQL_BATCH)).fetchone()
            parts.append((parse_ints(t, n), parse_ints(ts, n), parse_ints(ln, n)))
    except (ValueError, TypeError, Warning, sqlite3.Error):
        return None
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))  # type: ignore[return-value]


def _rows_loop(rows: Iterable[tuple[Any, Any, Any]],
               size_of: Callable[[Any], int]) -> tuple[I64, I64, I64]:
    tid_l, time_l, size_l = [], [], []
    for tid, ts, value in rows:
        tid_l.append(tid)
        time_l.append(ts)
        size_l.append(size_of(value))
    return tuple(np.asarray(x, dtype=np.int64) for x in (tid_l, time_l, size_l))  # type: ignore[return-value]


def _columns(con: sqlite3.Connection, db: Path, fast: bool, message_zstd: bool,
             wal: bool) -> tuple[tuple[I64, I64, I64], str]:
    """(topic ids, timestamps, payload sizes) and how they were read, cheapest way first."""
    if not fast:
        size = (lambda b: zstd_size(bytes(b))) if message_zstd else len
        return _rows_loop(con.execute("SELECT topic_id, timestamp, data FROM messages"), size), "stream"
    if message_zstd:  # the decompressed size is in each zstd frame header
        def frame_size(row: Any) -> int:
            head, mid = row
            size = zstd_header_size(head)
            if size < 0:
                (blob,) = con.execute("SELECT data FROM messages WHERE id = ?", (mid,)).fetchone()
                size = zstd_size(bytes(blob))
            return size

        cur = con.execute("SELECT topic_id, timestamp, substr(data, 1, 18), id FROM messages")
        return _rows_loop(((tid, ts, (head, mid)) for tid, ts, head, mid in cur), frame_size), "sql"
    if not wal:  # immutable file: straight from the B-tree pages
        try:
            return sqlitepages.read_file(db, con), "sqlite-pages"
        except NoIndex:
            pass
    columns = _sql_columns(con)
    if columns is not None:
        return columns, "sql"
    cur = con.execute("SELECT topic_id, timestamp, length(data) FROM messages")
    flat = np.fromiter(itertools.chain.from_iterable(cur), dtype=np.int64).reshape(-1, 3)
    return (flat[:, 0], flat[:, 1], flat[:, 2]), "sql"


HEAD = 4 + STAMP_SIZE  # a CDR payload's first bytes up to the end of header.stamp


def _stamped_rows(con: sqlite3.Connection, db: Path, wal: bool, ids: list[int]) -> tuple[I64, I64, U8]:
    """(topic ids, timestamps, first :data:`HEAD` bytes of the blob) of the rows of topics
    ``ids``, when the C walk did not give them: the numpy page walk, else one SQL pass.
    NoIndex when such a blob is shorter."""
    root = None if wal else sqlitepages.messages_root(con)
    if root is not None:
        (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
        try:
            with open_mmap(db) as mm:
                return sqlitepages.read_blob_heads(mm, root, int(count), ids, HEAD)
        except NoIndex:
            pass  # the SQL pass below
    marks = ",".join("?" * len(ids))
    n, tids_text, times_text, heads, shortest = con.execute(
        "SELECT count(*), group_concat(topic_id), group_concat(timestamp), "
        f"group_concat(hex(substr(data, 1, {HEAD})), ''), min(length(data)) "
        f"FROM messages WHERE topic_id IN ({marks})", tuple(ids)).fetchone()  # noqa: S608 - only '?'
    if n == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, HEAD), np.uint8)
    if shortest is None or int(shortest) < HEAD:
        raise NoIndex("a stamped message shorter than its header")
    raw = np.frombuffer(bytes.fromhex(heads), dtype=np.uint8)
    if raw.size != n * HEAD:
        raise NoIndex("stamp bytes do not match the message count")
    return parse_ints(tids_text, n), parse_ints(times_text, n), raw.reshape(n, HEAD)


def _add_stamps(acc: Accumulator, wanted: dict[int, StampAt], tids: I64, times: I64, heads: U8) -> None:
    """The stamps of rows (topic ids, timestamps, first bytes of their CDR blobs) by topic."""
    if any(not at.cdr or at.offset != 4 for at in wanted.values()):
        raise NoIndex("header.stamp not right after the CDR encapsulation")
    stamps = cdr_head_stamps(heads)
    ids = list(wanted)
    zeros = np.zeros(tids.size, np.int64)
    by_time = sqlitepages.group_by_topic(tids, times, zeros, ids)  # C counting sorts, row order kept
    by_stamp = sqlitepages.group_by_topic(tids, stamps, zeros, ids) if by_time is not None else None
    for k, (tid, at) in enumerate(wanted.items()):
        if by_time is not None and by_stamp is not None:
            acc.add_stamps(at.topic, by_time[0][k], by_stamp[0][k])
        else:
            mask = tids == tid
            acc.add_stamps(at.topic, times[mask], stamps[mask])


def read_sqlite(db: Path, fast: bool = True, message_zstd: bool = False,
                stamps: StampFinder | None = None) -> Accumulator:
    """One rosbag2 sqlite3 file. Method: "sqlite-pages" (B-tree pages, the fast path), "sql"
    (one SQL pass: WAL present, message compression or an unexpected table) or "stream".
    ``stamps``: which topics' header stamps to read too (NoIndex with message compression or
    without ``fast``)."""
    acc = Accumulator()
    with connect_db(db) as (con, wal):
        try:
            topic_rows = con.execute("SELECT id, name, type FROM topics").fetchall()
        except sqlite3.DatabaseError as exc:
            raise Damaged(f"not a rosbag2 sqlite3 database ({exc})") from None
        topics = {int(tid): (str(name), str(mtype or "")) for tid, name, mtype in topic_rows}
        wanted = dict(stamps(con)) if stamps is not None else {}
        if wanted and (message_zstd or not fast):
            raise NoIndex("header stamps are read in place only from uncompressed payloads, on the fast path")
        in_walk = None
        stamped: tuple[I64, I64, U8] | None = None
        if wanted and not wal:
            root = sqlitepages.messages_root(con)
            if root is not None:
                (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
                try:
                    with open_mmap(db) as mm:
                        in_walk = sqlitepages.read_messages_heads(mm, root, int(count), list(wanted), HEAD)
                except NoIndex:
                    pass  # the extension is not built, or the table is unusual: the other ways
        if in_walk is not None:
            tids, times, sizes, rows, heads = in_walk
            acc.method = "sqlite-pages"
            if rows.size and int(sizes[rows].min()) < HEAD:
                raise NoIndex("a stamped message shorter than its header")
            stamped = (tids[rows], times[rows], heads)
        else:
            (tids, times, sizes), acc.method = _columns(con, db, fast, message_zstd, wal)
            stamped = _stamped_rows(con, db, wal, list(wanted)) if wanted else None
    if stamped is not None:
        _add_stamps(acc, wanted, *stamped)
    grouped = sqlitepages.group_by_topic(tids, times, sizes, list(topics))
    if grouped is not None:  # one counting sort in C
        for (name, mtype), tt, nbytes in zip(topics.values(), *grouped, strict=True):
            acc.add(name, mtype, tt, nbytes)
        return acc
    if len(topics) <= 16:  # a mask per topic beats a sort of all rows
        known = np.zeros(tids.size, dtype=bool)
        for tid, (name, mtype) in topics.items():
            mask = tids == tid
            known |= mask
            acc.add(name, mtype, times[mask], int(sizes[mask].sum()))
        if not known.all():
            raise Damaged(f"messages for unknown topic id(s) {sorted(set(tids[~known].tolist()))}")
        return acc
    order = np.argsort(tids, kind="stable")
    tids, times, sizes = tids[order], times[order], sizes[order]
    present = tids[np.r_[True, tids[1:] != tids[:-1]]] if tids.size else tids
    unknown = set(present.tolist()) - set(topics)
    if unknown:
        raise Damaged(f"messages for unknown topic id(s) {sorted(unknown)}")
    for tid, (name, mtype) in topics.items():
        lo, hi = np.searchsorted(tids, [tid, tid + 1])
        acc.add(name, mtype, times[lo:hi], int(sizes[lo:hi].sum()))
    return acc


def read_storage_file(path: Path, fast: bool = True, message_zstd: bool = False,
                      stamps: StampFinder | None = None) -> Accumulator:
    """One storage file of a rosbag2 recording (file compression undone first); ``stamps``:
    header stamps read in the same pass (not from compressed files)."""
    if path.name.endswith(".zstd"):
        if stamps is not None:
            raise NoIndex("header stamps are not read in place from a compressed file")
        with _decompressed(path) as plain:
            return read_storage_file(plain, fast, message_zstd)
    fmt = sniff(read_head(path))
    if fmt == "rosbag2-sqlite3":
        return read_sqlite(path, fast, message_zstd, stamps)
    if fmt == "mcap":
        with open_mmap(path) as mm:
            return mcapfile.read(mm, fast, message_zstd, stamps)
    if fmt == "zstd":
        raise InputError(path, "zstd-compressed file without a .zstd suffix")
    raise InputError(path, "not a sqlite3 or MCAP storage file")


def read_dir(root: Path, fast: bool = True, stamps: StampFinder | None = None) -> tuple[Accumulator, str]:
    """Every storage file of the directory ``root`` (``stamps``: with header stamps, each
    file's own definitions deciding which topics have them)."""
    meta_path = root / "metadata.yaml"
    meta = parse_metadata(meta_path) if meta_path.is_file() else None
    files = resolve_files(root, meta)
    if not files:
        if meta is not None and meta.storage not in ("", "sqlite3", "mcap"):
            raise InputError(root, f"unknown storage {meta.storage!r} and no .db3 or .mcap file")
        raise InputError(root, "no .db3 or .mcap file: not a rosbag2 recording")
    message_zstd = meta is not None and meta.compression_mode == "MESSAGE"
    acc = Accumulator()
    for f in files:
        try:
            acc.extend(read_storage_file(f, fast, message_zstd, stamps))
        except InputError:
            raise
        except Exception as exc:  # corrupt data can fail anywhere: one clear line, never a traceback
            raise InputError(f, describe(exc)) from None
    if meta is not None:
        for name, mtype in meta.topics:
            acc.declare(name, mtype)
    return acc, "rosbag2-" + (storage_of(files[0]) or "unknown")
