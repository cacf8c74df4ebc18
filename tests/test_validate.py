"""validate (eq 10): constructed runs at known fractions of the planned rates."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perfros_bag.errors import InfeasibleError, InputError
from perfros_bag.ingest.stats import RecordingStats, TopicStats
from perfros_bag.system.planfile import parse_plan
from perfros_bag.validation.eq10 import TracedCpu, check_run, default_cpu_trace

# Two computers; node a has one topic, node b two (its ratio is the mean of both).
PLAN: dict[str, Any] = {
    "format": "perfros-bag/plan@1", "problem": 1, "method": "test", "status": "optimal",
    "objective": 65.0,
    "computers": {"robot1": {"kind": "robot", "capacity": 100, "cpu": 60},
                  "server": {"kind": "server", "capacity": 400, "cpu": 120}},
    "links": [{"between": ["robot1", "server"], "bandwidth_kBps": 3.0, "load_kBps": 1.0}],
    "nodes": {
        "a": {"computer": "robot1", "parameter": "rate", "value": 10, "cpu": 60, "performance": 80,
              "weight": 0.5, "topics": {"/a/out": {"frequency_hz": 10, "bandwidth_kBps": 1.0}}},
        "b": {"computer": "server", "parameter": None, "value": None, "cpu": 120, "performance": 50,
              "weight": 0.5, "topics": {"/b/x": {"frequency_hz": 20, "bandwidth_kBps": 2.0},
                                        "/b/y": {"frequency_hz": 5, "bandwidth_kBps": 0.5}}},
    },
}
PLANNED_HZ = {"/a/out": 10, "/b/x": 20, "/b/y": 5}
SPAN_S = 10  # every constructed topic spans exactly 10 s


def times_at(freq: float, span_s: int = SPAN_S, t0: int = 1_700_000_000_000_000_000) -> np.ndarray:
    """Timestamps with (n - 1) / span == freq exactly: an integer period in ns."""
    period = round(1e9 / freq)
    assert period * freq == 1e9, "choose frequencies with an integer period in ns"
    n = int(round(freq * span_s)) + 1
    return t0 + np.arange(n, dtype=np.int64) * period


def stats_at(factor: float, *, drop: tuple[str, ...] = (), extra: tuple[str, ...] = (),
             size: int = 100) -> RecordingStats:
    topics: dict[str, TopicStats] = {}
    for t, f in PLANNED_HZ.items():
        if t in drop:
            continue
        ts = times_at(f * factor)
        topics[t] = TopicStats(t, "std_msgs/msg/String", len(ts), size * len(ts), ts)
    for t in extra:
        ts = times_at(2)
        topics[t] = TopicStats(t, "std_msgs/msg/String", len(ts), 10 * len(ts), ts)
    return RecordingStats(Path("run.mcap"), "mcap", topics)


def plan(**changes: Any) -> Any:
    data = json.loads(json.dumps(PLAN))
    data.update(changes)
    return parse_plan(data, "plan.json")


def overall_expected() -> float:
    return sum(n["weight"] * n["performance"] for n in PLAN["nodes"].values())


def test_eighty_percent_gives_point_eight_performance() -> None:
    v = check_run(stats_at(0.8), plan())
    for n in v.nodes:
        assert n.p_measured == pytest.approx(0.8 * n.p_expected, abs=1e-9)
        assert n.deviation_pct == pytest.approx(20.0, abs=1e-9)
        for t in n.topics:
            assert t.f_measured == pytest.approx(0.8 * PLANNED_HZ[t.topic], abs=1e-9)
    assert v.overall_expected == pytest.approx(65.0)
    assert v.overall_measured == pytest.approx(0.8 * 65.0, abs=1e-9)
    assert v.deviation_pct == pytest.approx(20.0, abs=1e-9)
    assert not v.passed


def test_planned_rates_pass() -> None:
    v = check_run(stats_at(1.0), plan())
    assert v.deviation_pct == pytest.approx(0.0, abs=1e-9)
    assert v.passed
    assert v.missing_topics == []


def test_mean_of_ratios_for_a_node_with_several_topics() -> None:
    # /b/x at 16 of 20 Hz, /b/y at 2 of 5 Hz: b's ratio is (0.8 + 0.4) / 2 = 0.6, the
    # mean of the ratios, not the ratio of the sums (18 / 25 = 0.72).
    s = stats_at(1.0)
    for t, f in (("/b/x", 16), ("/b/y", 2)):
        ts = times_at(f)
        s.topics[t] = TopicStats(t, "x", len(ts), 0, ts)
    v = check_run(s, plan())
    b = next(n for n in v.nodes if n.node == "b")
    assert b.ratio == pytest.approx(0.6, abs=1e-12)
    assert b.p_measured == pytest.approx(50 * 0.6, abs=1e-9)
    assert v.overall_measured == pytest.approx(0.5 * 80 + 0.5 * 30, abs=1e-9)


def test_missing_topic_counts_zero_and_is_flagged() -> None:
    v = check_run(stats_at(1.0, drop=("/a/out",)), plan())
    a = next(n for n in v.nodes if n.node == "a")
    (t,) = a.topics
    assert t.status == "missing" and t.f_measured == 0.0 and t.messages == 0
    assert a.flagged and a.p_measured == 0.0
    assert v.missing_topics == ["/a/out"]
    assert v.overall_measured == pytest.approx(0.5 * 50)
    assert any("/a/out" in note for note in v.notes)
    assert v.to_dict()["nodes"][0]["flagged"] is True


def test_unplanned_topics_listed_not_counted() -> None:
    v = check_run(stats_at(1.0, extra=("/rosout", "/tf")), plan())
    assert [u.topic for u in v.unplanned_topics] == ["/rosout", "/tf"]
    assert v.deviation_pct == pytest.approx(0.0, abs=1e-9)


def test_topic_without_expected_frequency_leaves_node_as_expected() -> None:
    data = json.loads(json.dumps(PLAN))
    data["nodes"]["a"]["topics"]["/a/out"]["frequency_hz"] = None
    v = check_run(stats_at(0.5), parse_plan(data, "plan.json"))
    a = next(n for n in v.nodes if n.node == "a")
    assert not a.counted and a.p_measured == a.p_expected and a.deviation_pct == 0.0
    assert a.topics[0].status == "no-expectation"
    # only b deviates (50 %), weighted: 0.5*25 off 65
    assert v.deviation_pct == pytest.approx(100 * 0.5 * 25 / 65, abs=1e-9)


def test_cap_limits_measured_to_expected() -> None:
    fast = stats_at(1.25)
    assert check_run(fast, plan()).overall_measured == pytest.approx(1.25 * 65, abs=1e-9)
    capped = check_run(fast, plan(), cap=True)
    assert capped.overall_measured == pytest.approx(65, abs=1e-9)
    assert all(n.p_measured == n.p_expected for n in capped.nodes)


def test_topic_names_match_without_leading_slash() -> None:
    s = stats_at(0.8)
    s.topics = {k.lstrip("/"): v for k, v in s.topics.items()}
    v = check_run(s, plan())
    assert v.deviation_pct == pytest.approx(20.0, abs=1e-9)
    assert v.unplanned_topics == []


def test_cpu_overload_per_computer() -> None:
    # robot1: 1 node at 130 % of a 2-core trace -> 65 units on capacity 100 (ok);
    # at 230 % -> 115 units: overloaded. server: 150 % of 4 cores -> 150 units of 400.
    ok = {"a": TracedCpu(130.0, 2, "t.csv"), "b": TracedCpu(150.0, 4, "t.csv")}
    v = check_run(stats_at(1.0), plan(), node_cpu=ok)
    comp = {c.name: c for c in v.computers}
    assert comp["robot1"].cpu_measured == pytest.approx(130 / 200 * 100)
    assert comp["server"].cpu_measured == pytest.approx(150 / 400 * 400)
    assert v.overloaded_computers == []
    hot = dict(ok, a=TracedCpu(230.0, 2, "t.csv"))
    v = check_run(stats_at(1.0), plan(), node_cpu=hot)
    assert v.overloaded_computers == ["robot1"]
    assert {c.name: c.overloaded for c in v.computers} == {"robot1": True, "server": False}


def test_computer_without_traced_nodes_is_unknown() -> None:
    v = check_run(stats_at(1.0), plan(), node_cpu={"a": TracedCpu(10.0, 2, "t.csv")})
    comp = {c.name: c for c in v.computers}
    assert comp["server"].cpu_measured is None and comp["server"].overloaded is None
    assert comp["server"].unmatched_nodes == ["b"]


def test_infeasible_plan_is_refused() -> None:
    data = {"format": "perfros-bag/plan@1", "problem": 1, "method": "x", "status": "infeasible",
            "reason": "node 'a' fits on no computer", "nodes": {}}
    with pytest.raises(InfeasibleError) as caught:
        check_run(stats_at(1.0), parse_plan(data, "p.json"), plan_path="p.json")
    assert str(caught.value) == "p.json: infeasible: node 'a' fits on no computer (nothing to validate)"
    assert caught.value.exit_code == 2


def test_default_cpu_trace(tmp_path: Path) -> None:
    run = tmp_path / "run.mcap"
    run.write_bytes(b"")
    assert default_cpu_trace(run) is None
    (tmp_path / "run.cpu.csv").write_text("")
    assert default_cpu_trace(run) == tmp_path / "run.cpu.csv"
    bagdir = tmp_path / "bag2"
    bagdir.mkdir()
    (bagdir / "bag2.cpu.csv").write_text("")
    assert default_cpu_trace(bagdir) == bagdir / "bag2.cpu.csv"
    (tmp_path / "bag2.cpu.csv").write_text("")
    assert default_cpu_trace(bagdir) == tmp_path / "bag2.cpu.csv"


@settings(max_examples=40, deadline=None)
@given(st.lists(st.sampled_from([1, 2, 4, 5, 8, 10, 16, 20, 25, 40]), min_size=3, max_size=3),
       st.floats(0, 50), st.booleans())
def test_eq10_against_independent_sum(freqs: list[int], tolerance: float, cap: bool) -> None:
    topics = {}
    for t, f in zip(PLANNED_HZ, freqs, strict=True):
        ts = times_at(f)
        topics[t] = TopicStats(t, "x", len(ts), len(ts), ts)
    v = check_run(RecordingStats(Path("r"), "mcap", topics), plan(), cap=cap, tolerance=tolerance)
    ra = freqs[0] / 10
    rb = (freqs[1] / 20 + freqs[2] / 5) / 2
    if cap:
        ra, rb = min(ra, 1.0), min(rb, 1.0)
    measured = 0.5 * 80 * ra + 0.5 * 50 * rb
    assert v.overall_measured == pytest.approx(measured, rel=1e-12)
    dev = 100 * abs(measured - 65) / 65
    assert v.deviation_pct == pytest.approx(dev, rel=1e-9, abs=1e-9)
    if abs(dev - tolerance) > 1e-6:
        assert v.passed == (dev <= tolerance)
    if cap:
        assert all(n.p_measured <= n.p_expected + 1e-12 for n in v.nodes)


# ---------------------------------------------------------------------------------------
# end to end: recordings written with the MCAP and rosbags writers, the CLI


def write_mcap(path: Path, factor: float, drop: tuple[str, ...] = ()) -> None:
    from mcap.writer import Writer

    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name="std_msgs/msg/String", encoding="ros2msg", data=b"string data")
        for t, hz in PLANNED_HZ.items():
            if t in drop:
                continue
            cid = w.register_channel(topic=t, message_encoding="cdr", schema_id=sid)
            for i, ns in enumerate(times_at(hz * factor).tolist()):
                w.add_message(channel_id=cid, log_time=ns, publish_time=ns, data=b"\0" * 40, sequence=i)
        w.finish()


def write_rosbag(path: Path, factor: float, kind: str) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if kind != "ros1" else Stores.ROS1_NOETIC)
    String = store.types["std_msgs/msg/String"]
    if kind == "ros1":
        from rosbags.rosbag1 import Writer as W1

        with W1(path) as w1:
            for t, hz in PLANNED_HZ.items():
                conn = w1.add_connection(t, "std_msgs/msg/String", typestore=store, callerid="/pub")
                for ns in times_at(hz * factor).tolist():
                    w1.write(conn, ns, store.serialize_ros1(String(data="x" * 30), "std_msgs/msg/String"))
        return
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if kind == "rosbag2-mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w2:
        for t, hz in PLANNED_HZ.items():
            conn = w2.add_connection(t, "std_msgs/msg/String", typestore=store)
            for ns in times_at(hz * factor).tolist():
                w2.write(conn, ns, store.serialize_cdr(String(data="x" * 30), "std_msgs/msg/String"))


def run_cli(*args: str) -> Any:
    from typer.testing import CliRunner

    from perfros_bag.cli import app

    return CliRunner().invoke(app, list(args))


@pytest.fixture
def plan_file(tmp_path: Path) -> Path:
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(PLAN))
    return p


@pytest.mark.parametrize("kind", ["mcap", "ros1", "rosbag2-sqlite3", "rosbag2-mcap"])
def test_cli_recordings_at_80_and_100_percent(tmp_path: Path, plan_file: Path, kind: str) -> None:
    for factor, code in ((0.8, 1), (1.0, 0)):
        run = tmp_path / f"run{int(factor * 100)}"
        if kind == "mcap":
            run = run.with_suffix(".mcap")
            write_mcap(run, factor)
        elif kind == "ros1":
            run = run.with_suffix(".bag")
            write_rosbag(run, factor, kind)
        else:
            write_rosbag(run, factor, kind)
        r = run_cli("validate", str(run), str(plan_file), "--json")
        assert r.exit_code == code, r.output
        doc = json.loads(r.stdout)
        assert doc["format"] == "perfros-bag/validation@1"
        assert doc["overall"]["measured"] == pytest.approx(factor * 65.0, abs=1e-9)
        assert doc["overall"]["deviation_pct"] == pytest.approx(100 * (1 - factor), abs=1e-9)
        assert doc["overall"]["passed"] is (code == 0)
        for n in doc["nodes"]:
            assert n["p_measured"] == pytest.approx(factor * n["p_expected"], abs=1e-9)


def test_cli_tolerance_and_tables(tmp_path: Path, plan_file: Path) -> None:
    run = tmp_path / "run.mcap"
    write_mcap(run, 0.8)
    assert run_cli("validate", str(run), str(plan_file), "--tolerance", "20.5").exit_code == 0
    r = run_cli("validate", str(run), str(plan_file))
    assert r.exit_code == 1
    assert "eq 10" in r.stdout and "20.00 %" in r.stdout


def test_cli_missing_topic_flagged(tmp_path: Path, plan_file: Path) -> None:
    run = tmp_path / "run.mcap"
    write_mcap(run, 1.0, drop=("/b/y",))
    r = run_cli("validate", str(run), str(plan_file), "--json")
    doc = json.loads(r.stdout)
    assert doc["missing_topics"] == ["/b/y"]
    b = next(n for n in doc["nodes"] if n["node"] == "b")
    assert b["flagged"] and b["ratio"] == pytest.approx(0.5)
    by = next(t for t in b["topics"] if t["topic"] == "/b/y")
    assert by["status"] == "missing" and by["f_measured"] == 0.0
    assert r.exit_code == 1  # 0.5 * 25 of 65 lost: 19 %


def write_trace(path: Path, rows: list[tuple[str, float]], ncpu: int, t0_s: float) -> None:
    lines = ["# host=h", f"# logical_cpus={ncpu}", "# interval_s=1", "time,pid,node,process,cpu_percent,rss_bytes"]
    for k in range(1, 10):  # samples inside the 10 s recording
        for pid, (node, pct) in enumerate(rows, start=100):
            lines.append(f"{t0_s + k:.3f},{pid},{node},python3,{pct},1000")
    path.write_text("\n".join(lines) + "\n")


def test_cli_cpu_trace_overload(tmp_path: Path, plan_file: Path) -> None:
    run = tmp_path / "run.mcap"
    write_mcap(run, 1.0)
    t0 = 1_700_000_000.0
    # default trace beside the recording: a at 130 % of 2 cores = 65 units of 100 (ok)
    write_trace(tmp_path / "run.cpu.csv", [("/a", 130.0), ("b", 100.0)], 2, t0)
    doc = json.loads(run_cli("validate", str(run), str(plan_file), "--json").stdout)
    comp = {c["computer"]: c for c in doc["computers"]}
    assert comp["robot1"]["cpu_measured"] == pytest.approx(65.0)
    assert comp["server"]["cpu_measured"] == pytest.approx(100 / 200 * 400)
    assert doc["overloaded"] == []
    # an explicit hot trace: 230 % of 2 cores = 115 units > 100
    hot = tmp_path / "hot.cpu.csv"
    write_trace(hot, [("a", 230.0), ("b", 100.0), ("unrelated", 50.0)], 2, t0)
    r = run_cli("validate", str(run), str(plan_file), "--cpu", str(hot), "--json")
    doc = json.loads(r.stdout)
    assert doc["overloaded"] == ["robot1"]
    assert {c["computer"]: c["overloaded"] for c in doc["computers"]} == {"robot1": True, "server": False}
    assert r.exit_code == 0  # frequencies are as planned: overload alone does not fail eq 10
    r = run_cli("validate", str(run), str(plan_file), "--cpu", str(hot))
    assert "overloaded" in r.stdout


def linked_system() -> dict[str, Any]:
    """The plan's system with a 3 kB/s link between its two computers, crossed both ways."""
    return {
        "computers": [{"name": "robot1", "kind": "robot", "capacity": 100},
                      {"name": "server", "kind": "server", "capacity": 400}],
        "links": [{"between": ["robot1", "server"], "bandwidth_kBps": 3.0}],
        "nodes": [{"name": "a", "weight": 0.5, "topics": ["/a/out"], "settings": [{"cpu": 60, "performance": 80}]},
                  {"name": "b", "weight": 0.5, "topics": ["/b/x", "/b/y"],
                   "settings": [{"cpu": 120, "performance": 50}]}],
        "edges": [{"from": "a", "to": "b"}, {"from": "b", "to": "a", "topic": "/b/y"}],
    }


