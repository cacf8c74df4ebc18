"""The machine speed reference (perfros_bag/cpu/speed.py) and where its factor goes: the CPU
trace's ``# speed_factor=`` comment (written by record-cpu, optional to read), manifest.yaml's
optional ``speed_factor``, characterisation.csv's appended ``speed_factor`` column."""

from __future__ import annotations

import csv
import itertools
import json
import shutil
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.characterisation.csvfile import COLUMNS, read_characterisation
from perfros_bag.characterisation.manifest import load_manifest, write_manifest
from perfros_bag.cli import app
from perfros_bag.cpu import speed as speed_mod
from perfros_bag.cpu.speed import (
    REFERENCE_S,
    Speed,
    measure_speed,
    reference_workload,
    speed_problem,
)
from perfros_bag.cpu.trace import (
    parse_cpu_trace,
    read_cpu_trace,
    trace_header,
    trace_speed,
    write_cpu_trace,
)
from perfros_bag.errors import InputError

ROOT = Path(__file__).resolve().parent.parent
FIX = ROOT / "fixtures" / "recordings"
HEADER = "# host=h\n# logical_cpus=2\n# interval_s=0.5\n"
COLS = "time,pid,node,process,cpu_percent,rss_bytes\n"
ROWS = "100.5,1,a,python3,50,10\n101.0,1,a,python3,70,10\n"


# --------------------------------------------------------------------------- the workload


def test_reference_workload_is_deterministic_and_small() -> None:
    assert reference_workload() == reference_workload()
    s = measure_speed()
    assert 0 < s.reference_s < 2.0  # ~0.06 s on the reference machine; generous for a loaded one
    assert s.factor == pytest.approx(REFERENCE_S / s.reference_s)


def test_factor_from_a_fake_slow_workload() -> None:
    """A fake CPU clock: the three runs take 0.30, 0.22 and 0.25 s; the best (0.22) counts."""
    ticks = iter([10.0, 10.30, 20.0, 20.22, 30.0, 30.25])
    s = measure_speed(timer=lambda: next(ticks))
    assert s.reference_s == pytest.approx(0.22)
    assert s.factor == pytest.approx(REFERENCE_S / 0.22)
    assert s.factor < 1  # four times slower than the reference machine


def test_factor_from_a_monkeypatched_thread_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """The default timer is time.thread_time: a machine 3x slower than the reference."""
    clock = itertools.count(step=3 * REFERENCE_S)
    monkeypatch.setattr(speed_mod.time, "thread_time", lambda: next(clock))
    s = speed_mod.measure_speed(timer=speed_mod.time.thread_time)
    assert s.factor == pytest.approx(1 / 3)


@pytest.mark.parametrize("value", [0, -1.0, float("nan"), float("inf"), "1.0", True, None])
def test_speed_problem_rejects(value: object) -> None:
    assert speed_problem(value) is not None


def test_speed_problem_accepts() -> None:
    assert speed_problem(1) is None and speed_problem(0.37) is None


# --------------------------------------------------------------------------- the trace


def test_trace_without_the_comment_still_parses() -> None:
    tr = parse_cpu_trace(HEADER + COLS + ROWS)
    assert tr.speed_factor is None and tr.reference_s is None and len(tr) == 2


def test_trace_with_the_comment_parses() -> None:
    tr = parse_cpu_trace(HEADER + "# speed_factor=0.85\n# reference_s=0.0647\n" + COLS + ROWS)
    assert tr.speed_factor == pytest.approx(0.85) and tr.reference_s == pytest.approx(0.0647)
    assert tr.logical_cpus == 2 and len(tr) == 2


@pytest.mark.parametrize("key", ["speed_factor", "reference_s"])
@pytest.mark.parametrize("raw", ["0", "-2", "nan", "inf", "-inf", "fast"])
def test_bad_speed_in_a_trace_is_one_line_naming_the_file(tmp_path: Path, key: str, raw: str) -> None:
    p = tmp_path / "bad.cpu.csv"
    p.write_text(HEADER + f"# {key}={raw}\n" + COLS + ROWS)
    with pytest.raises(InputError) as exc:
        read_cpu_trace(p)
    msg = str(exc.value)
    assert "bad.cpu.csv" in msg and key in msg and repr(raw) in msg and "\n" not in msg


def test_bad_speed_in_a_trace_via_characterise_is_exit_2(tmp_path: Path) -> None:
    d = tmp_path / "recs"
    shutil.copytree(FIX, d)
    trace = d / "tracker_f10.cpu.csv"
    text = trace.read_text()
    trace.write_text("# speed_factor=nan\n" + text)
    res = CliRunner().invoke(app, ["characterise", str(d), "--json"])
    assert res.exit_code in (1, 2)  # that recording fails, named; never a traceback
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "tracker_f10.cpu.csv" in lines[0] and "speed_factor" in lines[0], res.stderr


