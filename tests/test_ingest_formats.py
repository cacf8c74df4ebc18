"""Readers on recordings written by third-party writers (rosbags, mcap) from a known message list.

The expected numbers come from the list itself (tests/ingest_gen.py), not from a reader.
"""

from __future__ import annotations

import shutil
import sqlite3
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.ingest import read_recording
from perfros_bag.ingest.discover import find_recordings
from perfros_bag.ingest.stats import RecordingStats
from tests.ingest_gen import (
    Expected,
    Msg,
    anyreader_decode,
    by_topic,
    expected,
    random_msgs,
    write_mcap,
    write_ros1,
    write_rosbag2,
)

MSGS = random_msgs(np.random.default_rng(7), 800)


def check(rec: RecordingStats, exp: dict[str, Expected], publishers: bool = False) -> None:
    assert set(rec.topics) == set(exp)
    for name, e in exp.items():
        t = rec.topics[name]
        assert t.msgtype == e.msgtype, name
        assert t.messages == e.count, name
        assert t.bytes == e.nbytes, name
        assert t.times_ns.tolist() == e.times, name
        if publishers:
            assert set(t.publishers) == e.publishers, name


def both(path: Path, exp: dict[str, Expected], method: str = "index", publishers: bool = False) -> None:
    fast, slow = read_recording(path), read_recording(path, fast=False)
    check(fast, exp, publishers)
    check(slow, exp, publishers)
    assert fast.method == method and slow.method == "stream"


@pytest.mark.parametrize("compression", [None, "bz2", "lz4"])
def test_ros1_chunk_compressions(tmp_path: Path, compression: str | None) -> None:
    bag = write_ros1(tmp_path / "a.bag", MSGS, compression, chunk_threshold=8_000)
    both(bag, expected(MSGS, ros1=True), publishers=True)
    assert read_recording(bag).format == "ros1"


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("compression", [None, "file", "message"])
def test_rosbag2_storages_and_compression(tmp_path: Path, storage: str, compression: str | None) -> None:
    """zstd file or message compression: bytes are the decompressed payload sizes."""
    d = write_rosbag2(tmp_path / "b", MSGS, storage, compression, declare=[("/idle", "std_msgs/msg/String")])
    exp = expected(MSGS)
    exp["/idle"] = Expected("std_msgs/msg/String", 0, 0, [], set())
    pages = storage == "sqlite3" and compression != "message"
    both(d, exp, "sqlite-pages" if pages else "sql" if storage == "sqlite3" else "index")
    assert read_recording(d).format == f"rosbag2-{storage}"


@pytest.mark.parametrize("kw", [
    {}, {"compression": "lz4"}, {"compression": ""}, {"chunk_size": 100},
    {"chunked": False}, {"index": False}, {"summary": False}, {"summary": False, "index": False},
], ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()) or "default")
def test_mcap_variants(tmp_path: Path, kw: dict[str, object]) -> None:
    f = write_mcap(tmp_path / "c.mcap", MSGS, chunk_size=int(kw.pop("chunk_size", 16_000)), **kw)  # type: ignore[arg-type]
    indexed = kw.get("chunked", True) and kw.get("index", True) and kw.get("summary", True)
    both(f, expected(MSGS), "index" if indexed else "stream")


def test_mcap_ros1_callerid_publishers(tmp_path: Path) -> None:
    """ROS 1 profile MCAP: one channel per publisher with callerid metadata; channels merge."""
    f = write_mcap(tmp_path / "r.mcap", MSGS, callerid=True, chunk_size=8_000)
    both(f, expected(MSGS), publishers=True)


def test_mcap_json_without_schema(tmp_path: Path) -> None:
    f = write_mcap(tmp_path / "j.mcap", MSGS, encoding="json", schemaless=True)
    exp = expected(MSGS)
    for e in exp.values():
        e.msgtype = ""  # no schema: the type is unknown, the counts are not
    both(f, exp)


def test_ros1_unindexed_bag_is_streamed(tmp_path: Path) -> None:
    """A bag whose recorder was killed: index_pos 0 and no index section."""
    bag = write_ros1(tmp_path / "a.bag", MSGS, "lz4", chunk_threshold=8_000)
    raw = bytearray(bag.read_bytes())
    key = b"index_pos="
    at = raw.index(key) + len(key)
    (index_pos,) = struct.unpack_from("<Q", raw, at)
    struct.pack_into("<Q", raw, at, 0)
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bytes(raw[:index_pos]))
    both(cut, expected(MSGS, ros1=True), method="stream", publishers=True)


