"""The case study's pieces that need no ROS: profiles, wiring, CPU scaling, cgroups, CLI errors."""

from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from perfros_bag.casestudy.instances import table2_instance
from perfros_bag.casestudy.launcher import computer_cores, node_launches
from perfros_bag.casestudy.profiles import Calibration, NodeProfile, _interp, launch_for
from perfros_bag.cpu.trace import node_cpu, read_cpu_trace, write_cpu_trace
from perfros_bag.errors import PerfrosWarning
from perfros_bag.rosrun.cgroups import (
    MIN_QUOTA_US,
    PERIOD_US,
    CpuGroups,
    cgroup_version,
    emulated_trace,
    group_period_us,
    leftover_groups,
)
from perfros_bag.system.plan import Assignment
from perfros_bag.system.planfile import save_plan
from perfros_bag.system.rules import build_plan
from perfros_bag.system.systemfile import parse_system


@pytest.fixture
def inst1():  # type: ignore[no-untyped-def]
    return parse_system(table2_instance(1, continuous=False), "instance1.yaml")


def test_profile_reproduces_table1_and_interpolates(inst1) -> None:  # type: ignore[no-untyped-def]
    amcl = NodeProfile.of(inst1.node["amcl1"])
    assert [amcl.cpu(v) for v in (200, 500, 3000)] == [19, 41, 66]
    assert amcl.cpu(300) == pytest.approx(19 + 22 / 3)  # Table III Mod. 1, between 200 and 500
    assert amcl.frequency_hz(1000) == 2.5
    nav = NodeProfile.of(inst1.node["navigation1"])
    assert nav.cpu(15) == pytest.approx(44.5) and nav.frequency_hz(15) == pytest.approx(15)
    assert nav.bandwidth_kBps(15) == pytest.approx(0.75)
    assert nav.value_for_cpu(44.5) == pytest.approx(15)
    model = NodeProfile.of(inst1.node["model1"])
    assert model.cpu(80) == pytest.approx(17 + 76 * 23 / 3496)  # Table III baseline
    yb = NodeProfile.of(inst1.node["youbot_core1"])
    assert not yb.configurable and yb.cpu(None) == 16 and yb.frequency_hz(None) == 10
    # past the last setting: linear extrapolation of the last segment
    trk = NodeProfile.of(inst1.node["tracker1"])
    assert trk.cpu(30) == pytest.approx(240)


@given(st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)), min_size=2, max_size=6,
                unique_by=lambda p: round(p[0], 3)), st.floats(-2e3, 2e3))
def test_interp_passes_through_points_and_stays_between_them(points, x) -> None:  # type: ignore[no-untyped-def]
    pts = sorted(points)
    for px, py in pts:
        assert _interp(pts, px) == pytest.approx(py, abs=1e-6)
    if pts[0][0] <= x <= pts[-1][0]:
        i = next(k for k in range(1, len(pts)) if x <= pts[k][0])
        lo, hi = sorted((pts[i - 1][1], pts[i][1]))
        assert lo - 1e-6 <= _interp(pts, x) <= hi + 1e-6


def test_launch_numbers_by_hand(inst1) -> None:  # type: ignore[no-untyped-def]
    cal = Calibration(units_per_core=400, headroom=0.85, overhead_s=0.0006)
    ln = launch_for(inst1.node["tracker1"], "server", 20, cal)
    # 160 units * 0.85 / 400 units per core / 20 Hz = 17 ms of CPU per cycle, minus the overhead
    assert ln.rate_hz == 20 and ln.work_ms == pytest.approx(17 - 0.6)
    assert ln.target_cpu == pytest.approx(136)
    assert ln.message_bytes == 100 - 4  # 2.0 kB/s at 20 Hz; String adds a 4-byte length
    exp = launch_for(inst1.node["experiment"], "server", None, cal)
    assert exp.work_ms == 0 and exp.rate_hz == 10  # 1 unit is below rospy's own cost
    argv = ln.argv("abc")
    assert argv[0] == "/usr/bin/python3" and "__name:=tracker1" in argv and argv[argv.index("--run") + 1] == "abc"


