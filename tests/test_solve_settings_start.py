"""Problem 2 settings given as parameter values on a fitted model (they must map into the
curve's CPU range), what the fitted range means against ``parameter->cpu``, and the MIP
start the dispatcher gives the exact solver on big instances."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

import perfros_bag.solver.dispatch as solve_mod
from perfros_bag.casestudy.instances import table2_instance
from perfros_bag.cli import app
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.fitting.modelfile import ModelDocument, read_model
from perfros_bag.solver import fixed_choices, settings_from_values, solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.plan import Assignment, Plan
from perfros_bag.system.planfile import load_plan
from perfros_bag.system.systemfile import load_system, parse_system
from perfros_bag.system.types import Choice, System
from tests.test_fit_cli import table_i_rows, table_i_system, write_csv, write_yaml


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, System, ModelDocument]:
    """model.json built by `perfros-bag fit` from Table I numbers (1 % noise, 3 recordings)."""
    d = tmp_path_factory.mktemp("fitted")
    system_path = write_yaml(d / "system.yaml", table_i_system())
    csv_path = write_csv(d / "char.csv", table_i_rows())
    model = d / "model.json"
    result = CliRunner().invoke(app, ["fit", str(system_path), str(csv_path), "--out", str(model)])
    assert result.exit_code == 0, result.stderr
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        system, doc = load_system(model), read_model(model)
    return model, system, doc


def test_every_measured_setting_value_maps_into_the_curve_range(fitted: tuple[Path, System, ModelDocument]) -> None:
    """The reported bug: a setting's measured CPU lies just outside the fitted range, and
    fixed_choices refused it. Every measured value must now give a usable Problem 2 choice:
    the measured CPU clamped to the range, silently within one CPU unit, else with a warning."""
    _, system, _ = fitted
    curved = [n for n in system.nodes if n.curve is not None]
    assert len(curved) == 4
    outside = 0
    for node in curved:
        lo, hi = node.curve.domain  # type: ignore[union-attr]
        for s in node.settings:
            assert s.value is not None
            outside += not lo <= s.cpu <= hi
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                cpu = settings_from_values(system, {node.name: s.value})[node.name]
            expected = min(max(s.cpu, lo), hi)
            assert cpu == pytest.approx(expected)
            warned = [w for w in caught if issubclass(w.category, PerfrosWarning)]
            assert bool(warned) == (abs(expected - s.cpu) > 1 + 1e-6), (node.name, s.value, s.cpu, (lo, hi))
            if warned:
                assert node.name in str(warned[0].message) and f"{s.value:g}" in str(warned[0].message)
            (choice,) = fixed_choices(system, 2, {node.name: cpu})[node.name]
            assert lo - 1e-9 <= choice.cpu <= hi + 1e-9
            assert choice.performance == pytest.approx(node.curve(choice.cpu))  # type: ignore[misc]
    assert outside >= 2, "the fixture no longer reproduces a setting outside its fitted range"


def test_values_between_settings_and_unusable_values(fitted: tuple[Path, System, ModelDocument]) -> None:
    _, system, _ = fitted
    nav = system.node["navigation1"]
    rel = nav.relations["parameter->cpu"]
    lo, hi = nav.curve.domain  # type: ignore[union-attr]
    cpu = settings_from_values(system, {"navigation1": 7.0})["navigation1"]
    assert cpu == pytest.approx(min(max(rel(7.0), lo), hi))
    with pytest.raises(InputError, match="outside its parameter's range"):
        settings_from_values(system, {"navigation1": 21.0})
    with pytest.raises(InputError, match="not a finite number"):
        settings_from_values(system, {"navigation1": math.nan})


def test_cli_problem2_with_values_on_a_fitted_model(fitted: tuple[Path, System, ModelDocument], tmp_path: Path) -> None:
    model, system, _ = fitted
    plan_path = tmp_path / "plan.json"
    args = ["solve", str(model), "--problem", "2", "--method", "exact", "--out", str(plan_path),
            "--settings", "tracker1=10,model1=4,amcl1=3000,navigation1=20"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.stderr
    assert "Traceback" not in result.stderr
    plan = load_plan(plan_path)
    assert plan.status == "optimal"
    assert check_plan(system, plan) == []
    for name, value in (("tracker1", 10.0), ("model1", 4.0), ("amcl1", 3000.0), ("navigation1", 20.0)):
        lo, hi = system.node[name].curve.domain  # type: ignore[union-attr]
        measured = next(s.cpu for s in system.node[name].settings if s.value == value)
        assert plan.nodes[name].cpu == pytest.approx(min(max(measured, lo), hi))


def test_fitted_range_against_parameter_to_cpu(fitted: tuple[Path, System, ModelDocument]) -> None:
    """What docs/formats.md says about a fitted node's ``curve`` domain and its
    ``parameter->cpu`` relation: the domain is the measured CPU range of the rated
    settings, narrowed where the performance fit leaves [0, max rated], ends rounded
    inwards to whole units; parameter->cpu is a separate fit, so at the measured parameter
    ends it gives the fit's CPU, which differs from the measured one by its residual."""
    _, system, doc = fitted
    for node in system.nodes:
        if node.curve is None:
            continue
        lo, hi = node.curve.domain
        cpus = [s.cpu for s in node.settings]
        c2p = doc.fits[node.name]["cpu->performance"]
        assert c2p.domain == pytest.approx((min(cpus), max(cpus)))
        # the range: inside the measured one, each end within a unit of it unless narrowed
        assert min(cpus) <= lo <= hi <= max(cpus)
        assert lo == math.ceil(lo) and hi == math.floor(hi)
        top = max(s.performance for s in node.settings)
        assert lo - min(cpus) < 1 or node.curve(lo) == pytest.approx(0.0, abs=1e-6) or node.curve(lo - 1) < 0
        assert max(cpus) - hi < 1 or node.curve(hi + 1) > top - 1e-9
        # parameter->cpu at the measured ends: the fit's value, within its residual of the
        # measured CPU (the points are in the model's fits)
        rel = node.relations["parameter->cpu"]
        pts = dict(doc.fits[node.name]["parameter->cpu"].points)
        for v in rel.domain:
            assert rel(v) == pytest.approx(pts[v], rel=0.2)


