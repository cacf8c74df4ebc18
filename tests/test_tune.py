"""``tune`` without ROS: how a deployment's rows are weighed in the refit, each round's entry
from deploy.json and validation.json, tune.json's reader, and bad input (one line, exit 2,
nothing written). The loop itself on real ROS 1: tests/test_tune_e2e.py."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.errors import InputError
from perfros_bag.solver import solve
from perfros_bag.system.systemfile import load_system
from perfros_bag.tune.loop import (
    MIN_KEPT,
    THROTTLED_SHARE,
    USE_LEFT_OUT,
    USE_MEASURED,
    USE_RESCALED,
    kept_share,
    load_model,
    model_cpu,
    round_entry,
    weigh,
)
from perfros_bag.tune.tunefile import TUNE_FORMAT, TuneRound, read_tune, write_tune
from perfros_bag.validation.eq10 import ComputerCheck, NodeCheck, Validation
from tests.conftest import FIXTURES

BIN = Path(sys.executable).with_name("perfros-bag")


def _row(recording: str, node: str, value: Any, cpu: float | None = 10.0, freq: float = 10.0) -> Row:
    return Row(recording, node, "p", value, f"/{node}/out", "std_msgs/String", 30, 3.0, freq, 1.0, cpu,
               None if cpu is None else cpu * 1.2, 6, median_rate_hz=freq)


def _round(uses: dict[str, tuple[str, float]], **over: Any) -> TuneRound:
    """Round 1 as tune.json holds it, with each node's refit use and CPU factor."""
    return TuneRound.from_json({"round": 1, "dir": "round-1", "values": {}, "placement": {}, "expected": 1.0,
                                "measured": 1.0, "deviation_pct": 0.0, "within_tolerance": None, "computers": {},
                                "nodes": {n: {"refit": use, "cpu_factor": f} for n, (use, f) in uses.items()},
                                **over})


def _node(counted: bool, ratio: float, expected: float | None = None, measured: float | None = None,
          **over: Any) -> NodeCheck:
    """A node of validation.json: its kept ratio (and a driven node's input rates)."""
    return NodeCheck(over.pop("node", "n"), over.pop("computer", "r1"), 0.2, 50.0, 50.0 * ratio, ratio, 0.0, counted,
                     input_hz_expected=expected, input_hz_measured=measured, **over)


def test_a_deployment_supersedes_the_sweep_at_its_values_and_a_starved_node_is_rescaled() -> None:
    sweep = [_row("sweep/a.bag", "a", 5, 5.0), _row("sweep/b.bag", "a", 15, 8.0), _row("sweep/b.bag", "b", 2, 3.0),
             _row("sweep/b.bag", "c", 1, 4.0), _row("sweep/b.bag", "d", 1, 1.0)]
    deployed = [_row("round-1/run.bag", "a", 15, 12.0, freq=8.0), _row("round-1/run.bag", "b", 2, 3.5),
                _row("round-1/run.bag", "c", 1, 2.0), _row("round-1/run.bag", "other", None, 1.0)]
    done = [_round({"a": (USE_RESCALED, 1.25), "b": (USE_MEASURED, 1.0), "c": (USE_LEFT_OUT, 1.0)})]
    out = weigh(sweep + deployed, done)
    got = {(r.recording, r.node): r for r in out}
    # a at 15: the sweep's row gone, the starved deployment's row as at its planned rate
    assert ("sweep/b.bag", "a") not in got and ("sweep/a.bag", "a") in got
    a = got[("round-1/run.bag", "a")]
    assert (a.cpu_units_mean, a.cpu_units_p95, a.frequency_hz, a.median_rate_hz, a.bandwidth_kBps) == \
        pytest.approx((12.0 * 1.25, 14.4 * 1.25, 10.0, 10.0, 1.25))
    assert a.messages == 30 and a.value == 15  # counts and the value stay as recorded
    # b measured as it will run: it stands for value 2, the sweep's b at 2 is left out
    assert ("sweep/b.bag", "b") not in got and got[("round-1/run.bag", "b")].cpu_units_mean == 3.5
    # c starved without a rate: left out, so the sweep's row of c stays
    assert ("round-1/run.bag", "c") not in got and got[("sweep/b.bag", "c")].cpu_units_mean == 4.0
    # a node the plan does not have, and one no round measured: as any run
    assert ("round-1/run.bag", "other") in got and ("sweep/b.bag", "d") in got
    assert weigh(sweep, []) == sweep