def test_wiring_follows_the_system_edges(inst1) -> None:  # type: ignore[no-untyped-def]
    place = {n.name: "server" for n in inst1.nodes}
    place["youbot_core1"] = "robot1"
    choice = {n.name: n.choices()[-1] for n in inst1.nodes}
    plan = build_plan(inst1, Assignment(place, choice), problem=1, method="t", status="feasible")
    launches = {ln.name: ln for ln in node_launches(inst1, plan, Calibration())}
    assert set(launches["environment1"].subscribes) == {"/tracker1/out", "/amcl1/out"}
    assert set(launches["model1"].subscribes) == {"/environment1/out", "/experiment/out"}
    assert launches["youbot_core1"].computer == "robot1"
    assert launches["model1"].value == 10000
    # an override (RQ3) replaces the plan's value
    forced = {ln.name: ln for ln in node_launches(inst1, plan, Calibration(), {"amcl1": 300})}
    assert forced["amcl1"].value == 300
    assert computer_cores(inst1, plan, 400) == {"robot1": 0.25, "server": 1.0}


def test_plan_without_values_gets_them_from_cpu(inst1) -> None:  # type: ignore[no-untyped-def]
    place = {n.name: "server" for n in inst1.nodes}
    place["youbot_core1"] = "robot1"
    choice = {n.name: n.choices()[0] for n in inst1.nodes}
    plan = build_plan(inst1, Assignment(place, choice), problem=1, method="t", status="feasible")
    plan.nodes["navigation1"].value = None
    plan.nodes["navigation1"].cpu = 44.5
    nav = next(ln for ln in node_launches(inst1, plan, Calibration()) if ln.name == "navigation1")
    assert nav.value == pytest.approx(15) and nav.rate_hz == pytest.approx(15)


def test_emulated_trace_gives_units_per_core_through_the_contract_formula(tmp_path: Path) -> None:
    raw = tmp_path / "run.host.cpu.csv"
    rows = [(100.0 + k, 11, "model1", "python3", 10.0, 0) for k in range(3)]
    rows += [(100.0 + k, 12, "tracker1", "python3", 40.0, 0) for k in range(3)]
    rows += [(100.0 + k, 13, "roscore", "python3", 99.0, 0) for k in range(3)]
    write_cpu_trace(raw, rows, host="h", logical_cpus=2, interval_s=0.5)
    dest = tmp_path / "run.cpu.csv"
    emulated_trace(raw, dest, {"model1": "robot1", "tracker1": "server"}, {"robot1": 100.0, "server": 400.0}, 400.0)
    tr = read_cpu_trace(dest)
    assert tr.logical_cpus == 2 and "roscore" not in tr.node
    # 10 % of a core = 40 units when one core is 400 units, whichever computer it is on
    robot = node_cpu(tr, 100.0, nodes={"model1": None})
    server = node_cpu(tr, 400.0, nodes={"tracker1": None})
    assert robot["model1"].mean == pytest.approx(40.0)
    assert server["tracker1"].mean == pytest.approx(160.0)


@pytest.mark.parametrize("cores", [0.005, 0.05, 0.1, 0.25, 1.5])
@pytest.mark.parametrize("period", [5_000, 10_000, 100_000])
def test_group_period_keeps_the_quota_at_the_kernels_minimum(cores: float, period: int) -> None:
    """The period is the asked one unless cores x period falls under the 1 ms minimum quota;
    then the shortest period whose quota is at least 1 ms, so the share cores stays exact."""
    got = group_period_us(cores, period)
    if cores * period >= MIN_QUOTA_US:
        assert got == period
    else:
        assert got > period and cores * got >= MIN_QUOTA_US > cores * (got - 1)
    assert PERIOD_US == 10_000  # the default measured in docs/benchmarks.md, "CFS period"


