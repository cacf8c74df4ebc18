"""The B-tree page decoders of rosbag2's messages table (the C extension and the numpy one)
against SQLite's own answer, with rows that take the fixed-layout fast paths and rows that
need the general varint decoders (huge rowids, wide or negative topic ids, overflow pages)
mixed in one table; against each other on damaged files; the C counting sort by topic
against numpy masks."""

from __future__ import annotations

import os
import random
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.ingest import sqlitepages
from perfros_bag.ingest._accum import NoIndex
from tests.conftest import REALBAGS

DECODERS = ["c", "numpy"]

SCHEMA = ("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
          "timestamp INTEGER NOT NULL, data BLOB NOT NULL)")

ints = st.one_of(st.integers(-2**63, 2**63 - 1), st.integers(-300, 300), st.sampled_from([0, 1]))
# blob sizes: on the page, and past a 512-byte page's local limit (overflow pages)
row = st.tuples(st.integers(1, 2**62), ints, ints, st.one_of(st.integers(0, 400), st.integers(400, 3000)))


def _sql(con: sqlite3.Connection) -> tuple[np.ndarray, ...]:
    rows = con.execute("SELECT topic_id, timestamp, length(data) FROM messages ORDER BY id").fetchall()
    arr = np.array(rows, dtype=np.int64).reshape(-1, 3)
    return arr[:, 0], arr[:, 1], arr[:, 2]


def test_extension_is_built() -> None:
    """``make test`` builds the C decoder; a silent fallback to numpy would leave it untested
    (and the reader ~4x slower on small messages)."""
    assert sqlitepages.DECODER == "c", (
        "perfros_bag/ingest/_sqlitecells.c is not built: reinstall with a C compiler "
        "(rm .venv/.installed-stamp && make setup, or pip install -e .)")


@pytest.mark.parametrize("decoder", DECODERS)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(row, min_size=1, max_size=300, unique_by=lambda r: r[0]),
       page_size=st.sampled_from([512, 1024, 4096, 65536]))
def test_pages_equal_sqlite(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, decoder: str,
                            rows: list[tuple[int, int, int, int]], page_size: int) -> None:
    monkeypatch.setattr(sqlitepages, "DECODER", decoder)
    db = tmp_path / "m.db3"
    db.unlink(missing_ok=True)
    con = sqlite3.connect(db)
    con.execute(f"PRAGMA page_size = {page_size}")
    con.execute(SCHEMA)
    con.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)",
                    [(i, t, ts, bytes(n)) for i, t, ts, n in rows])
    con.commit()
    got = sqlitepages.read_file(db, con)
    exp = _sql(con)
    con.close()
    for g, e in zip(got, exp, strict=True):
        np.testing.assert_array_equal(g, e)


def _varint_lengths(data: bytes, count: int) -> list[int]:
    """Independent varint walk: lengths of the first ``count`` varints of ``data``."""
    out, pos = [], 0
    for _ in range(count):
        n = 1
        while n < 9 and data[pos + n - 1] >= 0x80:
            n += 1
        out.append(n)
        pos += n
    return out


@given(st.lists(st.binary(min_size=48, max_size=48), min_size=1, max_size=50))
def test_layout_lookup_matches_a_varint_walk(cells: list[bytes]) -> None:
    m = np.frombuffer(b"".join(cells), dtype=np.uint8).reshape(-1, 48)
    bits = sqlitepages._cont_bits(m)
    for cell, key in zip(cells, bits.tolist(), strict=True):
        assert key == sum(1 << j for j in range(16) if cell[j] >= 0x80)
        lens = _varint_lengths(cell, 7)
        fits = sum(lens) <= 16 and max(lens) <= 4 and lens[2:6] == [1, 1, 1, 1]
        lay = sqlitepages._layout(key)
        assert (lay is not None) == fits
        if lay is not None:
            assert lay == (lens[0], lens[0] + lens[1], lens[6])


def _table(path: Path) -> tuple[int, int]:
    con = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
    try:
        root = sqlitepages.messages_root(con)
        (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
    finally:
        con.close()
    assert root is not None
    return root, int(count)


def _many_pages(path: Path) -> Path:
    """A messages table on 512-byte pages: three B-tree levels, overflow pages, mixed widths."""
    rng = random.Random(3)
    con = sqlite3.connect(path)
    con.execute("PRAGMA page_size = 512")
    con.execute(SCHEMA)
    con.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)",
                    [(i + 1, rng.choice([1, 2, 300, -4]), 10**18 + i * 997 if i % 5 else i,
                      bytes(rng.choice([0, 9, 9, 40, 40, 130, 900]))) for i in range(3000)])
    con.commit()
    con.close()
    return path