def _plan_and_model(tmp_path: Path) -> tuple[Any, Path]:
    system = {"computers": [{"name": "r1", "kind": "robot", "capacity": 100}, {"name": "r2", "kind": "robot",
                                                                             "capacity": 100}],
              "nodes": [{"name": n, "weight": 0.2, "parameter": {"name": "p"}, "topics": [f"/{n}/out"],
                         "residence": [c],
                         "settings": [{"value": 1, "cpu": 10, "performance": 50, "frequency_hz": 10},
                                      {"value": 2, "cpu": 20, "performance": 100, "frequency_hz": 10}]}
                        for n, c in (("a", "r1"), ("b", "r1"), ("c", "r1"), ("d", "r2"), ("e", "r1"))]}
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(system))
    return solve(load_system(path), 1, "exact"), path


def test_a_round_weighs_each_node_by_its_computers_throttling_and_its_kept_rate(tmp_path: Path) -> None:
    plan, model = _plan_and_model(tmp_path)
    (tmp_path / "round-1").mkdir()
    plan_path = tmp_path / "round-1" / "plan.json"
    periods = 1000
    record = {"values": {"a": 2, "b": 2, "c": 2, "d": 2, "e": 2}, "run_id": "x1", "cpu_cap": {"mode": "cgroup-v1"},
              "network": {"mode": "unshaped"},
              "throttling": {"r1": {"nr_periods": periods, "nr_throttled": THROTTLED_SHARE * periods},
                             "r2": {"nr_periods": periods, "nr_throttled": THROTTLED_SHARE * periods - 1}}}
    node = {"a": (30.0, 0.6, True), "b": (25.0, 0.99, True), "c": (28.0, 1.0, False), "d": (30.0, 0.6, True),
            "e": (None, 1.0, True)}
    validation = Validation("run.bag", "ros1", "plan.json", 5.0, True, 100.0, 80.0, 20.0,
                            [_node(counted, r, node=n, computer=plan.nodes[n].computer, cpu_expected=20.0,
                                   cpu_measured=m) for n, (m, r, counted) in node.items()],
                            [ComputerCheck(c, 100.0, 80.0, 99.0, False) for c in ("r1", "r2")])
    entry = round_entry(1, plan, plan_path, model, record, validation, tolerance=5.0).to_json()
    assert entry["computers"]["r1"]["starved"] and not entry["computers"]["r2"]["starved"]
    n = entry["nodes"]
    assert n["a"]["refit"] == USE_RESCALED and n["a"]["cpu_need"] == pytest.approx(30.0 / 0.6)  # starved, kept 60 %
    assert n["b"]["refit"] == USE_MEASURED and n["b"]["cpu_need"] == 25.0  # starved computer, kept 99 %
    assert n["c"]["refit"] == USE_LEFT_OUT and n["c"]["cpu_need"] is None  # starved, no rate to compare
    assert n["d"]["refit"] == USE_MEASURED and n["d"]["cpu_need"] == 30.0  # its computer was not starved
    assert n["e"]["refit"] == USE_LEFT_OUT  # no CPU measured
    assert n["a"]["model_cpu_before"] == 20.0 and n["a"]["value"] == 2  # the system's setting at the value
    assert not entry["within_tolerance"] and entry["placement"] == {k: v.computer for k, v in plan.nodes.items()}
    # the round as tune.json holds it, read back (TuneRound.from_json) and written again: the same bytes
    path = tmp_path / "tune.json"
    write_tune(path, _doc(rounds=[entry]))
    again = read_tune(path)
    again["rounds"] = [TuneRound.from_json(r).to_json() for r in again["rounds"]]
    write_tune(tmp_path / "again.json", again)
    assert (tmp_path / "again.json").read_bytes() == path.read_bytes()
    validation.nodes[0].ratio = 0.001
    assert round_entry(1, plan, plan_path, model, record, validation, 5.0).nodes["a"].cpu_factor == 1 / MIN_KEPT


