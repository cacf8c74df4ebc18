"""characterise: rows against the values the fixtures were generated with (Table I), CPU
against an independent pandas computation over the trace files, bad input as one line and
exit 2, one bad recording among good ones as exit 1 with the good rows written."""

from __future__ import annotations

import csv
import json
import math
import pickle
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from perfros_bag.casestudy.instances import TABLE_I
from perfros_bag.characterisation.csvfile import (
    COLUMNS,
    Row,
    read_characterisation,
    write_characterisation,
)
from perfros_bag.characterisation.manifest import load_manifest
from perfros_bag.characterisation.recording import characterise_recording
from perfros_bag.characterisation.table import characterise, find_entries, table_one
from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.fitting.build import measured_settings
from perfros_bag.ingest import read_recording
from perfros_bag.system.systemfile import load_system, parse_system

ROOT = Path(__file__).resolve().parent.parent
FIX = ROOT / "fixtures" / "recordings"
BIN = ROOT / ".venv" / "bin" / "perfros-bag"
sys.path.insert(0, str(ROOT / "fixtures"))
import make_fixtures as mf  # noqa: E402

CONTRACT = ("recording, node, parameter, value, topic, msgtype, messages, duration_s, frequency_hz, "
            "bandwidth_kBps, cpu_units_mean, cpu_units_p95, cpu_samples").split(", ")