def test_ros1_damaged_index_falls_back(tmp_path: Path) -> None:
    """An index-data offset pointing into another record: detected, the stream is used."""
    bag = write_ros1(tmp_path / "a.bag", MSGS, None, chunk_threshold=8_000)
    from perfros_bag.ingest.rosbag1 import OP_INDEX, read_record

    raw = bytearray(bag.read_bytes())
    pos = 13
    while (rec := read_record(raw, pos, len(raw))).op != OP_INDEX:  # locate the first index-data
        pos = rec.end
    (off,) = struct.unpack_from("<I", raw, rec.data_start + 8)  # its first entry's offset
    struct.pack_into("<I", raw, rec.data_start + 8, off + 3)
    bag.write_bytes(bytes(raw))
    fast = read_recording(bag)
    assert fast.method == "stream"
    check(fast, expected(MSGS, ros1=True))


def test_mcap_lost_summary_is_streamed(tmp_path: Path) -> None:
    """Cut after the data-end record (summary and footer lost): all data is still there."""
    f = write_mcap(tmp_path / "c.mcap", MSGS, chunk_size=8_000)
    raw = f.read_bytes()
    (summary_start,) = struct.unpack_from("<Q", raw, len(raw) - 8 - 20)
    f.write_bytes(raw[:summary_start])
    rec = read_recording(f)
    check(rec, expected(MSGS))
    assert rec.method == "stream"


def _split(msgs: list[Msg], k: int) -> list[list[Msg]]:
    return [msgs[i::k] for i in range(k)]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("meta", ["stale-prefix", "none", "v5-empty-storage"])
def test_rosbag2_split_files(tmp_path: Path, storage: str, meta: str) -> None:
    """Split recordings, metadata quirks: storage from the suffix, stale prefixes, no metadata."""
    suffix = ".db3" if storage == "sqlite3" else ".mcap"
    rec_dir = tmp_path / "rec"
    rec_dir.mkdir()
    parts = _split(MSGS, 3)
    for i, part in enumerate(parts):
        d = write_rosbag2(tmp_path / f"p{i}", part, storage)
        shutil.move(str(next(d.glob(f"*{suffix}"))), rec_dir / f"rec_{i}{suffix}")
    names = [f"rec_{i}{suffix}" for i in range(3)]
    if meta == "stale-prefix":
        paths = "".join(f"    - old_dir/{n}\n" for n in names)
        (rec_dir / "metadata.yaml").write_text(
            "rosbag2_bagfile_information:\n  version: 2\n  storage_identifier: " + storage
            + "\n  relative_file_paths:\n" + paths + "  message_count: 999999\n")
    elif meta == "v5-empty-storage":
        paths = "".join(f"    - {n}\n" for n in names)
        (rec_dir / "metadata.yaml").write_text(
            'rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: ""\n'
            "  relative_file_paths:\n" + paths + "  files:\n    []\n  topics_with_message_count:\n"
            "    - topic_metadata: {name: /declared, type: std_msgs/msg/String}\n      message_count: 0\n")
    exp = expected(MSGS)
    if meta == "v5-empty-storage":
        exp["/declared"] = Expected("std_msgs/msg/String", 0, 0, [], set())
    both(rec_dir, exp, "sqlite-pages" if storage == "sqlite3" else "index")


def test_loose_db3_and_metadata_path(tmp_path: Path) -> None:
    d = write_rosbag2(tmp_path / "b", MSGS, "sqlite3")
    db = next(d.glob("*.db3"))
    both(db, expected(MSGS), "sqlite-pages")
    check(read_recording(d / "metadata.yaml"), expected(MSGS))
    assert read_recording(db).format == "rosbag2-sqlite3"


def test_loose_zstd_storage_file(tmp_path: Path) -> None:
    d = write_rosbag2(tmp_path / "b", MSGS, "mcap", "file")
    f = next(d.glob("*.mcap.zstd"))
    check(read_recording(f), expected(MSGS))


