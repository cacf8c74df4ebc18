"""``perfros-bag solve``: exit codes, pure JSON on stdout with --json, plan.json written
and checkable, one clear error line (never a traceback) on bad input and infeasibility."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.casestudy.instances import table2_instance
from perfros_bag.cli import app
from perfros_bag.solver.check import check_plan
from perfros_bag.system.planfile import load_plan
from perfros_bag.system.systemfile import load_system

ROOT = Path(__file__).resolve().parent.parent
INSTANCE1 = ROOT / "fixtures" / "casestudy" / "instance1.yaml"
runner = CliRunner()


def cli(*args: str) -> tuple[int, str, str]:
    r = runner.invoke(app, ["solve", *args])
    assert "Traceback" not in r.stderr, r.stderr
    # the only exception allowed out of a verb is its exit (an error already printed as one line)
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    return r.exit_code, r.stdout, r.stderr


def infeasible_system(tmp_path: Path) -> Path:
    data = table2_instance(1)
    data["computers"][0]["capacity"] = 10
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_solve_writes_a_checkable_plan(tmp_path: Path) -> None:
    out = tmp_path / "plan.json"
    code, stdout, _ = cli(str(INSTANCE1), "--problem", "1", "--method", "greedy", "--out", str(out))
    assert code == 0
    assert "youbot_core1" in stdout and "robot1" in stdout and "objective" in stdout
    plan = load_plan(out)
    assert plan.status == "feasible" and plan.method == "greedy"
    assert check_plan(load_system(INSTANCE1), plan) == []


@pytest.mark.parametrize("method", ["greedy", "greedy+", "bruteforce"])
def test_json_stdout_is_pure_json(tmp_path: Path, method: str) -> None:
    data = table2_instance(1)
    if method == "bruteforce":  # keep it tiny: the discrete Table I settings
        from perfros_bag.casestudy.instances import casestudy_system

        data = casestudy_system(1, 1, continuous=False)
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(data))
    code, stdout, stderr = cli(str(path), "--problem", "2", "--method", method, "--json")
    assert code == 0
    doc = json.loads(stdout)
    assert doc["format"] == "perfros-bag/plan@1" and doc["problem"] == 2 and doc["method"] == method
    assert "computers" in stderr  # the tables went to stderr


def test_model_json_input(tmp_path: Path) -> None:
    path = tmp_path / "model.json"
    path.write_text(json.dumps({"system": table2_instance(1)}))
    code, stdout, _ = cli(str(path), "--json")
    assert code == 0 and json.loads(stdout)["status"] == "feasible"


def test_infeasible_exit_2_with_reason_and_plan(tmp_path: Path) -> None:
    path = infeasible_system(tmp_path)
    out = tmp_path / "plan.json"
    code, stdout, stderr = cli(str(path), "--out", str(out))
    assert code == 2
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert lines == [f"error: {path}: infeasible: youbot_core1 needs 16 CPU on robot1 (residence) but robot1 has 10"]
    plan = json.loads(out.read_text())
    assert plan["status"] == "infeasible" and "youbot_core1" in plan["reason"]
    code, stdout, stderr = cli(str(path), "--json")
    assert code == 2 and json.loads(stdout)["status"] == "infeasible"


def test_problem2_settings_values_and_plan(tmp_path: Path) -> None:
    code, stdout, _ = cli(str(INSTANCE1), "--problem", "2", "--settings", "tracker1=15,model1=cpu:40", "--json")
    assert code == 0
    doc = json.loads(stdout)
    assert doc["nodes"]["tracker1"]["cpu"] == 120 and doc["nodes"]["model1"]["cpu"] == 40
    assert doc["nodes"]["amcl1"]["cpu"] == 66  # not given: its maximum
    p1 = tmp_path / "p1.json"
    assert cli(str(INSTANCE1), "--problem", "1", "--out", str(p1))[0] == 0
    code, stdout, _ = cli(str(INSTANCE1), "--problem", "2", "--settings", str(p1), "--json")
    assert code == 0
    p1_cpu = {n: v["cpu"] for n, v in json.loads(p1.read_text())["nodes"].items()}
    assert {n: v["cpu"] for n, v in json.loads(stdout)["nodes"].items()} == p1_cpu


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.yaml"], "missing.yaml"),
        ([str(INSTANCE1), "--problem", "3"], "--problem must be 1 or 2"),
        ([str(INSTANCE1), "--method", "magic"], "--method must be one of"),
        ([str(INSTANCE1), "--resolution", "0"], "--resolution must be a finite number > 0"),
        ([str(INSTANCE1), "--problem", "2", "--settings", "tracker1=30"],
         "value 30 is outside its parameter's range [10, 25]"),
        ([str(INSTANCE1), "--problem", "2", "--settings", "youbot_core1=3"], "no setting with value 3"),
        ([str(INSTANCE1), "--problem", "2", "--settings", "ghost=1"], "unknown node 'ghost'"),
        ([str(INSTANCE1), "--problem", "2", "--settings", "tracker1"], "expected node=value"),
        ([str(INSTANCE1), "--settings", "tracker1=10"], "--settings applies to Problem 2"),
        ([str(ROOT / "fixtures" / "casestudy" / "instance6.yaml"), "--method", "bruteforce"],
         "too large for bruteforce"),
    ],
)
def test_bad_input_one_error_line(args: list[str], message: str) -> None:
    code, stdout, stderr = cli(*args)
    assert code == 2
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], stderr


def test_bad_yaml_and_bad_system(tmp_path: Path) -> None:
    broken = tmp_path / "broken.yaml"
    broken.write_text("computers: [\n")
    code, _, stderr = cli(str(broken))
    assert code == 2 and "broken.yaml" in stderr
    nocap = tmp_path / "nocap.yaml"
    data = table2_instance(1)
    del data["computers"][1]["capacity"]  # fine for Problem 2, not for Problem 1
    nocap.write_text(yaml.safe_dump(data))
    code, _, stderr = cli(str(nocap), "--problem", "1")
    assert code == 2 and "Problem 1 needs every capacity" in stderr
    assert cli(str(nocap), "--problem", "2", "--json")[0] == 0


def test_console_script_end_to_end(tmp_path: Path) -> None:
    """The installed entry point: exit 2 and no traceback on an infeasible instance."""
    exe = Path(sys.executable).parent / "perfros-bag"
    path = infeasible_system(tmp_path)
    r = subprocess.run([str(exe), "solve", str(path), "--json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "infeasible: youbot_core1" in r.stderr
    assert json.loads(r.stdout)["status"] == "infeasible"


def test_a_fleet_past_its_time_limit_still_gets_a_checked_plan_and_a_proven_bound(tmp_path: Path) -> None:
    """A time limit far shorter than the set-up: exit 0, the best plan at hand (status
    feasible unless proven), its bound in plan.json between the objective and Σ w·max P."""
    from perfros_bag.casestudy.instances import fleet_instance
    from perfros_bag.solver import fixed_choices
    from perfros_bag.solver.instance import trivial_bound

    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(fleet_instance(200, 20, seed=0)))
    out = tmp_path / "plan.json"
    code, stdout, _ = cli(str(path), "--method", "exact", "--time-limit", "0.001", "--json", "-o", str(out))
    assert code == 0
    doc = json.loads(stdout)
    assert doc == json.loads(out.read_text())
    system = load_system(path)
    plan = load_plan(out)
    assert check_plan(system, plan) == []
    assert plan.status in ("feasible", "optimal") and plan.objective is not None and plan.bound is not None
    ceiling = trivial_bound(system, fixed_choices(system, 1))
    assert plan.objective - 1e-9 <= plan.bound <= ceiling + 1e-9
    assert (plan.status == "optimal") == (plan.bound - plan.objective <= 1e-6 * plan.objective)


def test_piped_tables_keep_every_name_whole(tmp_path: Path) -> None:
    """Issue 33, item 13: not on a terminal (a pipe, a file, CI's log) rich drew tables at 80
    columns and cut names to 'navigat…'; now every node and computer name is there in full,
    on one line of the table, and nothing is cut with an ellipsis."""
    data = table2_instance(2)
    renamed = {n["name"]: f"navigation_stack_{n['name']}_with_a_long_descriptive_name" for n in data["nodes"]}
    for n in data["nodes"]:
        n["name"] = renamed[n["name"]]
    for e in data.get("edges", []):
        e["from"], e["to"] = renamed[e["from"]], renamed[e["to"]]
    computers = {c["name"]: f"{c['name']}-onboard-computer-in-the-rear-bay" for c in data["computers"]}
    for c in data["computers"]:
        c["name"] = computers[c["name"]]
    for link in data.get("links", []):
        link["between"] = [computers[x] for x in link["between"]]
    for n in data["nodes"]:
        if n.get("residence"):
            n["residence"] = [computers[x] for x in n["residence"]]
        if n.get("coresidence"):
            n["coresidence"] = [renamed[x] for x in n["coresidence"]]
    path = tmp_path / "long.yaml"
    path.write_text(yaml.safe_dump(data))
    code, stdout, stderr = cli(str(path), "--method", "greedy")
    assert code == 0, stderr
    assert "…" not in stdout
    rows = stdout.splitlines()
    for name in [*renamed.values(), *computers.values()]:
        assert any(name in row for row in rows), name


def test_process_seconds_counts_from_the_process_start() -> None:
    """The interpreter's own start (here a 1 s sleep before the import) counts."""
    code = "import time; time.sleep(1.0); from perfros_bag.cli.solve import process_seconds; print(process_seconds())"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert 1.0 <= float(done.stdout) < 30, done.stderr


def test_time_limit_is_the_whole_process_the_solver_gets_the_rest(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 33, item 11: with --time-limit 60 and 7 s already spent by the process
    (start-up, reading), the solver is handed 60 - 7 - the wind-down: 1 s + 1 % of 60 s +
    5 ms per row of the plan's tables (instance 1: its nodes, computers and links)."""
    import perfros_bag.cli.solve as solve_cli
    import perfros_bag.solver as solver

    handed: list[float | None] = []
    real = solver.solve

    def spy(*args: object, **kwargs: object) -> object:
        handed.append(kwargs["time_limit"])  # type: ignore[arg-type]
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(solver, "solve", spy)
    monkeypatch.setattr("perfros_bag.cli._app.WHOLE_PROCESS", True)  # as the console script sets it
    monkeypatch.setattr(solve_cli, "process_seconds", lambda: 7.0)
    code, _, stderr = cli(str(INSTANCE1), "--method", "exact", "--time-limit", "60")
    assert code == 0, stderr
    data = yaml.safe_load(INSTANCE1.read_text())
    rows = len(data["nodes"]) + len(data["computers"]) + len(data["links"])
    assert handed == [pytest.approx(60 - 7 - (1 + 0.01 * 60 + 0.005 * rows))]
    monkeypatch.setattr(solve_cli, "process_seconds", lambda: 59.5)  # nothing left: the floor, not a negative
    handed.clear()
    cli(str(INSTANCE1), "--method", "exact", "--time-limit", "60")
    assert handed == [0.01]
    # called from another program (this test's process started long ago): from the verb's start
    monkeypatch.setattr("perfros_bag.cli._app.WHOLE_PROCESS", False)
    handed.clear()
    cli(str(INSTANCE1), "--method", "exact", "--time-limit", "60")
    (given,) = handed
    assert given is not None and 60 - (1 + 0.6 + 0.005 * rows) - 5 < given <= 60 - (1 + 0.6 + 0.005 * rows)


def test_a_fleet_plan_shows_its_first_node_rows_and_says_how_many_more() -> None:
    """Above NODE_ROWS nodes the table stops (rendering a fleet's 1,180 rows cost seconds):
    the first rows are the plan's own nodes in order, then one line counts the rest."""
    import io

    from rich.console import Console

    from perfros_bag.casestudy.instances import fleet_instance
    from perfros_bag.cli.solve import NODE_ROWS, print_plan
    from perfros_bag.solver import solve
    from perfros_bag.system.systemfile import parse_system

    system = parse_system(fleet_instance(NODE_ROWS + 37, 40, seed=3), "fleet.yaml")
    plan = solve(system, 1, "greedy")
    assert len(plan.nodes) > NODE_ROWS
    buf = io.StringIO()
    print_plan(Console(file=buf, width=240, color_system=None), plan)
    text = buf.getvalue()
    names = list(plan.nodes)
    shown = [n for n in names if f"│ {n} " in text]
    assert shown == names[:NODE_ROWS]
    assert "... 37 more (plan.json has every node)" in text
    small = solve(parse_system(table2_instance(1), "t2.yaml"), 1, "greedy")
    buf = io.StringIO()
    print_plan(Console(file=buf, width=240, color_system=None), small)
    assert all(f"│ {n} " in buf.getvalue() for n in small.nodes) and "more (plan.json" not in buf.getvalue()
