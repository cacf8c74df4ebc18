"""model.json ``unmeasured`` and solve's ``measured?`` column: which values the recordings
ran, and the leave-one-out error a value never measured carries, recomputed here with numpy's
own least squares from the points model.json states."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.cli.solve import measured_note
from perfros_bag.fitting.modelfile import read_model, read_unmeasured, value_errors
from perfros_bag.system.planfile import load_plan
from tests.test_fit_cli import TABLE_I, table_i_rows, table_i_system, write_csv, write_yaml

pytestmark = pytest.mark.filterwarnings("ignore")


def _loo(form: str, points: list[list[float]]) -> float | None:
    """Leave-one-out RMSE of a polynomial form (in x, or ln x for log) by numpy.polyfit."""
    x = np.array([p[0] for p in points], dtype=float)
    y = np.array([p[1] for p in points], dtype=float)
    if form not in ("linear", "quadratic", "log") or len(x) < 3:
        return None
    u = np.log(x) if form == "log" else x
    deg = 2 if form == "quadratic" else 1
    errs = []
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        errs.append(np.polyval(np.polyfit(u[keep], y[keep], deg), u[i]) - y[i])
    return float(np.sqrt(np.mean(np.square(errs))))


@pytest.fixture
def model(tmp_path: Path) -> Path:
    system = write_yaml(tmp_path / "system.yaml", table_i_system())
    char = write_csv(tmp_path / "char.csv", table_i_rows())
    out = tmp_path / "model.json"
    res = CliRunner().invoke(app, ["fit", str(system), str(char), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def test_model_json_states_the_measured_values_and_each_fits_loo_error(model: Path) -> None:
    doc = json.loads(model.read_text())
    checked = 0
    for name, (_param, _t, rows) in TABLE_I.items():
        entry = doc["unmeasured"][name]
        assert entry["measured_values"] == sorted(float(r[0]) for r in rows) and entry["driven"] is False
        for quantity, rel in (("cpu", "parameter->cpu"), ("frequency_hz", "parameter->frequency"),
                              ("bandwidth_kBps", "parameter->bandwidth")):
            fit = doc["fits"][name].get(rel)
            if fit is None:
                assert quantity not in entry["loo_rmse"]
                continue
            expected = _loo(fit["form"], fit["points"])
            if expected is not None:
                assert entry["loo_rmse"][quantity] == pytest.approx(expected, rel=1e-4, abs=1e-9)
                checked += 1
    assert checked >= 4
    assert set(doc["unmeasured"]) == set(TABLE_I)  # nodes without fits have no entry
    assert read_model(model).unmeasured.keys() == doc["unmeasured"].keys()  # the reader keeps it


def test_the_solve_table_says_measured_or_the_loo_error(model: Path, tmp_path: Path) -> None:
    doc = json.loads(model.read_text())
    entry = doc["unmeasured"]["navigation1"]
    plan_path = tmp_path / "plan.json"
    res = CliRunner().invoke(app, ["solve", str(model), "--problem", "2", "--method", "exact",
                                   "--settings", "navigation1=15,tracker1=20,amcl1=500,model1=3500",
                                   "--out", str(plan_path)])
    assert res.exit_code == 0, res.output
    plan = load_plan(plan_path)
    notes = measured_note(plan, read_unmeasured(model))
    assert set(notes) == set(TABLE_I)
    for name in TABLE_I:
        value = plan.nodes[name].value
        measured = any(abs((value or 0) - r[0]) <= 1e-6 * max(1.0, r[0]) for r in TABLE_I[name][2])
        assert notes[name].startswith("yes" if measured else "no")
    assert plan.nodes["navigation1"].value == pytest.approx(15, abs=0.5)  # never measured (2, 10, 20)
    errors = value_errors(read_unmeasured(model)["navigation1"], plan.nodes["navigation1"].value)
    assert errors is not None
    for quantity, err in errors.items():
        assert err == entry["loo_rmse"][quantity]
        shown = "?" if err is None else f"{err:.2f}".rstrip("0").rstrip(".")
        assert f"±{shown}" in notes["navigation1"]


def test_a_driven_nodes_error_follows_its_input_rate() -> None:
    from perfros_bag.fitting.modelfile import Unmeasured

    u = Unmeasured((1.0, 2.0), {"cpu_base": 0.5, "cpu_per_hz": 0.1, "out_per_in": 0.02, "bytes_per_msg": 100.0},
                   driven=True)
    assert value_errors(u, 2.0, input_hz=10.0) is None
    e: dict[str, Any] | None = value_errors(u, 1.5, input_hz=10.0, frequency_hz=9.0, bandwidth_kBps=9.0)
    assert e == pytest.approx({"cpu": 0.5 + 0.1 * 10, "frequency_hz": 0.02 * 10,
                               "bandwidth_kBps": (100 * 9 + 1000 * 0.2) / 1000})
    throttle = Unmeasured((2.0, 6.0), {"cpu_base": 0.0, "cpu_per_hz": 0.02}, driven=True, rule="period")
    e = value_errors(throttle, 4.5, input_hz=15.0, frequency_hz=3.75, bandwidth_kBps=900.0)
    assert e is not None and e["frequency_hz"] == 0.0 and e["cpu"] == pytest.approx(0.3)
