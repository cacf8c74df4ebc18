"""`perfros-bag fit`: system.yaml + characterisation.csv -> model.json, plots, bad input,
and the round trip characterise -> fit -> solve."""

from __future__ import annotations

import csv
import json
import statistics
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.fitting.modelfile import MODEL_FORMAT, read_model
from perfros_bag.system.systemfile import load_system, parse_system
from perfros_bag.system.types import Node
from tests.conftest import FIXTURES

HEADER = ["recording", "node", "parameter", "value", "topic", "msgtype", "messages", "duration_s",
          "frequency_hz", "bandwidth_kBps", "cpu_units_mean", "cpu_units_p95", "cpu_samples"]

# Table I (casestudy.md): node -> (parameter, type, [(value, cpu, freq, kB/s, performance)])
TABLE_I: dict[str, tuple[str, str, list[tuple[float, float, float, float, float]]]] = {
    "tracker1": ("output_freq", "float",
                 [(10, 80, 10, 1.0, 40), (15, 120, 15, 1.5, 70), (20, 160, 20, 2.0, 90), (25, 200, 25, 2.5, 100)]),
    "model1": ("goals", "int", [(4, 17, 10, 5, 20), (3500, 40, 10, 5, 70), (10000, 60, 10, 5, 100)]),
    "amcl1": ("particles", "int", [(200, 19, 2.5, 1, 20), (500, 41, 2.5, 1, 50), (3000, 66, 2.5, 1, 100)]),
    "navigation1": ("controller_freq", "float", [(2, 25, 2, 0.1, 10), (10, 39, 10, 0.5, 65), (20, 50, 20, 1.0, 100)]),
}
FIXED = {"experiment": (1, 10, 1, "server"), "environment1": (1, 10, 0.5, None),
         "planner1": (1, 10, 0.5, None), "youbot_core1": (16, 10, 0.5, "robot1")}


def table_i_system() -> dict[str, Any]:
    nodes: list[dict[str, Any]] = []
    for name, (cpu, f, bw, res) in FIXED.items():
        node: dict[str, Any] = {"name": name, "weight": 0.05, "topics": [f"/{name}/out"],
                                "settings": [{"cpu": cpu, "performance": 100, "frequency_hz": f, "bandwidth_kBps": bw}]}
        if res:
            node["residence"] = [res]
        nodes.append(node)
    for name, (param, ptype, rows) in TABLE_I.items():
        nodes.append({"name": name, "weight": 0.2, "parameter": {"name": param, "type": ptype},
                      "topics": [f"/{name}/out"],
                      **({"residence": ["server"]} if name == "tracker1" else {}),
                      "settings": [{"value": v, "cpu": c, "performance": p, "frequency_hz": f, "bandwidth_kBps": b}
                                   for v, c, f, b, p in rows]})
    return {"computers": [{"name": "robot1", "kind": "robot", "capacity": 100},
                          {"name": "server", "kind": "server", "capacity": 400}],
            "links": [{"between": ["robot1", "server"], "bandwidth_kBps": 37500}],
            "nodes": nodes,
            "edges": [{"from": "tracker1", "to": "environment1"}, {"from": "amcl1", "to": "navigation1"}]}


def table_i_rows(seed: int = 0, repeats: int = 3, noise: float = 0.01) -> list[dict[str, Any]]:
    """Measured rows around Table I: `repeats` recordings per setting, multiplicative noise."""
    rng = np.random.default_rng(seed)
    rows: list[dict[str, Any]] = []
    for name, (param, _t, table) in TABLE_I.items():
        for v, c, f, b, _p in table:
            for r in range(repeats):
                rows.append({"recording": f"{name}_{v}_{r}.bag", "node": name, "parameter": param, "value": v,
                             "topic": f"/{name}/out", "msgtype": "std_msgs/String", "messages": 100, "duration_s": 10,
                             "frequency_hz": f * (1 + rng.normal(0, noise)),
                             "bandwidth_kBps": b * (1 + rng.normal(0, noise)),
                             "cpu_units_mean": c * (1 + rng.normal(0, noise)), "cpu_units_p95": c * 1.1,
                             "cpu_samples": 20})
    for name, (cpu, f, bw, _res) in FIXED.items():
        rows.append({"recording": "fixed.bag", "node": name, "parameter": "", "value": "", "topic": f"/{name}/out",
                     "msgtype": "std_msgs/String", "messages": 100, "duration_s": 10, "frequency_hz": f,
                     "bandwidth_kBps": bw, "cpu_units_mean": cpu * 1.05, "cpu_units_p95": cpu, "cpu_samples": 20})
    return rows


