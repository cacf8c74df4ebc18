"""fixtures/throttle on Debian's real, unmodified nodes (image_publisher at 15 Hz ->
topic_tools' throttle, its rate the knob -> opencv_apps' fback_flow): ``sweep`` -> ``init``
-> ``characterise`` -> ``fit`` -> ``solve`` -> ``deploy`` with no file written by hand.

Checked against independent sources: the throttle's output, planned and deployed, against the
closed form of topic_tools' rule (a frame passes once 1/rate s have elapsed since the last one
passed: F_in / ceil(F_in / rate)), and the deployed rates against Debian's rosbag API; a value
the sweep never ran (4.5) is planned at its step (15 / 4 = 3.75 Hz, where a smooth fit between
the measured 3.75 and 5 Hz says more), the solve table says it was not measured, and its
deployment holds too.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.conftest import FIXTURES
from tests.test_sweep_e2e import BIN, _bag_rates, _nothing_left

# slow: three sweeps of real nodes (~2.5 min); `make test-slow` runs it, the rules have unit tests
pytestmark = [pytest.mark.ros, pytest.mark.slow]

APP = FIXTURES / "throttle" / "throttle.launch"
SPACE = FIXTURES / "throttle" / "space.yaml"
RAW, THROTTLED = "/camera/image_raw", "/camera/image_throttled"


def _cli(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([str(BIN), *args], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env={**os.environ, "COLUMNS": "200"})
    assert "Traceback" not in done.stderr, done.stderr
    return done


def _step(f_in: float, rate: float) -> float:
    """topic_tools' throttle, closed form: the fewest input periods that exceed its period."""
    return f_in / max(1, math.ceil(f_in / rate - 1e-9))


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The README's steps on fixtures/throttle, up to plan.json (each step must succeed)."""
    for tool in ("/usr/lib/topic_tools/throttle", "/usr/lib/opencv_apps/fback_flow",
                 "/usr/lib/image_publisher/image_publisher"):
        assert Path(tool).exists(), f"{tool} missing: make setup-debs (see the Makefile's DEBS)"
    d = tmp_path_factory.mktemp("throttle")
    for args in (("sweep", str(APP), "--space", str(SPACE), "--out", "runs/"),
                 ("init", "runs/", "--out", "system.yaml"),
                 ("characterise", "runs/", "--system", "system.yaml", "--out", "characterisation.csv"),
                 ("fit", "system.yaml", "characterisation.csv", "--out", "model.json"),
                 ("solve", "model.json", "--problem", "1", "--method", "exact", "--out", "plan.json")):
        step = _cli(*args, cwd=d)
        assert step.returncode == 0, (args[0], step.stderr)
    return d


def _deploy(d: Path, plan: str, out: str) -> tuple[dict[str, Any], dict[str, float], subprocess.CompletedProcess[str]]:
    """``deploy`` (4 s), its validation.json and the run's rates by Debian's rosbag API; nothing left running."""
    step = _cli("deploy", plan, str(APP), "--space", str(SPACE), "--out", out, "--duration", "4", cwd=d)
    run = d / out
    validation = json.loads((run / "validation.json").read_text())
    record = json.loads((run / "deploy.json").read_text())
    _nothing_left(run, {record["run_id"]}, set())
    return validation, _bag_rates(run / "run.bag"), step


def test_the_throttle_is_drafted_driven_with_the_step_and_planned_at_it(pipeline: Path) -> None:
    d = pipeline
    nodes = {n["name"]: n for n in yaml.safe_load((d / "system.yaml").read_text())["nodes"]}
    throttle, flow = nodes["throttle"], nodes["flow"]
    assert throttle["input"] == RAW and throttle["topics"] == [THROTTLED]
    values = yaml.safe_load(SPACE.read_text())["vary"][0]["values"]
    assert [s["value"] for s in throttle["settings"]] == values
    assert all(s["step"] == "period" and s["max_frequency_hz"] == s["value"] for s in throttle["settings"])
    assert flow["input"] == THROTTLED  # the heavy node follows the throttle's output
    assert "input" not in nodes["camera"]

    plan = json.loads((d / "plan.json").read_text())["nodes"]
    f_in = plan["throttle"]["input_hz"]
    assert f_in == pytest.approx(plan["camera"]["topics"][RAW]["frequency_hz"])
    out = plan["throttle"]["topics"][THROTTLED]["frequency_hz"]
    assert out == pytest.approx(_step(f_in, plan["throttle"]["value"]), rel=1e-9)
    assert plan["flow"]["input_hz"] == pytest.approx(out)
    # (deployed by the next test at a value never measured: one deployment keeps the suite short)


def test_a_value_never_measured_is_planned_at_its_step_and_said_so(pipeline: Path) -> None:
    d = pipeline
    measured = yaml.safe_load(SPACE.read_text())["vary"][0]["values"]
    model = json.loads((d / "model.json").read_text())
    (throttle,) = (n for n in model["system"]["nodes"] if n["name"] == "throttle")
    f_in = json.loads((d / "plan.json").read_text())["nodes"]["throttle"]["input_hz"]
    # a grid value the sweep never ran, where the step is not at a whole ratio of the camera
    value = next(s["value"] for s in throttle["settings"] if s["value"] not in measured
                 and 0.1 < (f_in / s["value"]) % 1 < 0.9)
    assert model["unmeasured"]["throttle"]["measured_values"] == measured
    step = _cli("solve", "model.json", "--problem", "2", "--method", "exact", "--settings", f"throttle={value}",
                "--out", "plan-unmeasured.json", cwd=d)
    assert step.returncode == 0, step.stderr
    row = next(line for line in step.stdout.splitlines() if "throttle" in line)
    assert "no: CPU" in row and "Hz ±0" in row  # not measured; the step, not a fit, gives its rate
    assert "yes" in _cli("solve", "model.json", "--problem", "1", "--method", "exact", cwd=d).stdout
    plan = json.loads((d / "plan-unmeasured.json").read_text())["nodes"]
    f_in = plan["throttle"]["input_hz"]
    out = plan["throttle"]["topics"][THROTTLED]["frequency_hz"]
    assert plan["throttle"]["value"] == pytest.approx(value)
    assert out == pytest.approx(_step(f_in, value), rel=1e-9)
    assert plan["flow"]["input_hz"] == pytest.approx(out)

    validation, rates, step = _deploy(d, "plan-unmeasured.json", "deployed-unmeasured/")
    deviation = validation["overall"]["deviation_pct"]
    print(f"throttle fixture at {value} (never measured): deploy deviation {deviation:.2f} %")  # pytest -s
    assert deviation <= 2.5, step.stdout
    assert step.returncode == 0, step.stderr
    assert rates[THROTTLED] == pytest.approx(_step(rates[RAW], value), rel=0.025)
