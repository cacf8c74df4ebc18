"""``solve --measured-only`` and plan.json's ``measured`` / ``loo_error``: on Table I's fitted
model with a server too small for every node at its best, the plan chooses only values the
recordings ran, and its objective is the optimum over those values found by enumerating every
combination of measured settings and placements here (the capacities, residences and the link
checked by hand from model.json's numbers, not by the solver's code)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.fitting.modelfile import read_unmeasured, value_errors
from perfros_bag.system.planfile import load_plan
from tests.test_fit_cli import TABLE_I, table_i_rows, table_i_system, write_csv, write_yaml

pytestmark = pytest.mark.filterwarnings("ignore")

SERVER = 230.0  # binds: every node at its best needs ~395 CPU units over 100 + SERVER


@pytest.fixture
def model(tmp_path: Path) -> Path:
    system = table_i_system()
    for c in system["computers"]:
        if c["name"] == "server":
            c["capacity"] = SERVER
    sys_path = write_yaml(tmp_path / "system.yaml", system)
    char = write_csv(tmp_path / "char.csv", table_i_rows())
    out = tmp_path / "model.json"
    res = CliRunner().invoke(app, ["fit", str(sys_path), str(char), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def _enumerate(doc: dict[str, Any]) -> float:
    """max Σ w·P over every measured setting of every node and every placement that fits."""
    measured = {n: {float(v) for v in u["measured_values"]} for n, u in doc["unmeasured"].items()}
    system = doc["system"]
    caps = {c["name"]: c["capacity"] for c in system["computers"]}
    link = system["links"][0]
    nodes = system["nodes"]
    options = []
    for n in nodes:
        settings = [s for s in n["settings"] if n["name"] not in measured or float(s["value"]) in measured[n["name"]]]
        places = n.get("residence") or list(caps)
        options.append([(s, c) for s in settings for c in places])
    best = float("-inf")
    for combo in itertools.product(*options):
        used = dict.fromkeys(caps, 0.0)
        where = {}
        for n, (s, c) in zip(nodes, combo, strict=True):
            used[c] += s["cpu"]
            where[n["name"]] = (s, c)
        if any(used[c] > caps[c] + 1e-9 for c in caps):
            continue
        load = sum(where[e["from"]][0]["bandwidth_kBps"] for e in system["edges"]
                   if where[e["from"]][1] != where[e["to"]][1])
        if load > link["bandwidth_kBps"]:
            continue
        best = max(best, sum(n["weight"] * s["performance"] for n, (s, _c) in zip(nodes, combo, strict=True)))
    return best


@pytest.mark.parametrize("method", ["exact", "bruteforce", "greedy"])
def test_measured_only_chooses_measured_values_and_exact_finds_their_optimum(
        model: Path, tmp_path: Path, method: str) -> None:
    doc = json.loads(model.read_text())
    plan_path = tmp_path / "plan.json"
    res = CliRunner().invoke(app, ["solve", str(model), "--problem", "1", "--method", method, "--measured-only",
                                   "--out", str(plan_path)])
    assert res.exit_code == 0, res.output
    plan = load_plan(plan_path)
    raw = json.loads(plan_path.read_text())["nodes"]
    for name, entry in doc["unmeasured"].items():
        assert plan.nodes[name].value in entry["measured_values"], (name, plan.nodes[name].value)
        assert raw[name]["measured"] is True and "loo_error" not in raw[name]
    for name in set(raw) - set(doc["unmeasured"]):
        assert "measured" not in raw[name]  # a node without fits says nothing
    optimum = _enumerate(doc)
    if method == "greedy":
        assert plan.objective <= optimum + 1e-6
    else:
        assert plan.objective == pytest.approx(optimum, rel=1e-6)


def test_without_the_option_a_value_between_is_marked_with_its_loo_error(model: Path, tmp_path: Path) -> None:
    plan_path = tmp_path / "plan.json"
    res = CliRunner().invoke(app, ["solve", str(model), "--problem", "1", "--method", "exact", "--out", str(plan_path)])
    assert res.exit_code == 0, res.output
    raw = json.loads(plan_path.read_text())["nodes"]
    unmeasured = read_unmeasured(model)
    between = [n for n in TABLE_I if not unmeasured[n].measured(raw[n]["value"])]
    assert between, "the curve's plan should use some value never measured"
    assert _enumerate(json.loads(model.read_text())) <= json.loads(plan_path.read_text())["objective"] + 1e-6
    for name in TABLE_I:
        n = raw[name]
        errors = value_errors(unmeasured[name], n["value"])
        assert n["measured"] is (errors is None)
        if errors is None:
            assert "loo_error" not in n
        else:
            assert n["loo_error"] == pytest.approx(errors)
    assert load_plan(plan_path).nodes[between[0]].loo_error == pytest.approx(raw[between[0]]["loo_error"])


def test_measured_only_needs_a_fitted_model_and_a_plan_with_a_bad_flag_is_refused(model: Path, tmp_path: Path) -> None:
    sys_path = write_yaml(tmp_path / "plain.yaml", table_i_system())
    res = CliRunner().invoke(app, ["solve", str(sys_path), "--measured-only"])
    assert res.exit_code == 2 and "--measured-only needs a model.json" in res.output
    plan_path = tmp_path / "plan.json"
    assert CliRunner().invoke(app, ["solve", str(model), "--out", str(plan_path)]).exit_code == 0
    doc = json.loads(plan_path.read_text())
    doc["nodes"]["tracker1"]["measured"] = "yes"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    res = CliRunner().invoke(app, ["validate", "missing.bag", str(bad)])
    assert res.exit_code == 2 and "'measured' must be true or false" in res.output and "Traceback" not in res.output
