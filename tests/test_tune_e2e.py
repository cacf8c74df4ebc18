"""``tune`` on real ROS 1 with the synthetic node whose CPU is known (casestudy_node.py: v ms of
CPU work per message at 10 Hz, i.e. 10·v units of 1000 per core, plus rospy's own).

The sweep's record of the top setting is made deliberately wrong (its CPU trace halved, as
if measured on a machine twice as fast), so the first plan deploys that setting on a
computer too small for it. The deployment starves (its cgroup throttled, the node keeps a
share of its rate), the loop takes its recording as one more characterisation run, rescales
the starved node to its planned rate, refits and deploys a setting that fits. Checked
against independent sources: the known work per message, the rate Debian's rosbag reader
counts in the round's bag and the host's raw CPU trace; nothing the rounds started is left
(processes, cgroups, namespaces). A second start resumes; Ctrl-C and a node dying in a round
keep the finished rounds and leave nothing.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.rosrun.cgroups import leftover_groups
from perfros_bag.rosrun.network import leftover_namespaces
from perfros_bag.rosrun.processes import leftover_processes
from perfros_bag.tune.loop import load_model, model_cpu
from perfros_bag.tune.tunefile import read_tune
from tests.conftest import communicate_or_stacks
from tests.test_casestudy_e2e import BAG_RATES, ROS_PY, _cgroups_work
from tests.test_sweep_e2e import BIN, _nothing_left, _running, _tags_and_ports, _wait, ros_package

pytestmark = pytest.mark.ros

NODE = Path(__file__).resolve().parent.parent / "perfros_bag" / "casestudy" / "nodes" / "casestudy_node.py"
RATE_HZ = 10
UNITS = 1000  # CPU units per core: the solver's whole-unit CPU levels are then fine enough
CAPACITY = 120  # robot1: 12 % of a core; the node needs 10·v (+ rospy's own) at value v
LOW, HIGH = 5, 15  # ms of CPU work per message: 50 and 150 units
TOP = "worker-work_ms-15"


def _need(value: float) -> float:
    """The CPU units the node's work alone takes at ``value`` (ms per message, 10 Hz)."""
    return value * RATE_HZ * UNITS / 1000


def _env(d: Path) -> dict[str, str]:
    return dict(os.environ, ROS_PACKAGE_PATH=str(d / "pkgs"))


def _app(d: Path) -> dict[str, Path]:
    """A ROS package running casestudy_node.py as ``worker``, its launch file, space and system."""
    assert os.path.exists("/usr/bin/roscore") and os.path.exists(ROS_PY), "make setup-debs"
    ros_package(d / "pkgs", "perfros_tune", {"worker": f'#!/bin/sh\nexec {ROS_PY} {NODE} "$@"\n'})
    launch = d / "app.launch"
    launch.write_text(f'<launch><arg name="work_ms" default="{LOW}"/>'
                      f'<node name="worker" pkg="perfros_tune" type="worker" args="--name worker --rate {RATE_HZ} '
                      '--work-ms $(arg work_ms) --pub /worker/out"/></launch>')
    space = d / "space.yaml"
    space.write_text(yaml.safe_dump({
        "duration_s": 3, "settle_s": 1, "design": "one-at-a-time", "startup_timeout_s": 30,
        "vary": [{"node": "worker", "parameter": {"name": "work_ms", "unit": "ms"}, "arg": "work_ms",
                  "values": [LOW, HIGH], "default": LOW}]}))
    system = d / "system.yaml"
    system.write_text(yaml.safe_dump({
        "computers": [{"name": "robot1", "kind": "robot", "capacity": CAPACITY}],
        "nodes": [{"name": "worker", "weight": 1, "parameter": {"name": "work_ms", "unit": "ms"},
                   "topics": ["/worker/out"], "process": "^/worker$",
                   "settings": [{"value": LOW, "cpu": _need(LOW), "performance": 50},
                                {"value": HIGH, "cpu": _need(HIGH), "performance": 100}]}]}, sort_keys=False))
    return {"launch": launch, "space": space, "system": system}


def _tune(d: Path, files: dict[str, Path], out: Path, *extra: str,
          popen: bool = False) -> Any:
    args = [str(BIN), "tune", str(files["launch"]), "--space", str(files["space"]), "--system", str(files["system"]),
            "--out", str(out), "--units-per-core", str(UNITS), "--headroom", "0.1", *extra]
    if popen:
        return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_env(d))
    return subprocess.run(args, capture_output=True, text=True, timeout=150, env=_env(d))