def run_subprocess(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """The real console script: stdout/stderr exactly as a user's pipe sees them."""
    return subprocess.run([str(BIN), *map(str, args)], capture_output=True, text=True, timeout=120)


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


def run(*args: str | Path) -> Ran:
    """In-process (fast) via typer's CliRunner, stdout and stderr kept apart."""
    res = CliRunner().invoke(app, [str(a) for a in args])
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return Ran(res.exit_code, res.stdout, res.stderr)


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def kind(node: str) -> str:
    return node.rstrip("0123456789")


def table_i(node: str, value: float | None) -> tuple[float, float, float]:
    for v, cpu, _perf, freq, bw in TABLE_I[kind(node)][2]:
        if v is None or v == value:
            return cpu, freq, bw
    raise AssertionError(f"{node}={value} not in Table I")


def independent_cpu(trace: Path, start_s: float, end_s: float, capacity: float,
                    procs: dict[str, str | None]) -> dict[str, tuple[float, float, int]]:
    """pandas: rows in the window, node by name or regex, sum per time."""
    lines = trace.read_text().splitlines()
    meta = dict(ln[1:].strip().split("=", 1) for ln in lines if ln.startswith("#"))
    df = pd.read_csv(trace, comment="#")
    ncpu = int(meta["logical_cpus"])
    df = df[(df.time >= start_s) & (df.time <= end_s)].copy()

    def owner(row: pd.Series) -> str:
        for n in procs:
            if row.node == n:
                return n
        for n, rx in procs.items():
            if rx and (pd.Series([row.node, row.process]).str.contains(rx, regex=True).any()):
                return n
        return ""

    df["owner"] = df.apply(owner, axis=1)
    df = df[df.owner != ""]
    sums = df.groupby(["owner", "time"]).cpu_percent.sum() / (100 * ncpu) * capacity
    return {n: (g.mean(), float(np.percentile(g.to_numpy(), 95)), len(g)) for n, g in sums.groupby(level=0)}


@pytest.fixture(scope="module")
def fixture_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """characterise on the bundled fixtures once: its CSV and PNG in the returned directory."""
    d = tmp_path_factory.mktemp("c")
    r = run("characterise", FIX, "--out", d / "characterisation.csv", "--plot", d / "characterisation.png")
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    return d


@pytest.fixture(scope="module")
def fixture_rows(fixture_run: Path) -> list[dict[str, str]]:
    return read_csv(fixture_run / "characterisation.csv")


def test_columns_are_the_contract(fixture_rows: list[dict[str, str]]) -> None:
    assert list(fixture_rows[0])[: len(CONTRACT)] == CONTRACT
    assert list(fixture_rows[0]) == list(COLUMNS)


def test_fixtures_reproduce_table_i(fixture_rows: list[dict[str, str]]) -> None:
    manifest = load_manifest(FIX / "manifest.yaml")
    system = load_system(FIX / "system.yaml")
    by_rec = {e.name: e for e in manifest.recordings}
    seen: set[tuple[str, str]] = set()
    for rec in mf.RECORDINGS:
        rows = [r for r in fixture_rows if r["recording"] == rec.path]
        assert sorted(r["node"] for r in rows) == sorted(rec.nodes), rec.path
        entry = by_rec[rec.path]
        t0_ns = (mf.T0_S + 100 * mf.RECORDINGS.index(rec)) * 1_000_000_000
        start_ns, end_ns = mf.window(rec, t0_ns)
        capacity = system.computer[entry.computer or ""].capacity or 0
        cpu = independent_cpu(entry.cpu or Path(), start_ns / 1e9, end_ns / 1e9, capacity,
                              {n.name: n.process for n in system.nodes})
        for r in rows:
            node = r["node"]
            value = rec.settings.get(node)
            exp_cpu, exp_f, exp_bw = table_i(node, value)
            assert r["topic"] == f"/{node}/out"
            assert int(r["messages"]) == round(exp_f * mf.DURATION_S) + 1
            assert float(r["duration_s"]) == pytest.approx(mf.DURATION_S, abs=1e-9)
            assert float(r["frequency_hz"]) == pytest.approx(exp_f, rel=1e-6)
            assert float(r["bandwidth_kBps"]) == pytest.approx(exp_bw, rel=1e-9)
            assert float(r["cpu_units_mean"]) == pytest.approx(exp_cpu, abs=1e-6)
            mean, p95, n = cpu[node]
            assert float(r["cpu_units_mean"]) == pytest.approx(mean, rel=1e-9)
            assert float(r["cpu_units_p95"]) == pytest.approx(p95, rel=1e-9)
            assert int(r["cpu_samples"]) == n == 20  # 0.25, 0.75, ... 9.75 s into the 10.0x s window
            assert float(r["median_rate_hz"]) == pytest.approx(exp_f, rel=1e-6)
            if value is not None:
                assert r["value"] == f"{value:g}"  # whole numbers as written in the manifest: "10", not "10.0"
                assert r["parameter"] == system.node[node].parameter.name  # type: ignore[union-attr]
            else:
                assert r["value"] == "" and r["parameter"] == ""
            seen.add((node, "" if value is None else str(value)))
    # every Table I setting of every node kind is covered
    expected = {(f"{k}1" if k not in ("experiment",) else k, "" if v is None else str(float(v)))
                for k, (_, _, settings) in TABLE_I.items() for v, *_ in settings}
    assert {(n, str(float(v)) if v else "") for n, v in seen} == expected


def test_json_is_pure_and_equals_csv(fixture_rows: list[dict[str, str]], tmp_path: Path) -> None:
    r = run_subprocess("characterise", FIX, "--json")
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)  # stdout holds only the document
    assert "characterisation" in r.stderr  # the table went to stderr
    assert len(data) == len(fixture_rows)
    for j, c in zip(data, fixture_rows, strict=True):
        assert list(j) == list(COLUMNS)
        for k in COLUMNS:
            if c[k] == "":
                assert j[k] is None
            elif isinstance(j[k], float):
                assert j[k] == pytest.approx(float(c[k]), rel=1e-12)
            else:
                assert str(j[k]) == c[k]


def test_fast_and_slow_paths_agree() -> None:
    entries, _ = find_entries(FIX)
    system = load_system(FIX / "system.yaml")
    fast = characterise(entries, system, fast=True)
    slow = characterise(entries, system, fast=False)
    assert not fast.failures and fast.rows == slow.rows


def test_per_recording_work_is_picklable() -> None:
    """The fleet ships (entry, system) to workers: both pickle, the function is top-level."""
    entries, _ = find_entries(FIX)
    system = load_system(FIX / "system.yaml")
    fn = pickle.loads(pickle.dumps(characterise_recording))
    rows = fn(pickle.loads(pickle.dumps(entries[0])), pickle.loads(pickle.dumps(system)))
    assert rows == characterise_recording(entries[0], system)
    assert pickle.loads(pickle.dumps(rows)) == rows


def test_table_one_averages_over_recordings() -> None:
    entries, _ = find_entries(FIX)
    res = characterise(entries, load_system(FIX / "system.yaml"))
    table = {(t.node, t.value): t for t in table_one(res.rows)}
    assert table[("environment1", None)].recordings == 3
    assert table[("tracker1", 20.0)].cpu == pytest.approx(160)
    assert table[("tracker1", 20.0)].frequency_hz == pytest.approx(20)
    assert table[("navigation1", 2.0)].bandwidth_kBps == pytest.approx(0.1)
    assert len(table) == 4 + 3 + 3 + 3 + 4  # configurable settings + 4 fixed nodes