def test_writer_and_reader_round_trip(tmp_path: Path) -> None:
    p = tmp_path / "w.cpu.csv"
    write_cpu_trace(p, [(1.0, 1, "a", "a", 5.0, 1)], host="h", logical_cpus=4, interval_s=0.5,
                    speed_factor=1.234567, reference_s=0.0445)
    text = p.read_text()
    assert "# speed_factor=1.235\n# reference_s=0.0445\n" + COLS in text  # comment lines first, header unchanged
    tr = read_cpu_trace(p)
    assert tr.speed_factor == pytest.approx(1.235) and tr.reference_s == pytest.approx(0.0445)
    assert trace_speed(p) == pytest.approx(1.235)
    assert trace_header("h", 1, 0.5).endswith("# interval_s=0.5\n" + COLS)  # without: as before


def test_trace_speed_is_none_without_or_when_bad(tmp_path: Path) -> None:
    p = tmp_path / "t.cpu.csv"
    p.write_text(HEADER + COLS + ROWS)
    assert trace_speed(p) is None
    p.write_text(HEADER + "# speed_factor=-3\n" + COLS + ROWS)
    assert trace_speed(p) is None
    assert trace_speed(tmp_path / "missing.cpu.csv") is None


def test_record_cpu_writes_the_factor(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from perfros_bag.cpu import record

    monkeypatch.setattr(speed_mod, "measure_speed", lambda: Speed(0.11, REFERENCE_S / 0.11))
    out = tmp_path / "r.cpu.csv"
    assert record.record_cpu(out, ["^no-such-process-xyz$"], 0.05, duration=0.12, handle_signals=False) == 0
    tr = read_cpu_trace(out)
    assert tr.speed_factor == pytest.approx(REFERENCE_S / 0.11, rel=1e-3) and tr.reference_s == pytest.approx(0.11)
    out2 = tmp_path / "r2.cpu.csv"
    assert record.record_cpu(out2, ["^no-such-process-xyz$"], 0.05, duration=0.12, handle_signals=False,
                             speed=False) == 0
    assert read_cpu_trace(out2).speed_factor is None


def test_emulated_trace_keeps_the_factor(tmp_path: Path) -> None:
    from perfros_bag.rosrun.cgroups import emulated_trace

    raw = tmp_path / "run.host.cpu.csv"
    write_cpu_trace(raw, [(1.0, 1, "/a", "a", 50.0, 1)], host="h", logical_cpus=2, interval_s=0.5,
                    speed_factor=0.9, reference_s=0.061)
    emulated_trace(raw, tmp_path / "run.cpu.csv", {"/a": "robot"}, {"robot": 50.0}, 100.0)
    tr = read_cpu_trace(tmp_path / "run.cpu.csv")
    assert tr.speed_factor == pytest.approx(0.9) and tr.reference_s == pytest.approx(0.061)


# --------------------------------------------------------------------------- the manifest


def test_manifest_round_trips_speed_factor(tmp_path: Path) -> None:
    p = tmp_path / "manifest.yaml"
    write_manifest(p, [{"path": "a.bag", "settings": {"n": 1}, "speed_factor": 0.93},
                       {"path": "b.bag"}])
    doc = yaml.safe_load(p.read_text())
    assert doc["recordings"][0]["speed_factor"] == 0.93
    m = load_manifest(p)
    assert m.recordings[0].speed_factor == pytest.approx(0.93) and m.recordings[1].speed_factor is None


@pytest.mark.parametrize("raw", ["0", "-1", ".nan", ".inf", "fast", "true", "[1]"])
def test_bad_speed_factor_in_a_manifest_is_one_line(tmp_path: Path, raw: str) -> None:
    d = tmp_path / "recs"
    shutil.copytree(FIX, d)
    text = (d / "manifest.yaml").read_text()
    (d / "manifest.yaml").write_text(text.replace("- path: tracker_f10.bag\n",
                                                  f"- path: tracker_f10.bag\n  speed_factor: {raw}\n", 1))
    with pytest.raises(InputError) as exc:
        load_manifest(d / "manifest.yaml")
    assert "manifest.yaml" in str(exc.value) and "recordings[0].speed_factor" in str(exc.value)
    res = CliRunner().invoke(app, ["characterise", str(d), "--out", str(tmp_path / "c.csv")])
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "speed_factor" in lines[0], res.stderr
    assert not (tmp_path / "c.csv").exists()
    with pytest.raises(InputError):
        write_manifest(tmp_path / "m.yaml", [{"path": "a.bag", "speed_factor": float("nan")}])


# --------------------------------------------------------------------------- characterise


def test_characterise_records_the_factor_in_an_appended_column(tmp_path: Path) -> None:
    d = tmp_path / "recs"
    shutil.copytree(FIX, d)
    out = tmp_path / "plain.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--out", str(out)])
    assert res.exit_code == 0, res.stderr
    assert next(csv.reader(out.open())) == list(COLUMNS)  # no factor anywhere: the columns as before
    plain = {(r.recording, r.node, r.topic): r for r in read_characterisation(out).rows}

    data = yaml.safe_load((d / "manifest.yaml").read_text())
    data["recordings"][0]["speed_factor"] = 0.8  # tracker_f10.bag: the manifest says it
    (d / "manifest.yaml").write_text(yaml.safe_dump(data))
    other = data["recordings"][1]["path"]  # tracker_f15: its trace says it
    trace = d / f"{other}.cpu.csv" if (d / f"{other}.cpu.csv").exists() else d / other / f"{other}.cpu.csv"
    trace.write_text("# speed_factor=1.25\n" + trace.read_text())
    out2 = tmp_path / "speed.csv"
    res = CliRunner().invoke(app, ["characterise", str(d), "--out", str(out2)])
    assert res.exit_code == 0, res.stderr
    header = next(csv.reader(out2.open()))
    assert header == [*COLUMNS, "speed_factor"]
    back = read_characterisation(out2)
    for r in back.rows:
        want = 0.8 if r.recording == "tracker_f10.bag" else 1.25 if r.recording == other else None
        assert r.speed_factor == (None if want is None else pytest.approx(want))
        # recorded, not applied: every CPU figure is what it was without the factor
        assert r.cpu_units_mean == plain[(r.recording, r.node, r.topic)].cpu_units_mean
    res = CliRunner().invoke(app, ["characterise", str(d), "--json"])
    rows = json.loads(res.stdout)
    assert list(rows[0]) == [*COLUMNS, "speed_factor"]
    res = CliRunner().invoke(app, ["characterise", str(FIX), "--json"])
    assert "speed_factor" not in json.loads(res.stdout)[0]


