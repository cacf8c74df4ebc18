"""fit with a node's measured metric (system.yaml ``metric``, characterisation.csv's
``metric_value``): parameter -> performance from the measurements, model.json names the source."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from perfros_bag.characterisation.csvfile import COLUMNS
from perfros_bag.cli import app
from perfros_bag.errors import PerfrosWarning
from perfros_bag.fitting.build import build_model
from perfros_bag.fitting.modelfile import read_model

SYSTEM = """
computers: [{name: robot1, kind: robot, capacity: 100}]
nodes:
  - name: detector
    weight: 1
    parameter: {name: rate, unit: Hz}
    topics: [/detector/count]
    %s
    settings:
      - {value: 1, cpu: 10, performance: 10}
      - {value: 2, cpu: 20, performance: 20}
      - {value: 3, cpu: 30, performance: 30}
"""
# (value, recording, cpu, metric_value)
MEASURED = [(1, "a", 11.0, 2.0), (1, "b", 13.0, 4.0), (2, "c", 21.0, 5.0), (3, "d", 29.0, 9.0)]


def _files(tmp_path: Path, metric: str,
           measured: list[tuple[int, str, float, float | None]] = MEASURED) -> tuple[Path, Path]:
    system = tmp_path / "system.yaml"
    system.write_text(SYSTEM % metric)
    table = tmp_path / "c.csv"
    with table.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(COLUMNS))
        w.writeheader()
        for value, rec, cpu, metric_value in measured:
            for topic in ("/detector/count", "/detector/debug"):  # the metric repeats on the node's rows
                row: dict[str, Any] = {c: "" for c in COLUMNS}
                row.update(recording=rec, node="detector", parameter="rate", value=value, topic=topic,
                           frequency_hz=value, bandwidth_kBps=value, cpu_units_mean=cpu,
                           metric_value="" if metric_value is None else metric_value)
                w.writerow(row)
    return system, table


def _expected(better: str, lo: float, hi: float) -> list[tuple[float, float]]:
    """Performance per value by hand: the recordings' mean metric mapped linearly over [lo, hi]."""
    means = {1: (2.0 + 4.0) / 2, 2: 5.0, 3: 9.0}
    share = {v: (m - lo) / (hi - lo) for v, m in means.items()}
    return [(float(v), 100 * (s if better == "higher" else 1 - s)) for v, s in sorted(share.items())]


@pytest.mark.parametrize("better", ["higher", "lower"])
def test_fit_takes_performance_from_the_metric(tmp_path: Path, better: str) -> None:
    system, table = _files(tmp_path,
                           f"metric: {{topic: /detector/count, field: data, better: {better}, range: [0, 10]}}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        result = build_model(system, table)
    fit = result.fits["detector"]["parameter->performance"]
    assert fit.source == "metric"
    assert result.fits["detector"]["cpu->performance"].source == "metric"
    assert [p[0] for p in fit.points] == [1.0, 2.0, 3.0]
    for (x, y), (ex, ey) in zip(fit.points, _expected(better, 0, 10), strict=True):
        assert x == ex and y == pytest.approx(ey)
    settings = result.document.system["nodes"][0]["settings"]
    assert [s["performance"] for s in settings] == pytest.approx([y for _, y in _expected(better, 0, 10)])


def test_without_a_range_the_measured_range_maps_to_0_100(tmp_path: Path) -> None:
    system, table = _files(tmp_path, "metric: {topic: /detector/count, field: data}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        fit = build_model(system, table).fits["detector"]["parameter->performance"]
    assert [y for _, y in fit.points] == pytest.approx([y for _, y in _expected("higher", 3.0, 9.0)])


def test_without_a_metric_the_settings_are_the_source(tmp_path: Path) -> None:
    system, table = _files(tmp_path, "")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        fit = build_model(system, table).fits["detector"]["parameter->performance"]
    assert fit.source == "settings"
    assert [y for _, y in fit.points] == [10.0, 20.0, 30.0]


def test_a_metric_measured_once_falls_back_with_a_warning(tmp_path: Path) -> None:
    measured = [(v, r, c, m if v == 1 else None) for v, r, c, m in MEASURED]
    system, table = _files(tmp_path, "metric: {topic: /detector/count, field: data, range: [0, 10]}", measured)
    with pytest.warns(PerfrosWarning, match=r"metric /detector/count measured at 1 value\(s\)"):
        fit = build_model(system, table).fits["detector"]["parameter->performance"]
    assert fit.source == "settings"


def test_model_json_says_the_source_and_reads_back(tmp_path: Path) -> None:
    system, table = _files(tmp_path, "metric: {topic: /detector/count, field: data, range: [0, 10]}")
    model = tmp_path / "model.json"
    res = CliRunner().invoke(app, ["fit", str(system), str(table), "--out", str(model)])
    assert res.exit_code == 0, res.output
    doc = json.loads(model.read_text())
    assert doc["fits"]["detector"]["parameter->performance"]["source"] == "metric"
    assert "source" not in doc["fits"]["detector"]["parameter->cpu"]
    assert read_model(model).fits["detector"]["cpu->performance"].source == "metric"
