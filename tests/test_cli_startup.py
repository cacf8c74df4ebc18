"""Start-up: ``--help`` loads no heavy library and no other verb; the lazy verb table matches
the verbs' real commands; ``import perfros_bag`` stays light; the public API; no Dask.

The import checks run the real entry point in a fresh interpreter and look at its
``sys.modules`` when it exits. No timing is asserted.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
import pkgutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import typer

import perfros_bag
import perfros_bag.cli
from perfros_bag.cli._app import app
from perfros_bag.cli._lazy import VERBS

ROOT = Path(__file__).resolve().parent.parent
#: never imported for --help (nor by ``import perfros_bag``)
HEAVY = {"numpy", "pandas", "matplotlib", "highspy", "sklearn", "scipy", "dask", "distributed"}
CLI_PACKAGE = "perfros_bag.cli"


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ, **extra)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [extra.get("PYTHONPATH"), str(ROOT),
                                                      os.environ.get("PYTHONPATH")]))
    return env


#: runs the real entry point (``python -m perfros_bag``), then writes ``sys.modules`` to a file
_PROBE = """\
import json, runpy, sys
out, sys.argv = sys.argv[1], ["perfros-bag", *sys.argv[2:]]
try:
    {run}
finally:
    with open(out, "w") as f:
        json.dump(sorted(sys.modules), f)
"""


def imported_by(*args: str, code: str = "runpy.run_module('perfros_bag', run_name='__main__')",
                ) -> tuple[subprocess.CompletedProcess[str], set[str]]:
    """Run ``code`` (the CLI) with ``ARGS`` in a fresh interpreter: the process and the names
    of every module it imported."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "modules.json"
        proc = subprocess.run([sys.executable, "-c", _PROBE.format(run=code), str(out), *args],
                              capture_output=True, text=True, env=_env(COLUMNS="120"), timeout=120)
        modules = set(json.loads(out.read_text()))
    return proc, modules


def _verb_modules(modules: set[str]) -> set[str]:
    return {m for m in modules if m.startswith(CLI_PACKAGE + ".") and not m.split(".")[-1].startswith("_")}


def test_top_level_help_imports_no_verb_and_lists_every_verb() -> None:
    proc, modules = imported_by("--help")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "perfros_bag.cli._app" in modules  # the parse of -X importtime works
    assert not modules & HEAVY, sorted(modules & HEAVY)
    assert not _verb_modules(modules), sorted(_verb_modules(modules))
    rows = [line[2:] for line in proc.stdout.splitlines() if line.startswith("│ ") and line[2] not in " -"]
    assert [row.split()[0] for row in rows] == list(VERBS)  # every verb, in the table's order
    for row, verb in zip(rows, VERBS.values(), strict=True):
        assert verb.help.splitlines()[0] in row


@pytest.mark.parametrize("args", [[v] for v in VERBS] + [["casestudy", "run"], ["casestudy", "cleanup"]],
                         ids=" ".join)
def test_verb_help_imports_only_that_verb_and_nothing_heavy(args: list[str]) -> None:
    proc, modules = imported_by(*args, "--help")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"Usage: perfros-bag {' '.join(args)}" in proc.stdout
    assert not modules & HEAVY, sorted(modules & HEAVY)
    assert _verb_modules(modules) == {VERBS[args[0]].module}


def _all_real_commands() -> dict[str, typer.core.TyperCommand | typer.core.TyperGroup]:
    """Import every verb module of the package (as the eager CLI did): name -> command."""
    for mod in pkgutil.iter_modules(perfros_bag.cli.__path__):
        if not mod.name.startswith("_"):
            importlib.import_module(f"{CLI_PACKAGE}.{mod.name}")
    return dict(typer.main.get_group(app).commands)


def test_verb_table_matches_the_real_commands() -> None:
    real = _all_real_commands()
    assert set(real) == set(VERBS)
    modules = {m.name for m in pkgutil.iter_modules(perfros_bag.cli.__path__) if not m.name.startswith("_")}
    assert {v.module for v in VERBS.values()} == {f"{CLI_PACKAGE}.{m}" for m in modules}
    for name, command in real.items():
        # what typer shows in the verb list: the docstring's first paragraph
        assert VERBS[name].help == inspect.cleandoc(command.help or "").split("\n\n")[0], name
    for name, verb in VERBS.items():
        callback = real[name].callback
        if callback is not None:  # a group (casestudy) has none; its sub-commands live in its module
            assert inspect.unwrap(callback).__module__ == verb.module, name


