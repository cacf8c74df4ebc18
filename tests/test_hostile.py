"""Hostile and careless inputs (issue 16): every verb refuses, in one line with exit 2,
another of the tool's files in the wrong place, plans/models/tables with non-finite or
out-of-range numbers and deep nesting; inputs that ran without end are refused in seconds
(run as subprocesses: the timeout is a hang detector, not a speed test); every ``--json``
is strict JSON with nothing else on stdout."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.cli import app

ROOT = Path(__file__).resolve().parent.parent
RECORDINGS = ROOT / "fixtures" / "recordings"
BAG = RECORDINGS / "tracker_f10.bag"
HANG_LIMIT_S = 60  # a hang detector: every case ends in a few seconds


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """The CLI as a user runs it: a fresh interpreter (this tree first on the path)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "perfros_bag", *args], capture_output=True, text=True,
                          timeout=HANG_LIMIT_S, env=env, cwd=cwd)


def strict_json(text: str) -> Any:
    def refuse(name: str) -> Any:
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def one_error_line(stderr: str) -> str:
    """The only line of stderr (warnings aside), an ``error:`` line."""
    lines = [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ") and "Traceback" not in stderr, stderr
    return lines[0]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One of each of the tool's files, made by the tool from the bundled recordings."""
    d = tmp_path_factory.mktemp("own")
    out = {"system": d / "system.yaml", "csv": d / "characterisation.csv", "model": d / "model.json",
           "plan": d / "plan.json", "validation": d / "validation.json", "info": d / "info.json",
           "manifest": d / "manifest.yaml"}
    out["system"].write_text((RECORDINGS / "system.yaml").read_text())
    out["manifest"].write_text((RECORDINGS / "manifest.yaml").read_text())
    steps = [("characterise", str(RECORDINGS), "--out", str(out["csv"])),
             ("fit", str(out["system"]), str(out["csv"]), "--out", str(out["model"])),
             ("solve", str(out["model"]), "--out", str(out["plan"]))]
    for step in steps:
        r = run_cli(*step)
        assert r.returncode == 0, r.stderr
    r = run_cli("validate", str(BAG), str(out["plan"]), "--out", str(out["validation"]))
    assert r.returncode in (0, 1), r.stderr
    r = run_cli("info", str(BAG), "--json")
    assert r.returncode == 0, r.stderr
    out["info"].write_text(r.stdout)
    return out


# --------------------------------------------------------------------------- --json purity


@pytest.mark.parametrize("verb", ["solve-greedy", "solve-greedy+", "solve-exact", "solve-p2-exact", "fit",
                                  "validate", "info", "characterise"])
def test_every_json_output_is_strict_json_alone_on_stdout(files: dict[str, Path], tmp_path: Path,
                                                          verb: str) -> None:
    args = {
        "solve-greedy": ["solve", str(files["model"]), "--json"],
        "solve-greedy+": ["solve", str(files["model"]), "--method", "greedy+", "--json"],
        "solve-exact": ["solve", str(files["model"]), "--method", "exact", "--json"],
        "solve-p2-exact": ["solve", str(files["system"]), "-p", "2", "--method", "exact", "--json"],
        "fit": ["fit", str(files["system"]), str(files["csv"]), "--out", str(tmp_path / "m.json"), "--json"],
        "validate": ["validate", str(BAG), str(files["plan"]), "--json"],
        "info": ["info", str(BAG), "--json"],
        "characterise": ["characterise", str(RECORDINGS), "--json"],
    }[verb]
    r = run_cli(*args)
    assert r.returncode in (0, 1), r.stderr
    strict_json(r.stdout)  # the whole of stdout: no banner, no table, no NaN


# --------------------------------------------------------------------------- wrong kind of file


def _wrong_kinds() -> list[tuple[str, list[str], str]]:
    """(case, args with {kind} placeholders, what the message must say was expected)."""
    cases: list[tuple[str, list[str], str]] = []
    for kind in ("plan", "validation", "info", "csv", "manifest"):
        cases.append((f"solve<-{kind}", ["solve", f"{{{kind}}}"], "a system.yaml or model.json"))
    for kind in ("model", "system", "validation", "info", "csv"):
        cases.append((f"validate<-{kind}", ["validate", str(BAG), f"{{{kind}}}"], ""))
        cases.append((f"export<-{kind}", ["export", f"{{{kind}}}", "--format", "roslaunch", "--out", "{out}"], ""))
    for kind in ("model", "validation", "csv"):
        cases.append((f"report-plan<-{kind}", ["report", "--plan", f"{{{kind}}}", "--out", "{out}"], ""))
    for kind in ("plan", "validation"):
        cases.append((f"report-model<-{kind}", ["report", "--model", f"{{{kind}}}", "--out", "{out}"], ""))
    for kind in ("plan", "model", "info"):
        cases.append((f"report-validation<-{kind}", ["report", "--validation", f"{{{kind}}}", "--out", "{out}"],
                      "expected a perfros-bag validation"))
    for kind in ("plan", "model", "system"):
        cases.append((f"report-characterisation<-{kind}", ["report", "--characterisation", f"{{{kind}}}",
                                                           "--out", "{out}"], "expected a characterisation.csv"))
    for kind in ("plan", "model", "system", "manifest"):
        cases.append((f"fit-csv<-{kind}", ["fit", "{system}", f"{{{kind}}}", "--out", "{out}"],
                      "a characterisation.csv"))
    for kind in ("plan", "validation", "csv", "manifest"):
        cases.append((f"fit-system<-{kind}", ["fit", f"{{{kind}}}", "{csv}", "--out", "{out}"],
                      "a system.yaml or model.json"))
    for kind in ("plan", "model", "csv", "system", "manifest"):
        cases.append((f"characterise<-{kind}", ["characterise", f"{{{kind}}}", "--out", "{out}"],
                      "a folder of recordings or one recording"))
    cases.append(("solve-settings<-model", ["solve", "{system}", "-p", "2", "--settings", "{model}"], ""))
    cases.append(("characterise-manifest<-plan", ["characterise", str(RECORDINGS), "--manifest", "{plan}",
                                                  "--out", "{out}"], "a manifest"))
    return cases


@pytest.mark.parametrize(("case", "args", "expected"), _wrong_kinds(), ids=[c[0] for c in _wrong_kinds()])
def test_a_file_of_another_kind_says_what_it_is(files: dict[str, Path], tmp_path: Path, case: str,
                                                args: list[str], expected: str) -> None:
    out = tmp_path / "out"
    given = case.split("<-")[1]
    argv = [a.format(out=out, **{k: str(v) for k, v in files.items()}) for a in args]
    r = CliRunner().invoke(app, argv)
    assert r.exit_code == 2, (case, r.output)
    line = one_error_line(r.stderr)
    what = {"plan": "plan", "model": "model", "system": "system description", "validation": "validation",
            "info": "recording summary", "csv": "characterisation table", "manifest": "manifest"}[given]
    assert "this is a" in line and what in line, line
    assert expected in line, line
    assert not out.exists()


# --------------------------------------------------------------------------- non-finite, out of range


def _plan_mutations() -> list[tuple[str, Callable[[dict[str, Any]], None], str]]:
    def node(d: dict[str, Any]) -> dict[str, Any]:
        return d["nodes"][next(iter(d["nodes"]))]  # type: ignore[no-any-return]

    def on_mars(d: dict[str, Any]) -> None:
        node(d)["computer"] = "mars"

    def over_capacity(d: dict[str, Any]) -> None:
        n = node(d)
        n["cpu"] = d["computers"][n["computer"]]["capacity"] * 2

    return [
        ("objective NaN", lambda d: d.update(objective=float("nan")), "'objective' must be a finite number"),
        ("cpu 1e308", lambda d: node(d).update(cpu=1e308), "'cpu' must be at most"),
        ("cpu -1", lambda d: node(d).update(cpu=-1), "'cpu' must be >= 0"),
        ("cpu > capacity", over_capacity, "exceeds the capacity"),
        ("weight -0.5", lambda d: node(d).update(weight=-0.5), "'weight' must be > 0"),
        ("weight 0", lambda d: node(d).update(weight=0), "'weight' must be > 0"),
        ("performance inf", lambda d: node(d).update(performance=float("inf")), "'performance' must be a finite"),
        ("value -inf", lambda d: node(d).update(value=float("-inf")), "'value' must be a finite"),
        ("value huge int", lambda d: node(d).update(value=10 ** 400), "'value' must be a finite"),
        ("frequency -1", lambda d: node(d)["topics"][next(iter(node(d)["topics"]))].update(frequency_hz=-1),
         "'frequency_hz' must be >= 0"),
        ("capacity NaN", lambda d: d["computers"]["server"].update(capacity=float("nan")), "'capacity' must be"),
        ("no computers", lambda d: d.update(computers={}), "the plan has no computers"),
        ("node on unknown computer", on_mars, "not among the plan's computers"),
        ("format says model", lambda d: d.update(format="perfros-bag/model@1"), "this is a perfros-bag model"),
    ]


@pytest.mark.parametrize(("verb", "label", "mutate", "problem"),
                         [(verb, *m) for verb in ("validate", "export", "report") for m in _plan_mutations()],
                         ids=[f"{verb}-{m[0]}" for verb in ("validate", "export", "report") for m in _plan_mutations()])
def test_plans_with_bad_numbers_are_refused(files: dict[str, Path], tmp_path: Path, verb: str, label: str,
                                            mutate: Callable[[dict[str, Any]], None], problem: str) -> None:
    data = json.loads(files["plan"].read_text())
    mutate(data)
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))  # Python writes NaN/Infinity as the bare words a hostile file holds
    out = tmp_path / "out"
    argv = {"validate": ["validate", str(BAG), str(path), "--out", str(out)],
            "export": ["export", str(path), "--format", "roslaunch", "--out", str(out)],
            "report": ["report", "--plan", str(path), "--out", str(out)]}[verb]
    r = CliRunner().invoke(app, argv)
    assert r.exit_code == 2, (label, r.output)
    line = one_error_line(r.stderr)
    assert line.startswith(f"error: {path}: ") and problem in line, line
    assert not out.exists()