def _doc(**over: Any) -> dict[str, Any]:
    r = {"round": 1, "dir": "round-1", "values": {"a": 2}, "placement": {"a": "r1"}, "expected": 1.0,
         "measured": 1.0, "deviation_pct": 0.0, "within_tolerance": True, "nodes": {}, "computers": {}}
    return {"format": TUNE_FORMAT, "rounds": [r], "stopped": {"reason": "within tolerance", "after_round": 1},
            **over}


def test_tune_json_reader(tmp_path: Path) -> None:
    path = tmp_path / "tune.json"
    write_tune(path, _doc())
    assert read_tune(path) == _doc()
    bad = [(_doc(format="perfros-bag/plan@1"), "this is a perfros-bag plan"),
           (_doc(rounds={}), "'rounds' must be a list"),
           (_doc(rounds=[{**_doc()["rounds"][0], "round": 2}]), r"rounds\[0\]: 'round' must be 1"),
           (_doc(rounds=[{"round": 1}]), r"rounds\[0\]: missing 'dir'"),
           (_doc(stopped={"reason": "bored"}), "'stopped' must be null or name a reason")]
    for doc, message in bad:
        path.write_text(json.dumps(doc))
        with pytest.raises(InputError, match=message):
            read_tune(path)
    path.write_text(json.dumps(_doc()).replace('"expected": 1.0', '"expected": 1e300'))
    with pytest.raises(InputError, match=r"rounds\[0\]\.expected: must be at most"):
        read_tune(path)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    # a hang guard: a refusal takes seconds, a minute or more on a loaded machine
    return subprocess.run([str(BIN), "tune", *args], capture_output=True, text=True, timeout=300)


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path: Path) -> None:
    app = FIXTURES / "app"
    out = tmp_path / "out"
    base = [str(app / "app.launch"), "--space", str(app / "space.yaml"), "--system",
            str(FIXTURES / "recordings" / "system.yaml"), "--out", str(out)]
    for extra, message in ((["--headroom", "1"], "headroom must be in [0, 1), got 1.0"),
                           (["--headroom", "-0.1"], "headroom must be in [0, 1), got -0.1"),
                           (["--rounds", "0"], "--rounds must be a whole number > 0, got 0"),
                           (["--method", "magic"], "unknown method 'magic'"),
                           (["--tolerance", "nan"], "--tolerance must be a finite number >= 0, got nan"),
                           (["--duration", "inf"], "--duration must be a finite number > 0, got inf")):
        done = _cli(*base, *extra)
        assert done.returncode == 2, (extra, done.stderr)
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {message}"), (extra, lines)
        assert "Traceback" not in done.stderr and not out.exists()
    # a tune.json made with another method is not resumed
    out.mkdir()
    system = FIXTURES / "recordings" / "system.yaml"
    made = {"launch": str(app / "app.launch"), "space": str(app / "space.yaml"), "system": str(system),
            "system_sha256": hashlib.sha256(system.read_bytes()).hexdigest(), "method": "greedy", "headroom": 0.0,
            "units_per_core": 100.0}
    (out / "tune.json").write_text(json.dumps({**_doc(), **made}))
    done = _cli(*base)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "tune.json: its rounds were made with method 'greedy', not 'exact'" in done.stderr
    assert sorted(p.name for p in out.iterdir()) == ["tune.json"]


