"""No verb removes or overwrites anything of an earlier run until every input is read and
checked (issue 33, item 1; docs/architecture.md, Conventions).

Every verb that writes into a folder (or a file in it) runs against a folder holding an
earlier run's results and one bad input; it must end in one ``error:`` line with exit 2,
and every byte of the folder must be as it was (no file removed, changed or added).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from perfros_bag.cli import app

ROOT = Path(__file__).resolve().parent.parent
APP = ROOT / "fixtures" / "app" / "app.launch"
SPACE = APP.with_name("space.yaml")
RECORDINGS = ROOT / "fixtures" / "recordings"
INSTANCE = ROOT / "fixtures" / "casestudy" / "instance1.yaml"

#: what an earlier deploy / sweep / tune / case-study run / report leaves in its folder
EARLIER = ("run.bag", "run.cpu.csv", "run.host.cpu.csv", "validation.json", "deploy.json", "manifest.yaml",
           "graph.yaml", "run.json", "tune.json", "space.yaml", "index.html", "plan.json", "model.json",
           "characterisation.csv", "system.yaml", "app.launch", "frontier.json", "sweep/manifest.yaml",
           "sweep/run-1.bag", "round-1/plan.json")


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def earlier(tmp_path: Path) -> Path:
    """A folder of an earlier run's results: every file distinct bytes."""
    folder = tmp_path / "results"
    for i, name in enumerate(EARLIER):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(f"earlier result {i}: {name}\n".encode() + bytes(range(256)))
    return folder


def make_inputs(tmp_path: Path) -> None:
    """The good and bad inputs the cases name."""
    plan = tmp_path / "plan.json"  # a feasible plan of the app fixture's camera on one computer
    plan.write_text(json.dumps({
        "format": "perfros-bag/plan@1", "problem": 1, "method": "greedy", "status": "feasible", "objective": 1.0,
        "computers": {"here": {"kind": "robot", "capacity": 100, "cpu": 10}}, "links": [],
        "nodes": {"camera": {"computer": "here", "value": 5, "cpu": 10, "performance": 1, "weight": 1}}}))
    corrupt = tmp_path / "corrupt.yaml"
    corrupt.write_text("computers: [\n  - {name: here\n")
    other = tmp_path / "other.yaml"  # a valid system without the plan's computer "here"
    other.write_text(INSTANCE.read_text())
    bad_json = tmp_path / "bad.json"
    bad_json.write_text('{"format": "perfros-bag/plan@1", ')
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("not,a,characterisation\n1,2\n")
    # a feasible plan of the case study's instance, by the tool
    from perfros_bag.solver import solve
    from perfros_bag.system.planfile import save_plan
    from perfros_bag.system.systemfile import load_system

    save_plan(solve(load_system(INSTANCE), 1, "greedy"), tmp_path / "cs.json")


def cases(tmp_path: Path, d: Path) -> dict[str, list[str]]:
    plan = str(tmp_path / "plan.json")
    bad = {k: str(tmp_path / v) for k, v in {"missing": "missing.yaml", "corrupt": "corrupt.yaml",
                                             "other": "other.yaml", "json": "bad.json", "csv": "bad.csv"}.items()}
    app_, space, system = str(APP), str(SPACE), str(RECORDINGS / "system.yaml")
    return {
        # the defect: deploy removed the earlier run.bag, validation.json, ... before reading --system
        "deploy --system missing": ["deploy", plan, app_, "--space", space, "--out", str(d),
                                    "--system", bad["missing"]],
        "deploy --system corrupt": ["deploy", plan, app_, "--space", space, "--out", str(d),
                                    "--system", bad["corrupt"]],
        "deploy --system mismatched": ["deploy", plan, app_, "--space", space, "--out", str(d),
                                       "--system", bad["other"]],
        "deploy bad space": ["deploy", plan, app_, "--space", bad["corrupt"], "--out", str(d)],
        "casestudy run bad --set": ["casestudy", "run", "--system", str(INSTANCE), "--plan", str(tmp_path / "cs.json"),
                                    "--out", str(d), "--set", "no_such_node=1"],
        "sweep bad space": ["sweep", app_, "--space", bad["corrupt"], "--out", str(d)],
        "tune bad system": ["tune", app_, "--space", space, "--system", bad["corrupt"], "--out", str(d)],
        "report bad plan": ["report", "--out", str(d), "--plan", bad["json"]],
        "fit bad characterisation": ["fit", system, bad["csv"], "--out", str(d / "model.json"), "--plots", str(d)],
        "solve bad system": ["solve", bad["corrupt"], "--out", str(d / "plan.json")],
        "export bad plan": ["export", bad["json"], "--format", "roslaunch", "--out", str(d / "app.launch")],
        "characterise bad manifest": ["characterise", str(RECORDINGS), "--manifest", bad["corrupt"],
                                      "--out", str(d / "characterisation.csv")],
        "validate bad plan": ["validate", str(RECORDINGS / "tracker_f10.bag"), bad["json"],
                              "--out", str(d / "validation.json")],
        "init bad folder": ["init", str(d), "--out", str(d / "system.yaml")],
    }


CASE_NAMES = list(cases(Path("/x"), Path("/y")))


@pytest.mark.parametrize("case", CASE_NAMES)
def test_a_bad_input_leaves_every_byte_of_an_earlier_run(case: str, tmp_path: Path, earlier: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    make_inputs(tmp_path)
    before = snapshot(earlier)
    result = CliRunner().invoke(app, cases(tmp_path, earlier)[case])
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert snapshot(earlier) == before, case