def test_a_plan_for_another_system_is_refused(files: dict[str, Path], tmp_path: Path) -> None:
    data = json.loads(files["plan"].read_text())
    data["computers"]["robot9"] = {"kind": "robot", "capacity": 100, "cpu": 0}
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))
    for argv in (["validate", str(BAG), str(path), "--system", str(files["system"])],
                 ["export", str(path), "--format", "roslaunch", "--out", str(tmp_path / "x"),
                  "--system", str(files["system"])]):
        r = CliRunner().invoke(app, argv)
        assert r.exit_code == 2, r.output
        assert "'robot9' are not in the system" in one_error_line(r.stderr)


def _model_mutations() -> list[tuple[str, Callable[[dict[str, Any]], None], str]]:
    def fit(d: dict[str, Any]) -> dict[str, Any]:
        return d["fits"]["tracker1"]["cpu->performance"]  # type: ignore[no-any-return]

    return [
        ("coef NaN", lambda d: fit(d)["coef"].__setitem__(0, float("nan")), "coef[0]: must be a finite number"),
        ("domain inf", lambda d: fit(d)["domain"].__setitem__(1, float("inf")), "domain[1]: must be a finite"),
        ("point 1e308", lambda d: fit(d)["points"][0].__setitem__(1, 1e308), "points[0][1]: must be at most"),
        ("loo -1", lambda d: fit(d).update(loo_rmse=-1.0), "loo_rmse: must be >= 0"),
        ("std NaN", lambda d: d["measured"]["tracker1"][0]["cpu"].update(std=float("nan")), "cpu.std"),
        ("recordings -3", lambda d: d["measured"]["tracker1"][0].update(recordings=-3), "recordings"),
    ]


