"""Bad budgets at the command line (issue 29, "Bad input"): a budget that is not a positive
finite number of ms, and a budget on a chain whose hops cannot be followed, are one line on
stderr naming the file and the chain, exit 2, nothing written; the same chain without a
budget is accepted (its latency is then only a warning, not an error)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_latency import SYSTEM
from typer.testing import CliRunner

from perfros_bag.cli import app

runner = CliRunner()


def _solve(tmp_path: Path, text: str, *extra: str) -> tuple[int, list[str]]:
    path = tmp_path / "system.yaml"
    path.write_text(text)
    res = runner.invoke(app, ["solve", str(path), "--problem", "1", "--method", "exact",
                              "--out", str(tmp_path / "plan.json"), *extra])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["system.yaml"]  # nothing written
    return res.exit_code, [ln for ln in res.stderr.splitlines() if ln.strip()]


@pytest.mark.parametrize(("budget", "says"), [
    ("{p95: .nan}", "budget_ms.p95: must be a finite number"),
    ("{p50: -.inf}", "budget_ms.p50: must be a finite number"),
    ("{p95: true}", "budget_ms.p95: must be a finite number"),
    ("{p95: '120 ms'}", "budget_ms.p95: must be a finite number"),
    ("{p95: -0.0}", "budget_ms.p95: must be > 0"),
    ("{p95: 1.0e+400}", "budget_ms.p95"),
    ("{p95: [100]}", "budget_ms.p95"),
])
def test_a_budget_that_is_not_a_positive_finite_number(tmp_path: Path, budget: str, says: str) -> None:
    text = SYSTEM.replace("    topics: [/camera/image_raw, /detector/found]\n",
                          f"    topics: [/camera/image_raw, /detector/found]\n    budget_ms: {budget}\n")
    for extra in ((), ("--pareto-budget", "vision")):
        code, lines = _solve(tmp_path, text, *extra)
        assert code == 2
        assert len(lines) == 1 and "system.yaml" in lines[0] and "chain 'vision'" in lines[0], lines
        assert says in lines[0], lines[0]


def test_a_budget_on_a_chain_that_cannot_be_followed(tmp_path: Path) -> None:
    # /log is published by the logger, which keeps its own clock (no input): it stamps afresh
    text = SYSTEM.replace("    topics: [/camera/image_raw, /detector/found]\n",
                          "    topics: [/camera/image_raw, /log]\n    budget_ms: {p95: 100}\n")
    code, lines = _solve(tmp_path, text)
    assert code == 2
    assert len(lines) == 1 and "system.yaml" in lines[0], lines
    assert "chain 'vision': budget_ms: its latency cannot be predicted: hop /camera/image_raw -> /log: /log is " \
           "published by 'logger', not driven by /camera/image_raw" in lines[0]
    assert "stamped afresh" in lines[0]
    # without the budget the same chain is accepted: a plan is written, the chain only warned about
    path = tmp_path / "system.yaml"
    path.write_text(text.replace("    budget_ms: {p95: 100}\n", ""))
    res = runner.invoke(app, ["solve", str(path), "--problem", "1", "--out", str(tmp_path / "plan.json")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "plan.json").exists()
    assert "chain 'vision'" in res.stderr and "cannot be predicted" in res.stderr


def test_pareto_budget_on_a_chain_that_cannot_be_followed(tmp_path: Path) -> None:
    """A chain without a budget may stamp afresh (only warned about); --pareto-budget on it
    would give it one: refused the same way."""
    text = SYSTEM.replace("topics: [/camera/image_raw, /detector/found]", "topics: [/camera/image_raw, /log]")
    for extra in ((), ("--pareto", "50:100:3")):
        code, lines = _solve(tmp_path, text, "--pareto-budget", "vision", *extra)
        assert code == 2
        assert len(lines) == 1 and "system.yaml" in lines[0], lines
        assert "--pareto-budget: chain 'vision': its latency cannot be predicted" in lines[0]
        assert "stamped afresh" in lines[0]
