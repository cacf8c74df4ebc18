"""``membership: choose`` deployed (issue 34): a plan that runs one nodelet of the nodelet
fixture (fixtures/nodelet: a camera, one manager hosting opencv_apps' people_detect and
smoothing) standalone on the camera's computer while its manager and the other nodelet run on
the server. ``deploy`` runs it as ``nodelet standalone`` in its own computer's cgroup and
network namespace, and restarts it so for a new plan (control.json); ``export`` writes it so.

Checked against independent sources: the kernel's own view of the running processes
(``/proc/PID/cmdline``, the cgroup's ``cgroup.procs``, ``ip netns identify``), the recorded
bag's message counts read with rosbags, and the exported XML parsed with ElementTree."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import yaml

from perfros_bag.system.planfile import load_plan
from tests.conftest import FIXTURES, communicate_or_stacks

BIN = Path(sys.executable).with_name("perfros-bag")
LAUNCH = FIXTURES / "nodelet" / "nodelet.launch"
FRAME = 230_400  # bytes per camera frame (circles.png, 320x240 rgb8)


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN), *args], capture_output=True, text=True, timeout=timeout)


def _system(path: Path) -> Path:
    """The fixture's nodes on a robot (with the camera) and a server, under ``membership:
    choose``: the manager lives on the server, which holds it with the detector but not the
    smoother too; the robot holds the smoother with its copy of the frames but not the
    detector; so the one best plan runs the smoother standalone on the robot (the only way
    to keep both nodelets at their best settings)."""
    cam = "/camera/image_raw"
    doc = {
        "computers": [{"name": "robot", "kind": "robot", "capacity": 40},
                      {"name": "server", "kind": "server", "capacity": 60}],
        "links": [{"between": ["robot", "server"], "bandwidth_kBps": 20000}],
        "membership": "choose",
        "nodes": [
            {"name": "camera", "weight": 0.2, "residence": ["robot"], "topics": [cam],
             "launch": {"package": "image_publisher", "type": "image_publisher"},
             "settings": [{"cpu": 3.0, "performance": 100, "frequency_hz": 5, "bandwidth_kBps": 5 * FRAME / 1000}]},
            {"name": "vision_manager", "weight": 0.1, "residence": ["server"],
             "settings": [{"cpu": 1.0, "performance": 100}], "copy_cpu_per_MBps": 2.0},
            {"name": "people", "weight": 0.4, "container": "vision_manager", "input": cam,
             "launch": {"package": "opencv_apps", "type": "people_detect"},
             "parameter": {"name": "scale0"}, "topics": ["/people/found"],
             "settings": [{"value": 1.1, "cpu": 0.5, "cpu_per_hz": 10.0, "performance": 100, "bytes_per_msg": 300},
                          {"value": 1.4, "cpu": 0.5, "cpu_per_hz": 5.0, "performance": 40, "bytes_per_msg": 300}]},
            {"name": "smooth", "weight": 0.3, "container": "vision_manager", "input": cam,
             "launch": {"package": "opencv_apps", "type": "smoothing"},
             "parameter": {"name": "kernel_size"}, "topics": ["/smooth/image"],
             "settings": [{"value": 13, "cpu": 0.5, "cpu_per_hz": 2.4, "performance": 100, "bytes_per_msg": FRAME},
                          {"value": 7, "cpu": 0.5, "cpu_per_hz": 1.4, "performance": 60, "bytes_per_msg": FRAME}]},
        ],
        "edges": [{"from": "camera", "to": "people"}, {"from": "camera", "to": "smooth"}],
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _require_ros() -> None:
    for tool in ("/usr/bin/roslaunch", "/usr/lib/nodelet/nodelet", "/usr/share/opencv_apps/nodelet_plugins.xml"):
        assert os.path.exists(tool), f"{tool} missing: make setup-debs (see the Makefile's DEBS)"


def _space(path: Path) -> Path:
    doc = yaml.safe_load((FIXTURES / "nodelet" / "space.yaml").read_text())
    doc.update(duration_s=4, settle_s=0.5)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _solved(tmp_path: Path) -> tuple[Path, Path]:
    """The system and its best plan: smooth standalone on the robot, its manager on the server."""
    system = _system(tmp_path / "system.yaml")
    done = _cli("solve", str(system), "--problem", "1", "--method", "exact", "--out", str(tmp_path / "plan.json"))
    assert done.returncode == 0, done.stderr
    plan = load_plan(tmp_path / "plan.json")
    assert {n: (pn.computer, pn.standalone) for n, pn in plan.nodes.items()} == {
        "camera": ("robot", False), "vision_manager": ("server", False), "people": ("server", False),
        "smooth": ("robot", True)}
    return system, tmp_path / "plan.json"


def _cmdline(pid: int) -> list[str]:
    return Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")[:-1]


def _netns(pid: int) -> str:
    return subprocess.run(["ip", "netns", "identify", str(pid)], capture_output=True, text=True,
                          check=True).stdout.strip()


def _seen_while_running(live_path: Path, proc: subprocess.Popen[str],
                        restarted: tuple[str, int] | None = None) -> dict[str, Any]:
    """What the kernel says of each deployed node while the deploy records: its command line,
    whether its computer's cgroup lists it, its network namespace (live.json names the
    processes, the groups and the namespaces). ``restarted``: (node, old PID): once that node
    runs again under another PID and no restart is under way."""
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            live = json.loads(live_path.read_text())
        except (OSError, ValueError):
            time.sleep(0.1)
            continue
        if restarted is not None and (live["restarting"] or live["nodes"][restarted[0]]["pid"] == restarted[1]):
            time.sleep(0.1)
            continue
        seen = {}
        for name, node in live["nodes"].items():
            pid, computer = node["pid"], node["computer"]
            procs = (Path(live["cgroups"][computer]) / "cgroup.procs").read_text().split()
            seen[name] = {"argv": _cmdline(pid), "computer": computer, "in_group": str(pid) in procs,
                          "netns": _netns(pid), "computer_netns": live["namespaces"][computer], "pid": pid}
        return seen
    raise AssertionError(f"live.json never said so (deploy exit code {proc.poll()})")


@pytest.mark.ros
def test_deploy_runs_a_standalone_nodelet_on_its_own_computer(tmp_path: Path) -> None:
    _require_ros()
    system, plan = _solved(tmp_path)
    out = tmp_path / "dep"
    # a re-plan (control.json, as watch --adapt writes it): smooth at another value, still standalone
    from perfros_bag.sweep.control import write_control
    from perfros_bag.system.planfile import save_plan

    smaller = load_plan(plan)
    smaller.nodes["smooth"].value = 7.0
    save_plan(smaller, tmp_path / "smaller.json")
    with subprocess.Popen([str(BIN), "deploy", str(plan), str(LAUNCH), "--space", str(_space(tmp_path / "space.yaml")),
                           "--out", str(out), "--duration", "8", "--system", str(system)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        seen = _seen_while_running(out / "live.json", proc)
        write_control(out, None, tmp_path / "smaller.json", ["test"])
        again = _seen_while_running(out / "live.json", proc, restarted=("/smooth", seen["/smooth"]["pid"]))
        _, stderr = communicate_or_stacks(proc, 300)
    assert proc.returncode in (0, 1), stderr  # 1: the validation did not hold (judged below, not here)
    assert not [x for x in stderr.splitlines() if x.startswith("error")], stderr
    # the smoother: `nodelet standalone` in the robot's cgroup and namespace, no manager named
    smooth = seen["/smooth"]
    assert smooth["argv"][1:3] == ["standalone", "opencv_apps/smoothing"] and "load" not in smooth["argv"]
    assert "__name:=smooth" in smooth["argv"] and "vision_manager" not in smooth["argv"]
    assert smooth["computer"] == "robot" and smooth["in_group"] and smooth["netns"] == smooth["computer_netns"]
    # the detector's loader still loads it into its manager, both on the server
    people, manager = seen["/people"], seen["/vision_manager"]
    assert people["argv"][1:4] == ["load", "opencv_apps/people_detect", "vision_manager"]
    assert manager["argv"][1:2] == ["manager"]
    for node in (people, manager, seen["/camera"]):
        assert node["in_group"] and node["netns"] == node["computer_netns"]
    assert people["computer"] == manager["computer"] == "server" and seen["/camera"]["computer"] == "robot"
    assert smooth["computer_netns"] != manager["computer_netns"]
    # restarted in place for the new plan: standalone again, at its new value, on the robot
    moved = again["/smooth"]
    assert moved["argv"][1:3] == ["standalone", "opencv_apps/smoothing"] and "load" not in moved["argv"]
    assert moved["computer"] == "robot" and moved["in_group"] and moved["netns"] == moved["computer_netns"]
    assert again["/vision_manager"]["pid"] == manager["pid"] and again["/people"]["pid"] == people["pid"]

    deployed = json.loads((out / "deploy.json").read_text())
    assert {n: (x["computer"], x.get("standalone", False)) for n, x in deployed["nodes"].items()} == {
        "/camera": ("robot", False), "/vision_manager": ("server", False), "/people": ("server", False),
        "/smooth": ("robot", True)}
    assert deployed["nodes"]["/smooth"]["pid"] == moved["pid"]
    assert [r["restarted"] for r in deployed["replans"]] == [["/smooth"]]
    assert deployed["leftover_cgroups"] == [] and deployed["leftover_namespaces"] == []
    for x in seen.values():  # every node stopped: no process of its PID runs its command line any more
        try:
            assert _cmdline(x["pid"]) != x["argv"]
        except FileNotFoundError:
            pass
    # both nodelets' outputs are in the bag (rosbags' own reader)
    from rosbags.highlevel import AnyReader

    with AnyReader([out / "run.bag"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts.get("/smooth/image", 0) > 0 and counts.get("/people/found", 0) > 0
    valid = json.loads((out / "validation.json").read_text())
    cpu = {n["node"]: n["cpu_measured"] for n in valid["nodes"]}
    # the smoothing runs in its own process; the detection in the manager, not its loader
    assert cpu["smooth"] > 5 * cpu["people"] and cpu["vision_manager"] > 5 * cpu["people"]
    graph = yaml.safe_load((out / "graph.yaml").read_text())
    containers = {n["name"]: n.get("container") for n in graph["nodes"]}
    assert containers["/smooth"] is None and containers["/people"] == "/vision_manager"


def _launch_nodes(path: Path) -> dict[str, ET.Element]:
    return {n.get("name") or "": n for n in ET.parse(path).getroot().iter("node")}


@pytest.mark.ros
def test_export_writes_the_standalone_nodelet_on_its_machine(tmp_path: Path) -> None:
    """export --launch: the smoother as `nodelet standalone` with the robot's machine, its
    remaps and parameters as the user's file gives them (that file's own XML), and Debian's
    roslaunch reading the written file into that command line; the detector still loaded
    into its manager on the server. --format roslaunch without --launch and ROS 2's
    per-computer files likewise (the class from opencv_apps' own plugin description)."""
    _require_ros()
    system, plan = _solved(tmp_path)
    space = _space(tmp_path / "space.yaml")
    done = _cli("export", str(plan), "--format", "roslaunch", "--launch", str(LAUNCH), "--space", str(space),
                "--system", str(system), "--out", str(tmp_path / "planned.launch"))
    assert done.returncode == 0, done.stderr
    planned, user = _launch_nodes(tmp_path / "planned.launch"), _launch_nodes(LAUNCH)
    smooth, people = planned["smooth"], planned["people"]
    loader = (user["smooth"].get("args") or "").split()
    assert loader[0] == "load"
    assert (smooth.get("args") or "").split() == ["standalone", loader[1]]
    assert smooth.get("pkg") == "nodelet" and smooth.get("type") == "nodelet" and smooth.get("machine") == "robot"
    assert [(r.get("from"), r.get("to")) for r in smooth.iter("remap")] == \
        [(r.get("from"), r.get("to")) for r in user["smooth"].iter("remap")]
    assert [p.get("name") for p in smooth.iter("param")] == [p.get("name") for p in user["smooth"].iter("param")]
    args = {a.get("name"): a.get("default") for a in ET.parse(tmp_path / "planned.launch").getroot().iter("arg")}
    kernel = next(p for p in smooth.iter("param") if p.get("name") == "kernel_size")
    assert kernel.get("value") == "$(arg kernel_size)" and args["kernel_size"] == "13"
    assert (people.get("args") or "").split() == (user["people"].get("args") or "").split()
    assert people.get("machine") == planned["vision_manager"].get("machine") == "server"
    # Debian's roslaunch reads the written file into the standalone command line
    shown = subprocess.run(["roslaunch", "--args", "/smooth", str(tmp_path / "planned.launch")], capture_output=True,
                           text=True, timeout=120, env={**os.environ, "ROS_HOME": str(tmp_path / "ros")})
    assert shown.returncode == 0, shown.stderr
    words = shown.stdout.split()
    at = words.index("/usr/lib/nodelet/nodelet")
    assert words[at + 1:at + 3] == ["standalone", "opencv_apps/smoothing"]
    assert "image:=camera/image_raw" in words and "__name:=smooth" in words and "load" not in words

    done = _cli("export", str(plan), "--format", "roslaunch", "--system", str(system), "--out",
                str(tmp_path / "plain.launch"))
    assert done.returncode == 0, done.stderr
    plain = _launch_nodes(tmp_path / "plain.launch")
    assert (plain["smooth"].get("args") or "").split() == ["standalone", "opencv_apps/smoothing"]
    assert plain["smooth"].get("machine") == "robot"
    assert (plain["people"].get("args") or "").split() == ["load", "opencv_apps/people_detect", "/vision_manager"]

    done = _cli("export", str(plan), "--format", "ros2-params", "--system", str(system), "--out",
                str(tmp_path / "p.yaml"))
    assert done.returncode == 0, done.stderr
    plugins = ET.parse("/usr/share/opencv_apps/nodelet_plugins.xml").getroot()
    cls = {c.get("name"): c.get("type") for c in plugins.iter("class")}
    robot, server = (ET.parse(tmp_path / f"p.{c}.launch.xml").getroot() for c in ("robot", "server"))
    own = list(robot.iter("node_container"))
    assert len(own) == 1 and [(n.get("name"), n.get("plugin")) for n in own[0].iter("composable_node")] == [
        ("smooth", cls["opencv_apps/smoothing"])]
    (host,) = server.iter("node_container")
    assert host.get("name") == "vision_manager"
    assert [(n.get("name"), n.get("plugin")) for n in host.iter("composable_node")] == [
        ("people", cls["opencv_apps/people_detect"])]


def test_a_replan_restarts_a_node_whose_standalone_flag_changes(tmp_path: Path) -> None:
    """deploy's control file: a new plan that runs smooth standalone on the robot is applied
    (not refused as a split) and restarts smooth alone, as `nodelet standalone`; one that puts
    it back into its manager restarts it as its loader; one that only flags it standalone on
    its manager's computer restarts it too. An unmarked split is still not applied."""
    from perfros_bag.errors import PerfrosWarning
    from perfros_bag.rosrun.cgroups import CpuGroups
    from perfros_bag.sweep.control import Control, write_control
    from perfros_bag.sweep.deploy import plan_run
    from perfros_bag.sweep.nodelets import Nodelet
    from perfros_bag.sweep.space import load_space
    from perfros_bag.system.plan import Plan, PlannedComputer, PlannedNode
    from perfros_bag.system.planfile import save_plan

    def plan(smooth_on: str, alone: bool) -> Plan:
        nodes = {n: PlannedNode("robot" if n == "camera" else "server", 5.0, 50.0, 1.0)
                 for n in ("camera", "vision_manager", "people", "smooth")}
        nodes["smooth"] = PlannedNode(smooth_on, 5.0, 50.0, 1.0, standalone=alone)
        return Plan(1, "exact", "optimal", computers={"robot": PlannedComputer("robot", 100.0, 10.0),
                                                      "server": PlannedComputer("server", 100.0, 10.0)}, nodes=nodes)

    calls: list[tuple[list[tuple[str, str]], frozenset[str]]] = []

    def restart_many(batch: list[tuple[str, Any, Any, str]], standalone: frozenset[str] = frozenset()) -> dict:
        calls.append(([(b[0], b[3]) for b in batch], standalone))
        return {b[0]: 100 + len(calls) for b in batch}

    restarter = SimpleNamespace(watch=SimpleNamespace(pids={f"/{n}": (1, 0.0) for n in ("camera", "people", "smooth",
                                                                                        "vision_manager")}),
                                restart_many=restart_many)
    groups = CpuGroups("t", {"robot": 1.0, "server": 1.0}, root=tmp_path)
    for c in ("robot", "server"):
        (tmp_path / c).mkdir()
        groups.dirs[c] = tmp_path / c
    first = plan("server", False)
    space = load_space(FIXTURES / "nodelet" / "space.yaml")
    nodelets = {f"/{n}": Nodelet(f"/{n}", f"opencv_apps/{t}", "/vision_manager", ("/camera/image_raw",))
                for n, t in (("people", "people_detect"), ("smooth", "smoothing"))}
    control = Control(tmp_path, space, {}, plan_run(first, space, {}),
                      {n: pn.computer for n, pn in first.nodes.items()}, groups, 100.0, False, nodelets=nodelets)
    for seq, (where, alone) in enumerate([("robot", True), ("server", False), ("server", True)], start=1):
        save_plan(plan(where, alone), tmp_path / f"p{seq}.json")
        write_control(tmp_path, seq, tmp_path / f"p{seq}.json", ["why"])
        os.utime(tmp_path / "control.json", (seq, seq))
        control.tick(restarter)  # type: ignore[arg-type]
        assert control.seq == seq
        assert calls[-1] == ([("/smooth", where)], frozenset({"/smooth"}) if alone else frozenset())
        assert control.standalone == ({"smooth"} if alone else set())
    assert len(calls) == 3
    save_plan(plan("robot", False), tmp_path / "split.json")
    write_control(tmp_path, 4, tmp_path / "split.json", ["why"])
    os.utime(tmp_path / "control.json", (4, 4))
    with pytest.warns(PerfrosWarning, match=r"not applied: .*split.json: container vision_manager: node smooth on "
                                            r"robot but its container vision_manager on server"):
        control.tick(restarter)  # type: ignore[arg-type]
    assert len(calls) == 3 and control.seq == 3


def test_watch_adapt_lists_a_changed_standalone_mark(tmp_path: Path) -> None:
    """watch --adapt sends a re-plan to the deploy only when changes.txt lists something: a
    plan that only runs a node standalone (same computer, same value) is a change."""
    from perfros_bag.system.plan import Plan, PlannedComputer, PlannedNode
    from perfros_bag.watch.adapt import changes

    def plan(alone: bool, computer: str = "server") -> Plan:
        return Plan(1, "exact", "optimal", computers={"server": PlannedComputer("server", 100.0, 10.0)},  # type: ignore
                    nodes={"mgr": PlannedNode("server", 1.0, 100.0, 0.5),
                           "smooth": PlannedNode(computer, 5.0, 100.0, 0.5, "kernel_size", 7.0, standalone=alone)})

    assert changes(plan(False), plan(False)) == []
    assert changes(plan(False), plan(True)) == ["smooth: in its container -> standalone"]
    assert changes(plan(True, "robot"), plan(False)) == [
        "smooth: computer robot -> server, standalone -> in its container"]


def test_deploy_and_export_refuse_a_standalone_plan_under_keep(tmp_path: Path) -> None:
    """The same plan read with its system saying ``membership: keep``: one line, exit 2,
    nothing started or written."""
    system, plan = _solved(tmp_path)
    keep = yaml.safe_load(system.read_text())
    keep["membership"] = "keep"
    (tmp_path / "keep.yaml").write_text(yaml.safe_dump(keep, sort_keys=False))
    out = tmp_path / "dep"
    for args in (("deploy", str(plan), str(LAUNCH), "--space", str(_space(tmp_path / "space.yaml")), "--out", str(out),
                  "--duration", "2"),
                 ("export", str(plan), "--format", "roslaunch", "--launch", str(LAUNCH), "--space",
                  str(tmp_path / "space.yaml"), "--out", str(out / "x.launch"))):
        done = _cli(*args, "--system", str(tmp_path / "keep.yaml"), timeout=120)
        lines = [x for x in done.stderr.splitlines() if x.strip()]
        assert done.returncode == 2 and len(lines) == 1, done.stderr
        assert lines[0].startswith(f"error: {plan}: ") and "node smooth: standalone, but the system's membership " \
            "is keep" in lines[0], lines[0]
        assert not out.exists()


@pytest.mark.ros
def test_export_warns_of_a_standalone_mark_on_a_node_the_launch_file_runs_plainly(tmp_path: Path) -> None:
    """export --launch of a plan marking the camera ``standalone``: the user's file starts the
    camera as a node of its own (image_publisher, no ``nodelet load``), so it is written as that
    file says, with a warning naming it; the smoother's mark still makes it `nodelet standalone`."""
    from perfros_bag.system.plan import Plan, PlannedComputer, PlannedNode
    from perfros_bag.system.planfile import save_plan

    _require_ros()
    where = {"camera": "robot", "vision_manager": "server", "people": "server", "smooth": "robot"}
    nodes = {n: PlannedNode(c, 1.0, 100.0, 0.25) for n, c in where.items()}
    nodes["camera"].standalone = nodes["smooth"].standalone = True
    save_plan(Plan(1, "exact", "optimal", computers={c: PlannedComputer(c, 100.0, 2.0) for c in ("robot", "server")},
                   nodes=nodes), tmp_path / "plan.json")
    done = _cli("export", str(tmp_path / "plan.json"), "--format", "roslaunch", "--launch", str(LAUNCH), "--space",
                str(_space(tmp_path / "space.yaml")), "--out", str(tmp_path / "planned.launch"))
    assert done.returncode == 0, done.stderr
    warned = [line for line in done.stderr.splitlines() if "standalone" in line]
    assert len(warned) == 1 and "node(s) camera: the plan runs them standalone" in warned[0], done.stderr
    assert "smooth" not in warned[0]
    planned, user = _launch_nodes(tmp_path / "planned.launch"), _launch_nodes(LAUNCH)
    camera = planned["camera"]
    assert (camera.get("pkg"), camera.get("type")) == (user["camera"].get("pkg"), user["camera"].get("type"))
    assert camera.get("machine") == "robot" and "standalone" not in (camera.get("args") or "")
    assert (planned["smooth"].get("args") or "").split()[0] == "standalone"


@pytest.mark.ros
def test_plain_export_types_an_int_setting_as_roslaunch_types_the_users_file(tmp_path: Path) -> None:
    """The plan holds the smoother's kernel_size as 13.0 and system.yaml gives its parameter
    no type. Debian's roslaunch, reading the user's own file at that value, makes it an int;
    it must read the plain export (--format roslaunch, no --launch) and the planned one
    (--launch) into that same int, not the double 13.0 a node reading an int cannot take."""
    _require_ros()
    system, plan = _solved(tmp_path)
    value = load_plan(plan).nodes["smooth"].value
    assert value is not None and float(value).is_integer()
    own = yaml.safe_load(subprocess.run(["roslaunch", "--dump-params", str(LAUNCH), f"kernel_size:={value:g}"],
                                        capture_output=True, text=True, timeout=120, check=True).stdout)
    assert type(own["/smooth/kernel_size"]) is int
    done = _cli("export", str(plan), "--format", "roslaunch", "--system", str(system), "--out",
                str(tmp_path / "plain.launch"))
    assert done.returncode == 0, done.stderr
    done = _cli("export", str(plan), "--format", "roslaunch", "--launch", str(LAUNCH), "--space",
                str(_space(tmp_path / "space.yaml")), "--system", str(system), "--out",
                str(tmp_path / "planned.launch"))
    assert done.returncode == 0, done.stderr
    for out in ("plain.launch", "planned.launch"):
        params = yaml.safe_load(subprocess.run(["roslaunch", "--dump-params", str(tmp_path / out)], capture_output=True,
                                               text=True, timeout=120, check=True).stdout)
        got = params["/smooth/kernel_size"]
        assert type(got) is int and got == own["/smooth/kernel_size"], (out, got)