def test_the_report_has_the_loops_section_only_when_tune_json_is_given(tmp_path: Path) -> None:
    from perfros_bag.report.html import build_report

    node = {"computer": "r1", "value": 15, "cpu_planned": 77.0, "cpu_measured": 121.0, "kept_ratio": 0.77,
            "starved": True, "cpu_need": 157.1, "cpu_factor": 1.3, "refit": USE_RESCALED, "model_cpu_before": 77.2,
            "model_cpu_after": 157.0}
    first = {**_doc()["rounds"][0], "values": {"worker": 15}, "expected": 99.4, "measured": 76.3,
             "deviation_pct": 23.3, "within_tolerance": False, "nodes": {"worker": node},
             "computers": {"r1": {"capacity": 120.0, "starved": True}}}
    second = {**first, "round": 2, "dir": "round-2", "values": {"worker": 10}, "deviation_pct": 0.1,
              "within_tolerance": True, "nodes": {"worker": {**node, "value": 10, "refit": USE_MEASURED}},
              "computers": {"r1": {"capacity": 120.0, "starved": False}}}
    path = tmp_path / "tune.json"
    write_tune(path, _doc(rounds=[first, second], stopped={"reason": "within tolerance", "after_round": 2}))
    page = build_report(tmp_path / "rep", tune=path).read_text()
    assert '<h2 id="tune">' in page and "stopped: within tolerance after round 2" in page
    rows = page.split('id="tune-rounds"', 1)[1].split("</table>", 1)[0]
    assert rows.count("<tr") == 3 and rows.count('class="bad"') == 1 and "worker=15" in rows
    assert page.split('id="tune-nodes"', 1)[1].split("</table>", 1)[0].count("<tr") == 3
    assert (tmp_path / "rep" / "tune.png").read_bytes()[:4] == b"\x89PNG"
    assert 'id="tune"' not in build_report(tmp_path / "none").read_text()
    assert "base characterisation" not in page
    write_tune(path, _doc(rounds=[first], stopped=None, base="/abs/base.csv", base_sha256="0" * 64))
    assert "fitted on the base characterisation /abs/base.csv (no sweep)" in \
        build_report(tmp_path / "based", tune=path).read_text()


def test_a_driven_node_is_judged_by_what_it_made_of_its_input(tmp_path: Path) -> None:
    """A driven node's kept share is its output's over its input's (a camera that dropped
    frames upstream does not make its detector look starved); its model CPU follows the
    plan's input rate (cpu + cpu_per_hz x F_in)."""
    assert kept_share(_node(True, 0.4, 10.0, 5.0)) == pytest.approx(0.8)
    assert kept_share(_node(True, 0.4)) == 0.4
    assert kept_share(_node(False, 1.0)) is None
    system = {"computers": [{"name": "r1", "kind": "robot", "capacity": 100}],
              "nodes": [{"name": "cam", "weight": 0.5, "topics": ["/cam/out"],
                         "settings": [{"cpu": 1, "performance": 100, "frequency_hz": 10}]},
                        {"name": "det", "weight": 0.5, "input": "/cam/out", "parameter": {"name": "k"},
                         "topics": ["/det/out"],
                         "settings": [{"value": 1, "cpu": 2, "cpu_per_hz": 0.5, "performance": 50},
                                      {"value": 2, "cpu": 2, "cpu_per_hz": 1.5, "performance": 100}]}]}
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(system))
    model = load_model(path)
    assert model_cpu(model, "det", 2, 10.0) == pytest.approx(2 + 1.5 * 10)
    assert model_cpu(model, "det", 2, 4.0) == pytest.approx(2 + 1.5 * 4)
    assert model_cpu(model, "det", 3, 10.0) is None and model_cpu(model, "cam", None) == 1


# --------------------------------------------------------------------------- driven nodes, --base

