"""Message contents: header stamps and latency (perfros_bag/ingest/contents.py).

The fast path (stamp read at its offset) is checked against the libraries' full
deserialisation (rosbags AnyReader / the mcap reader + rosbags typestores) on every stamped
message of shared/realbags and of generated recordings; latencies against the list of
messages as written."""

from __future__ import annotations

import json
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import REALBAGS, assert_same_stats
from contents_gen import (
    TOPICS,
    Sent,
    sent_messages,
    solve_and_validate,
    typestore,
    write_mcap,
    write_ros1,
    write_rosbag2,
)
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import PerfrosError, PerfrosWarning
from perfros_bag.ingest import read_recording
from perfros_bag.ingest._accum import Damaged, NoIndex
from perfros_bag.ingest.contents import (
    fast_stamps,
    latency_of,
    library_stamps,
    read_latency,
    read_stamps,
)
from perfros_bag.ingest.decode import Undecodable, topic_types


def _sorted_pairs(times: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    order = np.lexsort((stamps, times))
    return np.stack([times[order], stamps[order]])


def _assert_same_stamps(fast: dict, library: dict) -> None:
    assert sorted(fast) == sorted(library)
    for topic in library:
        np.testing.assert_array_equal(_sorted_pairs(*fast[topic]), _sorted_pairs(*library[topic]), err_msg=topic)


def _realbags() -> list[Path]:
    if not REALBAGS.is_dir():
        return []
    return sorted(p for p in REALBAGS.iterdir() if p.suffix != ".tsv")


@pytest.mark.parametrize("path", _realbags(), ids=lambda p: p.name)
def test_fast_stamps_equal_the_libraries_on_realbags(path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        try:
            library = library_stamps(path)
        except Undecodable:
            # a recording the libraries refuse: the fast path must refuse it too, not guess
            with pytest.raises((PerfrosError, NoIndex, Damaged)):
                fast_stamps(path)
            return
    fast, types = fast_stamps(path)  # where the libraries find no stamped topic, neither may it
    _assert_same_stamps(fast, library)
    counts = {t: s.messages for t, s in read_recording(path).topics.items()}
    for topic, (times, _) in fast.items():  # every stamped message, none skipped
        assert types[topic].stamped and times.size == counts[topic]


def test_realbags_have_stamped_topics_in_every_container() -> None:
    if not REALBAGS.is_dir():
        pytest.skip("no shared/realbags")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        ros1 = read_latency(REALBAGS / "robot_localization_test1.bag")
        sqlite = read_latency(REALBAGS / "plotjuggler_rosbag2_test")
    assert set(ros1) == {"/fix", "/husky_velocity_controller/odom", "/imu/data"}
    assert set(sqlite) == {"/imu", "/battery", "/pose"}  # /rosout, /parameter_events: no header
    assert all(v is not None for v in [*ros1.values(), *sqlite.values()])


SENT = sent_messages(600)


def _writers(tmp: Path) -> dict[str, Path]:
    return {
        "ros1": write_ros1(tmp / "a.bag", SENT),
        "ros1-bz2": write_ros1(tmp / "b.bag", SENT, "bz2"),
        "ros1-lz4": write_ros1(tmp / "c.bag", SENT, "lz4"),
        "rosbag2-sqlite3": write_rosbag2(tmp / "d", SENT),
        "rosbag2-mcap": write_rosbag2(tmp / "e", SENT, "mcap"),
        "rosbag2-message-zstd": write_rosbag2(tmp / "f", SENT, "mcap", compression="message"),
        "mcap-zstd-some-big-endian": write_mcap(tmp / "g.mcap", SENT, big_endian_every=7),
        "mcap-lz4": write_mcap(tmp / "h.mcap", SENT, compression="lz4"),
    }


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _writers(tmp_path_factory.mktemp("contents"))


def _sent_stamps(topic: str) -> tuple[np.ndarray, np.ndarray]:
    msgs = [s for s in SENT if s.topic == topic]
    return (np.array([s.time_ns for s in msgs], dtype=np.int64), np.array([s.stamp_ns for s in msgs], dtype=np.int64))


@pytest.mark.parametrize("kind", ["ros1", "ros1-bz2", "ros1-lz4", "rosbag2-sqlite3", "rosbag2-mcap",
                                  "rosbag2-message-zstd", "mcap-zstd-some-big-endian", "mcap-lz4"])
def test_stamps_equal_the_libraries_and_the_messages_written(generated: dict[str, Path], kind: str) -> None:
    path = generated[kind]
    stamps, types = read_stamps(path)
    assert {t for t, tt in types.items() if tt.stamped} == {"/detector/scored", "/imu"}
    assert types["/detector/plain"].stamped is False
    _assert_same_stamps(stamps, library_stamps(path))
    for topic in ("/detector/scored", "/imu"):
        np.testing.assert_array_equal(_sorted_pairs(*stamps[topic]), _sorted_pairs(*_sent_stamps(topic)))


@pytest.mark.parametrize("kind", ["ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap-zstd-some-big-endian"])
def test_fast_path_reads_these_without_the_libraries(generated: dict[str, Path], kind: str) -> None:
    fast, _ = fast_stamps(generated[kind])
    assert sorted(fast) == ["/detector/scored", "/imu"]


def test_latency_is_receive_minus_stamp_without_zero_stamps(generated: dict[str, Path]) -> None:
    latency = read_latency(generated["ros1"])
    assert set(latency) == {"/detector/scored", "/imu"}
    for topic in latency:
        delays = [(s.time_ns - s.stamp_ns) / 1e9 for s in SENT if s.topic == topic and s.stamp_ns != 0]
        got = latency[topic]
        assert got is not None and got.messages == len(delays)
        assert got.p50_s == pytest.approx(float(np.median(delays)), abs=1e-9)
        assert got.p95_s == pytest.approx(float(np.percentile(delays, 95)), abs=1e-9)
        assert got.max_s == pytest.approx(max(delays), abs=1e-9)


def test_all_zero_stamps_give_no_latency_and_a_warning(tmp_path: Path) -> None:
    sent = [Sent("/imu", 1_700_000_000_000_000_000 + i * 10**7, 0, 1.0) for i in range(5)]
    path = write_rosbag2(tmp_path / "z", sent)
    with pytest.warns(PerfrosWarning, match=r"/imu: every header.stamp is 0"):
        assert read_latency(path)["/imu"] is None
    assert latency_of(np.array([5], np.int64), np.array([0], np.int64)) is None


def test_an_undecodable_topic_warns_and_leaves_the_others(tmp_path: Path) -> None:
    from mcap.writer import Writer

    ts = typestore()
    path = tmp_path / "broken.mcap"
    good = [s for s in SENT if s.topic == "/imu"]
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        text, _ = ts.generate_msgdef("sensor_msgs/msg/Imu", ros_version=2)
        imu = w.register_channel("/imu", "cdr", w.register_schema("sensor_msgs/msg/Imu", "ros2msg", text.encode()))
        bad = w.register_channel("/odd", "cdr", w.register_schema("odd_msgs/msg/Odd", "ros2msg",
                                                                  b"std_msgs/Header header\n%%% not a field"))
        from contents_gen import _message

        for s in good:
            w.add_message(imu, log_time=s.time_ns, data=bytes(ts.serialize_cdr(_message(ts, s), "sensor_msgs/msg/Imu")),
                          publish_time=s.time_ns)
            w.add_message(bad, log_time=s.time_ns, data=b"\x00\x01\x00\x00garbage", publish_time=s.time_ns)
        w.finish()
    with pytest.warns(PerfrosWarning, match=r"/odd: no definition of odd_msgs/msg/Odd"):
        latency = read_latency(path)
    assert set(latency) == {"/imu"} and latency["/imu"] is not None
    assert topic_types(path)["/odd"].stamped is None


def test_a_recording_the_libraries_cannot_open_is_one_warning(tmp_path: Path) -> None:
    path = tmp_path / "x.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 40)
    with pytest.warns(PerfrosWarning, match="latency not read"):
        assert read_latency(path) == {}


# --------------------------------------------------------------------------- CLI


def test_info_json_has_latency_only_when_asked(generated: dict[str, Path]) -> None:
    runner = CliRunner()
    plain = json.loads(runner.invoke(app, ["info", str(generated["rosbag2-sqlite3"]), "--json"]).stdout)
    assert plain["latency_read"] is False
    assert all(t["latency_p50_s"] is None for t in plain["topics"])
    res = runner.invoke(app, ["info", str(generated["rosbag2-sqlite3"]), "--json", "--latency"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    by_topic = {t["topic"]: t for t in doc["topics"]}
    expected = read_latency(generated["rosbag2-sqlite3"])
    assert by_topic["/detector/plain"]["latency_max_s"] is None
    for topic in ("/detector/scored", "/imu"):
        lat = expected[topic]
        assert lat is not None
        assert by_topic[topic]["latency_p95_s"] == pytest.approx(lat.p95_s, abs=1e-6)
        assert by_topic[topic]["latency_max_s"] == pytest.approx(lat.max_s, abs=1e-6)


def test_characterise_latency_columns(generated: dict[str, Path], tmp_path: Path) -> None:
    from perfros_bag.characterisation.csvfile import read_characterisation

    d = tmp_path / "recs"
    d.mkdir()
    shutil.copy(generated["ros1"], d / "run.bag")
    out = tmp_path / "c.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--latency", "--out", str(out)])
    assert res.exit_code == 0, res.output
    table = read_characterisation(out)
    assert table.columns[-5:] == ("metric_value", "latency_p50_s", "latency_p95_s", "latency_max_s", "input_hz")
    rows = {r.topic: r for r in table.rows}
    expected = read_latency(generated["ros1"])
    assert rows["/detector/plain"].latency_p50_s is None
    for topic in TOPICS:
        lat = expected.get(topic)
        assert rows[topic].latency_max_s == (None if lat is None else pytest.approx(lat.max_s))


# --------------------------------------------------------------------------- metrics

SYSTEM_YAML = """
computers: [{name: robot1, kind: robot, capacity: 100}]
nodes:
  - name: detector
    weight: 1
    parameter: {name: rate, unit: Hz}
    topics: [/detector/scored, /detector/plain]
    metric: {topic: /detector/scored, field: %s, aggregate: %s, better: higher, range: [0, 10]}
    settings:
      - {value: 1, cpu: 10, performance: 50}
      - {value: 2, cpu: 20, performance: 80}
"""


def _system(tmp_path: Path, field: str = "score", how: str = "mean") -> Path:
    path = tmp_path / "system.yaml"
    path.write_text(SYSTEM_YAML % (field, how))
    return path


@pytest.mark.parametrize("how", ["mean", "median", "p5", "p95"])
@pytest.mark.parametrize("kind", ["ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap-lz4"])
def test_metric_is_the_aggregate_of_the_field_as_written(generated: dict[str, Path], tmp_path: Path,
                                                         kind: str, how: str) -> None:
    from perfros_bag.ingest.contents import read_metric
    from perfros_bag.system.systemfile import load_system

    metric = load_system(_system(tmp_path, how=how)).node["detector"].metric
    assert metric is not None
    scores = np.array([s.score for s in SENT if s.topic == "/detector/scored"])
    expected = {"mean": scores.mean(), "median": np.median(scores), "p5": np.percentile(scores, 5),
                "p95": np.percentile(scores, 95)}[how]
    assert read_metric(generated[kind], metric) == pytest.approx(float(expected), rel=1e-12)


def test_metric_list_and_string_fields_count_their_elements(generated: dict[str, Path], tmp_path: Path) -> None:
    from perfros_bag.ingest.contents import field_value, read_metric
    from perfros_bag.system.systemfile import load_system

    metric = load_system(_system(tmp_path, field="header.frame_id")).node["detector"].metric
    assert metric is not None and read_metric(generated["ros1"], metric) == len("base")
    assert field_value({"a": {"b": [1, 2, 7]}}, "a.b[2]") == 7.0
    assert field_value({"a": {"b": [1, 2, 7]}}, "a.b") == 3.0
    with pytest.raises(ValueError, match="no 'c'"):
        field_value({"a": 1}, "c")


def test_metric_rate_is_the_topic_frequency(generated: dict[str, Path], tmp_path: Path) -> None:
    from perfros_bag.ingest.contents import read_metric
    from perfros_bag.system.systemfile import load_system

    metric = load_system(_system(tmp_path, how="rate")).node["detector"].metric
    times = [s.time_ns for s in SENT if s.topic == "/detector/scored"]
    assert metric is not None
    assert read_metric(generated["rosbag2-mcap"], metric) \
        == pytest.approx((len(times) - 1) / ((times[-1] - times[0]) / 1e9))


def test_a_metric_field_that_is_not_there_warns_and_stays_empty(generated: dict[str, Path], tmp_path: Path) -> None:
    from perfros_bag.ingest.contents import read_metric
    from perfros_bag.system.systemfile import load_system

    metric = load_system(_system(tmp_path, field="header.nothing")).node["detector"].metric
    assert metric is not None
    with pytest.warns(PerfrosWarning, match=r"metric /detector/scored: not read: field 'header.nothing'"):
        assert read_metric(generated["ros1"], metric) is None


@pytest.mark.parametrize(("metric", "problem"), [
    ("{topic: /x, field: a, aggregate: average}", "aggregate: must be one of mean, median, p5, p95, rate"),
    ("{topic: /x, field: a, better: more}", "better: must be 'higher' or 'lower'"),
    ("{topic: /x}", "needs a 'field'"),
    ("{topic: /x, field: a, range: [5, 1]}", "range: high must be above low"),
    ("{topic: /x, field: a, scale: 3}", "unknown key(s) 'scale'"),
])
def test_metric_mistakes_are_one_line_errors(tmp_path: Path, metric: str, problem: str) -> None:
    from perfros_bag.errors import InputError
    from perfros_bag.system.systemfile import load_system

    path = tmp_path / "s.yaml"
    path.write_text((SYSTEM_YAML % ("a", "mean")).replace(
        "{topic: /detector/scored, field: a, aggregate: mean, better: higher, range: [0, 10]}", metric))
    with pytest.raises(InputError, match=re.escape(problem)):
        load_system(path)


def test_characterise_writes_the_metric_on_the_node_rows(generated: dict[str, Path], tmp_path: Path) -> None:
    from perfros_bag.characterisation.csvfile import read_characterisation

    d = tmp_path / "recs"
    d.mkdir()
    shutil.copy(generated["ros1"], d / "run.bag")
    out = tmp_path / "c.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--system", str(_system(tmp_path)), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rows = read_characterisation(out).rows
    mean_score = float(np.mean([s.score for s in SENT if s.topic == "/detector/scored"]))
    detector = [r for r in rows if r.node == "detector"]
    assert {"/detector/scored", "/detector/plain"} <= {r.topic for r in detector}
    assert all(r.metric_value == pytest.approx(mean_score) for r in detector)
    assert all(r.metric_value is None for r in rows if r.node != "detector")
    assert all(r.latency_p50_s is None for r in rows)  # not asked for


def test_validate_puts_the_measured_metric_beside_eq10(generated: dict[str, Path], tmp_path: Path) -> None:
    system = tmp_path / "system.yaml"
    system.write_text((SYSTEM_YAML % ("score", "mean")).replace(
        "performance: 50}", "performance: 50, frequency_hz: 33.3}").replace(
        "performance: 80}", "performance: 80, frequency_hz: 33.3}"))
    res, saved = solve_and_validate(system, generated["rosbag2-mcap"], tmp_path)
    node = json.loads(res.stdout)["nodes"][0]
    mean_score = float(np.mean([s.score for s in SENT if s.topic == "/detector/scored"]))
    assert node["metric_value"] == pytest.approx(mean_score)
    assert node["p_metric"] == pytest.approx(100 * mean_score / 10)  # range [0, 10], higher is better
    assert node["metric_deviation_pct"] \
        == pytest.approx(100 * abs(node["p_metric"] - node["p_expected"]) / node["p_expected"])
    assert "measured metric" in res.stderr  # the table beside eq 10
    from perfros_bag.report.html import build_report, fmt

    page = build_report(tmp_path / "report", validation=saved).read_text()
    section = page.split('id="validation-metric"', 1)[1].split("</table>", 1)[0]
    assert f">{fmt(node['p_metric'])}<" in section


def test_report_shows_metric_and_latency(generated: dict[str, Path], tmp_path: Path) -> None:
    from perfros_bag.report.html import build_report, fmt

    d = tmp_path / "recs"
    d.mkdir()
    shutil.copy(generated["ros1"], d / "run.bag")
    out = tmp_path / "c.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--system", str(_system(tmp_path)), "--latency",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    page = build_report(tmp_path / "report", characterisation=out).read_text()
    assert 'id="contents-table"' in page
    section = page.split('id="contents-table"', 1)[1].split("</table>", 1)[0]
    lat = read_latency(generated["ros1"])["/imu"]
    mean_score = float(np.mean([s.score for s in SENT if s.topic == "/detector/scored"]))
    assert lat is not None and f">{fmt(lat.max_s)}<" in section
    assert f">{fmt(mean_score)}<" in section
    assert "/detector/plain" in section  # the node's metric is on its every row
    plain = build_report(tmp_path / "r2", characterisation=write_plain_csv(tmp_path)).read_text()
    assert "contents-table" not in plain


def write_plain_csv(tmp_path: Path) -> Path:
    path = tmp_path / "plain.csv"
    path.write_text("recording,node,value,topic,frequency_hz,bandwidth_kBps,cpu_units_mean\nr,n,1,/t,1.0,2.0,3.0\n")
    return path


def _damaged_copies(src: Path, dst: Path) -> list[Path]:
    """Truncated at 60 % and with 4 KB of zeros in the middle: every storage file."""
    out = []
    for kind, cut in (("cut", True), ("zeroed", False)):
        target = dst / f"{kind}-{src.name}"
        if src.is_dir():
            shutil.copytree(src, target)
            files = [p for p in target.iterdir() if p.suffix in (".db3", ".mcap")]
        else:
            shutil.copy(src, target)
            files = [target]
        for f in files:
            data = bytearray(f.read_bytes())
            if cut:
                data = data[:len(data) * 6 // 10]
            else:
                mid = len(data) // 2
                data[mid:mid + 4096] = bytes(min(4096, len(data) - mid))
            f.write_bytes(bytes(data))
        out.append(target)
    return out


@pytest.mark.parametrize("kind", ["ros1", "ros1-bz2", "rosbag2-sqlite3", "rosbag2-mcap", "mcap-zstd-some-big-endian"])
def test_damaged_recordings_warn_never_raise(generated: dict[str, Path], tmp_path: Path, kind: str) -> None:
    from perfros_bag.ingest.contents import read_metric
    from perfros_bag.ingest.rosgraph import read_graph
    from perfros_bag.system.systemfile import load_system

    metric = load_system(_system(tmp_path)).node["detector"].metric
    assert metric is not None
    for path in _damaged_copies(generated[kind], tmp_path):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PerfrosWarning)
            latency = read_latency(path)
            read_metric(path, metric)
            read_graph(path)
        assert set(latency) <= {"/detector/scored", "/imu"}
        res = CliRunner().invoke(app, ["info", str(path), "--latency", "--json"])
        assert res.exit_code in (0, 2) and "Traceback" not in res.output, res.output
        if res.exit_code == 2:
            assert res.stderr.startswith("error: ") and len(res.stderr.strip().splitlines()) == 1


def test_ros1_profile_mcap_stamps_after_seq(tmp_path: Path) -> None:
    from contents_gen import write_mcap_ros1

    path = write_mcap_ros1(tmp_path / "ros1.mcap", SENT)
    fast, types = fast_stamps(path)  # the ROS 1 layout inside MCAP: the stamp after seq
    assert types["/imu"].stamp_offset == 4
    _assert_same_stamps(fast, library_stamps(path))
    for topic in ("/detector/scored", "/imu"):
        np.testing.assert_array_equal(_sorted_pairs(*fast[topic]), _sorted_pairs(*_sent_stamps(topic)))


def test_metric_of_json_payloads_through_the_mcap_reader(tmp_path: Path) -> None:
    from contents_gen import write_mcap_json

    from perfros_bag.ingest.contents import read_metric
    from perfros_bag.system.types import Aggregate, Metric

    path = write_mcap_json(tmp_path / "json.mcap", SENT)
    scores = [s.score for s in SENT if s.topic == "/detector/scored"]
    assert read_metric(path, Metric("/detector/scored", "score", Aggregate.MEDIAN)) \
        == pytest.approx(float(np.median(scores)))
    assert read_metric(path, Metric("/detector/scored", "boxes", Aggregate.MEAN)) == pytest.approx(
        float(np.mean([int(abs(s)) for s in scores])))
    assert read_latency(path) == {}  # json: no definition says it has a Header


def _db3_files(generated: dict[str, Path]) -> list[Path]:
    dirs = [generated["rosbag2-sqlite3"]]
    if REALBAGS.is_dir():
        dirs += [REALBAGS / "plotjuggler_rosbag2_test", REALBAGS / "event_camera_test_events_1_db3"]
    return [f for d in dirs for f in sorted(d.glob("*.db3"))]


def test_blob_heads_from_the_pages_equal_sqlite(generated: dict[str, Path]) -> None:
    """sqlitepages.read_blob_heads against SQLite's own substr() on every row."""
    import mmap
    import sqlite3

    from perfros_bag.ingest import sqlitepages

    for db in _db3_files(generated):
        con = sqlite3.connect(f"file:{db}?mode=ro&immutable=1", uri=True)
        ids = [tid for (tid,) in con.execute("SELECT id FROM topics")]
        wanted = [tid for (tid,) in con.execute("SELECT DISTINCT topic_id FROM messages WHERE length(data) >= 12")]
        wanted = [t for t in wanted if con.execute("SELECT min(length(data)) FROM messages WHERE topic_id = ?",
                                                   (t,)).fetchone()[0] >= 12]
        rows = con.execute(f"SELECT topic_id, timestamp, substr(data, 1, 12) FROM messages WHERE topic_id IN "
                           f"({','.join('?' * len(wanted))}) ORDER BY rowid", wanted).fetchall()
        (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
        root = sqlitepages.messages_root(con)
        con.close()
        assert ids and root is not None
        with db.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            tids, times, heads = sqlitepages.read_blob_heads(mm, root, count, wanted, 12)
            got = list(zip(tids.tolist(), times.tolist(), [bytes(h) for h in heads], strict=True))
            del tids, times, heads
        assert got == [(t, ts, bytes(h)) for t, ts, h in rows], db


def _sqlite_ways(db: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, dict]:
    """The stamps of one .db3 read by read_sqlite's three ways: the C page walk copying the
    blobs' heads, the numpy page walks (as without the extension: read_blob_heads), one SQL
    pass."""
    from perfros_bag.ingest import rosbag2, sqlitepages
    from perfros_bag.ingest.stamps import Finder

    def refuse(*_a: object, **_k: object) -> None:
        raise NoIndex("refused by the test")

    def stamps() -> dict:
        finder = Finder()
        return finder.stamps(rosbag2.read_sqlite(db, stamps=finder))

    with monkeypatch.context() as m:  # the C walk gives them: no other way is tried
        m.setattr(rosbag2, "_stamped_rows", refuse)
        ways = {"c-walk": stamps()}
    with monkeypatch.context() as m:  # no extension: the numpy walks, topics split by masks
        m.setattr(sqlitepages, "DECODER", "numpy")
        ways["numpy-pages"] = stamps()
        m.setattr(sqlitepages, "read_blob_heads", refuse)
        ways["sql"] = stamps()
    return ways


def test_sqlite_stamps_are_the_same_every_way(generated: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    from perfros_bag.ingest import sqlitepages

    assert sqlitepages.DECODER == "c"  # the suite fails if the extension was not built
    for db in _db3_files(generated):
        ways = _sqlite_ways(db, monkeypatch)
        for got in ways.values():
            _assert_same_stamps(got, ways["c-walk"])
    generated_db = next(generated["rosbag2-sqlite3"].glob("*.db3"))
    _assert_same_stamps(_sqlite_ways(generated_db, monkeypatch)["c-walk"], library_stamps(generated["rosbag2-sqlite3"]))


def test_c_walk_blob_heads_equal_sqlite_substr(generated: dict[str, Path]) -> None:
    """sqlitepages.read_messages_heads (the C walk) against SQLite's own substr() of every
    row of the wanted topics, zero-filled past a shorter blob, and its columns against
    read_messages."""
    import mmap
    import sqlite3

    from perfros_bag.ingest import sqlitepages

    for db in _db3_files(generated):
        con = sqlite3.connect(f"file:{db}?mode=ro&immutable=1", uri=True)
        ids = [tid for (tid,) in con.execute("SELECT id FROM topics")]
        for want in (ids, ids[:1]):
            rows = con.execute(f"SELECT rowid, substr(data, 1, 12) FROM messages WHERE topic_id IN "
                               f"({','.join('?' * len(want))}) ORDER BY rowid", want).fetchall()
            all_rowids = [r for (r,) in con.execute("SELECT rowid FROM messages ORDER BY rowid")]
            (count,) = con.execute("SELECT count(*) FROM messages").fetchone()
            root = sqlitepages.messages_root(con)
            assert root is not None
            with db.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                tids, times, sizes, at, heads = sqlitepages.read_messages_heads(mm, root, count, want, 12)
                plain = sqlitepages.read_messages(mm, root, count)
                got = [(all_rowids[i], bytes(h)) for i, h in zip(at.tolist(), heads, strict=True)]
                for a, b in zip((tids, times, sizes), plain, strict=True):
                    np.testing.assert_array_equal(a, b)
                del tids, times, sizes, at, heads, plain
            assert got == [(r, bytes(h).ljust(12, b"\0")) for r, h in rows], db
        con.close()


@pytest.mark.parametrize("kind", ["ros1", "ros1-bz2", "ros1-lz4", "rosbag2-sqlite3", "rosbag2-mcap",
                                  "rosbag2-message-zstd", "mcap-zstd-some-big-endian", "mcap-lz4"])
def test_one_pass_equals_the_two_reads(generated: dict[str, Path], kind: str) -> None:
    """read_with_latency (stamps gathered in the index pass) == read_recording + read_latency,
    and the in-pass stamps == the stamped-chunks-only path == the libraries."""
    from perfros_bag.ingest.contents import read_with_latency
    from perfros_bag.ingest.stamps import read_with_stamps

    path = generated[kind]
    stats, latency = read_with_latency(path)
    assert_same_stats(stats, read_recording(path))
    assert latency == read_latency(path)
    assert latency["/imu"] is not None
    if kind != "rosbag2-message-zstd":  # payloads are zstd frames: the libraries decode
        acc, _fmt, finder = read_with_stamps(path)
        only, _fmt, finder_only = read_with_stamps(path, stamped_only=True)
        _assert_same_stamps(finder.stamps(acc), library_stamps(path))
        _assert_same_stamps(finder_only.stamps(only), finder.stamps(acc))


@pytest.mark.parametrize("path", _realbags(), ids=lambda p: p.name)
def test_one_pass_equals_the_two_reads_on_realbags(path: Path) -> None:
    from perfros_bag.errors import InputError
    from perfros_bag.ingest.contents import read_with_latency

    try:
        expected = read_recording(path)
    except InputError as exc:  # a broken recording: the same one-line error
        with pytest.raises(InputError) as got:
            read_with_latency(path)
        assert str(got.value) == str(exc)
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        stats, latency = read_with_latency(path)
        assert latency == read_latency(path)
    assert_same_stats(stats, expected)


def test_cdr_head_stamps_equal_cdr_stamps_both_byte_orders() -> None:
    """The (rows, 12) matrix decoder against the positional one (and rosbags) on little- and
    big-endian heads, negative seconds included."""
    from perfros_bag.ingest._payload import cdr_head_stamps, cdr_stamps

    store = typestore()
    time_t = store.types["builtin_interfaces/msg/Time"]
    header_t = store.types["std_msgs/msg/Header"]
    rng = np.random.default_rng(7)
    heads, expected = [], []
    for k in range(200):
        sec, nsec = int(rng.integers(-2**31, 2**31)), int(rng.integers(0, 10**9))
        raw = bytes(store.serialize_cdr(header_t(stamp=time_t(sec=sec, nanosec=nsec), frame_id="f"),
                                        "std_msgs/msg/Header", little_endian=k % 3 != 0))
        heads.append(np.frombuffer(raw[:12], np.uint8))
        expected.append(sec * 1_000_000_000 + nsec)
    matrix = np.stack(heads)
    got = cdr_head_stamps(matrix)
    np.testing.assert_array_equal(got, np.array(expected, np.int64))
    np.testing.assert_array_equal(got, cdr_stamps(matrix.reshape(-1), np.arange(200, dtype=np.int64) * 12))
    matrix[5, 1] = 3  # an encapsulation other than plain CDR
    with pytest.raises(NoIndex):
        cdr_head_stamps(matrix)


def test_metrics_of_several_nodes_are_read_in_one_pass(generated: dict[str, Path],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import perfros_bag.ingest.contents as contents
    from perfros_bag.system.types import Aggregate, Metric

    metrics = {"a": Metric("/detector/scored", "score", Aggregate.MEAN), "b": Metric("/imu", "linear_acceleration.x",
                                                                                     Aggregate.P95),
               "c": Metric("/detector/scored", "count", Aggregate.MEDIAN), "d": Metric("/imu", "nope"),
               "e": Metric("/detector/plain", "score", Aggregate.RATE)}
    calls: list[set[str]] = []
    real = contents.decoded_messages

    def counted(path: Path, topics: set[str]):  # type: ignore[no-untyped-def]
        calls.append(set(topics))
        return real(path, topics)

    monkeypatch.setattr(contents, "decoded_messages", counted)
    with pytest.warns(PerfrosWarning, match=r"metric /imu: not read: field 'nope'"):
        got = contents.read_metrics(generated["ros1"], metrics)
    assert calls == [{"/detector/scored", "/imu"}]
    scored = [s.score for s in SENT if s.topic == "/detector/scored"]
    imu = [s.score for s in SENT if s.topic == "/imu"]
    assert got["a"] == pytest.approx(float(np.mean(scored)))
    assert got["b"] == pytest.approx(float(np.percentile(imu, 95)))
    assert got["c"] == pytest.approx(float(np.median([int(abs(x)) for x in scored])))
    assert got["d"] is None
    plain = [s.time_ns for s in SENT if s.topic == "/detector/plain"]
    assert got["e"] == pytest.approx((len(plain) - 1) / ((plain[-1] - plain[0]) / 1e9))