def test_sqlite_wal_is_read(tmp_path: Path) -> None:
    """A recorder that died with committed messages still in the WAL: they are counted."""
    d = write_rosbag2(tmp_path / "b", MSGS, "sqlite3")
    db = next(d.glob("*.db3"))
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    con = sqlite3.connect(db)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA wal_autocheckpoint=0")
    tid = con.execute("SELECT id FROM topics WHERE name='/t2'").fetchone()[0]
    last = MSGS[-1].time_ns + 1000
    con.execute("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", (tid, last, b"x" * 77))
    con.commit()
    for f in d.iterdir():  # copy while the WAL is live, like a crash
        shutil.copy(f, crashed / f.name)
    con.close()
    assert (crashed / (db.name + "-wal")).stat().st_size > 0
    exp = expected([*MSGS, Msg("/t2", "std_msgs/msg/String", last, b"x" * 77)])
    both(crashed, exp, "sql")  # the B-tree pages do not hold the WAL's rows: SQL


def test_sqlite_pages_equal_sql_with_overflow_and_small_ints(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Big blobs (overflow pages), tiny and negative-free small timestamps (1-6 byte integers),
    a multi-level B-tree: the page reader equals SQLite's own answer (SQL path forced)."""
    from perfros_bag.ingest import sqlitepages
    from perfros_bag.ingest._accum import NoIndex

    rng = np.random.default_rng(5)
    msgs = [Msg(f"/b{i % 2}", "std_msgs/msg/String", int(t), rng.bytes(int(n)))
            for i, (t, n) in enumerate(zip(sorted(rng.integers(0, 2**40, 300)),
                                           rng.choice([0, 5, 3000, 70_000], 300), strict=True))]
    d = write_rosbag2(tmp_path / "b", msgs, "sqlite3")
    pages = read_recording(d)
    assert pages.method == "sqlite-pages"
    check(pages, expected(msgs))

    def refuse(*_: object) -> None:
        raise NoIndex("forced")

    monkeypatch.setattr(sqlitepages, "read_file", refuse)
    sql = read_recording(d)
    assert sql.method == "sql"
    check(sql, expected(msgs))


def test_ros1_and_mcap_empty_but_declared(tmp_path: Path) -> None:
    """Valid recordings without messages: declared topics at 0 messages."""
    from rosbags.rosbag1 import Writer

    bag = tmp_path / "e.bag"
    with Writer(bag) as w:
        w.add_connection("/quiet", "std_msgs/msg/String", msgdef="string data",
                         md5sum="992ce8a1687cec8c8bd883ec73ca41d1", callerid="/n")
    for fast in (True, False):
        rec = read_recording(bag, fast=fast)
        assert list(rec.topics) == ["/quiet"] and rec.messages == 0
        assert rec.topics["/quiet"].publishers == ("/n",) and rec.start_ns is None

    from mcap.writer import Writer as McapWriter

    f = tmp_path / "e.mcap"
    with f.open("wb") as s:
        mw = McapWriter(s)
        mw.start()
        mw.register_channel("/quiet", "json", 0)
        mw.finish()
    for fast in (True, False):
        rec = read_recording(f, fast=fast)
        assert list(rec.topics) == ["/quiet"] and rec.messages == 0


def test_find_recordings(tmp_path: Path) -> None:
    root = tmp_path / "recs"
    (root / "sub").mkdir(parents=True)
    write_ros1(root / "run10.bag", MSGS[:10])
    write_ros1(root / "run2.bag", MSGS[:10])
    write_mcap(root / "sub" / "x.mcap", MSGS[:10])
    write_rosbag2(root / "r2", MSGS[:10], "mcap")
    split = root / "sub" / "split"
    split.mkdir()
    write_mcap(split / "s_0.mcap", MSGS[:5])
    write_mcap(split / "s_1.mcap", MSGS[5:10])
    (root / "notes.txt").write_text("not a recording")
    (root / ".hidden.bag").write_text("")
    found = find_recordings(root)
    assert [p.relative_to(root).as_posix() for p in found] == [
        "r2", "run2.bag", "run10.bag", "sub/split", "sub/x.mcap"]
    assert find_recordings(root / "r2") == [root / "r2"]
    assert find_recordings(root / "run2.bag") == [root / "run2.bag"]
    for p in found:
        assert read_recording(p).messages == 10


_msg = st.tuples(st.integers(0, 2), st.integers(0, 10**12), st.binary(max_size=64), st.integers(0, 1))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(_msg, max_size=60), st.sampled_from(["ros1", "ros1-bz2", "mcap", "mcap-lz4", "sqlite3"]),
       st.sampled_from([0, 1_500_000_000_000_000_000]))