def _driven_row(recording: str, value: Any, input_hz: float | None, cpu: float = 10.0) -> Row:
    return Row(recording, "det", "scale", value, "/det/out", "std_msgs/String", 30, 3.0, input_hz or 10.0, 1.0, cpu,
               cpu * 1.2, 6, median_rate_hz=input_hz, input_hz=input_hz)


def test_a_driven_nodes_deployment_stands_for_its_value_at_the_input_rate_it_measured() -> None:
    """A paper node's deployment row stands for its value (every sweep row there left out); a
    driven node's for its value at its measured input rate: the sweep's rows at that value
    within 10 % of that rate are left out, the line's other rates stay."""
    from perfros_bag.tune.loop import SAME_INPUT

    sweep = [_driven_row(f"sweep/r{f:g}_s2.bag", 2, f) for f in (5.0, 9.2, 10.0, 11.6, 20.0)]
    sweep += [_driven_row("sweep/r10_s1.bag", 1, 10.0), _driven_row("sweep/none_s3.bag", 3, None)]
    sweep += [_row(f"sweep/r{f:g}_s2.bag", "a", 2, 5.0) for f in (5.0, 10.0)]
    deployed = [_driven_row("round-1/run.bag", 2, 10.5, cpu=14.0), _row("round-1/run.bag", "a", 2, 6.0)]
    done = [_round({"det": (USE_MEASURED, 1.0), "a": (USE_MEASURED, 1.0)})]
    got = {(r.recording, r.node) for r in weigh(sweep + deployed, done, driven={"det"})}
    # within 10 % of 10.5 Hz ([9.45, 11.55]): 10 only; 9.2 and 11.6 are just outside
    assert SAME_INPUT == 0.10
    assert ("sweep/r10_s2.bag", "det") not in got
    assert {("sweep/r5_s2.bag", "det"), ("sweep/r9.2_s2.bag", "det"), ("sweep/r11.6_s2.bag", "det"),
            ("sweep/r20_s2.bag", "det")} <= got
    # other values, and a sweep row without an input rate, stay; the deployment's row is kept
    assert {("sweep/r10_s1.bag", "det"), ("sweep/none_s3.bag", "det"), ("round-1/run.bag", "det")} <= got
    # the paper node: every sweep row at the deployed value left out
    assert not any(rec.startswith("sweep/") and node == "a" for rec, node in got) and ("round-1/run.bag", "a") in got
    # the same rows weighed as a paper node: every sweep row of det at 2 left out (the old rule)
    plain = {(r.recording, r.node) for r in weigh(sweep + deployed, done)}
    assert not any(rec.endswith("_s2.bag") and node == "det" for rec, node in plain)
    # a driven deployment row without an input rate stands for nothing
    blind = [_driven_row("round-1/run.bag", 2, None, cpu=14.0)]
    kept = weigh(sweep + blind, done, driven={"det"})
    assert sum(r.node == "det" and r.recording.startswith("sweep/") for r in kept) == 7


def test_a_starved_driven_node_is_rescaled_at_the_input_rate_it_got() -> None:
    """Its kept share r is its output's over its input's, so measured / r is its need for
    every message it got: CPU, output rate and bandwidth scale by 1 / r, its input_hz stays
    (one point of its line: output over input stays its out_per_in)."""
    row = _driven_row("round-1/run.bag", 2, 8.0, cpu=12.0)
    row = Row(**{**row.__dict__, "frequency_hz": 6.0, "median_rate_hz": 6.0, "bandwidth_kBps": 0.6})
    r = kept_share(_node(True, 0.6, 10.0, 8.0))
    assert r == pytest.approx(0.75)  # it made 6 of the 8 messages a second it got
    assert r is not None
    out = weigh([row], [_round({"det": (USE_RESCALED, 1 / r)})], driven={"det"})[0]
    assert out.input_hz == 8.0 and out.frequency_hz == pytest.approx(8.0) and out.median_rate_hz == pytest.approx(8.0)
    assert out.cpu_units_mean == pytest.approx(16.0) and out.bandwidth_kBps == pytest.approx(0.8)