def test_lazy_help_is_the_eager_help() -> None:
    """The verb list drawn from the table is the one drawn from the loaded verb modules."""
    proc, _ = imported_by("--help")
    load_all = ("import importlib; from perfros_bag.cli._lazy import VERBS; "
                "[importlib.import_module(v.module) for v in VERBS.values()]; "
                "runpy.run_module('perfros_bag', run_name='__main__')")
    eager, modules = imported_by("--help", code=load_all)
    assert _verb_modules(modules) == {v.module for v in VERBS.values()}
    assert proc.returncode == eager.returncode == 0, eager.stderr[-2000:]
    assert proc.stdout == eager.stdout


def test_unknown_verb_suggests_a_verb_not_loaded_yet() -> None:
    proc, modules = imported_by("solv")
    assert proc.returncode == 2
    assert "No such command 'solv'" in proc.stderr and "'solve'" in proc.stderr
    assert not _verb_modules(modules)


def test_import_perfros_bag_is_light() -> None:
    proc, modules = imported_by(code="import perfros_bag; perfros_bag.__version__; perfros_bag.PerfrosError")
    assert proc.returncode == 0, proc.stderr[-2000:]
    ours = {m for m in modules if m.startswith("perfros_bag")}
    assert ours == {"perfros_bag", "perfros_bag.errors"}
    assert not modules & (HEAVY | {"yaml", "rosbags", "mcap", "typer", "rich"})


def test_public_api_names_are_the_library_objects() -> None:
    from perfros_bag import errors
    from perfros_bag.characterisation import table
    from perfros_bag.export import writers
    from perfros_bag.fitting import build, modelfile
    from perfros_bag.ingest import read_recording, stats
    from perfros_bag.report import html
    from perfros_bag.solver import solve
    from perfros_bag.system import plan, planfile, systemfile, types
    from perfros_bag.validation import eq10

    expected = {
        "read_recording": read_recording, "RecordingStats": stats.RecordingStats,
        "TopicStats": stats.TopicStats, "load_system": systemfile.load_system, "System": types.System,
        "load_plan": planfile.load_plan, "save_plan": planfile.save_plan, "Plan": plan.Plan,
        "build_model": build.build_model, "read_model": modelfile.read_model,
        "write_model": modelfile.write_model, "find_entries": table.find_entries,
        "characterise": table.characterise, "solve": solve, "validate": eq10.validate_files,
        "Validation": eq10.Validation, "export_plan": writers.export_plan,
        "build_report": html.build_report, "PerfrosError": errors.PerfrosError,
        "InputError": errors.InputError, "InfeasibleError": errors.InfeasibleError,
        "PerfrosWarning": errors.PerfrosWarning,
    }
    assert set(perfros_bag.__all__) == set(expected) | {"__version__"}
    for name, obj in expected.items():
        assert getattr(perfros_bag, name) is obj, name
    assert set(perfros_bag.__all__) <= set(dir(perfros_bag))
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        perfros_bag.nonexistent  # noqa: B018
    namespace: dict[str, object] = {}
    exec("from perfros_bag import *", namespace)  # noqa: S102 - the star import resolves every name
    assert namespace["validate"] is eq10.validate_files


def test_version_matches_the_package_metadata() -> None:
    text = (ROOT / "pyproject.toml").read_text()
    assert f'\nversion = "{perfros_bag.__version__}"\n' in text


def test_workers_without_dask_says_how_to_install_it(tmp_path: Path) -> None:
    shim = tmp_path / "shim"
    shim.mkdir()  # dask and distributed made unimportable, as in an install without the extra
    (shim / "sitecustomize.py").write_text("import sys\nsys.modules['dask'] = None\n"
                                           "sys.modules['distributed'] = None\n")
    recordings = ROOT / "fixtures" / "recordings"
    for extra in (["--workers", "2"], ["--scheduler", "tcp://127.0.0.1:8786"]):
        out = tmp_path / "out.csv"
        proc = subprocess.run([sys.executable, "-m", "perfros_bag", "characterise", str(recordings),
                               "--out", str(out), *extra], capture_output=True, text=True, timeout=120,
                              env=_env(PYTHONPATH=str(shim)))
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1, proc.stderr
        assert lines[0].startswith("error: ") and "pip install 'perfros-bag[dask]'" in lines[0]
        assert not out.exists()
    check = subprocess.run([sys.executable, "-c", "import dask"], env=_env(PYTHONPATH=str(shim)),
                           capture_output=True, text=True, timeout=60)
    assert check.returncode != 0 and "dask" in check.stderr  # the shim did hide it