def test_property_any_message_list(tmp_path_factory: pytest.TempPathFactory,
                                   items: list[tuple[int, int, bytes, int]], fmt: str, t0: int) -> None:
    """Arbitrary topics, times (any order, duplicates, small or epoch-sized), sizes (also 0
    bytes), callerids."""
    msgs = [Msg(f"/p{k}", "std_msgs/msg/String", t0 + t, data, f"/c{c}") for k, t, data, c in items]
    d = tmp_path_factory.mktemp("prop")
    if fmt.startswith("ros1"):
        path = write_ros1(d / "p.bag", msgs, "bz2" if fmt.endswith("bz2") else None, chunk_threshold=500)
        exp = expected(msgs, ros1=True)
    elif fmt.startswith("mcap"):
        path = write_mcap(d / "p.mcap", msgs, compression="lz4" if fmt.endswith("lz4") else "zstd",
                          chunk_size=400)
        exp = expected(msgs)
    else:
        path = write_rosbag2(d / "p", msgs, "sqlite3")
        exp = expected(msgs)
    for fast in (True, False):
        check(read_recording(path, fast=fast), exp, publishers=fmt.startswith("ros1"))


def test_sqlite_pages_every_integer_width(tmp_path: Path) -> None:
    """A hand-made rosbag2 table: timestamps and topic ids of every SQLite integer width,
    negative values, 0 and 1 (serial types 8/9), empty and overflowing blobs. The page decoder
    must agree with SQLite itself (read by a plain SQL query here, not by our code)."""
    db = tmp_path / "hand.db3"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, "
                "serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL)")
    con.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
                "timestamp INTEGER NOT NULL, data BLOB NOT NULL)")
    ids = [0, 1, 2, 127, 128, 40_000, 70_000, 2**31 + 5]
    for tid in ids:
        con.execute("INSERT INTO topics VALUES (?, ?, 'std_msgs/msg/String', 'cdr', '')", (tid, f"/t{tid}"))
    stamps = [0, 1, -1, 5, -128, 127, 300, -40_000, 8_000_000, -(2**31), 2**40 + 3, -(2**47),
              2**62 + 11, -(2**63), 2**63 - 1]
    rng = np.random.default_rng(9)
    rows = [(ids[i % len(ids)], stamps[i % len(stamps)], rng.bytes(int(rng.choice([0, 1, 200, 9000]))))
            for i in range(600)]
    con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", rows)
    con.commit()
    truth: dict[str, tuple[int, int, list[int]]] = {}
    for tid, name in con.execute("SELECT id, name FROM topics"):
        n, size = con.execute("SELECT count(*), coalesce(sum(length(data)), 0) FROM messages "
                              "WHERE topic_id = ?", (tid,)).fetchone()
        times = [t for (t,) in con.execute("SELECT timestamp FROM messages WHERE topic_id = ? "
                                          "ORDER BY timestamp", (tid,))]
        truth[name] = (n, size, times)
    con.close()
    for fast in (True, False):
        rec = read_recording(db, fast=fast)
        assert rec.method == ("sqlite-pages" if fast else "stream")
        assert {k: (t.messages, t.bytes, t.times_ns.tolist()) for k, t in rec.topics.items()} == truth


@pytest.mark.parametrize("compression", ["message", None])
def test_a_loose_rosbag2_mcap_file_reports_what_its_directory_reports(tmp_path: Path, compression: str | None) -> None:
    """A rosbag2 MCAP storage file read on its own (no metadata.yaml beside it) says in its
    ``rosbag2`` Metadata record whether each payload is a zstd frame: the sizes are then the
    decompressed ones, as when the directory is read, and as rosbags' AnyReader decodes them.
    The chunk-range (split) read agrees."""
    from perfros_bag.characterisation.cluster import read_split

    rng = np.random.default_rng(7)
    msgs = random_msgs(rng, 300, topics=3, max_size=400)
    bag = write_rosbag2(tmp_path / "bag", msgs, storage="mcap", compression=compression)
    loose = tmp_path / "loose.mcap"
    shutil.copy(next(bag.glob("*.mcap")), loose)
    reference = anyreader_decode(bag)
    assert by_topic(read_recording(bag)) == reference
    for fast in (True, False):
        assert by_topic(read_recording(loose, fast=fast)) == reference, fast
    assert by_topic(read_split(loose, target_bytes=1)) == reference