def _fake_round(monkeypatch: pytest.MonkeyPatch, out: Path, round_rows: list[Row]) -> None:
    """Round 1's folder, its recording characterised as ``round_rows`` (no ROS)."""
    from perfros_bag.characterisation import table

    (out / "round-1").mkdir(parents=True)
    for name in ("run.bag", "run.host.cpu.csv"):
        (out / "round-1" / name).write_bytes(b"")

    def characterise(entries: Any, system: Any = None, **_: Any) -> Any:
        assert [e.name for e in entries] == ["round-1/run.bag"]  # the rounds' recordings only: no sweep
        return table.Result(list(round_rows), [], len(entries))

    monkeypatch.setattr(table, "characterise", characterise)


def test_a_base_run_fits_model_0_on_the_base_and_each_refit_on_it_plus_the_rounds(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--base: model 0 is the fit of the base rows; model 1 the base rows (weighed as the
    sweep's) plus round 1's. The driven detector deployed at value 1 with the camera at 10 Hz
    keeps its base rows at 5 and 20 Hz and gains the deployment's point; the camera (a paper
    node) at 10 is the deployment's alone. Expected lines computed here with numpy."""
    from perfros_bag.characterisation.csvfile import read_characterisation
    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import read_model
    from perfros_bag.tune.loop import fit_rounds
    from tests.test_fit_driven import detector_settings, lstsq, rows, system_yaml, write_inputs

    base_table = rows()
    sys_path, base = write_inputs(tmp_path, system_yaml(), base_table)
    system = load_system(sys_path)
    out = tmp_path / "out"
    out.mkdir()
    m0 = fit_rounds(out, sys_path, system, [], 100.0, base=base)
    assert not (out / "sweep").exists() and not (out / "manifest.yaml").exists()
    assert read_characterisation(out / "characterisation-0.csv").rows == base_table
    with pytest.warns(Warning):
        direct = build_model(sys_path, base).document.to_json()
    assert read_model(m0).to_json()["system"] == direct["system"]

    f_in = 10.2  # the deployment's measured camera rate: within 10 % of the base's 9.97 Hz
    deployed = [Row("round-1/run.bag", "camera", "rate", 10, "/camera/image", "sensor_msgs/Image", 30, 3.0, f_in,
                    1020.0, 7.5, 8.0, 6),
                Row("round-1/run.bag", "detector", "scale", 1.0, "/det/out", "std_msgs/String", 30, 3.0, f_in, 4.08,
                    2.0 + 3.0 * f_in + 4.0, 40.0, 6, input_hz=f_in)]
    _fake_round(monkeypatch, out, deployed)
    done = [_round({"camera": (USE_MEASURED, 1.0), "detector": (USE_MEASURED, 1.0)},
                   values={"camera": 10, "detector": 1.0})]
    m1 = fit_rounds(out, sys_path, system, done, 100.0, base=base)
    manifest = yaml.safe_load((out / "manifest.yaml").read_text())["recordings"]
    assert [e["path"] for e in manifest] == ["round-1/run.bag"]
    used = read_characterisation(out / "characterisation-1.csv").rows
    det1 = [r for r in used if r.node == "detector" and r.value == 1.0]
    assert sorted(r.input_hz or 0 for r in det1) == [4.98, f_in, 19.9]
    points = [(r.input_hz or 0.0, r.cpu_units_mean or 0.0) for r in det1]
    line = lstsq(points)
    got = detector_settings(read_model(m1).to_json())[1.0]
    assert (got["cpu"], got["cpu_per_hz"]) == pytest.approx(line, rel=1e-7)
    # calibration: the base's detector rows scaled by the deployment's CPU over model 0's at
    # the same value and input rate (computed here from model 0's line); the round's own row not
    m0_det = detector_settings(read_model(m0).to_json())[1.0]
    factor = (2.0 + 3.0 * f_in + 4.0) / (m0_det["cpu"] + m0_det["cpu_per_hz"] * f_in)
    assert factor > 1.05  # the 4 units more at 10 Hz
    original = {(r.recording, r.value): r.cpu_units_mean for r in base_table if r.node == "detector"}
    for r in used:
        if r.node == "detector" and r.recording != "round-1/run.bag":
            assert r.cpu_units_mean == pytest.approx(original[(r.recording, r.value)] * factor)
    # the other detector values keep every base row; the camera at 10 is the deployment's alone
    assert sum(r.node == "detector" and r.value != 1.0 for r in used) == 6
    cam10 = [r for r in used if r.node == "camera" and r.value == 10]
    assert [r.recording for r in cam10] == ["round-1/run.bag"]
    camera = next(n for n in read_model(m1).to_json()["system"]["nodes"] if n["name"] == "camera")
    assert next(s for s in camera["settings"] if s["value"] == 10)["cpu"] == pytest.approx(7.5)


def test_base_rows_named_like_a_round_are_renamed(tmp_path: Path) -> None:
    from perfros_bag.characterisation.csvfile import write_characterisation
    from perfros_bag.tune.loop import BASE_PREFIX, base_rows

    path = tmp_path / "base.csv"
    write_characterisation(path, [_row("round-1/run.bag", "a", 1), _row("sweep/round-1/run.bag", "a", 2),
                                  _row("x.bag", "a", 3)])
    assert [r.recording for r in base_rows(path)] == [f"{BASE_PREFIX}round-1/run.bag", "sweep/round-1/run.bag",
                                                      "x.bag"]


def test_a_bad_or_different_base_is_one_line_exit_2(tmp_path: Path) -> None:
    from tests.test_fit_driven import rows, system_yaml, write_inputs

    app = FIXTURES / "app"
    sys_path, base = write_inputs(tmp_path, system_yaml(), rows())
    out = tmp_path / "out"
    args = [str(app / "app.launch"), "--space", str(app / "space.yaml"), "--system", str(sys_path), "--out", str(out)]
    other = tmp_path / "other.csv"
    other.write_text("recording,node,value,topic,frequency_hz,bandwidth_kBps,cpu_units_mean\nx.bag,nobody,1,/t,1,1,1\n")
    for path, message in ((tmp_path / "missing.csv", "missing.csv: "),
                          (sys_path, "system.yaml: "),
                          (other, f"{other}: no row names a node of {sys_path}")):
        done = _cli(*args, "--base", str(path))
        assert done.returncode == 2, (path, done.stderr)
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], lines
        assert "Traceback" not in done.stderr and not out.exists()
    # a tune.json made from another base (or the same path with other bytes) is not resumed
    out.mkdir()
    made = {"launch": str(app / "app.launch"), "space": str(app / "space.yaml"), "system": str(sys_path),
            "system_sha256": hashlib.sha256(sys_path.read_bytes()).hexdigest(), "method": "exact",
            "headroom": 0.0, "units_per_core": 100.0}
    for stored, message in (({"base": str(other), "base_sha256": "0" * 64}, f"made with base '{other}', not '{base}'"),
                            ({"base": str(base), "base_sha256": "0" * 64}, "made with base_sha256 '000"),
                            ({}, f"made with base None, not '{base}'")):
        (out / "tune.json").write_text(json.dumps({**_doc(), **made, **stored}))
        done = _cli(*args, "--base", str(base))
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert f"tune.json: its rounds were made with {message.split('made with ')[1]}" in done.stderr, done.stderr
        assert sorted(p.name for p in out.iterdir()) == ["tune.json"]
    # and a swept tune.json's folder is not resumed with a base, nor a base's without one
    (out / "tune.json").write_text(json.dumps({**_doc(), **made, "base": str(base),
                                               "base_sha256": hashlib.sha256(base.read_bytes()).hexdigest()}))
    done = _cli(*args)
    assert done.returncode == 2 and f"made with base '{base}', not None" in done.stderr, done.stderr