def test_damaged_pages_fail_cleanly_and_decoders_agree(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Bytes flipped anywhere past the database header of real and generated rosbag2 files:
    each decoder returns rows or raises NoIndex (never crashes or raises anything else), and
    where both return rows they are the same rows."""
    sources = [next((REALBAGS / "plotjuggler_rosbag2_test").glob("*.db3")),
               next((REALBAGS / "event_camera_test_events_1_db3").glob("*.db3")),
               _many_pages(tmp_path / "many.db3")]
    rng = random.Random(20261123)
    outcomes = {"rows": 0, "refused": 0, "c only": 0, "numpy only": 0}
    for case in range(int(os.environ.get("PERFROS_FUZZ_CASES", "450"))):
        src = sources[case % len(sources)]
        root, count = _table(src)
        raw = bytearray(src.read_bytes())
        page_size = int.from_bytes(raw[16:18], "big")
        for _ in range(rng.choice([1, 2, 8, 32])):
            raw[rng.randrange(page_size, len(raw))] ^= 1 << rng.randrange(8)
        got: dict[str, tuple[np.ndarray, ...] | None] = {}
        for decoder in DECODERS:
            monkeypatch.setattr(sqlitepages, "DECODER", decoder)
            try:
                got[decoder] = sqlitepages.read_messages(bytes(raw), root, count)  # type: ignore[arg-type]
            except NoIndex:
                got[decoder] = None
        try:  # the C walk copying blob heads: the same checks, plus its own
            with_heads = sqlitepages.read_messages_heads(bytes(raw), root, count, [1, 300, -4], 12)  # type: ignore[arg-type]
        except NoIndex:
            with_heads = None
        if with_heads is not None:
            assert got["c"] is not None
            for a, b in zip(with_heads[:3], got["c"], strict=True):
                np.testing.assert_array_equal(a, b)
            rows = with_heads[3]
            assert np.isin(with_heads[0][rows], [1, 300, -4]).all() and np.all(np.diff(rows) > 0)
        if got["c"] is None or got["numpy"] is None:
            outcomes["refused" if got["c"] is got["numpy"] else
                     "numpy only" if got["c"] is None else "c only"] += 1
            continue
        outcomes["rows"] += 1
        for a, b in zip(got["c"], got["numpy"], strict=True):
            np.testing.assert_array_equal(a, b)
    assert outcomes["rows"] > 50 and outcomes["refused"] > 50, outcomes
    assert outcomes["c only"] == outcomes["numpy only"] == 0, outcomes  # same checks, same verdicts


def test_c_walk_blob_heads_with_overflow_pages_equal_sqlite(tmp_path: Path) -> None:
    """read_messages_heads on 512-byte pages (overflowing blobs, three B-tree levels, blobs
    shorter than the head) against SQLite's substr(), zero-filled."""
    db = _many_pages(tmp_path / "many.db3")
    root, count = _table(db)
    con = sqlite3.connect(db)
    for want in ([1, 300, -4], [2], [7]):
        rows = con.execute(f"SELECT rowid, substr(data, 1, 12) FROM messages WHERE topic_id IN "
                           f"({','.join('?' * len(want))}) ORDER BY rowid", want).fetchall()
        tids, _times, _sizes, at, heads = sqlitepages.read_messages_heads(db.read_bytes(), root, count, want, 12)  # type: ignore[arg-type]
        assert [(int(i) + 1, bytes(h)) for i, h in zip(at, heads, strict=True)] == \
               [(r, bytes(h or b"").ljust(12, b"\0")) for r, h in rows]  # rowid = row number + 1 here
        assert np.isin(tids[at], want).all()
    con.close()


@settings(max_examples=200, deadline=None)
@given(tids=st.lists(st.integers(-3, 12), max_size=200), ids=st.sets(st.integers(-3, 12), min_size=1),
       sparse=st.booleans())
def test_group_by_topic_equals_masks(tids: list[int], ids: set[int], sparse: bool) -> None:
    """The C counting sort against numpy masks; None where it must defer to the caller (a row
    with an unknown id, ids too sparse for its lookup table)."""
    id_list = sorted(ids) + ([2**40] if sparse else [])
    t = np.asarray(tids, dtype=np.int64)
    times = np.arange(t.size, dtype=np.int64) * 7 - 100
    sizes = (np.arange(t.size, dtype=np.int64) % 5) * 1000
    res = sqlitepages.group_by_topic(t, times, sizes, id_list)
    if sparse or not set(tids) <= ids:
        assert res is None
        return
    assert res is not None
    grouped, nbytes = res
    assert len(grouped) == len(nbytes) == len(id_list)
    for tid, g, nb in zip(id_list, grouped, nbytes, strict=True):
        np.testing.assert_array_equal(g, times[t == tid])
        assert nb == int(sizes[t == tid].sum())


def test_decode_rejects_bad_arguments_cleanly() -> None:
    """The extension's early exits (wrong output arrays, a bad page size or root) raise, and
    free nothing they did not allocate."""
    from perfros_bag.ingest import _sqlitecells

    buf = bytes(4096 * 4)
    ok = [np.empty(3, np.int64) for _ in range(3)]
    with pytest.raises(TypeError, match="int64"):
        _sqlitecells.decode(buf, 2, 4096, 4096, np.empty(3, np.int32), ok[1], ok[2], None, 0)
    with pytest.raises(ValueError, match="differ in length"):
        _sqlitecells.decode(buf, 2, 4096, 4096, ok[0], ok[1], np.empty(2, np.int64), None, 0)
    with pytest.raises(_sqlitecells.Malformed, match="bad page size"):
        _sqlitecells.decode(buf, 2, 4000, 4000, *ok, None, 0)
    with pytest.raises(_sqlitecells.Malformed, match="bad root page"):
        _sqlitecells.decode(buf, 9, 4096, 4096, *ok, None, 0)
