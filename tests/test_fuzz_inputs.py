"""A fuzz of every verb's inputs (issue 16): one place of a valid plan.json, model.json,
system.yaml or characterisation.csv is replaced by a hostile value (NaN, infinities, huge
and negative numbers, 400-digit integers, wrong types, control characters, deep nesting);
the verb's library path must then either work, writing strict JSON, or raise a
:class:`PerfrosError` (one line at the CLI) - never another exception, and never run past
a per-case time limit (a hang detector: every case takes well under a second)."""

from __future__ import annotations

import csv
import io
import json
import signal
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.errors import PerfrosError
from perfros_bag.fileio import NonFiniteOutputError, json_text

ROOT = Path(__file__).resolve().parent.parent
RECORDINGS = ROOT / "fixtures" / "recordings"
CASE_LIMIT_S = 30

HOSTILE: list[Any] = [
    float("nan"), float("inf"), float("-inf"), 1e308, -1e308, 1e13, -1, 0, 10 ** 400, -(10 ** 400), True, None,
    "", "x", "a\x00b", "\x1b[31m", "a" * 10_000, [], {}, [[[[[[[[[[1]]]]]]]]]], {"format": "perfros-bag/plan@1"},
]
CSV_HOSTILE = ["nan", "inf", "-inf", "1e308", "-1", "1e400", "9" * 5000, "x", "", "1e-320", "\x00", "0x10"]


class Hang(Exception):
    pass


@contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    def expired(signum: int, frame: Any) -> None:
        raise Hang(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def places(doc: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every place in a JSON-like document (the root excluded)."""
    out: list[tuple[Any, ...]] = [path] if path else []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += places(v, (*path, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += places(v, (*path, i))
    return out


def replaced(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    copy = json.loads(json.dumps(doc))
    target = copy
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return copy


def survives(action: Callable[[], Any]) -> None:
    """``action`` ends in time, with a result or a PerfrosError refusing the input (not a
    refusal to write the non-finite output it led to: such input must be refused first)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with time_limit(CASE_LIMIT_S):
                action()
        except NonFiniteOutputError:
            raise
        except PerfrosError:
            pass


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A characterisation, model and plan made by the library from the bundled recordings."""
    from perfros_bag.characterisation.csvfile import write_characterisation
    from perfros_bag.characterisation.table import characterise, find_entries
    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import write_model
    from perfros_bag.solver import solve
    from perfros_bag.system.planfile import plan_document
    from perfros_bag.system.systemfile import load_system

    d = tmp_path_factory.mktemp("fuzz")
    system = load_system(RECORDINGS / "system.yaml")
    entries, _ = find_entries(RECORDINGS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = characterise(entries, system).rows
        write_characterisation(d / "c.csv", rows)
        model = build_model(RECORDINGS / "system.yaml", d / "c.csv").document
        write_model(d / "model.json", model)
        plan = plan_document(solve(load_system(d / "model.json"), 1, "greedy"))
    return {"dir": d, "csv": (d / "c.csv").read_text(), "model": model.to_json(), "plan": plan,
            "system": yaml.safe_load((RECORDINGS / "system.yaml").read_text())}


FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                          HealthCheck.function_scoped_fixture])


@FUZZ
@given(data=st.data())
def test_fuzz_plan_for_validate_export_report(made: dict[str, Any], tmp_path: Path, data: st.DataObject) -> None:
    from perfros_bag.export.writers import export_plan
    from perfros_bag.system.planfile import load_plan, plan_document

    where = data.draw(st.sampled_from(places(made["plan"])))
    doc = replaced(made["plan"], where, data.draw(st.sampled_from(HOSTILE)))
    path = tmp_path / "plan.json"
    path.write_text(data.draw(st.sampled_from([json.dumps(doc)] * 9 + ["[" * 100_000])))

    def act() -> None:
        json_text(plan_document(load_plan(path)))
        for fmt in ("roslaunch", "ros2-params"):
            export_plan(path, fmt, tmp_path / f"out.{fmt}", RECORDINGS / "system.yaml")

    survives(act)


@FUZZ
@given(data=st.data())
def test_fuzz_model_for_solve_and_report(made: dict[str, Any], tmp_path: Path, data: st.DataObject) -> None:
    from perfros_bag.fitting.modelfile import read_model
    from perfros_bag.solver import solve
    from perfros_bag.system.planfile import plan_document
    from perfros_bag.system.systemfile import load_system

    where = data.draw(st.sampled_from(places(made["model"])))
    doc = replaced(made["model"], where, data.draw(st.sampled_from(HOSTILE)))
    path = tmp_path / "model.json"
    path.write_text(json.dumps(doc))
    method = data.draw(st.sampled_from(["greedy", "greedy+"]))

    def act() -> None:
        # the system part is checked when it is loaded (next line), fits and measured here
        survives(lambda: json_text({k: v for k, v in read_model(path).to_json().items() if k != "system"}))
        json_text(plan_document(solve(load_system(path), 1, method)))

    survives(act)


@FUZZ
@given(data=st.data())
def test_fuzz_system_for_solve(made: dict[str, Any], tmp_path: Path, data: st.DataObject) -> None:
    from perfros_bag.solver import solve
    from perfros_bag.system.planfile import plan_document
    from perfros_bag.system.systemfile import load_system

    where = data.draw(st.sampled_from(places(made["system"])))
    doc = replaced(made["system"], where, data.draw(st.sampled_from(HOSTILE)))
    path = tmp_path / "system.yaml"
    try:
        path.write_text(yaml.safe_dump(doc))
    except yaml.YAMLError:
        return
    problem = data.draw(st.sampled_from([1, 2]))
    survives(lambda: json_text(plan_document(solve(load_system(path), problem, "greedy"))))


@FUZZ
@given(data=st.data())
def test_fuzz_characterisation_for_fit(made: dict[str, Any], tmp_path: Path, data: st.DataObject) -> None:
    from perfros_bag.fitting.build import build_model

    rows = list(csv.reader(io.StringIO(made["csv"])))
    line = data.draw(st.integers(1, len(rows) - 1))
    column = data.draw(st.integers(0, len(rows[0]) - 1))
    rows[line][column] = data.draw(st.sampled_from(CSV_HOSTILE))
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    path = tmp_path / "c.csv"
    path.write_text(buf.getvalue())
    survives(lambda: json_text(build_model(RECORDINGS / "system.yaml", path).document.to_json()))


def test_the_time_limit_detects_a_hang() -> None:
    with pytest.raises(Hang):
        with time_limit(0.2):
            while True:
                pass