def test_a_round_holds_only_within_tolerance_and_with_no_node_held_back_by_its_cap() -> None:
    from perfros_bag.tune.loop import KEPT_ALL, holds

    def node(starved: bool, kept: float | None) -> dict[str, object]:
        return {"starved": starved, "kept_ratio": kept}

    fine = {"deviation_pct": 1.0, "nodes": {"a": node(False, 1.0), "b": node(True, 0.995)}}
    assert holds(_round({}, **fine), 2.5)  # b's computer was throttled, but b kept its rate: a burst, not a lack
    assert not holds(_round({}, **{**fine, "deviation_pct": 3.0}), 2.5)
    # within tolerance, but a node on a throttled computer fell behind: not a plan that holds
    assert not holds(_round({}, **{**fine, "nodes": {"a": node(False, 1.0), "b": node(True, KEPT_ALL - 0.01)}}), 2.5)
    # behind on a computer that was not throttled (its input fell): judged by the deviation
    assert holds(_round({}, **{**fine, "nodes": {"a": node(False, 0.9)}}), 2.5)
    assert holds(_round({}, deviation_pct=0.0, nodes={"c": node(True, None)}), 0.0)


def test_calibration_carries_how_a_node_ran_in_the_deployments_to_the_values_they_did_not_run() -> None:
    """Model 0 (the sweep's fit) says a needs 10 at value 1 and 20 at value 2; a deployment ran
    a at value 2 with 25 (x1.25): the sweep's rows of a at every value are scaled by 1.25, the
    round's own row is not; b was never deployed and keeps its rows; bounds hold."""
    from perfros_bag.system.systemfile import parse_system
    from perfros_bag.tune.loop import CALIBRATION_BOUNDS, calibrate

    model0 = parse_system({"computers": [{"name": "r1", "kind": "robot", "capacity": 100}],
                           "nodes": [{"name": n, "weight": 0.5, "parameter": {"name": "p"}, "topics": [f"/{n}/out"],
                                      "settings": [{"value": 1, "cpu": 10, "performance": 50, "frequency_hz": 10},
                                                   {"value": 2, "cpu": 20, "performance": 100, "frequency_hz": 10}]}
                                     for n in ("a", "b")]})
    sweep = [_row("sweep/x.bag", "a", 1, 10.0), _row("sweep/y.bag", "a", 2, 20.0), _row("sweep/x.bag", "b", 1, 10.0)]
    deployed = [_row("round-1/run.bag", "a", 2, 25.0)]
    out, factors = calibrate(sweep + deployed, [_round({})], model0)
    assert factors == {"a": pytest.approx(1.25)}
    got = {(r.recording, r.node): r for r in out}
    assert got[("sweep/x.bag", "a")].cpu_units_mean == pytest.approx(12.5)
    assert got[("sweep/x.bag", "a")].cpu_units_p95 == pytest.approx(12.0 * 1.25)
    assert got[("sweep/y.bag", "a")].cpu_units_mean == pytest.approx(25.0)
    assert got[("round-1/run.bag", "a")].cpu_units_mean == 25.0  # the round's own row as measured
    assert got[("sweep/x.bag", "b")].cpu_units_mean == 10.0
    # a deployment at ten times the sweep: the factor stops at the upper bound
    _, capped = calibrate(sweep + [_row("round-1/run.bag", "a", 2, 200.0)], [_round({})], model0)
    assert capped["a"] == CALIBRATION_BOUNDS[1]
    assert calibrate(sweep, [], model0) == (sweep, {})
    # a starved round's rescaled row sets no factor
    starved = [_round({}, nodes={"a": {"refit": USE_RESCALED}})]
    assert calibrate(sweep + deployed, starved, model0) == (sweep + deployed, {})