# --- the exact solver's MIP start on big instances --------------------------------------

def _system(instance: int) -> System:
    data = table2_instance(instance)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_system(data, "test.yaml")


def _spy(monkeypatch: pytest.MonkeyPatch) -> tuple[list[Assignment | None], list[float | None]]:
    import perfros_bag.solver.exact as exact_mod
    import perfros_bag.solver.local as local_mod

    starts: list[Assignment | None] = []
    budgets: list[float | None] = []
    real_exact, real_gp = exact_mod.solve_exact, local_mod.solve_greedy_plus

    def exact_spy(system: System, problem: int, choices: dict[str, list[Choice]], **kw: Any) -> Plan:
        starts.append(kw.get("start"))
        return real_exact(system, problem, choices, **kw)

    def gp_spy(system: System, problem: int, choices: dict[str, list[Choice]], **kw: Any) -> Plan:
        budgets.append(kw.get("time_budget"))
        return real_gp(system, problem, choices, **kw)

    monkeypatch.setattr(exact_mod, "solve_exact", exact_spy)
    monkeypatch.setattr(local_mod, "solve_greedy_plus", gp_spy)
    return starts, budgets


def test_small_instances_get_no_start(monkeypatch: pytest.MonkeyPatch) -> None:
    starts, budgets = _spy(monkeypatch)
    system = _system(6)
    assert solve_mod.exact_columns(system, fixed_choices(system, 1)) <= solve_mod.START_COLUMNS
    plan = solve(system, 1, "exact")
    assert starts == [None] and budgets == []
    assert plan.status == "optimal" and check_plan(system, plan) == []


def test_big_instances_get_greedy_plus_as_start(monkeypatch: pytest.MonkeyPatch) -> None:
    system = _system(5)
    reference = solve(system, 1, "exact")
    starts, budgets = _spy(monkeypatch)
    monkeypatch.setattr(solve_mod, "START_COLUMNS", 0)
    plan = solve(system, 1, "exact", time_limit=40.0)
    # a quarter of what is left of the limit when greedy+ starts (choices, pruning came first)
    assert len(budgets) == 1 and budgets[0] is not None
    assert 0.0 < solve_mod.START_SHARE * 40.0 - budgets[0] <= solve_mod.START_SHARE * plan.solve_s
    assert len(starts) == 1 and starts[0] is not None
    start = starts[0]
    assert set(start.placement) == {n.name for n in system.nodes}
    assert plan.status == "optimal" and check_plan(system, plan) == []
    assert plan.objective == pytest.approx(reference.objective, abs=1e-7)
    # Problem 2 proves fast without one (docs/solvers.md): no start
    starts.clear()
    p2 = solve(system, 2, "exact")
    assert starts == [None] and check_plan(system, p2) == []


def test_cli_exact_with_start_writes_a_checkable_plan(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import yaml

    monkeypatch.setattr(solve_mod, "START_COLUMNS", 0)
    path = tmp_path / "inst4.yaml"
    path.write_text(yaml.safe_dump(table2_instance(4)))
    out = tmp_path / "plan.json"
    result = CliRunner().invoke(app, ["solve", str(path), "--problem", "1", "--method", "exact",
                                      "--time-limit", "20", "--json", "--out", str(out)])
    assert result.exit_code == 0, result.stderr
    doc = json.loads(result.stdout)
    assert doc["status"] == "optimal"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from perfros_bag.system.systemfile import load_system

        system = load_system(path)
    assert check_plan(system, load_plan(out)) == []