def _halve_cpu(trace: Path) -> None:
    """The sweep's wrong record: every sample's cpu_percent halved."""
    lines = []
    for line in trace.read_text().splitlines():
        if line and not line.startswith("#") and not line.startswith("time,"):
            f = line.split(",")
            f[4] = repr(float(f[4]) / 2)
            line = ",".join(f)
        lines.append(line)
    trace.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def tuned(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("tune")
    files = _app(d)
    out = d / "out"
    swept = subprocess.run([str(BIN), "sweep", str(files["launch"]), "--space", str(files["space"]),
                            "--out", str(out / "sweep")], capture_output=True, text=True, timeout=120, env=_env(d))
    assert swept.returncode == 0, swept.stderr
    _halve_cpu(out / "sweep" / f"{TOP}.cpu.csv")
    done = _tune(d, files, out, "--rounds", "3")
    return {"d": d, "files": files, "out": out, "done": done}


def _mean_cpu(trace: Path, node: str) -> float:
    """Mean CPU units of ``node`` in a raw psutil trace (cpu_percent of one core = 100)."""
    rows = [line.split(",") for line in trace.read_text().splitlines()
            if line and not line.startswith("#") and not line.startswith("time,")]
    values = [float(r[4]) for r in rows if r[2] == node]
    return sum(values) / len(values) / 100 * UNITS


def test_the_loop_learns_the_known_cpu_and_converges(tuned: dict[str, Any]) -> None:
    done, out = tuned["done"], tuned["out"]
    assert "Traceback" not in done.stderr
    doc = read_tune(out / "tune.json")
    rounds = doc["rounds"]
    assert done.returncode == 0, done.stderr  # exit 0: the last round is within tolerance
    assert 2 <= len(rounds) <= 3 and doc["stopped"] == {"reason": "within tolerance", "after_round": len(rounds)}
    assert "round(s) run, 0 resumed; stopped: within tolerance" in done.stderr

    # round 1: the wrong model puts the top setting on robot1, which cannot hold it
    first = rounds[0]
    node = first["nodes"]["worker"]
    assert first["values"] == {"worker": HIGH} and node["value"] == HIGH
    before = model_cpu(load_model(out / "model-0.json"), "worker", HIGH)
    assert before is not None and before < 0.6 * _need(HIGH) <= CAPACITY * 1.5  # what the halved trace says
    assert node["model_cpu_before"] == pytest.approx(before)
    if _cgroups_work():
        assert first["cpu_cap"] != "uncapped" and first["computers"]["robot1"]["starved"]
        assert first["deviation_pct"] > doc["tolerance_pct"] and not first["within_tolerance"]
        # independently: the rate Debian's reader counts in the round's bag, the host's raw trace
        rates = json.loads(subprocess.run([ROS_PY, "-c", BAG_RATES, str(out / "round-1" / "run.bag")],
                                          capture_output=True, text=True, timeout=60, check=True,
                                          env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"}).stdout)
        kept = rates["/worker/out"] / RATE_HZ
        assert kept < 0.95 and node["kept_ratio"] == pytest.approx(kept, rel=0.1)
        used = _mean_cpu(out / "round-1" / "run.host.cpu.csv", "/worker")
        assert used <= CAPACITY * 1.1 and node["cpu_measured"] == pytest.approx(used, rel=0.15)
        assert node["refit"] == "rescaled to its planned rate"
        assert node["cpu_need"] == pytest.approx(node["cpu_measured"] / node["kept_ratio"])
        # the fit moved to the node's real need: the known work per message at the planned rate
        after = model_cpu(load_model(out / "model-1.json"), "worker", HIGH)
        assert after == pytest.approx(node["model_cpu_after"])
        assert abs(after - used / kept) < abs(before - used / kept)
        assert _need(HIGH) * 0.9 <= after <= _need(HIGH) * 1.3, after

    # the last round: a setting whose known work fits robot1, run within tolerance
    last = rounds[-1]
    assert last["within_tolerance"] and last["deviation_pct"] <= doc["tolerance_pct"]
    assert _need(last["values"]["worker"]) <= CAPACITY
    assert (out / "tune.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the manifest the refit characterised: the sweep's runs, then each round's at its values
    manifest = yaml.safe_load((out / "manifest.yaml").read_text())["recordings"]
    assert [e["path"] for e in manifest] == ["sweep/worker-work_ms-5.bag", f"sweep/{TOP}.bag"] + [
        f"round-{r['round']}/run.bag" for r in rounds]
    assert [e["settings"] for e in manifest[2:]] == [r["values"] for r in rounds]
    for r in rounds:  # every round's deployment: the plan's value, nothing left
        record = json.loads((out / r["dir"] / "deploy.json").read_text())
        assert record["values"] == r["values"] and record["run_id"] == r["run_id"]
        assert record["leftover_cgroups"] == [] and record["leftover_namespaces"] == []
        assert leftover_processes(r["run_id"]) == [] and leftover_groups(run_id=r["run_id"]) == []
        assert leftover_namespaces(f"d{r['run_id']}") == []
    _nothing_left(out, set(), set())


def test_a_second_start_resumes_after_the_finished_rounds(tuned: dict[str, Any]) -> None:
    out = tuned["out"]
    assert tuned["done"].returncode == 0, tuned["done"].stderr
    before = read_tune(out / "tune.json")
    again = _tune(tuned["d"], tuned["files"], out, "--rounds", "3")
    assert again.returncode == 0, again.stderr
    assert f"0 round(s) run, {len(before['rounds'])} resumed" in again.stderr
    assert read_tune(out / "tune.json") == before


def test_tune_base_starts_from_a_characterisation_without_sweeping(tuned: dict[str, Any], tmp_path: Path) -> None:
    """``--base``: the tuned folder's model-0 characterisation (the halved sweep) as the base
    of a new loop: no sweep, model 0 the same fit, round 1 deploys the same wrong plan, and the
    refit is the base plus round 1's recording (one round only: stopped after it)."""
    out = tuned["out"]
    assert tuned["done"].returncode == 0, tuned["done"].stderr
    base = tmp_path / "base.csv"
    shutil.copyfile(out / "characterisation-0.csv", base)
    new = tmp_path / "based"
    done = _tune(tuned["d"], tuned["files"], new, "--rounds", "1", "--base", str(base))
    assert done.returncode in (0, 1) and "Traceback" not in done.stderr, done.stderr
    assert not (new / "sweep").exists()
    doc = read_tune(new / "tune.json")
    assert doc["base"] == str(base) and len(doc["base_sha256"]) == 64 and len(doc["rounds"]) == 1
    assert json.loads((new / "model-0.json").read_text())["system"] == \
        json.loads((out / "model-0.json").read_text())["system"]
    assert doc["rounds"][0]["values"] == {"worker": HIGH}  # the base's wrong model, as the sweep's
    manifest = yaml.safe_load((new / "manifest.yaml").read_text())["recordings"]
    assert [e["path"] for e in manifest] == ["round-1/run.bag"]
    rows = (new / "characterisation-1.csv").read_text()
    assert "round-1/run.bag" in rows and "sweep/worker-work_ms-5.bag" in rows  # the base's rows kept
    if _cgroups_work():
        assert doc["rounds"][0]["nodes"]["worker"]["refit"] == "rescaled to its planned rate"
        after = model_cpu(load_model(new / "model-1.json"), "worker", HIGH)
        assert after is not None and _need(HIGH) * 0.9 <= after <= _need(HIGH) * 1.3, after
    run_id = doc["rounds"][0]["run_id"]
    assert leftover_processes(run_id) == [] and leftover_groups(run_id=run_id) == []
    _nothing_left(new, set(), set())


def _resume_state(tuned: dict[str, Any], dest: Path) -> Path:
    """A copy of the tuned folder as it stood after round 1 (tune.json with round 1 only)."""
    out = dest / "out"
    shutil.copytree(tuned["out"], out, ignore=shutil.ignore_patterns("round-2", "round-3", "model-2.json",
                                                                      "model-3.json"))
    doc = json.loads((out / "tune.json").read_text())
    doc["rounds"], doc["stopped"] = doc["rounds"][:1], None
    (out / "tune.json").write_text(json.dumps(doc))
    return out


def _disturb_round_2(tuned: dict[str, Any], tmp_path: Path, ready: str, what: str,
                     act: Callable[[subprocess.Popen[str]], None]) -> tuple[Path, bytes, int, str]:
    """Resume the tuned folder after round 1 and, once round 2 runs a process whose command
    line holds ``ready``, ``act`` on the tune process; then check nothing round 2 started is
    left and tune.json is as it was. Returns the folder, its tune.json, the exit code and stderr."""
    assert tuned["done"].returncode == 0, tuned["done"].stderr
    out = _resume_state(tuned, tmp_path)
    kept = (out / "tune.json").read_bytes()
    proc = _tune(tuned["d"], tuned["files"], out, "--rounds", "3", "--duration", "20", popen=True)
    try:
        _wait(lambda: bool(_running(out, ready)), proc, 60, what)
        tags, ports = _tags_and_ports(out)
        assert len(tags) == 1
        act(proc)
        _, stderr = communicate_or_stacks(proc, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "Traceback" not in stderr
    _nothing_left(out, tags, ports)
    for tag in tags:
        assert leftover_namespaces(f"d{tag}") == [], tag
    assert (out / "tune.json").read_bytes() == kept
    return out, kept, proc.returncode, stderr


def test_ctrl_c_in_a_round_keeps_the_finished_rounds_and_leaves_nothing(tuned: dict[str, Any],
                                                                       tmp_path: Path) -> None:
    _out, _kept, code, stderr = _disturb_round_2(tuned, tmp_path, str(NODE), "round 2's node",
                                                 lambda proc: proc.send_signal(signal.SIGINT))
    assert code == 130, stderr
    assert "interrupted: finished rounds are kept in tune.json" in stderr


def test_a_node_dying_in_a_round_is_one_line_and_keeps_the_finished_rounds(tuned: dict[str, Any],
                                                                          tmp_path: Path) -> None:
    def kill_the_node(proc: subprocess.Popen[str]) -> None:
        victims = _running(tmp_path / "out", str(NODE))
        assert len(victims) == 1
        victims[0].kill()

    out, _kept, code, stderr = _disturb_round_2(tuned, tmp_path, "__name:=perfros_record", "round 2's recording",
                                                kill_the_node)
    assert code == 2, stderr
    lines = [x for x in stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: round 2: the deployment failed ("), stderr
    assert f"rounds 1-1 are kept in {out / 'tune.json'}" in lines[0]


def test_a_forced_plan_beyond_its_computer_deploys_and_says_so(tuned: dict[str, Any], tmp_path: Path) -> None:
    """The worker at its top setting with its known need (150 units) on robot1 (120): refused
    as it is, deployed when plan.json says ``"forced": true``; deploy.json and the validation
    say it was forced."""
    from perfros_bag.validation.eq10 import FORCED_NOTE

    plan = json.loads((tuned["out"] / "round-1" / "plan.json").read_text())
    plan["nodes"]["worker"].update(value=HIGH, cpu=_need(HIGH))
    plan["computers"]["robot1"]["cpu"] = _need(HIGH)
    files = tuned["files"]

    def deploy(doc: dict[str, Any], name: str) -> subprocess.CompletedProcess[str]:
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(doc))
        return subprocess.run([str(BIN), "deploy", str(path), str(files["launch"]), "--space", str(files["space"]),
                               "--out", str(tmp_path / name), "--system", str(files["system"]), "--duration", "2",
                               "--units-per-core", str(UNITS)], capture_output=True, text=True, timeout=90,
                              env=_env(tuned["d"]))

    refused = deploy(plan, "plain")
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    assert f"node 'worker': 'cpu' {_need(HIGH):g} exceeds the capacity {CAPACITY:g} of its computer 'robot1'" \
        in refused.stderr
    assert not (tmp_path / "plain").exists()
    done = deploy({**plan, "forced": True}, "forced")
    assert done.returncode in (0, 1), done.stderr
    assert "plan: forced" in done.stderr and "Traceback" not in done.stderr
    record = json.loads((tmp_path / "forced" / "deploy.json").read_text())
    assert record["forced"] is True and record["values"] == {"worker": HIGH}
    assert FORCED_NOTE in json.loads((tmp_path / "forced" / "validation.json").read_text())["notes"]
    assert leftover_processes(record["run_id"]) == [] and leftover_groups(run_id=record["run_id"]) == []