def test_period_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from perfros_bag.errors import InputError
    from perfros_bag.rosrun.cgroups import PERIOD_ENV

    monkeypatch.delenv(PERIOD_ENV, raising=False)
    assert CpuGroups("t", {"r": 0.5}).period_us == PERIOD_US
    monkeypatch.setenv(PERIOD_ENV, "100000")
    groups = CpuGroups("t", {"r": 0.5})
    assert groups.period_us == 100_000 and groups.cap_record()["periods_us"] == {"r": 100_000}
    for bad in ("10ms", "999", "2000000"):
        monkeypatch.setenv(PERIOD_ENV, bad)
        with pytest.raises(InputError, match=PERIOD_ENV):
            CpuGroups("t", {"r": 0.5})


def test_emulated_trace_keeps_the_busy_threads(tmp_path: Path) -> None:
    raw = tmp_path / "run.host.cpu.csv"
    rows = [(100.0 + k, 11, "model1", "python3", 10.0, 0, 1.0 + k) for k in range(3)]
    rows += [(100.0, 13, "roscore", "python3", 99.0, 0, 4.0)]
    write_cpu_trace(raw, rows, host="h", logical_cpus=2, interval_s=0.5, threads=True)
    dest = tmp_path / "run.cpu.csv"
    emulated_trace(raw, dest, {"model1": "robot1"}, {"robot1": 100.0}, 400.0)
    tr = read_cpu_trace(dest)
    assert tr.threads.tolist() == [1.0, 2.0, 3.0]
    assert node_cpu(tr, 100.0, nodes={"model1": None})["model1"].threads == pytest.approx(2.0)


def test_cgroups_fall_back_to_uncapped_with_a_warning(tmp_path: Path) -> None:
    groups = CpuGroups("t1", {"robot1": 0.25}, root=tmp_path)
    assert cgroup_version(tmp_path) == "none"
    with pytest.warns(PerfrosWarning, match="UNCAPPED"):
        groups.create()
    assert groups.mode == "uncapped" and not groups.capped and groups.reason
    assert groups.wrap("robot1", ["/bin/true"]) == ["/bin/true"]
    assert groups.remove() == []


@pytest.mark.skipif(os.geteuid() != 0, reason="creating cgroups needs root (CI runs as root)")
def test_real_cgroup_quota_and_removal() -> None:
    import subprocess

    groups = CpuGroups("unit" + str(os.getpid()), {"robot1": 0.25})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        groups.create(capped=False)
    if not groups.capped:  # a machine whose cgroupfs is read-only: the fallback must say so
        assert groups.reason and caught
        return
    try:
        d = groups.dirs["robot1"]
        quota = d / ("cpu.cfs_quota_us" if groups.mode == "cgroup-v1" else "cpu.max")
        assert quota.read_text().split()[0] in ("-1", "max")
        groups.apply()
        assert quota.read_text().split()[0] == str(round(0.25 * PERIOD_US))  # 0.25 core of the period
        if groups.mode == "cgroup-v1":
            assert (d / "cpu.cfs_period_us").read_text().strip() == str(PERIOD_US)
        else:
            assert quota.read_text().split()[1] == str(PERIOD_US)
        groups.period_us = 100_000  # the period can change under a running group (the bench's)
        groups.apply()
        assert quota.read_text().split()[0] == "25000"
        out = subprocess.run(groups.wrap("robot1", ["/bin/cat", "/proc/self/cgroup"]), capture_output=True,
                             text=True, check=True).stdout
        assert d.name in out
    finally:
        assert groups.remove() == []
    assert leftover_groups(run_id=groups.run_id) == []


def _cli(*args: str) -> tuple[int, str]:
    from typer.testing import CliRunner

    from perfros_bag.cli import app

    result = CliRunner().invoke(app, list(args))
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, result.stderr


