"""Readers against the independent reference values of ../shared/realbags/EXPECTED.tsv.

EXPECTED.tsv (own ROS 1/MCAP/sqlite scanners, not this project's) lists per (file, topic):
type, count, bytes, first_ns, last_ns, span_s, mean_hz = (n-1)/span, bytes_per_s = bytes/span.
SOURCES.tsv marks the files that must be rejected ("[BAD]") and the message total of each.
"""

from __future__ import annotations

import csv
import functools
import json
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner, Result

from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.ingest import read_recording
from perfros_bag.ingest.stats import RecordingStats
from tests.conftest import REALBAGS

BIN = Path(sys.executable).with_name("perfros-bag")


def _rows(name: str) -> list[dict[str, str]]:
    lines = [ln for ln in (REALBAGS / name).read_text().splitlines() if ln and not ln.startswith("#")]
    return list(csv.DictReader(lines, delimiter="\t"))


EXPECTED: dict[str, list[dict[str, str]]] = defaultdict(list)
for _r in _rows("EXPECTED.tsv"):
    EXPECTED[_r["file"]].append(_r)
SOURCES = {r["file"].rstrip("/"): r for r in _rows("SOURCES.tsv")}
BAD = sorted(f for f, r in SOURCES.items() if "[BAD]" in r["notes"])
GOOD = sorted(f for f in SOURCES if f not in BAD)


@functools.cache
def _read(name: str, fast: bool = True) -> RecordingStats:
    """Each recording is read once per path (the results are not modified by the tests)."""
    return read_recording(REALBAGS / name, fast=fast)


def _first_ns(row: dict[str, str]) -> int | None:
    """EXPECTED leaves first_ns empty when it is 0 (the conformance file's log_time 0..9); then
    it follows from last_ns and mean_hz = (n-1)/span, computed independently of the reader."""
    if row["first_ns"]:
        return int(row["first_ns"])
    if int(row["count"]) == 0:
        return None
    span_ns = round((int(row["count"]) - 1) / float(row["mean_hz"]) * 1e9)
    return int(row["last_ns"]) - span_ns


def test_expected_covers_realbags() -> None:
    on_disk = {p.name for p in REALBAGS.iterdir() if not p.name.endswith(".tsv")}
    assert set(SOURCES) == on_disk
    assert set(EXPECTED) <= set(GOOD)
    assert {"rosbagjs_empty-file.bag", "webviz_invalid.bag", "rosbag-rs_dummy.bag"} <= set(BAD)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_matches_expected(name: str) -> None:
    """Fast path against EXPECTED (the streaming path equals it: test_fast_equals_stream)."""
    rec = _read(name)
    rows = {r["topic"]: r for r in EXPECTED[name]}
    assert set(rec.topics) == set(rows)
    for topic, row in rows.items():
        t = rec.topics[topic]
        assert t.msgtype == row["type"], topic
        assert t.messages == int(row["count"]) == t.times_ns.size, topic
        assert t.bytes == int(row["bytes"]), topic
        assert t.first_ns == _first_ns(row), topic
        assert t.last_ns == (int(row["last_ns"]) if row["last_ns"] else None), topic
        assert t.span_s == pytest.approx(float(row["span_s"]), abs=1e-6), topic
        if row["mean_hz"] and float(row["span_s"]) > 0:
            assert t.frequency_hz == pytest.approx(float(row["mean_hz"]), abs=1e-4, rel=1e-6), topic
            assert t.bandwidth_kBps * 1000 == pytest.approx(float(row["bytes_per_s"]), abs=0.06, rel=1e-6)
        elif t.messages >= 2 and t.span_s > 0:  # conformance file: 9 ns span, rounded to 0 in the TSV
            assert t.frequency_hz == pytest.approx(float(row["mean_hz"]), rel=1e-9)
        else:
            assert t.frequency_hz == 0.0 and t.bandwidth_kBps == 0.0
        assert np.all(np.diff(t.times_ns) >= 0)


def _same(a: RecordingStats, b: RecordingStats) -> None:
    assert list(a.topics) == list(b.topics)
    for k, ta in a.topics.items():
        tb = b.topics[k]
        assert (ta.msgtype, ta.messages, ta.bytes, ta.publishers) \
            == (tb.msgtype, tb.messages, tb.bytes, tb.publishers), k
        np.testing.assert_array_equal(ta.times_ns, tb.times_ns)


@pytest.mark.parametrize("name", GOOD)
def test_fast_equals_stream_and_sources(name: str) -> None:
    """On every good recording: the index fast path and the streaming path give identical
    numbers; the fast path really used the index or the SQLite pages (only index-less MCAP is
    streamed); message
    and topic totals are those of SOURCES.tsv."""
    fast, slow = _read(name), _read(name, False)
    _same(fast, slow)
    fmt = SOURCES[name]["format"]
    indexless = any(w in fmt for w in ("no summary", "unchunked"))
    sqlite = fmt.startswith("rosbag2 sqlite3")
    assert fast.method == ("stream" if indexless else "sqlite-pages" if sqlite else "index")
    assert slow.method == "stream"
    assert fast.messages == int(SOURCES[name]["messages"])
    assert len(fast.topics) == int(SOURCES[name]["topics"])


