"""Broken and edge inputs: one clear InputError ("<path>: <problem>") or a correct (empty)
result, never another exception; a seeded fuzz over real recordings checks exactly that."""

from __future__ import annotations

import random
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.ingest import read_recording
from perfros_bag.ingest.stats import RecordingStats
from tests.conftest import REALBAGS
from tests.ingest_gen import copy_tree, random_msgs, write_mcap, write_ros1, write_rosbag2

MSGS = random_msgs(np.random.default_rng(3), 300)


def _error(path: Path, *, contains: str = "") -> str:
    for fast in (True, False):
        with pytest.raises(InputError) as info:
            read_recording(path, fast=fast)
        msg = str(info.value)
        assert msg.startswith(f"{path}") and "\n" not in msg
        assert contains in msg
    return msg


def _cli_error(path: Path) -> str:
    res = CliRunner().invoke(app, ["info", str(path)])
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in res.stderr
    return lines[0]


@pytest.mark.parametrize("suffix", [".bag", ".mcap", ".db3"])
def test_zero_byte_files(tmp_path: Path, suffix: str) -> None:
    f = tmp_path / f"empty{suffix}"
    f.write_bytes(b"")
    _error(f, contains="empty file")
    _cli_error(f)


def test_missing_path(tmp_path: Path) -> None:
    _error(tmp_path / "nope.bag", contains="no such file")


def test_unknown_format(tmp_path: Path) -> None:
    f = tmp_path / "notes.bag"
    f.write_text("hello, I am not a bag\n")
    _error(f, contains="unknown format")


def test_old_ros1_version(tmp_path: Path) -> None:
    f = tmp_path / "old.bag"
    f.write_bytes(b"#ROSBAG V1.2\n" + b"\0" * 100)
    _error(f, contains="unsupported bag format")


@pytest.mark.parametrize("cut", [0.3, 0.7, 0.99])
def test_truncated_ros1_and_mcap(tmp_path: Path, cut: float) -> None:
    for f in (write_ros1(tmp_path / "a.bag", MSGS, "lz4", chunk_threshold=4000),
              write_mcap(tmp_path / "a.mcap", MSGS, chunk_size=4000)):
        raw = f.read_bytes()
        t = tmp_path / f"cut{f.suffix}"
        t.write_bytes(raw[: int(len(raw) * cut)])
        if f.suffix == ".mcap" and cut == 0.99:  # only summary lost: the data is complete
            assert read_recording(t).messages == len(MSGS)
        else:
            _error(t, contains="truncated")
        t.unlink()


def test_truncated_sqlite(tmp_path: Path) -> None:
    d = write_rosbag2(tmp_path / "b", MSGS, "sqlite3")
    db = next(d.glob("*.db3"))
    db.write_bytes(db.read_bytes()[:5000])
    msg = _error(d)
    assert db.name in msg  # names the storage file inside the directory


def test_empty_directory_and_junk_directory(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    _error(tmp_path / "empty", contains="not a rosbag2 recording")
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "README.txt").write_text("nothing here")
    _error(junk, contains="not a rosbag2 recording")
    _cli_error(junk)


def test_metadata_problems(tmp_path: Path) -> None:
    d = tmp_path / "r"
    d.mkdir()
    meta = d / "metadata.yaml"
    meta.write_text("rosbag2_bagfile_information: [unclosed\n")
    _error(d, contains="metadata.yaml")
    meta.write_text("just a string\n")
    _error(d, contains="not rosbag2 metadata")
    meta.write_text("rosbag2_bagfile_information:\n  storage_identifier: fancy\n  relative_file_paths: []\n")
    _error(d, contains="unknown storage 'fancy'")
    meta.write_text("rosbag2_bagfile_information:\n  storage_identifier: fancy\n"
                    "  relative_file_paths: [r_0.fancy]\n")
    (d / "r_0.fancy").write_bytes(b"x" * 10)
    _error(d, contains="unknown storage 'fancy'")
    meta.write_text("rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n"
                    "  relative_file_paths: [gone_0.db3]\n")
    _error(d, contains="gone_0.db3")
    _cli_error(d)