def copy_fixtures(tmp_path: Path) -> Path:
    d = tmp_path / "recs"
    shutil.copytree(FIX, d)
    return d


def edit_manifest(d: Path, fn: object) -> None:
    data = yaml.safe_load((d / "manifest.yaml").read_text())
    fn(data)  # type: ignore[operator]
    (d / "manifest.yaml").write_text(yaml.safe_dump(data))


def test_one_bad_recording_exit_1_good_rows_written(tmp_path: Path) -> None:
    d = copy_fixtures(tmp_path)
    raw = (d / "tracker_f10.bag").read_bytes()
    (d / "broken.bag").write_bytes(raw[: len(raw) // 3])
    (d / "broken.cpu.csv").write_text("not a trace\n")

    def add(data: dict) -> None:
        data["recordings"].insert(1, {"path": "broken.bag", "computer": "server"})
        data["recordings"].append({"path": "missing.mcap", "computer": "robot1"})

    edit_manifest(d, add)
    out = tmp_path / "c.csv"
    r = run_subprocess("characterise", d, "--out", out)
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 2
    assert "broken.bag" in errors[0] and "missing.mcap" in errors[1] and "not found" in errors[1]
    rows = read_csv(out)
    assert {r["recording"] for r in rows} == {rec.path for rec in mf.RECORDINGS}
    assert len(rows) == sum(len(rec.nodes) for rec in mf.RECORDINGS)


def test_bad_trace_fails_only_its_recording(tmp_path: Path) -> None:
    d = copy_fixtures(tmp_path)
    p = d / "robot_low.cpu.csv"
    lines = p.read_text().splitlines()
    lines[10] = "1700000400.25,1001,environment1,python3,lots,1"
    p.write_text("\n".join(lines) + "\n")
    out = tmp_path / "c.csv"
    r = run("characterise", d, "--out", out)
    assert r.returncode == 1
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "robot_low.cpu.csv: line 11: cpu_percent 'lots' is not a number" in err[0]
    assert "robot_low.bag" not in {row["recording"] for row in read_csv(out)}


def test_nothing_readable_exit_2_no_output(tmp_path: Path) -> None:
    d = tmp_path / "bad"
    d.mkdir()
    (d / "a.bag").write_bytes(b"")
    (d / "b.mcap").write_bytes(b"\x89MCAP0\r\n garbage")
    out = tmp_path / "c.csv"
    r = run("characterise", d, "--out", out)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and all(ln.startswith("error:") for ln in lines)
    assert "a.bag" in lines[0] and "b.mcap" in lines[1]
    assert not out.exists()


@pytest.mark.parametrize(("line", "needle"), [
    ("1700000400.25,1001,environment1", "line 11: expected 6 fields, got 3"),
    ("1700000400.25,abc,environment1,python3,1,1", "line 11: pid 'abc' is not an integer"),
])
def test_single_recording_with_malformed_trace_is_one_line_exit_2(tmp_path: Path, line: str, needle: str) -> None:
    d = tmp_path / "one"
    d.mkdir()
    shutil.copy(FIX / "robot_low.bag", d)
    lines = (FIX / "robot_low.cpu.csv").read_text().splitlines()
    lines[10] = line
    (d / "robot_low.cpu.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "c.csv"
    r = run("characterise", d, "--out", out, "--json")
    assert r.returncode == 2
    assert r.stdout == ""
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and needle in err[0] and "robot_low.cpu.csv" in err[0]
    assert not out.exists()


@pytest.mark.parametrize(("mutate", "needle"), [
    (lambda d: (d / "manifest.yaml").write_text("recordings: [\n  {path: x"), "invalid YAML"),
    (lambda d: (d / "manifest.yaml").write_text("recordings:\n  - {path: a.bag, colour: red}\n"),
     "unknown key(s) 'colour'"),
    (lambda d: (d / "manifest.yaml").write_text("recordings: 3\n"), "recordings: must be a list"),
    (lambda d: (d / "manifest.yaml").write_text("system: system.yaml\nrecordings:\n"
                                                "  - {path: tracker_f10.bag, settings: {nobody: 3}}\n"),
     "unknown node 'nobody'"),
    (lambda d: (d / "manifest.yaml").write_text("system: system.yaml\nrecordings:\n"
                                                "  - {path: tracker_f10.bag, computer: mars}\n"),
     "unknown computer 'mars'"),
    (lambda d: (d / "manifest.yaml").write_text("recordings:\n"
                                                "  - {path: tracker_f10.bag, settings: {tracker1: [1]}}\n"),
     "must be a number or a string"),
    (lambda d: (d / "system.yaml").write_text("computers: [}\n"), "system.yaml: invalid YAML"),
    (lambda d: (d / "system.yaml").write_text("computers: []\nnodes: []\n"), "at least one computer"),
])
def test_bad_manifest_or_system_is_one_line_exit_2(tmp_path: Path, mutate: object, needle: str) -> None:
    d = copy_fixtures(tmp_path)
    mutate(d)  # type: ignore[operator]
    out = tmp_path / "c.csv"
    r = run("characterise", d, "--out", out)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], r.stderr
    assert not out.exists()


def test_computer_without_system_is_an_error_for_that_recording(tmp_path: Path) -> None:
    d = copy_fixtures(tmp_path)
    edit_manifest(d, lambda data: data.pop("system"))
    r = run("characterise", d, "--json")
    assert r.returncode == 2  # every recording names a computer and no system gives capacities
    assert "no system.yaml" in r.stderr and "Traceback" not in r.stderr
    r = run("characterise", d, "--system", d / "system.yaml", "--json")
    assert r.returncode == 0 and len(json.loads(r.stdout)) == sum(len(x.nodes) for x in mf.RECORDINGS)


def test_without_manifest_topics_publishers_and_cpu_only_rows(tmp_path: Path) -> None:
    d = tmp_path / "plain"
    d.mkdir()
    for name in ("tracker_f10.bag", "tracker_f10.cpu.csv", "tracker_f25.mcap", "robot_mid", "robot_mid.cpu.csv"):
        src = FIX / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, d / name)
    r = run("characterise", d, "--json")
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    # every topic of every recording has a row
    topics = {(x["recording"], x["topic"]) for x in rows if x["topic"]}
    assert topics == {(rec.path, f"/{n}/out") for rec in mf.RECORDINGS
                      if rec.path in ("tracker_f10.bag", "tracker_f25.mcap", "robot_mid")
                      for n in rec.nodes}
    ros1 = {x["topic"]: x for x in rows if x["recording"] == "tracker_f10.bag" and x["topic"]}
    assert ros1["/tracker1/out"]["node"] == "/tracker1"  # ROS 1 callerid
    assert ros1["/experiment/out"]["node"] == "/experiment"
    # no computer: capacity 100 = the whole (4-CPU) machine -> experiment's 1 % of a core = 0.25
    assert ros1["/experiment/out"]["cpu_units_mean"] == pytest.approx(1 / 4)
    assert all(x["node"] == "" for x in rows if x["recording"] == "tracker_f25.mcap")
    # trace processes without a topic: CPU-only rows with an empty topic (2 cores -> /2)
    cpu_only = {x["node"]: x for x in rows if x["recording"] == "robot_mid" and not x["topic"]}
    assert set(cpu_only) == {"environment1", "model1", "planner1", "amcl", "navigation1", "youbot_core1",
                             "youbot_driver", "rosmaster"}
    assert cpu_only["model1"]["cpu_units_mean"] == pytest.approx(40.0)  # 80 % of a core out of 2 cores
    assert cpu_only["model1"]["duration_s"] == pytest.approx(10.035)


def test_node_without_topic_gets_a_cpu_row(tmp_path: Path) -> None:
    d = copy_fixtures(tmp_path)
    system = yaml.safe_load((d / "system.yaml").read_text())
    system["nodes"].append({"name": "master", "weight": 0.01, "process": "^rosmaster$",
                            "settings": [{"cpu": 3, "performance": 100}]})
    (d / "system.yaml").write_text(yaml.safe_dump(system))
    r = run("characterise", d, "--json")
    assert r.returncode == 0, r.stderr
    rows = [x for x in json.loads(r.stdout) if x["node"] == "master"]
    assert {x["recording"] for x in rows} == {"robot_low.bag", "robot_mid", "robot_high.mcap"}
    for x in rows:
        assert x["topic"] is None and x["messages"] is None and x["frequency_hz"] is None
        assert x["cpu_units_mean"] == pytest.approx(3.0) and x["cpu_samples"] == 20


def test_library_errors_are_input_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="directory not found"):
        find_entries(tmp_path / "nope")
    (tmp_path / "m.yaml").write_text("")
    with pytest.raises(InputError, match="manifest is empty"):
        find_entries(tmp_path, tmp_path / "m.yaml")