@pytest.mark.parametrize(("label", "mutate", "problem"), _model_mutations(), ids=[m[0] for m in _model_mutations()])
def test_models_with_bad_numbers_are_refused(files: dict[str, Path], tmp_path: Path, label: str,
                                             mutate: Callable[[dict[str, Any]], None], problem: str) -> None:
    data = json.loads(files["model"].read_text())
    mutate(data)
    path = tmp_path / "model.json"
    path.write_text(json.dumps(data))
    r = CliRunner().invoke(app, ["report", "--model", str(path), "--out", str(tmp_path / "out")])
    assert r.exit_code == 2, (label, r.output)
    line = one_error_line(r.stderr)
    assert line.startswith(f"error: {path}: ") and problem in line, line


def _with_cell(source: Path, target: Path, line: int, column: str, text: str) -> None:
    rows = list(csv.reader(io.StringIO(source.read_text())))
    rows[line - 1][rows[0].index(column)] = text
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    target.write_text(buf.getvalue())


@pytest.mark.parametrize(("column", "text", "problem"), [
    ("cpu_units_mean", "nan", "must be a finite number"), ("cpu_units_mean", "inf", "must be a finite number"),
    ("frequency_hz", "-1", "must be >= 0"), ("bandwidth_kBps", "1e13", "must be at most"),
    ("messages", "1.5", "not a whole number"), ("value", "1e400", "must be a finite number"),
    ("value", "-1e300", "must be at most"), ("duration_s", "ten", "is not a number"),
])
def test_characterisation_cells_out_of_range_are_refused(files: dict[str, Path], tmp_path: Path, column: str,
                                                          text: str, problem: str) -> None:
    path = tmp_path / "c.csv"
    _with_cell(files["csv"], path, 3, column, text)
    r = CliRunner().invoke(app, ["fit", str(files["system"]), str(path), "--out", str(tmp_path / "m.json")])
    assert r.exit_code == 2, r.output
    line = one_error_line(r.stderr)
    assert f"{path}: line 3: column {column}: " in line and problem in line, line
    assert not (tmp_path / "m.json").exists()