def test_cli_bad_input_is_one_line_exit_2(tmp_path: Path, inst1) -> None:  # type: ignore[no-untyped-def]
    system = tmp_path / "system.yaml"
    system.write_text(yaml.safe_dump(table2_instance(1, continuous=False)))
    place = {n.name: "server" for n in inst1.nodes}
    choice = {n.name: n.choices()[0] for n in inst1.nodes}
    plan = tmp_path / "plan.json"
    save_plan(build_plan(inst1, Assignment(place, choice), problem=1, method="t", status="feasible"), plan)
    out = tmp_path / "run"
    for args, needle in [
        (["--system", str(tmp_path / "nope.yaml"), "--plan", str(plan)], "nope.yaml"),
        (["--system", str(system), "--plan", str(tmp_path / "nope.json")], "nope.json"),
        (["--system", str(system), "--plan", str(plan), "--set", "amcl1"], "NODE=VALUE"),
        (["--system", str(system), "--plan", str(plan), "--set", "ghost=3"], "ghost"),
        (["--system", str(system), "--plan", str(plan), "--set", "youbot_core1=3"], "no parameter"),
    ]:
        rc, err = _cli("casestudy", "run", *args, "--out", str(out), "--duration", "1")
        assert rc == 2, err
        assert "Traceback" not in err and needle in err
        assert len([line for line in err.splitlines() if line.strip()]) <= 2, err
    assert not (out / "run.bag").exists()
    infeasible = tmp_path / "inf.json"
    infeasible.write_text('{"format": "perfros-bag/plan@1", "problem": 1, "method": "x", '
                          '"status": "infeasible", "reason": "robot1 too small", "nodes": {}}')
    rc, err = _cli("casestudy", "run", "--system", str(system), "--plan", str(infeasible), "--out", str(out))
    assert rc == 2 and "infeasible" in err


def test_run_requires_ros_tools_clearly(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, inst1) -> None:  # type: ignore[no-untyped-def]
    from perfros_bag.casestudy import launcher
    from perfros_bag.errors import PerfrosError

    monkeypatch.setattr(launcher, "ROSCORE", "roscore-that-does-not-exist")
    place = {n.name: "server" for n in inst1.nodes}
    choice = {n.name: n.choices()[0] for n in inst1.nodes}
    plan = build_plan(inst1, Assignment(place, choice), problem=1, method="t", status="feasible")
    with pytest.raises(PerfrosError, match="apt-get install"):
        launcher.run_plan(inst1, plan, tmp_path / "r", launcher.RunConfig(duration=1))


def test_cleanup_kills_a_runs_processes_and_groups_only(tmp_path: Path) -> None:
    import subprocess

    import psutil

    from perfros_bag.rosrun.processes import RUN_ENV, leftover_processes

    run_id = f"cleanup{os.getpid()}"
    started = time.monotonic()
    mine = subprocess.Popen(["sleep", "30"], env={**os.environ, RUN_ENV: run_id})
    other = subprocess.Popen(["sleep", "30"], env={**os.environ, RUN_ENV: run_id + "x"})
    group = None
    if os.geteuid() == 0:
        groups = CpuGroups(run_id, {"robot1": 0.25})
        groups.create(quiet=True)
        group = groups.dirs.get("robot1")
    try:
        assert mine.pid in leftover_processes(run_id) and other.pid not in leftover_processes(run_id)
        rc, err = _cli("casestudy", "cleanup", "--run", run_id)
        assert rc == 0, err
        mine.wait(5)  # killed (its status may already be reaped by psutil in this process)
        assert time.monotonic() - started < 20
        assert other.poll() is None and psutil.pid_exists(other.pid)
        assert leftover_processes(run_id) == []
        if group is not None:
            assert not group.exists()
    finally:
        other.kill()
        other.wait()
        if mine.poll() is None:
            mine.kill()


def test_a_foreign_server_on_the_master_port_is_not_a_master() -> None:
    """Another program (here: one answering binary garbage, as a Dask scheduler does) that
    took the port is not mistaken for roscore."""
    import socket
    import threading

    from perfros_bag.rosrun.master import master_call, master_state

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    port = srv.getsockname()[1]

    def serve() -> None:
        for _ in range(2):
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            conn.recv(4096)
            conn.sendall(b"\x00\x01\x02compression\xc0python pickle-protocol\n\n")
            conn.close()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        assert master_call(f"http://127.0.0.1:{port}", "getPid") is None
        assert master_state(f"http://127.0.0.1:{port}") is None
    finally:
        srv.close()
        t.join(2)