def test_no_recordings_found_exit_2(tmp_path: Path) -> None:
    r = run("characterise", tmp_path, "--out", tmp_path / "c.csv")
    assert r.returncode == 2 and "no recordings found" in r.stderr and "Traceback" not in r.stderr


def test_values_are_finite_numbers(fixture_rows: list[dict[str, str]]) -> None:
    for r in fixture_rows:
        for k in ("frequency_hz", "bandwidth_kBps", "cpu_units_mean", "cpu_units_p95", "duration_s"):
            assert math.isfinite(float(r[k]))


def test_empty_recording_is_a_correct_empty_result(tmp_path: Path) -> None:
    from mcap.writer import Writer

    d = tmp_path / "empty"
    d.mkdir()
    with (d / "nothing.mcap").open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="test")
        w.finish()
    out = tmp_path / "c.csv"
    r = run("characterise", d, "--out", out)
    assert r.returncode == 0, r.stderr
    assert out.read_text().splitlines() == [",".join(COLUMNS)]
    r = run("characterise", d, "--json")
    assert r.returncode == 0 and json.loads(r.stdout) == []


def test_plot_png(fixture_run: Path, tmp_path: Path) -> None:
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.report.characterisation_plots import plot_characterisation

    assert (fixture_run / "characterisation.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = [Row("r", n, "p", float(v), f"/{n}", "t", 11, 10.0, 1.0, 1.0, 5.0 * v, 6.0 * v, 20)
            for n in ("a", "b", "c") for v in ((1, 2) if n != "c" else (1,))]
    assert plot_characterisation(rows, tmp_path / "p.png") == 2  # c has a single setting
    assert (tmp_path / "p.png").stat().st_size > 1000
    assert plot_characterisation(rows[-1:], tmp_path / "none.png") == 0 and not (tmp_path / "none.png").exists()


