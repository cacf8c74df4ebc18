"""End to end on real ROS 1 (Debian's roscore, rospy, rosbag): instance 1 of the paper.

solve (Problem 1, Table I) -> ``casestudy run`` (20 s of recording, computers as cgroups)
-> ``validate``: the overall deviation (eq 10) is within tolerance, every topic's
frequency - recomputed independently with Debian's rosbag API under /usr/bin/python3 - is
within 5 % of the plan, and nothing the run started is left: no process carrying the
run's id, no roscore/rosbag/node process on its port, no cgroup. A second test interrupts
a run with SIGINT (Ctrl-C) while the nodes run and checks the same cleanup.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import psutil
import pytest

from perfros_bag.rosrun.cgroups import CpuGroups, leftover_groups
from perfros_bag.rosrun.processes import leftover_processes
from perfros_bag.solver import solve
from perfros_bag.system.planfile import save_plan
from perfros_bag.system.systemfile import load_system
from tests.conftest import FIXTURES, communicate_or_stacks

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).with_name("perfros-bag")
ROS_PY = "/usr/bin/python3"

# Independent frequency check: Debian's rosbag reader, not the project's.
BAG_RATES = r"""
import json, sys, rosbag
times = {}
with rosbag.Bag(sys.argv[1]) as bag:
    for topic, _msg, t in bag.read_messages():
        times.setdefault(topic, []).append(t.to_sec())
print(json.dumps({k: (len(v) - 1) / (v[-1] - v[0]) for k, v in times.items() if len(v) > 1}))
"""


def _require_ros() -> None:
    for tool in ("/usr/bin/roscore", "/usr/bin/rosbag", ROS_PY):
        assert os.path.exists(tool), f"{tool} missing: apt-get install ros-core python3-rospy python3-rosbag"


def _processes_on(port: int) -> list[str]:
    found = []
    for p in psutil.process_iter(["pid", "cmdline"]):
        try:
            cmd = " ".join(p.info["cmdline"] or [])
            env = p.environ()
        except (psutil.Error, OSError):
            continue
        if f":{port}" in env.get("ROS_MASTER_URI", "") or f"-p {port}" in cmd:
            found.append(f"{p.pid} {cmd}")
    return found


def _nothing_left(run_id: str, port: int) -> None:
    deadline = time.monotonic() + 5
    while (leftover_processes(run_id) or _processes_on(port)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert leftover_processes(run_id) == []
    assert _processes_on(port) == []
    assert leftover_groups(run_id=run_id) == []


@pytest.fixture(scope="module")
def instance1(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    _require_ros()
    d = tmp_path_factory.mktemp("cs")
    system = FIXTURES / "casestudy" / "instance1.yaml"  # Table II instance 1, Table I settings
    plan = d / "plan.json"
    save_plan(solve(load_system(system), 1, method="greedy"), plan)
    return system, plan


def test_instance1_runs_validates_and_leaves_nothing(instance1: tuple[Path, Path], tmp_path: Path) -> None:
    system, plan = instance1
    out = tmp_path / "run"
    done = subprocess.run([str(BIN), "casestudy", "run", "--system", str(system), "--plan", str(plan),
                           "--duration", "20", "--out", str(out), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    record = json.loads(done.stdout)
    run_id = record["run_id"]
    port = int(record["ros_master_uri"].rsplit(":", 1)[1])
    _nothing_left(run_id, port)
    assert record["killed"] == [] and record["leftover_cgroups"] == []
    for name in ("run.bag", "run.cpu.csv", "run.host.cpu.csv", "manifest.yaml", "plan.json", "run.json"):
        assert (out / name).is_file(), name

    from typer.testing import CliRunner

    from perfros_bag.cli import app

    val = CliRunner().invoke(app, ["validate", str(out / "run.bag"), str(out / "plan.json"),
                                   "--system", str(system), "--tolerance", "5", "--json"])
    assert val.exception is None or isinstance(val.exception, SystemExit), val.exception
    doc = json.loads(val.stdout)
    assert val.exit_code == 0, (doc["overall"], val.stderr)
    assert doc["overall"]["deviation_pct"] <= 5.0
    assert doc["missing_topics"] == []

    planned = json.loads(plan.read_text())
    expected = {t: r["frequency_hz"] for n in planned["nodes"].values() for t, r in n["topics"].items()}
    rates = json.loads(subprocess.run([ROS_PY, "-c", BAG_RATES, str(out / "run.bag")], capture_output=True,
                                      text=True, timeout=60, check=True).stdout)
    assert set(rates) == set(expected)
    for topic, f in expected.items():
        assert abs(rates[topic] / f - 1) < 0.05, (topic, rates[topic], f)

    # computers: the nodes ran where the plan put them, under their cap when capped
    where = {n["node"]: n["computer"] for n in doc["nodes"]}
    assert where == {k: v["computer"] for k, v in planned["nodes"].items()}
    if record["cpu_cap"]["mode"] == "uncapped":
        assert record["cpu_cap"]["reason"], "an uncapped run must say why"
    else:
        for comp in doc["computers"]:
            assert comp["cpu_measured"] <= comp["capacity"] * 1.05, comp


def _cgroups_work() -> bool:
    """Whether capped cgroups can be made here, probed with a throw-away group of our own."""
    groups = CpuGroups(run_id=f"probe{os.getpid()}", cores={"probe": 0.5})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        groups.create(quiet=True)
    try:
        return groups.capped
    finally:
        groups.remove()
        assert not leftover_groups(run_id=groups.run_id)


def test_ctrl_c_stops_everything(instance1: tuple[Path, Path], tmp_path: Path) -> None:
    system, plan = instance1
    out = tmp_path / "run"
    proc = subprocess.Popen([str(BIN), "casestudy", "run", "--system", str(system), "--plan", str(plan),
                             "--duration", "60", "--out", str(out)], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 45
    # wait until every node process runs (roscore is up by then; cgroups exist)
    logs = [out / "ros" / f"{n}.log" for n in json.loads(plan.read_text())["nodes"]]
    while not all(p.exists() for p in logs) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(0.5)
    assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
    run_ids = {p.environ().get("PERFROS_CASESTUDY_RUN") for p in psutil.Process(proc.pid).children(recursive=True)}
    run_ids.discard(None)
    assert len(run_ids) == 1
    run_id = run_ids.pop()
    port = int(next(p.environ()["ROS_MASTER_URI"].rsplit(":", 1)[1]
                    for p in psutil.Process(proc.pid).children(recursive=True)))
    assert leftover_processes(run_id), "the run's processes should be running before Ctrl-C"
    # the run made its cgroups exactly when this machine lets a process join a capped group
    assert bool(leftover_groups(run_id=run_id)) == _cgroups_work()
    proc.send_signal(signal.SIGINT)
    _, stderr = communicate_or_stacks(proc, 40)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    _nothing_left(run_id, port)
