"""The package docstring's walk through the public API runs as written, on the fixtures:
each step's result is checked against the same stage run through its own module."""

from __future__ import annotations

import json
from pathlib import Path

import perfros_bag as pb
from perfros_bag.characterisation.csvfile import write_characterisation
from perfros_bag.solver.check import check_plan
from tests.conftest import FIXTURES

RECORDINGS = FIXTURES / "recordings"


def test_the_docstring_walk_on_the_fixtures(tmp_path: Path) -> None:
    stats = pb.read_recording(RECORDINGS / "robot_low.bag")
    assert isinstance(stats, pb.RecordingStats) and stats.topics
    system = pb.load_system(RECORDINGS / "system.yaml")
    entries, manifest_system = pb.find_entries(RECORDINGS)  # the manifest names its system
    assert manifest_system == RECORDINGS / "system.yaml" and entries
    result = pb.characterise(entries, system)
    assert not result.failures and result.rows
    csv_path = tmp_path / "characterisation.csv"
    write_characterisation(csv_path, result.rows)
    fitted = pb.build_model(RECORDINGS / "system.yaml", csv_path)
    pb.write_model(tmp_path / "model.json", fitted.document)
    # the file rounds its numbers: what is read back writes the same bytes again
    pb.write_model(tmp_path / "again.json", pb.read_model(tmp_path / "model.json"))
    assert (tmp_path / "again.json").read_bytes() == (tmp_path / "model.json").read_bytes()
    model_system = pb.load_system(tmp_path / "model.json")
    plan = pb.solve(model_system, 1, "greedy")
    assert isinstance(plan, pb.Plan)
    assert check_plan(model_system, plan) == []  # the independent checker finds nothing wrong
    pb.save_plan(plan, tmp_path / "plan.json")
    assert pb.load_plan(tmp_path / "plan.json").objective == plan.objective
    check = pb.validate(RECORDINGS / "robot_low.bag", tmp_path / "plan.json")
    assert isinstance(check, pb.Validation)
    assert json.loads(json.dumps(check.to_dict()))["nodes"]