def test_trace_outside_the_window_falls_back_to_the_whole_trace_with_a_warning(tmp_path: Path) -> None:
    d = tmp_path / "shifted"
    d.mkdir()
    shutil.copy(FIX / "robot_low.bag", d)
    lines = (FIX / "robot_low.cpu.csv").read_text().splitlines()
    out_lines = []
    for ln in lines:
        if ln[:1].isdigit():
            t, rest = ln.split(",", 1)
            ln = f"{float(t) - 10_000:.3f},{rest}"  # another clock: 10,000 s earlier
        out_lines.append(ln)
    (d / "robot_low.cpu.csv").write_text("\n".join(out_lines) + "\n")
    r = run("characterise", d, "--json")
    assert r.returncode == 0, r.stderr
    assert "no sample inside the recording's time window" in r.stderr and "whole trace" in r.stderr
    rows = {x["node"]: x for x in json.loads(r.stdout)}
    # no manifest: ROS 1 publisher /model1 takes trace label model1's CPU, capacity 100 on 2 CPUs.
    # The whole trace: 20 samples in the (original) window averaging 34 %, 13 idle ones at 1.7 %
    assert rows["/model1"]["cpu_samples"] == 33
    assert rows["/model1"]["cpu_units_mean"] == pytest.approx((20 * 34 + 13 * 1.7) / 33 / 2, rel=1e-9)


def test_unwritable_outputs_are_one_line(tmp_path: Path) -> None:
    for args in (["--out", tmp_path], ["--json", "--plot", tmp_path], ["--out", tmp_path / "no" / "x.csv"]):
        target = tmp_path / "no"
        target.write_text("a file where a directory is expected")
        r = run("characterise", FIX, *args)
        assert r.returncode == 2, (args, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:"), r.stderr
        target.unlink()


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.floats(allow_nan=True) | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
        st.sampled_from(["path", "cpu", "computer", "settings", "system", "recordings", "x"]), inner, max_size=4),
    max_leaves=12)