def test_three_compressions_identical() -> None:
    base = _read("rosbagjs_example.bag")
    for other in ("rosbagjs_example-bz2.bag", "rosbagjs_example-lz4.bag"):
        rec = _read(other)
        for k, t in base.topics.items():  # compressed copies were rewritten without callerids
            o = rec.topics[k]
            assert (t.msgtype, t.messages, t.bytes) == (o.msgtype, o.messages, o.bytes)
            np.testing.assert_array_equal(t.times_ns, o.times_ns)
        assert set(rec.topics) == set(base.topics)


def test_event_camera_ros1_and_rosbag2_same_rates() -> None:
    a = _read("event_camera_test_events_1.bag").topics["/event_camera/events"]
    b = _read("event_camera_test_events_1_db3").topics["/event_camera/events"]
    np.testing.assert_array_equal(a.times_ns, b.times_ns)
    assert a.frequency_hz == b.frequency_hz > 200
    assert a.median_rate_hz == b.median_rate_hz
    assert a.p95_gap_s == b.p95_gap_s
    assert a.bytes != b.bytes  # ROS 1 vs CDR serialisation: bandwidth close, not equal
    assert a.bandwidth_kBps == pytest.approx(b.bandwidth_kBps, rel=0.01)


def test_publishers_from_callerid() -> None:
    rec = _read("rosbagjs_example.bag")
    assert rec.topics["/tf"].publishers == ("/turtle1_tf_broadcaster", "/turtle2_tf_broadcaster")
    assert rec.topics["/turtle1/pose"].publishers == ("/sim",)


@pytest.mark.parametrize("name", BAD)
def test_bad_recordings_raise_input_error(name: str) -> None:
    for fast in (True, False):
        with pytest.raises(InputError) as info:
            read_recording(REALBAGS / name, fast=fast)
        assert str(info.value).startswith(str(REALBAGS / name) + ": ")


def _cli(*args: str) -> Result:
    return CliRunner().invoke(app, list(args))


@pytest.mark.parametrize("name", BAD)
def test_cli_bad_recording_one_line_exit_2(name: str) -> None:
    res = _cli("info", str(REALBAGS / name))
    assert res.exit_code == 2
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and name in lines[0]
    assert res.stdout == ""


def test_cli_subprocess_bad_recording() -> None:
    """The installed console script: exit 2, one line, no traceback."""
    res = subprocess.run([str(BIN), "info", str(REALBAGS / "webviz_invalid.bag")],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.count("\n") == 1 and "webviz_invalid.bag: " in res.stderr


def test_cli_info_json_matches_expected() -> None:
    name = "rosbagjs_example.bag"
    res = _cli("info", str(REALBAGS / name), "--json")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["format"] == "perfros-bag/info@1" and doc["recording_format"] == "ros1"
    assert doc["read_method"] == "index"
    rows = {r["topic"]: r for r in EXPECTED[name]}
    assert [t["topic"] for t in doc["topics"]] == sorted(rows)
    for t in doc["topics"]:
        row = rows[t["topic"]]
        assert t["messages"] == int(row["count"]) and t["bytes"] == int(row["bytes"])
        assert (t["first_ns"], t["last_ns"]) == (int(row["first_ns"]), int(row["last_ns"]))
        if float(row["span_s"]) > 0:
            assert t["frequency_hz"] == pytest.approx(float(row["mean_hz"]), abs=1e-4)
            assert t["bandwidth_kBps"] * 1000 == pytest.approx(float(row["bytes_per_s"]), abs=0.06)
        else:
            assert t["frequency_hz"] == 0 and t["bandwidth_kBps"] == 0
    assert doc["messages"] == sum(int(r["count"]) for r in rows.values())


def test_cli_info_table_and_slow() -> None:
    name = "rosbag2_mcap_talker"
    fast, slow = _cli("info", str(REALBAGS / name)), _cli("info", str(REALBAGS / name), "--slow")
    assert fast.exit_code == slow.exit_code == 0
    def numbers(text: str) -> list[str]:  # all but the line saying how it was read
        return [ln for ln in text.splitlines() if not ln.startswith("format:")]

    assert numbers(fast.stdout) == numbers(slow.stdout)
    assert "read from the index records" in fast.stdout and "every record streamed" in slow.stdout
    for row in EXPECTED[name]:
        line = next(ln for ln in fast.stdout.splitlines() if f" {row['topic']} " in ln)
        assert f" {int(row['count'])} " in line and row["type"] in line
