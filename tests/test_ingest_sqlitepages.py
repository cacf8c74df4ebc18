"""The B-tree page decoder of rosbag2's messages table against SQLite's own answer, with rows
that take the fixed-layout fast path and rows that need the general varint decoder (huge
rowids, wide or negative topic ids) mixed in one batch."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.ingest import sqlitepages

SCHEMA = ("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
          "timestamp INTEGER NOT NULL, data BLOB NOT NULL)")

ints = st.one_of(st.integers(-2**63, 2**63 - 1), st.integers(-300, 300), st.sampled_from([0, 1]))
row = st.tuples(st.integers(1, 2**62), ints, ints, st.integers(0, 400))


def _sql(con: sqlite3.Connection) -> tuple[np.ndarray, ...]:
    rows = con.execute("SELECT topic_id, timestamp, length(data) FROM messages ORDER BY id").fetchall()
    arr = np.array(rows, dtype=np.int64).reshape(-1, 3)
    return arr[:, 0], arr[:, 1], arr[:, 2]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(row, min_size=1, max_size=300, unique_by=lambda r: r[0]))
def test_pages_equal_sqlite(tmp_path: Path, rows: list[tuple[int, int, int, int]]) -> None:
    db = tmp_path / "m.db3"
    db.unlink(missing_ok=True)
    con = sqlite3.connect(db)
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