@settings(max_examples=150, deadline=None)
@given(data=json_values)
def test_manifest_parser_never_crashes(data: object) -> None:
    """Any YAML-shaped document: a Manifest or one InputError line naming the file."""
    from perfros_bag.characterisation.manifest import parse_manifest

    try:
        m = parse_manifest(data, Path("m/manifest.yaml"))
    except InputError as exc:
        assert str(exc).startswith("m/manifest.yaml: ") and "\n" not in str(exc)
    else:
        for e in m.recordings:
            assert isinstance(e.name, str) and e.path == Path("m") / e.name
            assert all(isinstance(v, int | float | str) and not isinstance(v, bool) for v in e.settings.values())


def test_no_computer_with_a_system_warns_and_uses_the_whole_machine(tmp_path: Path) -> None:
    d = copy_fixtures(tmp_path)

    def drop(data: dict) -> None:
        data["recordings"] = [dict(e, computer=None) if e["path"] == "tracker_f15" else e for e in data["recordings"]
                              if e["path"] in ("tracker_f15", "tracker_f20")]
        for e in data["recordings"]:
            if e.get("computer") is None:
                e.pop("computer")

    edit_manifest(d, drop)
    r = run("characterise", d, "--json")
    assert r.returncode == 0, r.stderr
    assert "tracker_f15: no 'computer' in the manifest" in r.stderr
    rows = {(x["recording"], x["node"]): x for x in json.loads(r.stdout)}
    # server trace: 4 logical CPUs; capacity 400 (server) vs 100 (whole machine): a factor 4
    assert rows[("tracker_f15", "tracker1")]["cpu_units_mean"] == pytest.approx(120 / 4)
    assert rows[("tracker_f20", "tracker1")]["cpu_units_mean"] == pytest.approx(160)


def test_csv_reader_reads_back_what_the_writer_wrote(tmp_path: Path) -> None:
    entries, _ = find_entries(FIX)
    rows = characterise(entries, load_system(FIX / "system.yaml")).rows
    write_characterisation(tmp_path / "c.csv", rows)
    back = read_characterisation(tmp_path / "c.csv")
    assert back.rows == rows
    assert back.columns == COLUMNS and back.lines == list(range(2, len(rows) + 2))


def test_table_one_and_the_fit_share_one_aggregation(tmp_path: Path) -> None:
    """Two recordings of node n at value 5, two topics each; by hand: a recording's CPU is
    its rows' CPU, its frequency the mean over its topics, its bandwidth their sum; Table I
    averages the recordings; the fit keeps the declared topic only (when recorded)."""
    def row(rec: str, topic: str, f: float, b: float, cpu: float, value: int = 5) -> Row:
        return Row(rec, "n", "p", value, topic, "t", 10, 1.0, f, b, cpu, cpu, 4)

    rows = [row("r1", "/a", 10, 1, 50), row("r1", "/b", 20, 3, 50),
            row("r2", "/a", 12, 1.5, 60), row("r2", "/b", 22, 2.5, 60),
            row("r3", "/a", 30, 9, 90, value=7)]
    t = {(x.node, x.value): x for x in table_one(rows)}
    assert list(t) == [("n", 5), ("n", 7)]
    five = t[("n", 5)]
    assert five.recordings == 2
    assert five.cpu == pytest.approx((50 + 60) / 2)
    assert five.frequency_hz == pytest.approx(((10 + 20) / 2 + (12 + 22) / 2) / 2)
    assert five.bandwidth_kBps == pytest.approx(((1 + 3) + (1.5 + 2.5)) / 2)

    system = parse_system({"computers": [{"name": "c", "kind": "server"}],
                           "nodes": [{"name": "n", "weight": 1, "topics": ["/a"], "parameter": {"name": "p"},
                                      "settings": [{"value": 5, "cpu": 1, "performance": 1},
                                                   {"value": 7, "cpu": 2, "performance": 2}]}]})
    write_characterisation(tmp_path / "c.csv", rows)
    measured = measured_settings(read_characterisation(tmp_path / "c.csv"), system)["n"]
    assert [m.value for m in measured] == [5.0, 7.0] and [m.recordings for m in measured] == [2, 1]
    m5 = measured[0]
    assert m5.cpu is not None and m5.frequency_hz is not None and m5.bandwidth_kBps is not None
    assert (m5.cpu.mean, m5.cpu.count) == (pytest.approx(55), 2)
    assert m5.cpu.std == pytest.approx(math.sqrt(((50 - 55) ** 2 + (60 - 55) ** 2) / 1))
    assert m5.frequency_hz.mean == pytest.approx((10 + 12) / 2)  # /a only: the declared topic
    assert m5.bandwidth_kBps.mean == pytest.approx((1 + 1.5) / 2)
    assert set(m5.topics) == {"/a"}