def write_csv(path: Path, rows: list[dict[str, Any]], header: list[str] = HEADER) -> Path:
    with path.open("w", newline="") as h:
        w = csv.DictWriter(h, fieldnames=header, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return path


def write_yaml(path: Path, data: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture
def table_i(tmp_path: Path) -> tuple[Path, Path, list[dict[str, Any]]]:
    rows = table_i_rows()
    return write_yaml(tmp_path / "system.yaml", table_i_system()), write_csv(tmp_path / "char.csv", rows), rows


def run(*args: str) -> Any:
    result = CliRunner().invoke(app, ["fit", *args])
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.stderr
    return result


def one_error_line(result: Any) -> str:
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr)
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in result.stderr, result.stderr
    return errors[0]


# --- the model ---------------------------------------------------------------------------

def test_fit_writes_a_model_that_load_system_reads(table_i: tuple[Path, Path, list[dict[str, Any]]],
                                                   tmp_path: Path) -> None:
    system_path, csv_path, rows = table_i
    out = tmp_path / "model.json"
    result = run(str(system_path), str(csv_path), "--out", str(out))
    assert result.exit_code == 0, result.stderr
    doc = json.loads(out.read_text())
    assert doc["format"] == MODEL_FORMAT and doc["characterisation"] == str(csv_path)
    system = load_system(out)
    model = read_model(out)
    assert model.to_json() == doc  # the typed document writes back what it read
    model_system = parse_system(model.system, str(out))
    assert [n.name for n in model_system.nodes] == [n.name for n in system.nodes]
    for name, (_param, _t, table) in TABLE_I.items():
        node = system.node[name]
        assert node.curve is not None and node.curve.scale == 100
        assert set(node.relations) == {"parameter->cpu", "parameter->performance", "cpu->performance",
                                       "parameter->frequency", "parameter->bandwidth"}
        fits = doc["fits"][name]
        for rel, f in fits.items():
            assert set(f) >= {"form", "coef", "r2", "loo_rmse", "domain", "points", "warnings"}, rel
            assert f["form"] in ("linear", "log", "quadratic", "power")
        # measured CPU (mean over the recordings) replaces the expert's; performance stays
        for s, (v, _c, _f, _b, p) in zip(node.settings, table, strict=True):
            mine = [float(r["cpu_units_mean"]) for r in rows if r["node"] == name and r["value"] == v]
            assert s.value == v and s.performance == p
            assert s.cpu == pytest.approx(statistics.fmean(mine), rel=1e-6)
        # the spread is reported: std and count per setting
        for m, (v, *_rest) in zip(doc["measured"][name], table, strict=True):
            mine = [float(r["cpu_units_mean"]) for r in rows if r["node"] == name and r["value"] == v]
            assert m["value"] == v and m["recordings"] == 3 and m["cpu"]["count"] == 3
            assert m["cpu"]["std"] == pytest.approx(statistics.stdev(mine), rel=1e-5)
        # performance of the fitted curve agrees with Table I within a few units
        lo, hi = node.curve.domain
        for s in node.settings:
            if lo <= s.cpu <= hi:
                assert node.curve(s.cpu) == pytest.approx(s.performance, abs=4.0)
    # non-configurable nodes: measured CPU, no curve
    assert system.node["youbot_core1"].curve is None
    assert system.node["youbot_core1"].settings[0].cpu == pytest.approx(16 * 1.05)


def test_json_output_is_the_model_document(table_i: tuple[Path, Path, list[dict[str, Any]]], tmp_path: Path) -> None:
    system_path, csv_path, _ = table_i
    out = tmp_path / "m.json"
    result = run(str(system_path), str(csv_path), "--out", str(out), "--json")
    assert result.exit_code == 0
    assert json.loads(result.stdout) == json.loads(out.read_text())


def test_plots_one_png_per_fitted_node(table_i: tuple[Path, Path, list[dict[str, Any]]], tmp_path: Path) -> None:
    system_path, csv_path, _ = table_i
    result = run(str(system_path), str(csv_path), "--out", str(tmp_path / "m.json"), "--plots", str(tmp_path / "plots"))
    assert result.exit_code == 0, result.stderr
    pngs = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert pngs == sorted(f"{n}.png" for n in TABLE_I)
    for p in (tmp_path / "plots").iterdir():
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000


# --- bad input ---------------------------------------------------------------------------

def test_node_without_rows_is_a_warning_and_keeps_the_expert_numbers(tmp_path: Path) -> None:
    rows = [r for r in table_i_rows() if r["node"] != "amcl1"]
    system_path = write_yaml(tmp_path / "system.yaml", table_i_system())
    out = tmp_path / "m.json"
    result = run(str(system_path), str(write_csv(tmp_path / "c.csv", rows)), "--out", str(out))
    assert result.exit_code == 0, result.stderr
    assert "warning:" in result.stderr and "amcl1" in result.stderr and "no rows" in result.stderr
    amcl = load_system(out).node["amcl1"]
    assert amcl.curve is None and [s.cpu for s in amcl.settings] == [19, 41, 66]


def test_no_row_for_any_node_is_an_error(tmp_path: Path) -> None:
    rows = [dict(r, node="someone_else") for r in table_i_rows()]
    out = tmp_path / "m.json"
    line = one_error_line(run(str(write_yaml(tmp_path / "s.yaml", table_i_system())),
                              str(write_csv(tmp_path / "c.csv", rows)), "--out", str(out)))
    assert "c.csv" in line and "no row" in line
    assert not out.exists()


def test_non_numeric_parameter_value_is_one_error_line(tmp_path: Path) -> None:
    rows = table_i_rows()
    rows[4]["value"] = "lots"
    out = tmp_path / "m.json"
    line = one_error_line(run(str(write_yaml(tmp_path / "s.yaml", table_i_system())),
                              str(write_csv(tmp_path / "c.csv", rows)), "--out", str(out)))
    assert "c.csv" in line and "line 6" in line and "'lots'" in line and "not a number" in line
    assert not out.exists()


@pytest.mark.parametrize("drop", ["cpu_units_mean", "value", "node"])
def test_csv_missing_columns_is_one_error_line(tmp_path: Path, drop: str) -> None:
    header = [h for h in HEADER if h != drop]
    csv_path = write_csv(tmp_path / "c.csv", table_i_rows(), header)
    line = one_error_line(run(str(write_yaml(tmp_path / "s.yaml", table_i_system())), str(csv_path),
                              "--out", str(tmp_path / "m.json")))
    assert "c.csv" in line and "missing column" in line and drop in line


@pytest.mark.parametrize(("content", "problem"), [
    ("", "the file is empty (expected a characterisation.csv header)"),
    ("not,a,characterisation\n1,2,3\n",
     "not a characterisation.csv: missing column(s) recording, node, value, topic, frequency_hz, bandwidth_kBps, "
     "cpu_units_mean"),
    (",".join(HEADER) + "\n", "has a header but no rows"),
])
def test_empty_or_foreign_csv_is_one_error_line(tmp_path: Path, content: str, problem: str) -> None:
    csv_path = tmp_path / "c.csv"
    csv_path.write_text(content)
    line = one_error_line(run(str(write_yaml(tmp_path / "s.yaml", table_i_system())), str(csv_path),
                              "--out", str(tmp_path / "m.json")))
    assert line == f"error: {csv_path}: {problem}"
    assert not (tmp_path / "m.json").exists()


def test_missing_files_are_one_error_line(tmp_path: Path, table_i: tuple[Path, Path, list[dict[str, Any]]]) -> None:
    system_path, csv_path, _ = table_i
    assert "nope.csv" in one_error_line(run(str(system_path), str(tmp_path / "nope.csv"),
                                            "--out", str(tmp_path / "m.json")))
    assert "nope.yaml" in one_error_line(run(str(tmp_path / "nope.yaml"), str(csv_path),
                                             "--out", str(tmp_path / "m.json")))


def test_single_setting_is_a_warning_and_stays_discrete(tmp_path: Path) -> None:
    system = table_i_system()
    amcl = next(n for n in system["nodes"] if n["name"] == "amcl1")
    amcl["settings"] = amcl["settings"][:1]
    rows = [r for r in table_i_rows() if not (r["node"] == "amcl1" and r["value"] != 200)]
    out = tmp_path / "m.json"
    result = run(str(write_yaml(tmp_path / "s.yaml", system)), str(write_csv(tmp_path / "c.csv", rows)),
                 "--out", str(out))
    assert result.exit_code == 0, result.stderr
    assert "amcl1" in result.stderr and "single setting" in result.stderr
    node = load_system(out).node["amcl1"]
    assert node.curve is None and len(node.settings) == 1
    assert node.settings[0].cpu == pytest.approx(
        statistics.fmean(float(r["cpu_units_mean"]) for r in rows if r["node"] == "amcl1"))


def _grid(node: Node) -> np.ndarray:
    assert node.curve is not None
    lo, hi = node.curve.domain
    return np.array([node.curve(float(c)) for c in np.linspace(lo, hi, 1001)])


def test_non_monotone_performance_is_enforced_and_reported(tmp_path: Path) -> None:
    # the expert rated the top setting below the one before it: CPU -> performance rises
    # then falls, which a quadratic follows; the solver needs it non-decreasing
    system = table_i_system()
    system["nodes"] = [n for n in system["nodes"] if n["name"] != "tracker1"]
    perf = [20, 60, 85, 90, 75]
    system["nodes"].append({"name": "tracker1", "weight": 0.2, "parameter": {"name": "output_freq"},
                            "topics": ["/tracker1/out"],
                            "settings": [{"value": v, "cpu": 40 * (i + 1), "performance": p}
                                         for i, (v, p) in enumerate(zip([10, 15, 20, 25, 30], perf, strict=True))]})
    rows = [r for r in table_i_rows() if r["node"] != "tracker1"]
    for i, v in enumerate([10, 15, 20, 25, 30]):
        rows.append({"recording": f"t{v}.bag", "node": "tracker1", "value": v, "topic": "/tracker1/out",
                     "frequency_hz": v, "bandwidth_kBps": v / 10, "cpu_units_mean": 40 * (i + 1)})
    out = tmp_path / "m.json"
    result = run(str(write_yaml(tmp_path / "s.yaml", system)), str(write_csv(tmp_path / "c.csv", rows)),
                 "--out", str(out))
    assert result.exit_code == 0, result.stderr
    assert "tracker1" in result.stderr and "non-decreasing" in result.stderr
    node = load_system(out).node["tracker1"]
    values = _grid(node)
    assert np.all(np.diff(values) >= -1e-9)
    assert values.min() >= 0 and values.max() <= max(perf) + 1e-6
    fit = json.loads(out.read_text())["fits"]["tracker1"]["cpu->performance"]
    assert fit["form"] != "quadratic" and "quadratic" in fit["candidates"]


def test_non_monotone_parameter_to_cpu_is_enforced_and_reported(tmp_path: Path) -> None:
    rows = table_i_rows(noise=0.0)
    # tracker CPU goes up then down with the frame rate: no inverse for a quadratic
    cpu = {10: 80, 15: 160, 20: 190, 25: 150}
    for r in rows:
        if r["node"] == "tracker1":
            r["cpu_units_mean"] = cpu[r["value"]]
    out = tmp_path / "m.json"
    result = run(str(write_yaml(tmp_path / "s.yaml", table_i_system())), str(write_csv(tmp_path / "c.csv", rows)),
                 "--out", str(out))
    assert result.exit_code == 0, result.stderr
    assert "parameter->cpu" in result.stderr and "monotone" in result.stderr
    p2c = load_system(out).node["tracker1"].relations["parameter->cpu"]
    v = np.array([p2c(float(x)) for x in np.linspace(10, 25, 501)])
    assert np.all(np.diff(v) >= -1e-9) or np.all(np.diff(v) <= 1e-9)


# --- round trip: (fixtures ->) characterise -> fit -> solve --------------------------------

def _check_plan_maps_back(model: Path, plan: dict[str, Any]) -> int:
    """Every fitted node's planned value maps back through parameter->cpu to the planned
    CPU (up to the rounding of an int parameter), or is an end of the measured parameter
    range when the planned CPU lies beyond what the fit reaches from inside that range.
    Returns how many nodes were checked."""
    system = load_system(model)
    checked = 0
    for name, pn in plan["nodes"].items():
        node = system.node[name]
        if node.curve is None:
            continue
        checked += 1
        assert node.parameter is not None and pn["parameter"] == node.parameter.name
        p2c = node.relations["parameter->cpu"]
        value, cpu = pn["value"], pn["cpu"]
        lo, hi = node.curve.domain
        assert lo - 1e-6 <= cpu <= hi + 1e-6
        assert cpu == pytest.approx(round(cpu))  # every integer CPU unit of the domain
        assert pn["performance"] == pytest.approx(node.curve(cpu), abs=1e-6)
        vlo, vhi = p2c.domain
        assert vlo - 0.5 <= value <= vhi + 0.5
        reach = sorted((p2c(vlo), p2c(vhi)))
        if node.parameter.type == "int":
            assert value == round(value)
            # one parameter step either way bounds the CPU error of the rounding
            tol = abs(p2c(min(value + 1, vhi)) - p2c(max(value - 1, vlo))) + 1e-6
        else:
            tol = 1e-6 * max(1.0, cpu)
        if reach[0] + tol < cpu < reach[1] - tol:
            assert p2c(value) == pytest.approx(cpu, abs=tol), (name, value, cpu)
        else:  # beyond the fit's reach: the nearest end of the parameter range
            end = vlo if abs(cpu - p2c(vlo)) < abs(cpu - p2c(vhi)) else vhi
            assert value == pytest.approx(end, abs=0.5 if node.parameter.type == "int" else 1e-6) \
                or p2c(value) == pytest.approx(cpu, abs=tol), (name, value, cpu, reach)
        # expected frequency and bandwidth come from the fitted relations at that value
        at = min(max(value, vlo), vhi)
        topic = next(iter(pn["topics"].values()))
        assert topic["frequency_hz"] == pytest.approx(node.relations["parameter->frequency"](at), rel=1e-6)
        assert topic["bandwidth_kBps"] == pytest.approx(node.relations["parameter->bandwidth"](at), rel=1e-6)
    return checked


@pytest.mark.parametrize("method", ["greedy", "exact"])
def test_round_trip_table_i_fit_solve(table_i: tuple[Path, Path, list[dict[str, Any]]], tmp_path: Path,
                                      method: str) -> None:
    system_path, csv_path, _ = table_i
    model = tmp_path / "model.json"
    assert run(str(system_path), str(csv_path), "--out", str(model)).exit_code == 0
    plan_path = tmp_path / "plan.json"
    result = CliRunner().invoke(app, ["solve", str(model), "--problem", "1", "--method", method,
                                      "--out", str(plan_path)])
    assert result.exit_code == 0, result.stderr
    plan = json.loads(plan_path.read_text())
    assert plan["status"] in ("optimal", "feasible")
    assert _check_plan_maps_back(model, plan) == 4


def test_round_trip_from_the_fixture_recordings(tmp_path: Path) -> None:
    rec = FIXTURES / "recordings"
    char = tmp_path / "characterisation.csv"
    runner = CliRunner()
    result = runner.invoke(app, ["characterise", str(rec), "--out", str(char)])
    assert result.exit_code == 0, result.stderr
    model = tmp_path / "model.json"
    result = run(str(rec / "system.yaml"), str(char), "--out", str(model))
    assert result.exit_code == 0, result.stderr
    plan_path = tmp_path / "plan.json"
    result = runner.invoke(app, ["solve", str(model), "--problem", "1", "--method", "greedy", "--out", str(plan_path)])
    assert result.exit_code == 0, result.stderr
    plan = json.loads(plan_path.read_text())
    configurable = [n["name"] for n in yaml.safe_load((rec / "system.yaml").read_text())["nodes"] if n.get("parameter")]
    assert _check_plan_maps_back(model, plan) == len(configurable) > 0


def test_a_node_with_several_topics_gets_per_topic_rates_in_the_plan(tmp_path: Path) -> None:
    system = {"computers": [{"name": "r", "kind": "robot", "capacity": 100}],
              "nodes": [{"name": "lidar", "weight": 1, "parameter": {"name": "rate"}, "topics": ["/scan", "/cloud"],
                         "settings": [{"value": v, "cpu": 2 * v, "performance": 2 * v} for v in (10, 20, 30)]}]}
    rows = []
    for v in (10, 20, 30):
        rows.append({"recording": f"r{v}", "node": "lidar", "value": v, "topic": "/scan",
                     "frequency_hz": v, "bandwidth_kBps": v * 0.5, "cpu_units_mean": 2 * v})
        rows.append({"recording": f"r{v}", "node": "lidar", "value": v, "topic": "/cloud",
                     "frequency_hz": v / 10, "bandwidth_kBps": v * 3, "cpu_units_mean": 2 * v})
    model = tmp_path / "m.json"
    result = run(str(write_yaml(tmp_path / "s.yaml", system)), str(write_csv(tmp_path / "c.csv", rows)),
                 "--out", str(model))
    assert result.exit_code == 0, result.stderr
    rels = load_system(model).node["lidar"].relations
    assert {"parameter->frequency:/scan", "parameter->frequency:/cloud",
            "parameter->bandwidth:/scan", "parameter->bandwidth:/cloud"} <= set(rels)
    # node level: frequency is the mean over topics, bandwidth the sum
    assert rels["parameter->frequency"](20) == pytest.approx((20 + 2) / 2)
    assert rels["parameter->bandwidth"](20) == pytest.approx(10 + 60)
    plan_path = tmp_path / "plan.json"
    solved = CliRunner().invoke(app, ["solve", str(model), "--method", "exact", "--out", str(plan_path)])
    assert solved.exit_code == 0, solved.stderr
    node = json.loads(plan_path.read_text())["nodes"]["lidar"]
    v = node["value"]
    assert node["cpu"] == pytest.approx(2 * v, abs=1e-6)
    assert node["topics"]["/scan"] == pytest.approx({"frequency_hz": v, "bandwidth_kBps": v * 0.5})
    assert node["topics"]["/cloud"] == pytest.approx({"frequency_hz": v / 10, "bandwidth_kBps": v * 3})


def test_model_reader_names_the_broken_place_and_solve_needs_the_system_only(
        table_i: tuple[Path, Path, list[dict[str, Any]]], tmp_path: Path) -> None:
    """read_model checks the whole document (an error names file and place); load_system,
    what solve reads, takes the system part only, as a system.yaml."""
    system_path, csv_path, _ = table_i
    out = tmp_path / "model.json"
    assert run(str(system_path), str(csv_path), "--out", str(out)).exit_code == 0
    doc = json.loads(out.read_text())
    for mutate, problem in (
            (lambda d: d.update(format="other@1"), "not a perfros-bag model (format 'other@1', expected "
                                                   f"'{MODEL_FORMAT}')"),
            (lambda d: d["fits"]["amcl1"]["parameter->cpu"].update(form="cubic"),
             "fits.amcl1.parameter->cpu.form: unknown curve form 'cubic' (one of linear, log, quadratic, power)"),
            (lambda d: d["fits"]["amcl1"]["cpu->performance"]["points"].append([1]),
             "fits.amcl1.cpu->performance.points[3]: expected 2 numbers, got 1"),
            (lambda d: d["measured"]["amcl1"][0].update(cpu={"mean": 1, "std": 0}),
             "measured.amcl1[0].cpu.count: expected a whole number, got None")):
        broken = json.loads(json.dumps(doc))
        mutate(broken)
        path = tmp_path / "broken.json"
        path.write_text(json.dumps(broken))
        with pytest.raises(InputError) as info:
            read_model(path)
        assert str(info.value) == f"{path}: {problem}"
        assert load_system(path).node["amcl1"].curve == load_system(out).node["amcl1"].curve


def _bursty_table_i(tmp_path: Path, seed: int, high: float) -> tuple[list[dict[str, Any]], Path, Path]:
    """Table I's rows with each recording's p95 CPU 1.1-``high`` times its mean (random)."""
    rng = np.random.default_rng(seed)
    rows = table_i_rows()
    for r in rows:
        r["cpu_units_p95"] = float(r["cpu_units_mean"]) * float(rng.uniform(1.1, high))
    return rows, write_yaml(tmp_path / "system.yaml", table_i_system()), write_csv(tmp_path / "char.csv", rows)


def test_cpu_p95_plans_with_the_settings_bursts(tmp_path: Path) -> None:
    """`fit --cpu p95`: each setting's CPU is the mean over its recordings of their
    `cpu_units_p95` (computed here from the CSV rows), not of `cpu_units_mean`; model.json
    says which, and a model without the key reads as `mean`."""
    rows, system_path, csv_path = _bursty_table_i(tmp_path, seed=5, high=1.4)
    out = tmp_path / "model.json"
    result = run(str(system_path), str(csv_path), "--out", str(out), "--cpu", "p95")
    assert result.exit_code == 0, result.stderr
    doc = json.loads(out.read_text())
    assert doc["cpu_statistic"] == "p95"
    system = load_system(out)
    for name, (_param, _t, table) in TABLE_I.items():
        for s, (v, *_rest) in zip(system.node[name].settings, table, strict=True):
            p95 = [float(r["cpu_units_p95"]) for r in rows if r["node"] == name and r["value"] == v]
            mean = [float(r["cpu_units_mean"]) for r in rows if r["node"] == name and r["value"] == v]
            assert s.cpu == pytest.approx(statistics.fmean(p95), rel=1e-6)
            assert s.cpu > statistics.fmean(mean)
    del doc["cpu_statistic"]
    (tmp_path / "old.json").write_text(json.dumps(doc))
    assert read_model(tmp_path / "old.json").cpu_statistic == "mean"
    bad = run(str(system_path), str(csv_path), "--out", str(tmp_path / "x.json"), "--cpu", "p50")
    assert "p50" in one_error_line(bad) and not (tmp_path / "x.json").exists()


def test_a_plan_of_the_mean_model_sets_problem_2_on_the_p95_model(tmp_path: Path) -> None:
    """`solve --problem 2 --settings plan.json` on a model other than the plan's own (here
    `fit --cpu p95` of the same rows): each node is held at the plan's parameter value, at
    that value's CPU in the other model; a node without a parameter at its one setting."""
    rows, system_path, csv_path = _bursty_table_i(tmp_path, seed=9, high=1.3)
    mean_model, p95_model = tmp_path / "mean.json", tmp_path / "p95.json"
    assert run(str(system_path), str(csv_path), "--out", str(mean_model)).exit_code == 0
    assert run(str(system_path), str(csv_path), "--out", str(p95_model), "--cpu", "p95").exit_code == 0
    plan1, plan2 = tmp_path / "p1.json", tmp_path / "p2.json"
    solved = CliRunner().invoke(app, ["solve", str(mean_model), "--problem", "1", "--method", "exact",
                                      "--out", str(plan1)])
    assert solved.exit_code == 0, solved.stderr
    solved = CliRunner().invoke(app, ["solve", str(p95_model), "--problem", "2", "--method", "exact",
                                      "--settings", str(plan1), "--out", str(plan2)])
    assert solved.exit_code == 0, solved.stderr
    first, second = json.loads(plan1.read_text()), json.loads(plan2.read_text())
    p95 = load_system(p95_model)
    for name, planned in first["nodes"].items():
        node = p95.node[name]
        if planned.get("value") is None:
            assert len(node.settings) == 1
            want = node.settings[0].cpu
        else:
            at = [s.cpu for s in node.settings if s.value is not None and np.isclose(s.value, planned["value"])]
            want = at[0] if at else node.relations["parameter->cpu"](planned["value"])
            lo, hi = node.curve.domain if node.curve is not None else (want, want)
            want = min(max(want, lo), hi)
        assert second["nodes"][name]["cpu"] == pytest.approx(want, rel=1e-6), name
    # fed back to its own model, a plan keeps its own CPU levels
    again = tmp_path / "again.json"
    solved = CliRunner().invoke(app, ["solve", str(mean_model), "--problem", "2", "--method", "exact",
                                      "--settings", str(plan1), "--out", str(again)])
    assert solved.exit_code == 0, solved.stderr
    assert {n: v["cpu"] for n, v in json.loads(again.read_text())["nodes"].items()} == pytest.approx(
        {n: v["cpu"] for n, v in first["nodes"].items()})