def test_sqlite_that_is_not_rosbag2(tmp_path: Path) -> None:
    import sqlite3

    db = tmp_path / "other.db3"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE people (name TEXT)")
    con.commit()
    con.close()
    _error(db, contains="not a rosbag2 sqlite3 database")


def test_sqlite_message_with_unknown_topic(tmp_path: Path) -> None:
    import sqlite3

    d = write_rosbag2(tmp_path / "b", MSGS, "sqlite3")
    db = next(d.glob("*.db3"))
    con = sqlite3.connect(db)
    con.execute("INSERT INTO messages (topic_id, timestamp, data) VALUES (99, 1, x'00')")
    con.commit()
    con.close()
    _error(d, contains="unknown topic id")


def test_empty_rosbag2_valid(tmp_path: Path) -> None:
    d = write_rosbag2(tmp_path / "b", [], "mcap", declare=[("/a", "std_msgs/msg/String")])
    rec = read_recording(d)
    assert list(rec.topics) == ["/a"] and rec.messages == 0 and rec.topics["/a"].frequency_hz == 0


def test_mcap_with_wrong_magic(tmp_path: Path) -> None:
    f = write_mcap(tmp_path / "a.mcap", MSGS)
    raw = bytearray(f.read_bytes())
    raw[1] = ord("X")
    f.write_bytes(bytes(raw))
    _error(f, contains="unknown format")


# ---------------------------------------------------------------- fuzz
FUZZ_SOURCES = ["rosbagjs_example-lz4.bag", "rosbagjs_example.bag", "lichtblick_example.mcap",
                "mcap_conformance_TenMessages.mcap", "rosbag2_mcap_talker",
                "rosbag2_mcap_reindex_multiple_files_nometa", "plotjuggler_rosbag2_test"]
FUZZ_BUDGET_S = 10.0


def _target(root: Path) -> Path:
    """The file to damage: the recording itself, or a storage file of a rosbag2 directory."""
    if root.is_file():
        return root
    return sorted(p for p in root.iterdir() if p.suffix in (".mcap", ".db3"))[0]


def _sane(rec: RecordingStats) -> None:
    for t in rec.topics.values():
        assert t.messages == t.times_ns.size and t.bytes >= 0
        assert np.all(np.diff(t.times_ns) >= 0)
        assert t.frequency_hz >= 0 and t.bandwidth_kBps >= 0


def test_fuzz_truncate_and_flip(tmp_path: Path) -> None:
    """Truncations and byte flips of real recordings: a correct result or an InputError, nothing
    else. A truncated file that still reads must give exactly the original numbers (only
    non-data parts such as an MCAP summary may be lost)."""
    rng = random.Random(20240501)
    deadline = time.monotonic() + FUZZ_BUDGET_S
    done = {"truncate": 0, "flip": 0, "errors": 0}
    while time.monotonic() < deadline:
        name = rng.choice(FUZZ_SOURCES)
        work = tmp_path / f"case{sum(done.values())}"
        work.mkdir()
        copy = copy_tree(REALBAGS / name, work / name)
        original = read_recording(copy)
        target = _target(copy)
        raw = bytearray(target.read_bytes())
        kind = rng.choice(["truncate", "flip"])
        if kind == "truncate":
            raw = raw[: rng.randrange(0, len(raw))]
        else:
            for _ in range(rng.choice([1, 1, 2, 8])):
                raw[rng.randrange(len(raw))] ^= 1 << rng.randrange(8)
        target.write_bytes(bytes(raw))
        for fast in (True, False):
            try:
                rec = read_recording(copy, fast=fast)
            except InputError as exc:
                assert str(exc).startswith(str(copy)) and "\n" not in str(exc)
                done["errors"] += 1
                continue
            _sane(rec)
            if kind == "truncate":
                assert {k: (t.messages, t.bytes, t.times_ns.tolist()) for k, t in rec.topics.items()} == \
                    {k: (t.messages, t.bytes, t.times_ns.tolist()) for k, t in original.topics.items()}, \
                    (name, len(raw))
        done[kind] += 1
    assert done["truncate"] >= 10 and done["flip"] >= 10 and done["errors"] > 0, done