def test_units_per_core_keeps_the_measurement_apart_from_the_robot(tmp_path: Path) -> None:
    """The same runs characterised with two system.yaml that differ only in the computers'
    capacities (the sweep machine described as a smaller robot): with the manifest's own
    ``units_per_core`` the CPU columns are identical, and they are the trace's cpu_percent /
    100 x units_per_core (pandas over the trace files); without it, the old rule rescales."""
    d = copy_fixtures(tmp_path)
    edit_manifest(d, lambda data: [e.update(units_per_core=50) for e in data["recordings"]])
    base = yaml.safe_load((d / "system.yaml").read_text())
    small = dict(base, computers=[dict(c, capacity=c["capacity"] / 4) for c in base["computers"]])
    (d / "small.yaml").write_text(yaml.safe_dump(small))
    cpu_cols = ("cpu_units_mean", "cpu_units_p95", "cpu_samples")
    out = {}
    for name in ("system.yaml", "small.yaml"):
        r = run("characterise", d, "--system", d / name, "--json")
        assert r.returncode == 0, r.stderr
        out[name] = {(x["recording"], x["node"], x["topic"]): tuple(x[c] for c in cpu_cols)
                     for x in json.loads(r.stdout)}
    assert out["system.yaml"] == out["small.yaml"]
    manifest = load_manifest(d / "manifest.yaml")
    system = load_system(d / "system.yaml")
    procs = {n.name: n.process for n in system.nodes}
    for e in manifest.recordings:
        assert e.cpu is not None and e.units_per_core == 50
        stats = read_recording(e.path)
        ncpu = int(next(x for x in e.cpu.read_text().splitlines() if x.startswith("# logical_cpus=")).split("=")[1])
        expected = independent_cpu(e.cpu, stats.start_ns / 1e9, stats.end_ns / 1e9, 50 * ncpu, procs)
        for node, (mean, p95, n) in expected.items():
            got = next(v for k, v in out["small.yaml"].items() if k[:2] == (e.name, node))
            assert got[0] == pytest.approx(mean) and got[1] == pytest.approx(p95) and got[2] == n
    # the computer only says where it was measured: the robot may be another machine
    edit_manifest(d, lambda data: [e.update(computer="sweep-machine") for e in data["recordings"]])
    r = run("characterise", d, "--system", d / "small.yaml", "--json")
    assert r.returncode == 0, r.stderr
    assert {(x["recording"], x["node"], x["topic"]): tuple(x[c] for c in cpu_cols)
            for x in json.loads(r.stdout)} == out["small.yaml"]
    # and it needs no system.yaml to normalise (without one the nodes are the trace's labels)
    edit_manifest(d, lambda data: data.pop("system"))
    r = run("characterise", d, "--json")
    assert r.returncode == 0, r.stderr
    bare = {(x["recording"], x["node"]): x["cpu_units_mean"] for x in json.loads(r.stdout)}
    assert bare[("tracker_f15", "people_tracker")] == next(  # the trace's label of tracker1
        v[0] for k, v in out["small.yaml"].items() if k[:2] == ("tracker_f15", "tracker1"))
    # without units_per_core the computer's capacity normalises (the old contract, kept)
    def old(data: dict) -> None:
        data["recordings"] = [e for e in data["recordings"] if e["path"] == "tracker_f15"]
        data["recordings"][0].pop("units_per_core")
        data["recordings"][0]["computer"] = "server"

    edit_manifest(d, old)
    rows = {}
    for name in ("system.yaml", "small.yaml"):
        r = run("characterise", d, "--system", d / name, "--json")
        assert r.returncode == 0, r.stderr
        rows[name] = next(x for x in json.loads(r.stdout)
                          if x["recording"] == "tracker_f15" and x["node"] == "tracker1")
    assert rows["small.yaml"]["cpu_units_mean"] == pytest.approx(rows["system.yaml"]["cpu_units_mean"] / 4)


@pytest.mark.parametrize("bad", [0, -1, "many", True, float("inf")])
def test_bad_units_per_core_is_one_line(tmp_path: Path, bad: object) -> None:
    d = copy_fixtures(tmp_path)
    edit_manifest(d, lambda data: data["recordings"][0].update(units_per_core=bad))
    r = run("characterise", d, "--json")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "recordings[0].units_per_core: must be" in lines[0], r.stderr