def test_cli_links_with_system(tmp_path: Path, plan_file: Path) -> None:
    import yaml

    system = linked_system()
    sp = tmp_path / "system.yaml"
    sp.write_text(yaml.safe_dump(system))
    run = tmp_path / "run.mcap"
    write_mcap(run, 1.0)
    doc = json.loads(run_cli("validate", str(run), str(plan_file), "--system", str(sp), "--json").stdout)
    (link,) = doc["links"]
    # 40-byte payloads: /a/out 101 msgs and /b/y 51 msgs over 10 s
    assert link["measured_kBps"] == pytest.approx((101 * 40 + 51 * 40) / 10 / 1000)
    assert link["edges"] == ["a->b", "b->a"] and link["overloaded"] is False
    system["links"][0]["bandwidth_kBps"] = 0.5
    sp.write_text(yaml.safe_dump(system))
    doc = json.loads(run_cli("validate", str(run), str(plan_file), "--system", str(sp), "--json").stdout)
    assert doc["links"][0]["overloaded"] is True


def test_cli_bad_inputs_exit_2(tmp_path: Path, plan_file: Path) -> None:
    run = tmp_path / "run.mcap"
    write_mcap(run, 1.0)
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(run.read_bytes()[: len(run.read_bytes()) // 3])
    (tmp_path / "bad.json").write_text("{not json")
    infeasible = tmp_path / "inf.json"
    infeasible.write_text(json.dumps({"format": "perfros-bag/plan@1", "problem": 1, "method": "x",
                                      "status": "infeasible", "reason": "nope"}))
    badtrace = tmp_path / "bad.cpu.csv"
    badtrace.write_text("time,pid\n1,2\n")
    cases = [
        ([str(tmp_path / "absent.mcap"), str(plan_file)], "absent.mcap"),
        ([str(corrupt), str(plan_file)], "corrupt.mcap"),
        ([str(run), str(tmp_path / "bad.json")], "bad.json"),
        ([str(run), str(infeasible)], "infeasible"),
        ([str(run), str(plan_file), "--cpu", str(tmp_path / "none.cpu.csv")], "none.cpu.csv"),
        ([str(run), str(plan_file), "--cpu", str(badtrace)], "bad.cpu.csv"),
    ]
    for args, needle in cases:
        r = run_cli("validate", *args)
        assert r.exit_code == 2, (args, r.output)
        assert needle in r.output and "Traceback" not in r.output


# ---------------------------------------------------------------------------------------
# real recordings (../shared/realbags): frequencies against the independent EXPECTED.tsv


def expected_rows(realbags: Path) -> dict[str, list[dict[str, str]]]:
    import csv

    lines = [ln for ln in (realbags / "EXPECTED.tsv").read_text().splitlines() if not ln.startswith("#")]
    out: dict[str, list[dict[str, str]]] = {}
    for row in csv.DictReader(lines, delimiter="\t"):
        out.setdefault(row["file"], []).append(row)
    return out


@pytest.mark.parametrize("name", ["robot_localization_test1.bag", "plotjuggler_rosbag2_test",
                                  "rosbag2_mcap_talker", "event_camera_test_events_1_db3"])
def test_real_recordings_against_expected_tsv(realbags: Path, tmp_path: Path, name: str) -> None:
    rows = [r for r in expected_rows(realbags)[name] if float(r["mean_hz"] or 0) > 0]
    assert rows
    # one node per topic, planned at mean_hz / 0.8: every ratio is 0.8 -> deviation 20 %
    nodes = {f"n{i}": {"computer": "c", "cpu": 1, "performance": 10.0 * (i + 1), "weight": 1 / len(rows),
                       "topics": {r["topic"]: {"frequency_hz": float(r["mean_hz"]) / 0.8, "bandwidth_kBps": None}}}
             for i, r in enumerate(rows)}
    nodes["ghost"] = {"computer": "c", "cpu": 1, "performance": 5.0, "weight": 1e-12,  # weights are > 0
                      "topics": {"/not/recorded": {"frequency_hz": 1.0, "bandwidth_kBps": None}}}
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps({"format": "perfros-bag/plan@1", "problem": 1, "method": "t",
                                     "status": "optimal",
                                     "computers": {"c": {"kind": "server", "capacity": 100, "cpu": 1}},
                                     "links": [], "nodes": nodes}))
    r = run_cli("validate", str(realbags / name), str(plan_path), "--json")
    assert r.exit_code == 1, r.output
    doc = json.loads(r.stdout)
    assert doc["overall"]["deviation_pct"] == pytest.approx(20.0, abs=1e-3)
    by_topic = {t["topic"]: t for n in doc["nodes"] for t in n["topics"]}
    for row in rows:
        t = by_topic[row["topic"]]
        assert t["f_measured"] == pytest.approx(float(row["mean_hz"]), rel=1e-4)
        assert t["messages"] == int(row["count"])
    assert doc["missing_topics"] == ["/not/recorded"]
    listed = {u["topic"] for u in doc["unplanned_topics"]}
    assert listed == {r["topic"] for r in expected_rows(realbags)[name]} - set(by_topic)


@pytest.mark.parametrize("name", ["rosbagjs_empty-file.bag", "webviz_invalid.bag", "rosbagjs_no-messages.bag",
                                  "rosbag2_sqlite3_empty_bag"])
def test_real_bad_recordings_exit_2(realbags: Path, plan_file: Path, name: str) -> None:
    r = run_cli("validate", str(realbags / name), str(plan_file))
    assert r.exit_code == 2, r.output
    assert name in r.output and "Traceback" not in r.output


def test_simulated_demo_run(tmp_path: Path, plan_file: Path) -> None:
    """pipelines/simulate_run.py (the demo's run) passes at the planned rates and deviates
    by the rate factor otherwise; its CPU trace reproduces the planned loads."""
    import subprocess
    import sys

    from conftest import ROOT

    script = ROOT / "pipelines" / "simulate_run.py"
    for rate, code in ((1.0, 0), (0.8, 1)):
        run = tmp_path / f"sim{code}.mcap"
        p = subprocess.run([sys.executable, str(script), str(plan_file), str(run), "--seconds", "10",
                            "--rate", str(rate)], capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        r = run_cli("validate", str(run), str(plan_file), "--json")
        assert r.exit_code == code
        doc = json.loads(r.stdout)
        assert doc["overall"]["deviation_pct"] == pytest.approx(100 * (1 - rate), abs=1e-6)
        assert {c["computer"]: c["cpu_measured"] for c in doc["computers"]} \
            == pytest.approx({"robot1": 60, "server": 120})


def test_trace_host_differing_from_the_plan_is_noted() -> None:
    cpu = {"a": TracedCpu(10.0, 2, "t.csv", host="server"), "b": TracedCpu(10.0, 2, "t.csv", host="server")}
    v = check_run(stats_at(1.0), plan(), node_cpu=cpu)
    assert [n for n in v.notes if "was the plan deployed" in n] == [
        "node 'a' is planned on 'robot1' but its CPU trace t.csv was recorded on 'server': was the plan deployed?"]


def test_plan_without_any_expected_frequency_is_bad_input() -> None:
    data = json.loads(json.dumps(PLAN))
    for n in data["nodes"].values():
        for t in n["topics"].values():
            t["frequency_hz"] = 0
    with pytest.raises(InputError, match="nothing to compare"):
        check_run(stats_at(1.0), parse_plan(data, "p.json"), plan_path="p.json")


def test_cli_cpu_trace_matched_by_system_process_regex(tmp_path: Path, plan_file: Path) -> None:
    import yaml

    system = {
        "computers": [{"name": "robot1", "kind": "robot", "capacity": 100},
                      {"name": "server", "kind": "server", "capacity": 400}],
        "nodes": [{"name": "a", "weight": 0.5, "process": "^drv_.*", "settings": [{"cpu": 60, "performance": 80}]},
                  {"name": "b", "weight": 0.5, "settings": [{"cpu": 120, "performance": 50}]}],
    }
    sp = tmp_path / "system.yaml"
    sp.write_text(yaml.safe_dump(system))
    run = tmp_path / "run.mcap"
    write_mcap(run, 1.0)
    # two processes of node a (labels matched by the regex): their CPU adds up per sample
    write_trace(tmp_path / "run.cpu.csv", [("drv_left", 40.0), ("drv_right", 60.0), ("b", 8.0)], 4, 1_700_000_000.0)
    without = json.loads(run_cli("validate", str(run), str(plan_file), "--json").stdout)
    assert {c["computer"]: c["unmatched_nodes"] for c in without["computers"]} == {"robot1": ["a"], "server": []}
    doc = json.loads(run_cli("validate", str(run), str(plan_file), "--system", str(sp), "--json").stdout)
    comp = {c["computer"]: c for c in doc["computers"]}
    assert comp["robot1"]["cpu_measured"] == pytest.approx((40 + 60) / 400 * 100)
    assert comp["server"]["cpu_measured"] == pytest.approx(8 / 400 * 400)


def test_missing_plan_system_is_said_not_skipped_silently(tmp_path: Path) -> None:
    import warnings

    from perfros_bag.errors import PerfrosWarning
    from perfros_bag.system.planfile import plan_system

    plan = parse_plan({**PLAN, "system": "gone/system.yaml"})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert plan_system(plan, tmp_path / "plan.json") is None
    messages = [str(w.message) for w in caught if issubclass(w.category, PerfrosWarning)]
    assert len(messages) == 1 and "gone/system.yaml" in messages[0] and "links are not checked" in messages[0]


def test_validation_json_parts_read_back_to_the_same_bytes(tmp_path: Path, plan_file: Path) -> None:
    """Each typed part of a real validation.json (a run with a dropped topic, a CPU trace and
    a link) read back with its ``from_json`` writes the same JSON text, key order included."""
    import yaml

    from perfros_bag.fileio import json_text
    from perfros_bag.validation.eq10 import ComputerCheck, LinkCheck, NetworkCheck, NodeCheck, UnplannedTopic

    sp = tmp_path / "system.yaml"
    sp.write_text(yaml.safe_dump(linked_system()))
    run = tmp_path / "run.mcap"
    write_mcap(run, 0.8, drop=("/b/y",))
    write_trace(tmp_path / "run.cpu.csv", [("/a", 130.0), ("b", 100.0)], 2, 1_700_000_000.0)
    doc = json.loads(run_cli("validate", str(run), str(plan_file), "--system", str(sp), "--json").stdout)
    parts = {"nodes": NodeCheck, "computers": ComputerCheck, "links": LinkCheck, "media": LinkCheck,
             "network": NetworkCheck, "unplanned_topics": UnplannedTopic}
    assert doc["nodes"] and doc["computers"] and doc["links"]
    assert any(t["status"] == "missing" for n in doc["nodes"] for t in n["topics"])  # a topic of every status kind
    for key, kind in parts.items():
        again = [kind.from_json(x).to_dict() for x in doc[key]]  # type: ignore[attr-defined]
        assert json_text(again) == json_text(doc[key]), key