def test_the_model_keeps_its_recordings_median_speed_and_validate_notes_another(tmp_path: Path) -> None:
    """fit writes the median ``speed_factor`` of the rows it fitted into model.json (recorded,
    not applied); validate notes a run whose traces say the machine ran more than 15 % off it."""
    import statistics

    from perfros_bag.fitting.modelfile import read_model
    from perfros_bag.validation.eq10 import speed_note

    d = tmp_path / "recs"
    shutil.copytree(FIX, d)
    data = yaml.safe_load((d / "manifest.yaml").read_text())
    for i, entry in enumerate(data["recordings"]):
        entry["speed_factor"] = [0.8, 0.5, 0.75, 0.77, 0.79, 0.76][i % 6]
    (d / "manifest.yaml").write_text(yaml.safe_dump(data))
    csv_path, model_path = tmp_path / "char.csv", tmp_path / "model.json"
    assert CliRunner().invoke(app, ["characterise", str(d), "--out", str(csv_path)]).exit_code == 0
    res = CliRunner().invoke(app, ["fit", str(d / "system.yaml"), str(csv_path), "--out", str(model_path)])
    assert res.exit_code == 0, res.stderr
    rows = [r.speed_factor for r in read_characterisation(csv_path).rows]
    assert None not in rows
    model = read_model(model_path).speed_factor
    assert model == pytest.approx(statistics.median(rows))  # type: ignore[type-var]
    assert json.loads(model_path.read_text())["speed_factor"] == pytest.approx(model)
    assert model is not None

    def trace(name: str, speed: float | None) -> Path:
        p = tmp_path / name
        p.write_text(("" if speed is None else f"# speed_factor={speed}\n") + HEADER + COLS)
        return p

    slow = speed_note(str(model_path), [trace("slow.cpu.csv", model * 0.6)])
    assert slow is not None and f"{1 / 0.6:.2f}x" in slow and str(model_path) in slow
    fast = speed_note(str(model_path), [trace("fast.cpu.csv", model * 1.3)])
    assert fast is not None and f"{1 / 1.3:.2f}x" in fast
    assert speed_note(str(model_path), [trace("same.cpu.csv", model * 0.9)]) is None  # within 15 %
    assert speed_note(str(model_path), [trace("none.cpu.csv", None)]) is None  # the run's speed unknown
    assert speed_note(str(d / "system.yaml"), [trace("slow2.cpu.csv", 0.1)]) is None  # not a model
    bad = tmp_path / "bad.json"
    doc = json.loads(model_path.read_text())
    doc["speed_factor"] = -1
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="speed_factor"):
        read_model(bad)