# --------------------------------------------------------------------------- former hangs


def _deep(path: Path) -> Path:
    path.write_text("[" * 100_000)
    return path


def _linear_wide_model(files: dict[str, Path], path: Path) -> Path:
    """The model with tracker1's curve made linear over [1, 1e12] (its values stay small)."""
    data = json.loads(files["model"].read_text())
    for n in data["system"]["nodes"]:
        if n["name"] == "tracker1":
            n["curve"] = {"form": "linear", "coef": [1e-10, 1.0], "domain": [1, 1e12], "scale": 1.0}
            n.pop("relations", None)
    path.write_text(json.dumps(data))
    return path


def _power_system(files: dict[str, Path], path: Path, coef: list[float], cpu: list[float]) -> Path:
    data = yaml.safe_load(files["system"].read_text())
    data["nodes"].append({"name": "hot", "weight": 0.1, "curve": {"form": "power", "coef": coef, "cpu": cpu}})
    path.write_text(yaml.safe_dump(data))
    return path


HANGS: list[tuple[str, Callable[[dict[str, Path], Path], list[str]], str]] = [
    ("fit cpu 1e308", lambda f, d: (_with_cell(f["csv"], d / "c.csv", 3, "cpu_units_mean", "1e308"),
                                    ["fit", str(f["system"]), str(d / "c.csv"), "--out", str(d / "m.json")])[1],
     "column cpu_units_mean"),
    ("fit value 1e308", lambda f, d: (_with_cell(f["csv"], d / "c.csv", 3, "value", "1e308"),
                                      ["fit", str(f["system"]), str(d / "c.csv"), "--out", str(d / "m.json")])[1],
     "column value"),
    ("solve greedy+ domain 1e12", lambda f, d: ["solve", str(_linear_wide_model(f, d / "m.json")), "-m", "greedy+"],
     "more than the 100,000"),
    ("solve exact domain 1e12", lambda f, d: ["solve", str(_linear_wide_model(f, d / "m.json")), "-m", "exact"],
     "more than the 100,000"),
    ("solve resolution 1e-9", lambda f, d: ["solve", str(f["model"]), "--resolution", "1e-9"],
     "resolution 1e-09 gives"),
    ("solve -p 2 resolution 1e-9", lambda f, d: ["solve", str(f["model"]), "-p", "2", "--settings", "tracker1=15",
                                                 "--resolution", "1e-9"], "resolution 1e-09 gives"),
    ("greedy power 1e300", lambda f, d: ["solve", str(_power_system(f, d / "s.yaml", [1e300, 50], [1, 10]))],
     "curve.coef[0]: must be at most"),
    ("greedy+ power 1e300", lambda f, d: ["solve", str(_power_system(f, d / "s.yaml", [1e300, 50], [1, 10])),
                                          "-m", "greedy+"], "curve.coef[0]: must be at most"),
    ("greedy power overflows", lambda f, d: ["solve", str(_power_system(f, d / "s.yaml", [1e10, 200], [100, 1e4]))],
     "curve: gives inf at 10000"),
    ("greedy+ power overflows", lambda f, d: ["solve", str(_power_system(f, d / "s.yaml", [1e10, 200], [100, 1e4])),
                                              "-m", "greedy+"], "curve: gives inf at 10000"),
    ("validate deep", lambda f, d: ["validate", str(BAG), str(_deep(d / "p.json"))], "nested too deeply"),
    ("export deep", lambda f, d: ["export", str(_deep(d / "p.json")), "--format", "roslaunch", "--out",
                                  str(d / "x")], "nested too deeply"),
    ("report deep", lambda f, d: ["report", "--plan", str(_deep(d / "p.json")), "--out", str(d / "r")],
     "nested too deeply"),
    ("solve --settings deep", lambda f, d: ["solve", str(f["system"]), "-p", "2", "--settings",
                                            str(_deep(d / "p.json"))], "nested too deeply"),
    ("solve deep model", lambda f, d: ["solve", str(_deep(d / "m.json"))], "nested too deeply"),
]


@pytest.mark.parametrize(("label", "make", "problem"), HANGS, ids=[h[0] for h in HANGS])
def test_former_hangs_end_with_one_line(files: dict[str, Path], tmp_path: Path, label: str,
                                        make: Callable[[dict[str, Path], Path], list[str]], problem: str) -> None:
    r = run_cli(*make(files, tmp_path))  # subprocess.TimeoutExpired after HANG_LIMIT_S fails the test
    assert r.returncode == 2, (label, r.stderr)
    assert problem in one_error_line(r.stderr), r.stderr
    assert r.stdout == ""
